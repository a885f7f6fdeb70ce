"""The live view of a fleet's merged map in Rerun (`mergesvc view`, `mergesvc demo --view`):
scene.py holds what is shown, live.py draws it (rerun, an optional extra), feed.py fills it from
a fleet's Zenoh keys. See docs/view.md."""

from mergesvc.view.feed import FeedStats, ZenohFeed, observer
from mergesvc.view.live import (
    INSTALL_HINT,
    LiveView,
    ViewSink,
    blueprint,
    open_recording,
    require_rerun,
)
from mergesvc.view.scene import PALETTE, RETRACTED_RGB, FleetScene, PlacedObjects, Segments

__all__ = [
    "INSTALL_HINT",
    "PALETTE",
    "RETRACTED_RGB",
    "FeedStats",
    "FleetScene",
    "LiveView",
    "PlacedObjects",
    "Segments",
    "ViewSink",
    "ZenohFeed",
    "blueprint",
    "observer",
    "open_recording",
    "require_rerun",
]
