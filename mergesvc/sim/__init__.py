"""Simulation: seeded worlds with ground truth, vehicle runs through the tracker, fleets,
observation logs, the learned uncertainty head (imported as its leaf, mergesvc.sim.uncertainty),
and the generalization benchmark's worlds in foreign frame conventions.

Leaves: scenario (worlds drawn directly), runs (vehicle runs through the tracker), fleet (a fleet
in one pool), logs (observation logs), conventions (frame conventions), real_data (KITTI-00 and
DINO data in ../shared/data), appearance and worlds (the generalization worlds), uncertainty.

May import: mergesvc.core, mergesvc.errors.
"""

from mergesvc.sim.conventions import convention_rotation, rotate_world, supports_up
from mergesvc.sim.fleet import fleet_world
from mergesvc.sim.logs import read_observation_log
from mergesvc.sim.real_data import (
    DEFAULT_DATA_DIR,
    DINO_CENTROIDS,
    KITTI_GT,
    KITTI_ORB,
    load_dino_centroids,
    load_kitti_poses_34,
)
from mergesvc.sim.runs import drive_run, image_s_dataset, survey_embeddings, underwater_run
from mergesvc.sim.scenario import Family, Scenario, make_scenario
from mergesvc.sim.worlds import (
    World,
    WorldSpec,
    express,
    generator_world,
    kitti_world,
    pool_world,
)

__all__ = [
    "DEFAULT_DATA_DIR",
    "DINO_CENTROIDS",
    "KITTI_GT",
    "KITTI_ORB",
    "Family",
    "Scenario",
    "World",
    "WorldSpec",
    "convention_rotation",
    "drive_run",
    "express",
    "fleet_world",
    "generator_world",
    "image_s_dataset",
    "kitti_world",
    "load_dino_centroids",
    "load_kitti_poses_34",
    "make_scenario",
    "pool_world",
    "read_observation_log",
    "rotate_world",
    "supports_up",
    "survey_embeddings",
    "underwater_run",
]
