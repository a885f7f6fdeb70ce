"""Frame ids: every robot session has its own frame, named "{robot}/{session}"."""

from __future__ import annotations

from mergesvc.errors import InputError


def frame_name(robot_id: str, session_id: str) -> str:
    """The frame of one robot session: "{robot}/{session}" (robot ids may not contain "/")."""
    if not robot_id or not session_id:
        raise InputError("robot_id and session_id must be non-empty")
    if "/" in robot_id:
        raise InputError(f"robot_id {robot_id!r} may not contain '/'")
    return f"{robot_id}/{session_id}"


def split_frame(frame: str) -> tuple[str, str]:
    """Inverse of frame_name: (robot_id, session_id)."""
    robot_id, sep, session_id = frame.partition("/")
    if not sep or not robot_id or not session_id:
        raise InputError(f"frame {frame!r} is not '<robot>/<session>'")
    return robot_id, session_id
