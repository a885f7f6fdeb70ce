"""Frame ids: every robot session has its own frame, named "{robot}/{session}", and its
keyframes (pose indices k >= 0 of the session), named "{robot}/{session}#{k}".

`FrameId` is the id as a value (robot, session), checked when it is made; `str(frame_id)` is
the name the store and the status use. `frame_name` and `split_frame` are the same rules as
plain functions on strings. `KeyframeId` (frame, k) is one pose of a session: the nodes of the
service's pose graph. Keyframe 0 is the session's first pose, the origin of its frame.
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


@dataclass(frozen=True, order=True, slots=True)
class KeyframeId:
    """Keyframe `k` (a pose index, >= 0) of the session `frame`: "{robot}/{session}#{k}".

    A name parses at its last "#", so session ids may contain "#" too (session "s#2",
    keyframe 0: "r/s#2#0"). `InputError` for a negative or non-integer k."""

    frame: FrameId
    k: int

    def __post_init__(self) -> None:
        if not isinstance(self.frame, FrameId):
            raise InputError(f"frame must be a FrameId, got {type(self.frame).__name__}")
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < 0:
            raise InputError(f"keyframe must be an integer >= 0, got {self.k!r}")

    def __str__(self) -> str:
        return f"{self.frame}#{self.k}"

    @classmethod
    def parse(cls, name: str) -> KeyframeId:
        """The KeyframeId a name "{robot}/{session}#{k}" stands for."""
        frame, sep, k = name.rpartition("#")
        if not sep or not (k.isascii() and k.isdigit()):
            raise InputError(f"keyframe {name!r} is not '<robot>/<session>#<k>'")
        return cls(FrameId.parse(frame), int(k))

    @classmethod
    def origin(cls, frame: FrameId) -> KeyframeId:
        """Keyframe 0 of a session: its first pose, the origin of its frame."""
        return cls(frame, 0)


def keyframe_name(frame: FrameId | str, k: int) -> str:
    """The node name of keyframe k of a session frame: "{robot}/{session}#{k}"."""
    return str(KeyframeId(frame if isinstance(frame, FrameId) else FrameId.parse(frame), k))


def frame_name(robot_id: str, session_id: str) -> str:
    """The frame of one robot session: "{robot}/{session}" (robot ids may not contain "/")."""
    return str(FrameId(robot_id, session_id))


def split_frame(frame: str) -> tuple[str, str]:
    """Inverse of frame_name: (robot_id, session_id)."""
    f = FrameId.parse(frame)
    return f.robot, f.session


__all__ = ["FrameId", "KeyframeId", "frame_name", "keyframe_name", "split_frame"]
