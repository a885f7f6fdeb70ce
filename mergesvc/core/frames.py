"""Frame ids: every robot session has its own frame, named "{robot}/{session}".

`FrameId` is the id as a value (robot, session), checked when it is made; `str(frame_id)` is
the name the pose graph, the store and the status use. `frame_name` and `split_frame` are the
same rules as plain functions on strings.
"""

from __future__ import annotations

from dataclasses import dataclass

from mergesvc.errors import InputError


@dataclass(frozen=True, order=True, slots=True)
class FrameId:
    """The frame of one robot session. Robot ids may not contain "/"; session ids may (a name
    splits at its first "/"). Both must be non-empty. `InputError` otherwise."""

    robot: str
    session: str

    def __post_init__(self) -> None:
        if not isinstance(self.robot, str) or not isinstance(self.session, str):
            raise InputError("robot_id and session_id must be strings")
        if not self.robot or not self.session:
            raise InputError("robot_id and session_id must be non-empty")
        if "/" in self.robot:
            raise InputError(f"robot_id {self.robot!r} may not contain '/'")

    def __str__(self) -> str:
        return f"{self.robot}/{self.session}"

    @classmethod
    def parse(cls, frame: str) -> FrameId:
        """The FrameId a name "{robot}/{session}" stands for."""
        robot_id, sep, session_id = frame.partition("/")
        if not sep or not robot_id or not session_id:
            raise InputError(f"frame {frame!r} is not '<robot>/<session>'")
        return cls(robot_id, session_id)


def frame_name(robot_id: str, session_id: str) -> str:
    """The frame of one robot session: "{robot}/{session}" (robot ids may not contain "/")."""
    return str(FrameId(robot_id, session_id))


def split_frame(frame: str) -> tuple[str, str]:
    """Inverse of frame_name: (robot_id, session_id)."""
    f = FrameId.parse(frame)
    return f.robot, f.session


__all__ = ["FrameId", "frame_name", "split_frame"]
