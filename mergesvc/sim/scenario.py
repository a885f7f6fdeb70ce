"""Seeded synthetic worlds with ground truth, drawn directly: an object map and a submap cut
from a revisit (`make_scenario`), the `Scenario` that carries them with their truth, and the
appearance model (`EmbeddingModel`) every simulated world shares. Vehicle runs through the
tracker are in runs.py, fleets in fleet.py, observation logs in logs.py.

Embeddings have the structure measured on real DINO ViT-S centroids of underwater objects:
a shared direction (median cosine of different objects ~0.28), class prototypes, instance
offsets (instances of one class at cosine ~0.7-0.85), and per-observation noise that grows with
the image uncertainty s. Objects are fused from their observations with the semantic Kalman
filter of tracking.py, so variances and n_obs are what a vehicle would send.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from scipy.spatial.transform import Rotation

from mergesvc.core.model import ObjectArrays, ObjectMap, Submap, arrays_to_nodes
from mergesvc.core.tracking import fuse_observations

EMBEDDING_DIM = 384


class Family(str, Enum):
    UNDERWATER = "underwater"
    KITTI = "kitti"


UNDERWATER_CLASSES = ["towfish", "lobster_cage", "buoy", "tire", "anchor", "crate", "cone"]
KITTI_CLASSES = [
    "car", "pole", "sign", "tree", "trash_bin", "bench", "hydrant", "traffic_light",
    "bicycle", "bush", "parking_meter", "bollard", "mailbox", "lamp",
]


@dataclass(frozen=True)
class EmbeddingModel:
    """Generator of object appearances: shared direction + class prototype + instance offset."""

    shared_nd: np.ndarray  # (d,) common component of all objects
    prototypes_cd: np.ndarray  # (c, d)
    instance_scale: float = 0.55
    noise_per_s: float = 1.6  # relative noise norm per unit of image uncertainty s
    background_nd: np.ndarray | None = None  # (d,) unit: what a washed-out view looks like
    degrade_per_s: float = 0.6  # how far toward the background a view of uncertainty s goes

    @classmethod
    def create(
        cls,
        n_classes: int,
        rng: np.random.Generator,
        d: int = EMBEDDING_DIM,
        instance_scale: float = 0.55,
        noise_per_s: float = 1.6,
    ) -> EmbeddingModel:
        shared = rng.normal(size=d)
        shared *= 0.62 / np.linalg.norm(shared)
        protos = rng.normal(size=(n_classes, d))
        protos /= np.linalg.norm(protos, axis=1, keepdims=True)
        background = shared + rng.normal(size=d) / np.sqrt(d)
        background /= np.linalg.norm(background)
        return cls(shared, protos, instance_scale, noise_per_s, background)

    def instances(self, classes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """True appearance of each object, (n, d), norms 4-7 like DINO centroids."""
        n, d = len(classes), self.shared_nd.shape[0]
        offset = rng.normal(size=(n, d)) * self.instance_scale / np.sqrt(d)
        x = self.shared_nd + self.prototypes_cd[classes] + offset
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        return x * rng.uniform(4.1, 7.7, size=(n, 1))

    def observe(
        self, truth_nd: np.ndarray, s_n: np.ndarray, rng: np.random.Generator
    ) -> np.ndarray:
        """One noisy view per row; the noise norm is noise_per_s * s * |x| (views, light).

        A hard view (low contrast, bad light, textured background: high s) also drifts toward
        a shared washed-out appearance, by degrade_per_s * s of the way: that drift is what a
        learned uncertainty head can see in the embedding itself (uncertainty.py).
        """
        n, d = truth_nd.shape
        s_n = np.asarray(s_n, dtype=np.float64)
        norm = np.linalg.norm(truth_nd, axis=1)
        scale = self.noise_per_s * s_n * norm / np.sqrt(d)
        gain = rng.uniform(0.8, 1.2, size=(n, 1))  # brightness changes the norm
        view = truth_nd
        if self.background_nd is not None:
            a = np.clip(self.degrade_per_s * s_n, 0.0, 1.0)[:, None]
            view = (1.0 - a) * truth_nd + a * norm[:, None] * self.background_nd
        return gain * view + rng.normal(size=(n, d)) * scale[:, None]


@dataclass(frozen=True)
class Scenario:
    """A map, a submap, and the truth: which map object each submap object is (None: false
    detection) and the true T_map_submap as (R (3, 3), t (3,))."""

    map: ObjectMap
    submap: Submap
    truth: dict[str, str | None]
    R_map_submap: np.ndarray
    t_map_submap: np.ndarray
    paper_radius_m: float  # the paper's edge radius for this kind of world (2 m / 100 m)
    # submap id -> every map object that is the same true object (a map can hold duplicates
    # when the vehicle failed to re-associate); empty for make_scenario's one-to-one truth
    equivalent: dict[str, tuple[str, ...]] = field(default_factory=dict)

    def is_correct(self, submap_id: str, map_id: str) -> bool:
        """Whether matching submap_id to map_id is right (any equivalent map object counts)."""
        if submap_id in self.equivalent:
            return map_id in self.equivalent[submap_id]
        return self.truth.get(submap_id) == map_id

    def truth_dict(self) -> dict:
        q = Rotation.from_matrix(self.R_map_submap).as_quat()  # x y z w
        return {
            "matches": self.truth,
            "equivalent": {k: list(v) for k, v in self.equivalent.items() if len(v) > 1},
            "transform": {
                "translation": self.t_map_submap.tolist(),
                "quaternion_wxyz": [q[3], q[0], q[1], q[2]],
            },
        }


def _fused_objects(
    truth_nd: np.ndarray,
    n_obs: np.ndarray,
    model: EmbeddingModel,
    rng: np.random.Generator,
    s_range: tuple[float, float] = (0.05, 0.5),
) -> tuple[np.ndarray, np.ndarray]:
    """Observe each object n_obs times with random s, fuse with the semantic Kalman filter."""
    means, variances = [], []
    for x, k in zip(truth_nd, n_obs):
        s = rng.uniform(*s_range, size=k)
        ys = model.observe(np.repeat(x[None], k, axis=0), s, rng)
        mu, var = fuse_observations(ys, s)
        means.append(mu)
        variances.append(var)
    return np.array(means), np.array(variances)


def _layout(family: Family, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) true object centres."""
    if family is Family.UNDERWATER:
        # a 25 x 12 m pool, objects on the floor (3-4 m deep) or mid-water
        xy = rng.uniform([0, 0], [25, 12], size=(n, 2))
        z = rng.uniform(-4.0, -1.0, size=(n, 1))
        return np.hstack([xy, z])
    # streets on a 300 m grid block pattern; objects 3-9 m off the kerb, 0-3 m high
    streets = rng.integers(0, 4, size=n)
    along = rng.uniform(0, 600, size=n)
    side = rng.choice([-1, 1], size=n) * rng.uniform(3, 9, size=n)
    horizontal = rng.random(n) < 0.5
    x = np.where(horizontal, along, streets * 200 + side)
    y = np.where(horizontal, streets * 200 + side, along)
    return np.column_stack([x, y, rng.uniform(0, 3, size=n)])


