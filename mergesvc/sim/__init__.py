"""Simulation: seeded worlds with ground truth, vehicle runs through the tracker, fleets,
observation logs, the learned uncertainty head.

May import: mergesvc.core, mergesvc.errors.
"""

from mergesvc.sim.scenario import (
    Family,
    Frame,
    Scenario,
    drive_run,
    fleet_world,
    image_s_dataset,
    make_scenario,
    read_observation_log,
    underwater_run,
)

__all__ = [
    "Family",
    "Frame",
    "Scenario",
    "drive_run",
    "fleet_world",
    "image_s_dataset",
    "make_scenario",
    "read_observation_log",
    "underwater_run",
]