def _random_pose(family: Family, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A gravity-aligned robot frame (yaw, small tilt) at a random place."""
    tilt = np.radians(2.0)
    R = Rotation.from_euler(
        "zyx", [rng.uniform(-np.pi, np.pi), rng.normal(0, tilt), rng.normal(0, tilt)]
    ).as_matrix()
    span = 20.0 if family is Family.UNDERWATER else 500.0
    return R, rng.uniform(-span, span, size=3) * np.array([1, 1, 0.1])


def make_scenario(
    family: Family | str,
    seed: int,
    n_map: int | None = None,
    n_sub: int | None = None,
    n_outliers: int | None = None,
    instance_scale: float = 0.55,
    noise_per_s: float = 1.6,
) -> Scenario:
    """A seeded map + submap pair with ground truth. Defaults: the paper's sizes."""
    family = Family(family)
    rng = np.random.default_rng(seed)
    uw = family is Family.UNDERWATER
    classes_names = UNDERWATER_CLASSES if uw else KITTI_CLASSES
    n_map = n_map or (int(rng.integers(20, 41)) if uw else 605)
    n_sub = n_sub or (int(rng.integers(2, 6)) if uw else 20)
    if n_outliers is None:
        n_outliers = (1 if n_sub >= 4 else 0) if uw else 3
    model = EmbeddingModel.create(
        len(classes_names), rng, instance_scale=instance_scale, noise_per_s=noise_per_s
    )
    # class frequencies are skewed: many cars and poles, few hydrants
    weights = rng.dirichlet(np.ones(len(classes_names)) * 2.0)
    classes = rng.choice(len(classes_names), size=n_map, p=weights)
    truth_emb = model.instances(classes, rng)
    centres = _layout(family, n_map, rng)

    pos_sigma = (0.1, 0.5) if uw else (0.2, 1.5)
    # the map: many observations per object, position noise of the mapping session
    map_obs = rng.integers(3, 12, size=n_map)
    map_mu, map_var = _fused_objects(truth_emb, map_obs, model, rng)
    map_pos = centres + rng.normal(size=(n_map, 3)) * rng.uniform(*pos_sigma, size=(n_map, 1))
    map_ids = [f"m{k}" for k in range(n_map)]

    # the submap: objects around one place, revisited in another session with few observations
    anchor = centres[rng.integers(n_map)]
    near = np.argsort(np.linalg.norm(centres - anchor, axis=1))[:n_sub]
    sub_obs = rng.integers(1, 4, size=n_sub)
    sub_mu, sub_var = _fused_objects(truth_emb[near], sub_obs, model, rng)
    sub_world = centres[near] + rng.normal(size=(n_sub, 3)) * rng.uniform(
        *pos_sigma, size=(n_sub, 1)
    )
    # false detections (lighting, reflections): appearance of a random class, no true object
    if n_outliers:
        fake = model.instances(rng.integers(len(classes_names), size=n_outliers), rng)
        o_mu, o_var = _fused_objects(fake, np.ones(n_outliers, dtype=int), model, rng, (0.3, 0.5))
        spread = np.ptp(sub_world, axis=0) + (2.0 if uw else 10.0)
        o_pos = sub_world.mean(axis=0) + rng.uniform(-0.5, 0.5, size=(n_outliers, 3)) * spread
        sub_mu = np.vstack([sub_mu, o_mu])
        sub_var = np.vstack([sub_var, o_var])
        sub_world = np.vstack([sub_world, o_pos])
        sub_obs = np.concatenate([sub_obs, np.ones(n_outliers, dtype=int)])
    R, t = _random_pose(family, rng)  # T_map_submap
    sub_pos = (sub_world - t) @ R  # R^T (p - t)
    order = rng.permutation(len(sub_mu))
    sub_ids = [f"s{k}" for k in range(len(sub_mu))]
    truth_of = [map_ids[k] for k in near] + [None] * n_outliers
    truth = {sub_ids[j]: truth_of[order[j]] for j in range(len(order))}

    robot = "auv" if uw else "car"
    map_arr = ObjectArrays(map_ids, map_pos, map_mu, map_var, map_obs)
    sub_arr = ObjectArrays(
        sub_ids, sub_pos[order], sub_mu[order], sub_var[order], sub_obs[order]
    )
    return Scenario(
        map=ObjectMap(robot_id=f"{robot}1", session_id="s0", objects=arrays_to_nodes(map_arr)),
        submap=Submap(
            robot_id=f"{robot}2", session_id="s1", seq=0, objects=arrays_to_nodes(sub_arr)
        ),
        truth=truth,
        R_map_submap=R,
        t_map_submap=t,
        paper_radius_m=2.0 if uw else 100.0,
    )


__all__ = [
    "EMBEDDING_DIM",
    "KITTI_CLASSES",
    "UNDERWATER_CLASSES",
    "EmbeddingModel",
    "Family",
    "Scenario",
    "make_scenario",
]
