"""Tests of mergesvc.core.graph: GNC pose graph over robot-session frames (real GTSAM) and the
fusion of the objects of aligned frames."""

from __future__ import annotations

import itertools
import weakref
from collections.abc import Callable, Sequence
from typing import Any

import gtsam
import numpy as np
import pytest

from mergesvc.core.config import GraphConfig
from mergesvc.core.connectivity import bridges as _bridges
from mergesvc.core.folding import _fuse, _pack, _unpack
from mergesvc.core.frames import frame_name, split_frame
from mergesvc.core.fusion import ObjectLink, fuse_objects, links_from_factor
from mergesvc.core.graph import PoseGraph
from mergesvc.core.graph_job import SolveJob, SolveResult
from mergesvc.core.model import (
    Correspondence,
    Factor,
    FactorStatus,
    ObjectArrays,
    ObjectMap,
    ObjectNode,
    Transform,
)
from mergesvc.core.poses import compose_with_covariance as _compose
from mergesvc.core.poses import inverse_with_covariance as _inverse
from mergesvc.core.poses import pose3_from_transform, pose_error
from mergesvc.errors import InputError, SolverError

A, B, C, D, E, F = (f"{r}/s0" for r in "ABCDEF")
SIGMA_ROT_RAD = 0.01
SIGMA_TRANS_M = 0.1


def random_pose(rng: np.random.Generator, rot_rad: float = 1.0, trans_m: float = 30.0):
    return gtsam.Pose3.Expmap(
        np.r_[rng.uniform(-rot_rad, rot_rad, 3), rng.uniform(-1, 1, 3) * trans_m]
    )


def random_covariance(rng: np.random.Generator) -> np.ndarray:
    """A correlated SPD covariance with about SIGMA_ROT_RAD / SIGMA_TRANS_M marginal sigmas."""
    scale = np.diag(np.r_[[SIGMA_ROT_RAD] * 3, [SIGMA_TRANS_M] * 3])
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    corr = Q @ np.diag(rng.uniform(0.5, 1.5, 6)) @ Q.T
    d = np.sqrt(np.diag(corr))
    corr = corr / np.outer(d, d)
    return scale @ corr @ scale


class World:
    """Three robots' frames with known poses in a world frame; A is the anchor."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.T_world = {
            A: random_pose(self.rng),
            B: random_pose(self.rng),
            C: random_pose(self.rng),
        }

    def truth(self, a: str, b: str) -> gtsam.Pose3:
        return self.T_world[a].between(self.T_world[b])

    def T_anchor(self, frame: str) -> gtsam.Pose3:
        return self.truth(A, frame)

    def measure(self, a: str, b: str) -> tuple[gtsam.Pose3, np.ndarray]:
        """A correct factor: truth perturbed by noise drawn from its covariance."""
        cov = random_covariance(self.rng)
        xi = self.rng.multivariate_normal(np.zeros(6), cov)
        return self.truth(a, b).compose(gtsam.Pose3.Expmap(xi)), cov


def gross_error(T: gtsam.Pose3) -> gtsam.Pose3:
    """A wrong loop closure: 80 degrees of yaw and 15 m off."""
    return T.compose(gtsam.Pose3.Expmap(np.r_[0.0, 0.0, 1.4, 15.0, -10.0, 3.0]))


def redundant_graph(world: World, *, known_inlier: bool = False) -> PoseGraph:
    """Two correct factors per pair (a loop with redundancy) plus one wrong A-C factor."""
    graph = PoseGraph(anchor=A)
    for k, (a, b) in itertools.product(range(2), [(A, B), (B, C), (A, C)]):
        T, cov = world.measure(a, b)
        graph.add_factor(f"{a[0]}{b[0]}{k}", a, b, T, cov, known_inlier=known_inlier)
    T, cov = world.measure(A, C)
    # Wrong and overconfident: the smallest covariance, so it would be the first choice of a
    # naive initialisation and dominates a plain least-squares solve.
    graph.add_factor("wrong", A, C, gross_error(T), cov / 4, known_inlier=known_inlier)
    return graph


def assert_psd(S: np.ndarray) -> None:
    assert S.shape == (6, 6)
    np.testing.assert_allclose(S, S.T, rtol=0, atol=1e-12 * np.abs(S).max())
    assert np.linalg.eigvalsh(S).min() > 0


# --------------------------------------------------------------------------------------------
# Pose graph
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_gnc_recovers_true_poses_and_flags_exactly_the_wrong_factor(seed: int) -> None:
    world = World(seed)
    sol = redundant_graph(world).optimize()
    assert sol.gnc_ran
    assert sol.outlier_factor_ids == ["wrong"]
    assert sol.ambiguous_factor_ids == []
    assert sol.unchecked_factor_ids == []
    assert sol.weights["wrong"] < 0.5
    assert all(w >= 0.5 for f, w in sol.weights.items() if f != "wrong")
    assert sol.inlier_factor_ids == [f for f in sol.weights if f != "wrong"]
    assert set(sol.T_anchor_frame) == {A, B, C}
    for frame in (A, B, C):
        rot_err, trans_err = pose_error(sol.T_anchor_frame[frame], world.T_anchor(frame))
        # Two or more factors of sigma 0.01 rad / 0.1 m per frame: 4 sigma bounds.
        assert rot_err < 4 * SIGMA_ROT_RAD * np.sqrt(3)
        assert trans_err < 4 * SIGMA_TRANS_M * np.sqrt(3)
        assert_psd(sol.covariance_66[frame])
    assert sol.marginals_error is None


def test_without_gnc_the_wrong_factor_corrupts_the_frames() -> None:
    """The same graph solved as plain least squares (all factors known inliers) is far off,
    so the test above really measures GNC's robustness."""
    world = World(0)
    sol = redundant_graph(world, known_inlier=True).optimize()
    assert not sol.gnc_ran
    assert sol.outlier_factor_ids == []
    _, trans_err = pose_error(sol.T_anchor_frame[C], world.T_anchor(C))
    assert trans_err > 1.0


def test_spanning_tree_rejects_nothing() -> None:
    """No redundancy: every factor is a bridge, nothing can contradict it."""
    world = World(1)
    graph = PoseGraph()
    T_ab, cov_ab = world.measure(A, B)
    T_bc = gross_error(world.truth(B, C))
    graph.add_factor("AB", A, B, T_ab, cov_ab)
    graph.add_factor("BC", B, C, T_bc, random_covariance(world.rng))
    sol = graph.optimize()
    assert graph.anchor == A  # the first frame added
    assert not sol.gnc_ran
    assert sol.outlier_factor_ids == [] and sol.ambiguous_factor_ids == []
    assert sol.unchecked_factor_ids == ["AB", "BC"]
    # The solution is the measurements chained.
    assert sol.T_anchor_frame[B].equals(T_ab, 1e-6)
    assert sol.T_anchor_frame[C].equals(T_ab.compose(T_bc), 1e-6)
    assert max(sol.errors.values()) < 1e-9


def test_bridge_stays_unchecked_beside_a_checked_loop() -> None:
    """A loop A-B-C (redundant) plus a wrong bridge C-D: the bridge is not judged."""
    world = World(2)
    graph = redundant_graph(world)
    graph.add_factor("CD", C, D, gross_error(gtsam.Pose3()), np.eye(6) * 1e-4)
    sol = graph.optimize()
    assert sol.unchecked_factor_ids == ["CD"]
    assert sol.weights["CD"] == 1.0
    assert sol.outlier_factor_ids == ["wrong"]
    assert sol.T_anchor_frame[D].equals(
        sol.T_anchor_frame[C].compose(gross_error(gtsam.Pose3())), 1e-6
    )


def test_single_inconsistent_loop_is_ambiguous_not_rejected() -> None:
    """One triangle with one wrong factor: any of the three could be the wrong one."""
    world = World(3)
    graph = PoseGraph()
    for fid, (a, b) in (("AB", (A, B)), ("BC", (B, C))):
        graph.add_factor(fid, a, b, *world.measure(a, b))
    T, cov = world.measure(A, C)
    graph.add_factor("wrong", A, C, gross_error(T), cov)
    sol = graph.optimize()
    assert sol.gnc_ran
    assert sol.outlier_factor_ids == []
    assert len(sol.ambiguous_factor_ids) >= 1
    assert set(sol.ambiguous_factor_ids) <= {"AB", "BC", "wrong"}


def test_parallel_pair_does_not_confirm_the_other_side_of_the_loop() -> None:
    """A-B twice (consistent), B-C once, A-C wrong once: A-B is confirmed but which of B-C and
    A-C is wrong is not identifiable, so nothing is retracted."""
    world = World(4)
    graph = PoseGraph()
    graph.add_factor("AB0", A, B, *world.measure(A, B))
    graph.add_factor("AB1", A, B, *world.measure(A, B))
    graph.add_factor("BC", B, C, *world.measure(B, C))
    T, cov = world.measure(A, C)
    graph.add_factor("wrong", A, C, gross_error(T), cov)
    sol = graph.optimize()
    assert sol.outlier_factor_ids == []
    assert set(sol.ambiguous_factor_ids) <= {"BC", "wrong"}
    assert len(sol.ambiguous_factor_ids) >= 1


def test_consistent_loop_flags_nothing() -> None:
    world = World(5)
    graph = PoseGraph()
    for k, (a, b) in itertools.product(range(2), [(A, B), (B, C), (A, C)]):
        graph.add_factor(f"{a[0]}{b[0]}{k}", a, b, *world.measure(a, b))
    sol = graph.optimize()
    assert sol.outlier_factor_ids == [] and sol.ambiguous_factor_ids == []
    assert min(sol.weights.values()) >= 0.5


def test_single_factor_marginal_equals_its_covariance() -> None:
    """Anchor held by the prior, B = A * T_ab: the marginal of B (right perturbation) is the
    factor covariance; two identical parallel factors halve it."""
    rng = np.random.default_rng(6)
    cov = random_covariance(rng)
    T = random_pose(rng)
    one = PoseGraph(anchor=A)
    one.add_factor("f1", A, B, T, cov)
    sol = one.optimize()
    np.testing.assert_allclose(sol.covariance_66[B], cov, rtol=1e-5, atol=1e-12)
    assert_psd(sol.covariance_66[A])
    assert np.abs(sol.covariance_66[A]).max() < 1e-10

    two = PoseGraph(anchor=A)
    two.add_factor("f1", A, B, T, cov)
    two.add_factor("f2", B, A, T.inverse(), cov_inverse_direction(T, cov))
    sol2 = two.optimize()
    assert sol2.gnc_ran and sol2.outlier_factor_ids == []
    np.testing.assert_allclose(sol2.covariance_66[B], cov / 2, rtol=1e-5, atol=1e-12)


def cov_inverse_direction(T_a_b: gtsam.Pose3, cov: np.ndarray) -> np.ndarray:
    """Covariance of T_b_a = T_a_b^-1 given that of T_a_b (right perturbations): Ad(T_a_b)."""
    Ad = T_a_b.AdjointMap()
    return Ad @ cov @ Ad.T


def test_disconnected_frames_are_reported_not_aligned() -> None:
    world = World(7)
    graph = redundant_graph(world)
    graph.add_factor("DE", D, E, random_pose(world.rng), np.eye(6) * 1e-3)
    graph.add_frame(F)
    sol = graph.optimize()
    assert sol.components[0] == [A, B, C]
    assert sorted(map(sorted, sol.components[1:])) == [[D, E], [F]]
    assert sorted(sol.disconnected_frames) == [D, E, F]
    assert set(sol.T_anchor_frame) == {A, B, C}
    assert set(sol.covariance_66) == {A, B, C}
    assert "DE" not in sol.weights
    # Another component is solved on request, in its own anchor's frame.
    other = graph.optimize(anchor=D)
    assert set(other.T_anchor_frame) == {D, E}
    assert other.T_anchor_frame[D].equals(gtsam.Pose3(), 1e-9)
    assert other.components[0] == [D, E]


def test_factor_input_checks_and_replays() -> None:
    rng = np.random.default_rng(8)
    T = random_pose(rng)
    cov = random_covariance(rng)
    graph = PoseGraph()
    assert graph.add_factor("f", A, B, T.matrix(), cov)  # (4, 4) arrays are accepted
    assert not graph.add_factor("f", A, B, T, cov)  # identical replay: no-op
    with pytest.raises(InputError, match="already used"):
        graph.add_factor("f", A, B, T.compose(T), cov)
    with pytest.raises(InputError, match="positive definite"):
        graph.add_factor("g", A, B, T, -cov)
    with pytest.raises(InputError, match="symmetric"):
        graph.add_factor("g", A, B, T, cov + np.triu(np.ones((6, 6)), 1))
    bad = T.matrix()
    bad[:3, :3] *= 1.1
    with pytest.raises(InputError, match="rigid"):
        graph.add_factor("g", A, B, bad, cov)
    with pytest.raises(InputError, match="both"):
        graph.add_factor("g", A, A, T, cov)
    with pytest.raises(InputError, match="unknown anchor"):
        graph.optimize(anchor="Z/s9")
    with pytest.raises(InputError, match="empty"):
        PoseGraph().optimize()
    assert graph.remove_factor("f") and not graph.remove_factor("f")
    assert graph.frames == [A, B]


def test_wire_factor_is_added_and_retracted_one_skipped() -> None:
    rng = np.random.default_rng(9)
    T = random_pose(rng)
    cov = random_covariance(rng)
    q = T.rotation().toQuaternion()
    factor = Factor(
        factor_id="x1",
        robot_a="A",
        session_a="s0",
        robot_b="B",
        session_b="s0",
        T_a_b=Transform(
            translation=tuple(T.translation()), quaternion_wxyz=(q.w(), q.x(), q.y(), q.z())
        ),
        covariance=cov.tolist(),
        correspondences=[Correspondence(object_a="a1", object_b="b1", score=0.9)],
    )
    graph = PoseGraph()
    assert graph.add_factor_model(factor)
    sol = graph.optimize()
    assert sol.T_anchor_frame[B].equals(T, 1e-9)
    assert links_from_factor(factor) == [ObjectLink(A, "a1", B, "b1")]
    retracted = factor.model_copy(update={"factor_id": "x2", "status": FactorStatus.RETRACTED})
    assert not graph.add_factor_model(retracted)
    assert graph.factor_ids == ["x1"]


def test_bridges_against_brute_force() -> None:
    """Tarjan on multigraphs (parallel edges are not bridges) vs. counting components."""
    rng = np.random.default_rng(10)

    def n_components(n: int, edges: list[tuple[int, int]]) -> int:
        parent = list(range(n))

        def find(i: int) -> int:
            while parent[i] != i:
                i = parent[i]
            return i

        for u, v in edges:
            parent[find(u)] = find(v)
        return len({find(i) for i in range(n)})

    for _ in range(200):
        n = int(rng.integers(1, 8))
        m = int(rng.integers(0, 10))
        edges = [tuple(int(x) for x in rng.choice(n, 2, replace=n < 2)) for _ in range(m)]
        edges = [(u, v) for u, v in edges if u != v]
        base = n_components(n, edges)
        expected = {
            e for e in range(len(edges)) if n_components(n, edges[:e] + edges[e + 1 :]) > base
        }
        assert _bridges(n, edges) == expected


def test_frame_names() -> None:
    assert frame_name("auv1", "2024-05-01") == "auv1/2024-05-01"
    assert split_frame("auv1/s/2") == ("auv1", "s/2")
    with pytest.raises(InputError):
        frame_name("a/b", "s")
    with pytest.raises(InputError):
        split_frame("nosession")


def test_config_is_validated() -> None:
    assert GraphConfig().outlier_weight == 0.5
    with pytest.raises(ValueError):
        GraphConfig(inlier_probability=1.5)


# --------------------------------------------------------------------------------------------
# Object fusion
# --------------------------------------------------------------------------------------------


def arrays(ids, positions, embeddings, variances, n_obs) -> ObjectArrays:
    return ObjectArrays(
        ids=list(ids),
        position_xyz_m=np.array(positions, dtype=float),
        embeddings_nd=np.array(embeddings, dtype=float),
        variances_nd=np.array(variances, dtype=float),
        n_obs=np.array(n_obs),
    )


# T_A_B: 90 degrees about z, then 10 m along x.
T_AB = gtsam.Pose3(gtsam.Rot3.Rz(np.pi / 2), np.array([10.0, 0.0, 0.0]))


def test_two_member_object_matches_hand_computation() -> None:
    objs = {
        A: arrays(["a1", "a2"], [[1, 2, 0], [5, 5, 5]], [[1, 0], [1, 1]], [[1, 4], [1, 1]], [1, 2]),
        B: arrays(["b1"], [[1, 0, 0]], [[0, 1]], [[1, 1]], [3]),
    }
    poses = {A: gtsam.Pose3(), B: T_AB}
    fused = fuse_objects(objs, poses, [(A, "a1", B, "b1")])
    assert [o.id for o in fused.objects] == ["A/s0/a1", "A/s0/a2"]
    g = fused.objects[0]
    # b1 in A: Rz(90) (1, 0, 0) + (10, 0, 0) = (10, 1, 0); n_obs-weighted: (1 a1 + 3 b1) / 4.
    np.testing.assert_allclose(g.position, [7.75, 1.25, 0.0], atol=1e-12)
    # var = 1 / (1/var_a + 1/var_b) = (1/2, 4/5); mean = var (mu_a / var_a + mu_b / var_b).
    np.testing.assert_allclose(g.variance, [0.5, 0.8], atol=1e-12)
    np.testing.assert_allclose(g.embedding, [0.5, 0.8], atol=1e-12)
    assert g.n_obs == 4
    assert fused.members["A/s0/a1"] == [(A, "a1"), (B, "b1")]
    assert fused.member_of[(B, "b1")] == "A/s0/a1"
    single = fused.objects[1]
    assert single.variance == 1.0 and single.n_obs == 2 and single.position == (5.0, 5.0, 5.0)
    assert fused.conflicts == []
    assert fused.to_object_map().dim == 2


def test_union_find_chains_links_into_one_object() -> None:
    rng = np.random.default_rng(11)
    T_AC = random_pose(rng)
    p_true = np.array([3.0, -2.0, 1.0])  # one physical object, seen by three robots
    frames = {A: gtsam.Pose3(), B: T_AB, C: T_AC}
    objs = {}
    for f, T in frames.items():
        p_local = T.transformTo(p_true)
        oid = f[0].lower() + "1"
        objs[f] = arrays(
            [oid, oid + "x"], [p_local, [0, 0, 0]], [[1, 0], [0, 1]], [[2, 2]] * 2, [1, 1]
        )
    links = [(A, "a1", B, "b1"), ObjectLink(B, "b1", C, "c1")]
    fused = fuse_objects(objs, frames, links)
    assert len(fused.objects) == 4  # one fused object + three singletons
    g = fused.objects[0]
    assert fused.members[g.id] == [(A, "a1"), (B, "b1"), (C, "c1")]
    np.testing.assert_allclose(g.position, p_true, atol=1e-9)
    np.testing.assert_allclose(g.variance, 2 / 3, rtol=1e-12)
    assert g.n_obs == 3
    # The same result in any link order (union-find and the Gaussian product are commutative).
    again = fuse_objects(objs, frames, links[::-1])
    assert [o.model_dump() for o in again.objects] == [o.model_dump() for o in fused.objects]


def test_fusion_skips_unaligned_frames_reports_conflicts_and_keeps_labels() -> None:
    def node(oid: str, label: str | None) -> ObjectNode:
        return ObjectNode(
            id=oid, position=(0, 0, 0), embedding=[1.0, 0.0], variance=1.0, label=label
        )

    objs = {
        A: ObjectMap(
            robot_id="A", session_id="s0", objects=[node("a1", "chair"), node("a2", None)]
        ),
        B: ObjectMap(robot_id="B", session_id="s0", objects=[node("b1", "chair")]),
        D: ObjectMap(robot_id="D", session_id="s0", objects=[node("d1", "table")]),
    }
    poses = {A: gtsam.Pose3(), B: T_AB}  # D is not aligned
    links = [(A, "a1", B, "b1"), (B, "b1", A, "a2"), (A, "a1", D, "d1")]
    fused = fuse_objects(objs, poses, links)
    # Lists of ObjectNode and (4, 4) poses are accepted too, with the same result.
    as_lists = {f: list(m.objects) for f, m in objs.items()}
    same = fuse_objects(as_lists, {f: T.matrix() for f, T in poses.items()}, links)
    assert same == fused
    assert len(fused.objects) == 1
    assert fused.objects[0].label == "chair"
    assert fused.conflicts == ["A/s0/a1"]  # a1 and a2 were two objects in A's own map
    assert (D, "d1") not in fused.member_of
    with pytest.raises(InputError, match="no object"):
        fuse_objects(objs, poses, [(A, "zz", B, "b1")])


def test_wire_quaternion_is_normalised() -> None:
    """The wire accepts |q| within 1e-3 of 1; the rotation built from it must be orthonormal."""
    q = np.array([0.9, 0.1, -0.3, 0.2])
    T = pose3_from_transform([1.0, 2.0, 3.0], 1.0009 * q / np.linalg.norm(q))
    R = T.rotation().matrix()
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    with pytest.raises(InputError):
        pose3_from_transform([0, 0, 0], [0, 0, 0, 0])


# --------------------------------------------------------------------------------------------
# Keyframe nodes: odometry chains as known inliers (the service's multi-robot pose graph)
# --------------------------------------------------------------------------------------------


def chains(rng: np.random.Generator, n: int = 8,
           odo_scale: float = 1.0) -> tuple[PoseGraph, dict[str, gtsam.Pose3]]:
    """Two sessions A, B of n keyframes each ("A/s0#k"), joined by noisy odometry added as
    known inliers (covariance times odo_scale); returns the graph and the true pose of every
    keyframe (world frame)."""
    graph = PoseGraph(anchor=f"{A}#0")
    truth = {}
    odo_cov = np.diag([1e-4] * 3 + [4e-3] * 3) * odo_scale
    for s, start in ((A, random_pose(rng)), (B, random_pose(rng))):
        truth[f"{s}#0"] = start
        for k in range(1, n):
            step = gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.array([2.0, 0.0, 0.0]))
            truth[f"{s}#{k}"] = truth[f"{s}#{k - 1}"].compose(step)
            meas = step.compose(gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), odo_cov)))
            assert graph.add_factor(f"odom:{s}#{k - 1}-{k}", f"{s}#{k - 1}", f"{s}#{k}", meas,
                                    odo_cov, known_inlier=True)
    return graph, truth


def closure(rng, truth, a: str, b: str, wrong: bool = False) -> tuple[gtsam.Pose3, np.ndarray]:
    cov = random_covariance(rng)
    T = truth[a].between(truth[b]).compose(
        gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), cov)))
    return (gross_error(T) if wrong else T), cov


@pytest.mark.parametrize("seed", range(3))
def test_a_wrong_closure_between_chains_is_confirmed_by_two_others(seed: int) -> None:
    """A wrong closure between two odometry chains, with two correct ones elsewhere along them:
    the chains' tails are bridges, so without contracting the known-inlier odometry the wrong
    closure's ends would never be 2-edge-connected and it could only be ambiguous. Odometry is
    never weighed."""
    rng = np.random.default_rng(20 + seed)
    graph, truth = chains(rng)
    graph.add_factor("c1", f"{A}#1", f"{B}#2", *closure(rng, truth, f"{A}#1", f"{B}#2"))
    graph.add_factor("c2", f"{A}#4", f"{B}#5", *closure(rng, truth, f"{A}#4", f"{B}#5"))
    graph.add_factor("wrong", f"{A}#7", f"{B}#0",
                     *closure(rng, truth, f"{A}#7", f"{B}#0", wrong=True))
    sol = graph.optimize()
    assert sol.gnc_ran
    assert sol.outlier_factor_ids == ["wrong"]
    assert sol.ambiguous_factor_ids == []
    odometry = [f for f in graph.factor_ids if f.startswith("odom:")]
    assert all(sol.weights[f] == 1.0 for f in odometry)
    assert set(odometry) <= set(sol.inlier_factor_ids)
    T0_inv = truth[f"{A}#0"].inverse()
    for node, T in sol.T_anchor_frame.items():
        _, trans_err = pose_error(T, T0_inv.compose(truth[node]))
        assert trans_err < 1.5, node  # up to 14 m of noisy odometry from the closures


def test_one_closure_against_one_other_between_chains_is_ambiguous() -> None:
    rng = np.random.default_rng(30)
    graph, truth = chains(rng)
    graph.add_factor("c1", f"{A}#1", f"{B}#2", *closure(rng, truth, f"{A}#1", f"{B}#2"))
    graph.add_factor("wrong", f"{A}#6", f"{B}#0",
                     *closure(rng, truth, f"{A}#6", f"{B}#0", wrong=True))
    sol = graph.optimize()
    assert sol.outlier_factor_ids == []
    assert set(sol.ambiguous_factor_ids) <= {"c1", "wrong"} and sol.ambiguous_factor_ids


def test_a_closure_contradicting_known_inliers_alone_is_an_outlier() -> None:
    """A flagged factor whose two nodes are joined by known inliers alone (here: one chain)
    contradicts what cannot be wrong: a confirmed outlier."""
    rng = np.random.default_rng(31)
    graph, truth = chains(rng)
    graph.add_factor("c1", f"{A}#1", f"{B}#2", *closure(rng, truth, f"{A}#1", f"{B}#2"))
    graph.add_factor("c2", f"{A}#4", f"{B}#5", *closure(rng, truth, f"{A}#4", f"{B}#5"))
    T = gross_error(truth[f"{A}#2"].between(truth[f"{A}#6"]))
    graph.add_factor("self", f"{A}#2", f"{A}#6", T, random_covariance(rng))
    sol = graph.optimize()
    assert "self" in sol.outlier_factor_ids


def test_optimize_returns_the_last_solution_while_nothing_changed() -> None:
    world = World(12)
    graph = redundant_graph(world)
    rev = graph.revision
    sol = graph.optimize()
    assert graph.optimize() is sol and graph.revision == rev
    assert graph.optimize(marginals=False) is not sol  # another request
    light = graph.optimize(marginals=False)
    assert light.covariance_66 == {} and light.marginals_error is None
    for T_a, T_b in zip(light.T_anchor_frame.values(), sol.T_anchor_frame.values()):
        assert T_a.equals(T_b, 1e-9)
    T, cov = world.measure(A, B)
    graph.add_factor("AB9", A, B, T, cov)
    assert graph.revision > rev
    again = graph.optimize()
    assert again is not sol and "AB9" in again.weights
    assert graph.optimize() is again
    assert not graph.add_factor("AB9", A, B, T, cov)  # a replay changes nothing
    assert graph.optimize() is again
    assert graph.remove_factor("AB9")
    assert graph.optimize() is not again
    graph.add_frame(F)
    graph.anchor = B
    assert graph.optimize().anchor == B


def test_wire_factor_with_keyframes_ties_keyframe_nodes() -> None:
    rng = np.random.default_rng(13)
    T = random_pose(rng)
    q = T.rotation().toQuaternion()
    base = dict(
        robot_a="A", session_a="s0", robot_b="B", session_b="s0",
        T_a_b=Transform(translation=tuple(T.translation()),
                        quaternion_wxyz=(q.w(), q.x(), q.y(), q.z())),
        covariance=random_covariance(rng).tolist(),
    )
    graph = PoseGraph()
    assert graph.add_factor_model(Factor(factor_id="k", keyframe_a=3, keyframe_b=7, **base))
    assert graph.factor_nodes("k") == (f"{A}#3", f"{B}#7", False)
    assert graph.add_factor_model(Factor(factor_id="f", **base), keyframe_nodes=True)
    assert graph.factor_nodes("f") == (f"{A}#0", f"{B}#0", False)
    assert graph.add_factor_model(Factor(factor_id="g", **base))
    assert graph.factor_nodes("g") == (A, B, False)
    assert graph.add_factor_model(
        Factor(factor_id="h", keyframe_a=3, keyframe_b=7, **base), keyframe_nodes=False,
        known_inlier=True)
    assert graph.factor_nodes("h") == (A, B, True)
    assert graph.nodes == graph.frames == [f"{A}#3", f"{B}#7", f"{A}#0", f"{B}#0", A, B]
    assert graph.has_node(f"{A}#3") and not graph.has_node(f"{A}#4")
    with pytest.raises(InputError):
        graph.factor_nodes("nope")


def test_fusion_over_keyframe_nodes_names_objects_by_session() -> None:
    """Keys may be keyframe nodes: global ids and conflicts go by the session (frame_of)."""
    objs = {
        f"{A}#0": arrays(["a1"], [[1, 0, 0]], [[1, 0]], [[1, 1]], [1]),
        f"{A}#5": arrays(["a2"], [[0, 0, 0]], [[1, 0]], [[1, 1]], [1]),
        f"{B}#2": arrays(["b1"], [[0, 0, 0]], [[1, 0]], [[1, 1]], [1]),
    }
    poses = {f"{A}#0": gtsam.Pose3(), f"{A}#5": gtsam.Pose3(gtsam.Rot3(), np.array([5.0, 0, 0])),
             f"{B}#2": gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0, 0]))}
    frame_of = {f"{A}#0": A, f"{A}#5": A, f"{B}#2": B}
    fused = fuse_objects(objs, poses, [(f"{A}#0", "a1", f"{B}#2", "b1")], frame_of=frame_of)
    assert [o.id for o in fused.objects] == [f"{A}/a1", f"{A}/a2"]
    np.testing.assert_allclose(fused.objects[0].position, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(fused.objects[1].position, [5, 0, 0], atol=1e-12)
    assert fused.members[f"{A}/a1"] == [(f"{A}#0", "a1"), (f"{B}#2", "b1")]
    assert fused.conflicts == []
    joined = fuse_objects(objs, poses, [(f"{A}#0", "a1", f"{A}#5", "a2")], frame_of=frame_of)
    assert joined.conflicts == [f"{A}/a1"]  # two objects of session A
    plain = fuse_objects(objs, poses, [(f"{A}#0", "a1", f"{A}#5", "a2")])
    assert plain.conflicts == [] and plain.objects[0].id == f"{A}#0/a1"


@pytest.mark.parametrize("seed", range(3))
def test_a_warm_started_solve_converges_where_a_cold_one_does(seed: int) -> None:
    """Each solve starts from the last solution (new nodes chained from their neighbours): the
    graph built and solved step by step (closures, a wrong one, a new session's chain, the wrong
    one retracted) ends at every step where a cold solve of the same factors does, with the same
    verdicts."""
    rng = np.random.default_rng(40 + seed)
    graph, truth = chains(rng)
    cold_cfg = GraphConfig(warm_start=False)
    steps = [("c1", f"{A}#1", f"{B}#2", False), ("wrong", f"{A}#7", f"{B}#0", True),
             ("c2", f"{A}#4", f"{B}#5", False), ("c3", f"{A}#6", f"{B}#6", False)]
    done: list[tuple[str, str, str, gtsam.Pose3, np.ndarray, bool]] = []
    for fid in graph.factor_ids:
        a, b, _ = graph.factor_nodes(fid)
        f = graph._factors[fid]
        done.append((fid, a, b, f.T_a_b, f.covariance_66, True))
    for fid, a, b, wrong in steps:
        T, C = closure(rng, truth, a, b, wrong=wrong)
        done.append((fid, a, b, T, C, False))
    # a third chain joins late: its nodes are new to the warm start
    start = random_pose(rng)
    truth["C/s0#0"] = start
    for k in range(1, 5):
        step = gtsam.Pose3(gtsam.Rot3.Rz(-0.2), np.array([1.5, 0.0, 0.0]))
        truth[f"C/s0#{k}"] = truth[f"C/s0#{k - 1}"].compose(step)
        done.append((f"odom:C#{k}", f"C/s0#{k - 1}", f"C/s0#{k}", step, np.eye(6) * 1e-4, True))
    for fid, a, b in (("d1", f"{B}#3", "C/s0#1"), ("d2", f"{A}#5", "C/s0#3")):
        T, C = closure(rng, truth, a, b)
        done.append((fid, a, b, T, C, False))

    # replay step by step: solve warm after each change, compare with a cold twin
    warm = PoseGraph(anchor=graph.anchor)
    checked = 0
    for k, (fid, a, b, T, C, known) in enumerate(done):
        warm.add_factor(fid, a, b, T, C, known_inlier=known)
        if known:
            continue
        sol = warm.optimize(marginals=False)
        twin = PoseGraph(anchor=graph.anchor, config=cold_cfg)
        for item in done[: k + 1]:
            twin.add_factor(item[0], item[1], item[2], item[3], item[4], known_inlier=item[5])
        ref = twin.optimize(marginals=False)
        assert (sol.outlier_factor_ids, sol.ambiguous_factor_ids) == (
            ref.outlier_factor_ids, ref.ambiguous_factor_ids), fid
        for node, T_ref in ref.T_anchor_frame.items():
            rot, trans = pose_error(sol.T_anchor_frame[node], T_ref)
            assert rot < 1e-3 and trans < 1e-3, (fid, node, rot, trans)
        checked += 1
    assert checked == 6
    assert "wrong" in warm.optimize(marginals=False).outlier_factor_ids
    warm.remove_factor("wrong")
    sol = warm.optimize(marginals=False)
    twin = PoseGraph(anchor=graph.anchor, config=cold_cfg)
    for item in done:
        if item[0] != "wrong":
            twin.add_factor(item[0], item[1], item[2], item[3], item[4], known_inlier=item[5])
    ref = twin.optimize(marginals=False)
    assert sol.outlier_factor_ids == ref.outlier_factor_ids == []
    for node, T_ref in ref.T_anchor_frame.items():
        rot, trans = pose_error(sol.T_anchor_frame[node], T_ref)
        assert rot < 1e-3 and trans < 1e-3, (node, rot, trans)


def test_the_next_solve_starts_from_the_last_solution() -> None:
    """The start of a solve: last solution's poses for the nodes it placed (same anchor), the
    chain from a neighbour for new ones; with warm_start=False, the chain for all."""
    rng = np.random.default_rng(50)
    graph, truth = chains(rng)
    graph.add_factor("c1", f"{A}#1", f"{B}#2", *closure(rng, truth, f"{A}#1", f"{B}#2"))
    graph.add_factor("c2", f"{A}#4", f"{B}#5", *closure(rng, truth, f"{A}#4", f"{B}#5"))
    last = graph.optimize(marginals=False).T_anchor_frame
    T_new = gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0.0, 0.0]))
    graph.add_factor("odom:new", f"{B}#7", "B/s0#8", T_new, np.eye(6) * 1e-4, known_inlier=True)
    for warm in (True, False):
        graph.config = GraphConfig(warm_start=warm)
        comp = graph.components()[0]
        facs = list(graph._factors.values())
        start = graph._initial_values(graph.anchor, {graph.anchor: gtsam.Pose3()}, comp, facs)
        moved = [pose_error(start.atPose3(graph.key(n)), T)[1] for n, T in last.items()]
        assert (max(moved) < 1e-12) == warm, (warm, max(moved))
        expected = start.atPose3(graph.key(f"{B}#7")).compose(T_new)
        assert pose_error(start.atPose3(graph.key("B/s0#8")), expected)[1] < 1e-9
    # a removed factor may have pulled the last poses: the next solve starts cold, then warm
    graph.config = GraphConfig()
    graph.optimize(marginals=False)
    graph.remove_factor("c2")
    comp, facs = graph.components()[0], list(graph._factors.values())
    chained = graph._initial_values(graph.anchor, {graph.anchor: gtsam.Pose3()}, comp, facs)
    graph.config = GraphConfig(warm_start=False)
    cold = graph._initial_values(graph.anchor, {graph.anchor: gtsam.Pose3()}, comp, facs)
    assert all(pose_error(chained.atPose3(graph.key(n)), cold.atPose3(graph.key(n)))[1] < 1e-12
               for n in comp)
    graph.config = GraphConfig()
    last = graph.optimize(marginals=False).T_anchor_frame
    start = graph._initial_values(graph.anchor, {graph.anchor: gtsam.Pose3()}, comp, facs)
    assert max(pose_error(start.atPose3(graph.key(n)), T)[1] for n, T in last.items()) < 1e-12


@pytest.mark.parametrize("seed", range(4))
def test_the_least_squares_gate_keeps_gncs_verdicts(seed: int) -> None:
    """Least squares first, GNC only when a factor to judge leaves the TLS threshold there:
    built step by step (correct closures, then a wrong one, more closures, the wrong one
    retracted), every solve ends where GNC on every solve (gate off, cold start: the pipeline
    before the gate) does, with the same verdicts; the gate skips GNC while every closure is
    correct and never while the wrong one is in the graph."""
    rng = np.random.default_rng(60 + seed)
    graph, truth = chains(rng, n=10)
    items = [(fid, *graph.factor_nodes(fid)[:2], graph._factors[fid].T_a_b,
              graph._factors[fid].covariance_66, True) for fid in graph.factor_ids]
    pairs = [(f"{A}#{i}", f"{B}#{j}") for i, j in rng.integers(0, 10, size=(8, 2))]
    for k, (a, b) in enumerate(pairs[:4]):
        items.append((f"c{k}", a, b, *closure(rng, truth, a, b), False))
    items.append(("wrong", f"{A}#9", f"{B}#1", *closure(rng, truth, f"{A}#9", f"{B}#1",
                                                       wrong=True), False))
    for k, (a, b) in enumerate(pairs[4:], start=4):
        items.append((f"c{k}", a, b, *closure(rng, truth, a, b), False))

    gated = PoseGraph(anchor=graph.anchor)
    skipped, judged = [], []
    def compare(sol, present) -> None:
        ref_graph = PoseGraph(anchor=graph.anchor,
                              config=GraphConfig(least_squares_gate=False, warm_start=False))
        for it in present:
            ref_graph.add_factor(it[0], it[1], it[2], it[3], it[4], known_inlier=it[5])
        ref = ref_graph.optimize(marginals=False)
        assert not ref.gnc_skipped
        assert (sol.outlier_factor_ids, sol.ambiguous_factor_ids) == (
            ref.outlier_factor_ids, ref.ambiguous_factor_ids)
        for node, T_ref in ref.T_anchor_frame.items():
            rot, trans = pose_error(sol.T_anchor_frame[node], T_ref)
            assert rot < 1e-3 and trans < 1e-3, (node, rot, trans)

    for k, it in enumerate(items):
        gated.add_factor(it[0], it[1], it[2], it[3], it[4], known_inlier=it[5])
        if it[5]:
            continue
        sol = gated.optimize(marginals=False)
        compare(sol, items[: k + 1])
        (skipped if sol.gnc_skipped else judged).append(it[0])
        if sol.gnc_skipped:
            assert sol.outlier_factor_ids == [] and sol.ambiguous_factor_ids == []
            assert min(sol.weights.values()) == 1.0
    wrong_at = [it[0] for it in items].index("wrong")
    after_wrong = [it[0] for it in items[wrong_at:] if not it[5]]
    assert not set(after_wrong) & set(skipped), "GNC skipped with a wrong closure in the graph"
    assert len(skipped) >= 2  # the first closure is a bridge (nothing judged); later ones gated
    gated.remove_factor("wrong")
    sol = gated.optimize(marginals=False)
    assert sol.gnc_skipped
    compare(sol, [it for it in items if it[0] != "wrong"])


# -- folding (rule 5) ------------------------------------------------------------------------


def _empirical_covariance(T_mean: gtsam.Pose3, samples: list[gtsam.Pose3]) -> np.ndarray:
    xi = np.array([gtsam.Pose3.Logmap(T_mean.between(T)) for T in samples])
    return np.cov(xi.T)


def _whitened_spectrum(S: np.ndarray, S_ref: np.ndarray) -> np.ndarray:
    L = np.linalg.cholesky(S)
    Li = np.linalg.inv(L)
    return np.linalg.eigvalsh(Li @ S_ref @ Li.T)


@pytest.mark.parametrize("seed", range(3))
def test_composed_and_inverted_covariances_match_monte_carlo(seed: int) -> None:
    """The first-order propagation of rule 5 against sampling: perturb T_a, T_b on the right
    by noise of their covariances, compose (or invert), and compare the spread of the result
    (in the tangent space at the noiseless result) with the propagated covariance."""
    rng = np.random.default_rng(100 + seed)
    T_a, T_b = random_pose(rng), random_pose(rng, trans_m=20.0)
    S_a, S_b = random_covariance(rng), random_covariance(rng)

    def noisy(T: gtsam.Pose3, S: np.ndarray, n: int) -> list[gtsam.Pose3]:
        xs = rng.multivariate_normal(np.zeros(6), S, n)
        return [T.compose(gtsam.Pose3.Expmap(x)) for x in xs]

    n = 4000
    T, S = _compose(T_a, S_a, T_b, S_b)
    assert T.equals(T_a.compose(T_b), 1e-12)
    emp = _empirical_covariance(
        T, [a.compose(b) for a, b in zip(noisy(T_a, S_a, n), noisy(T_b, S_b, n), strict=True)])
    assert np.all(np.abs(_whitened_spectrum(S, emp) - 1.0) < 0.12)
    # the rotation's noise seen in T_b's translation: without the adjoint it is badly off
    assert np.abs(_whitened_spectrum(S_a + S_b, emp) - 1.0).max() > 1.0

    T_i, S_i = _inverse(T_a, S_a)
    assert T_i.equals(T_a.inverse(), 1e-12)
    emp = _empirical_covariance(T_i, [a.inverse() for a in noisy(T_a, S_a, n)])
    assert np.all(np.abs(_whitened_spectrum(S_i, emp) - 1.0) < 0.12)


def _two_chains(seed: int, n: int, hops: int,
                odo_scale: float = 1e-3) -> tuple[PoseGraph, dict[str, gtsam.Pose3]]:
    """chains() with odometry far better than the closures by default (a few cm and 0.02
    degrees of drift over 10 keyframes: what folding is for)."""
    graph, truth = chains(np.random.default_rng(seed), n, odo_scale)
    graph.config = GraphConfig(fold_hops=hops)  # odometry only so far: nothing folded yet
    return graph, truth


def _closures(seed: int, truth: dict[str, gtsam.Pose3], pairs: list[tuple[int, int]],
              wrong: set[int] = frozenset()) -> list[tuple[str, str, str, gtsam.Pose3, np.ndarray]]:
    rng = np.random.default_rng(seed + 1000)
    out = []
    for i, (ka, kb) in enumerate(pairs):
        a, b = f"{A}#{ka}", f"{B}#{kb}"
        out.append((f"c{i}", a, b, *closure(rng, truth, a, b, wrong=i in wrong)))
    return out


@pytest.mark.parametrize("seed", range(3))
def test_closures_that_agree_nearby_fold_and_the_solution_stays(seed: int) -> None:
    """Two chains of 30 keyframes with a correct closure at every keyframe pair (k, k): with
    fold_hops=10 the first closure is solved and the next ten (both ends within 10 keyframes)
    fold into it, and so on; every closure is listed and weighed 1, and the poses are those of
    the graph that solves every closure (fused measurements carry what the folded ones
    measured), within a fraction of the noise."""
    graph, truth = _two_chains(40 + seed, 30, hops=10, odo_scale=1e-4)
    plain, _ = _two_chains(40 + seed, 30, hops=0, odo_scale=1e-4)
    closures = _closures(seed, truth, [(k, k) for k in range(30)])
    for c in closures:
        graph.add_factor(*c)
        plain.add_factor(*c)
    solved = [c[0] for c in closures if graph.representative(c[0]) is None]
    assert solved == ["c0", "c11", "c22"]
    assert graph.representative("c5") == "c0" and graph.representative("c12") == "c11"
    assert graph.folded_count == 27
    assert set(graph.factor_ids) == set(plain.factor_ids)
    sol, ref = graph.optimize(), plain.optimize()
    assert sol.outlier_factor_ids == ref.outlier_factor_ids == []
    assert all(sol.weights[c[0]] == 1.0 for c in closures)
    assert sol.folded["c29"] == "c22" and len(sol.folded) == 27
    T0_inv = truth[f"{A}#0"].inverse()
    worst_fold = worst_plain = worst_gap = 0.0
    for node, T in sol.T_anchor_frame.items():
        true = T0_inv.compose(truth[node])
        worst_fold = max(worst_fold, pose_error(T, true)[1])
        worst_plain = max(worst_plain, pose_error(ref.T_anchor_frame[node], true)[1])
        worst_gap = max(worst_gap, pose_error(T, ref.T_anchor_frame[node])[1])
    assert worst_gap < 0.25, worst_gap
    assert worst_fold < 1.5 * worst_plain + 0.1, (worst_fold, worst_plain)


def test_folding_only_the_representative_would_lose_its_support() -> None:
    """Nine agreeing closures and one wrong one, all between the same two stretches of the
    chains: folded, the wrong one disagrees, so it is solved against one representative; the
    fused measurement keeps the nine's weight, GNC flags the wrong one, and the folded closures
    count as parallel paths (rule 3), so it is a confirmed outlier as in the graph that solves
    them all. Its representative's closures share the representative's weight."""
    graph, truth = _two_chains(50, 12, hops=10)
    plain, _ = _two_chains(50, 12, hops=0)
    closures = _closures(50, truth, [(k, k) for k in range(9)] + [(4, 4)], wrong={9})
    for c in closures:
        graph.add_factor(*c)
        plain.add_factor(*c)
    assert graph.representative("c9") is None  # the wrong one is solved, not folded
    assert graph.folded_count == 8
    sol, ref = graph.optimize(), plain.optimize()
    assert ref.outlier_factor_ids == ["c9"]
    assert sol.outlier_factor_ids == ["c9"]
    assert all(sol.weights[f"c{i}"] == sol.weights["c0"] > 0.5 for i in range(9))


def test_a_wrong_representatives_folded_closures_are_judged_on_their_own() -> None:
    """A wrong closure solved first, then one that agrees with it (wrong the same way) folds
    into it; correct closures along the chains contradict both: the wrong closure is a
    confirmed outlier, reported alone. Removing it sends the folded one back to the graph,
    where it is solved (nothing near agrees with it) and judged on its own: an outlier too."""
    graph, truth = _two_chains(60, 30, hops=3)
    rng = np.random.default_rng(61)
    T, cov = closure(rng, truth, f"{A}#2", f"{B}#2", wrong=True)
    graph.add_factor("wrong", f"{A}#2", f"{B}#2", T, cov)
    odo = truth[f"{B}#2"].between(truth[f"{B}#3"])  # the same gross error, one keyframe on
    graph.add_factor("also", f"{A}#2", f"{B}#3", T.compose(odo), cov)
    for k in (10, 20, 28):
        graph.add_factor(f"ok{k}", f"{A}#{k}", f"{B}#{k}",
                         *closure(rng, truth, f"{A}#{k}", f"{B}#{k}"))
    assert graph.representative("also") == "wrong"
    sol = graph.optimize()
    assert sol.outlier_factor_ids == ["wrong"]
    assert sol.weights["also"] == sol.weights["wrong"] < 0.5
    assert graph.remove_factor("wrong")
    assert graph.representative("also") is None
    assert "also" in graph.optimize().outlier_factor_ids
    assert graph.remove_factor("also") and graph.folded_count == 0
    assert graph.optimize().outlier_factor_ids == []


def test_removing_a_folded_factor_restores_the_representatives_measurement() -> None:
    graph, truth = _two_chains(70, 6, hops=5)
    closures = _closures(70, truth, [(1, 1), (2, 2)])
    graph.add_factor(*closures[0])
    own_T, own_C = closures[0][3], 0.5 * (closures[0][4] + closures[0][4].T)
    graph.add_factor(*closures[1])
    assert graph.representative("c1") == "c0"
    fused = graph._measurement(graph._factors["c0"])
    assert not fused[0].equals(own_T, 1e-6)
    assert np.linalg.det(fused[1]) < np.linalg.det(own_C)  # more information
    assert graph.remove_factor("c1") and not graph.remove_factor("c1")
    after = graph._measurement(graph._factors["c0"])
    assert after[0].equals(own_T, 0.0) and np.array_equal(after[1], own_C)
    with pytest.raises(InputError, match="unknown factor"):
        graph.representative("c1")


def test_closures_that_correct_the_odometry_are_not_folded() -> None:
    """Where the odometry between two closures' ends is about as uncertain as a closure
    (chains()' own odometry: 0.01 rad a keyframe), a closure corrects the drift: nothing folds,
    however close (fold_drift); better odometry folds them."""
    for odo_scale, folded in ((1.0, 0), (1e-3, 8)):
        graph, truth = _two_chains(80, 10, hops=10, odo_scale=odo_scale)
        for c in _closures(80, truth, [(k, k) for k in range(9)]):
            graph.add_factor(*c)
        assert graph.folded_count == folded, odo_scale


@pytest.mark.parametrize("seed", range(3))
def test_fused_measurement_is_gtsams_least_squares_of_the_parallel_factors(seed: int) -> None:
    """The reference for rule 5's fusion: GTSAM solving the measurements as parallel factors
    between a fixed node and a free one (the pose graph's own form; the fusion solves them as
    priors on one pose) gives the fused pose (the mean) and, as the free node's marginal, the
    fused covariance."""
    rng = np.random.default_rng(200 + seed)
    T_true = random_pose(rng)
    items = []
    for _ in range(int(rng.integers(2, 7))):
        C = random_covariance(rng) * rng.uniform(0.3, 3.0)
        items.append((T_true.compose(gtsam.Pose3.Expmap(
            rng.multivariate_normal(np.zeros(6), C))), C))
    T, C = _fuse(items)
    graph = gtsam.NonlinearFactorGraph()
    x0, x1 = gtsam.symbol("x", 0), gtsam.symbol("x", 1)
    graph.add(gtsam.NonlinearEqualityPose3(x0, gtsam.Pose3()))
    for Ti, Ci in items:
        graph.add(gtsam.BetweenFactorPose3(x0, x1, Ti,
                                           gtsam.noiseModel.Gaussian.Covariance(Ci)))
    init = gtsam.Values()
    init.insert(x0, gtsam.Pose3())
    init.insert(x1, items[0][0])
    est = gtsam.LevenbergMarquardtOptimizer(graph, init).optimize()
    assert T.equals(est.atPose3(x1), 1e-9)
    marg = gtsam.Marginals(graph, est).marginalCovariance(x1)
    np.testing.assert_allclose(C, marg, rtol=1e-6, atol=1e-12)


def test_a_folded_measurement_is_packed_without_loss() -> None:
    rng = np.random.default_rng(210)
    T, C = random_pose(rng), random_covariance(rng)
    C = 0.5 * (C + C.T)  # as the graph holds it
    T2, C2 = _unpack(_pack(T, C))
    assert T2.equals(T, 1e-14)
    np.testing.assert_array_equal(C2, C)


def test_a_folded_factor_is_replayed_refused_and_survives_its_odometry() -> None:
    """The same folded factor again is a no-op, another one under its id is refused; removing
    the odometry a folded factor was carried along sends it back to the graph."""
    graph, truth = _two_chains(90, 8, hops=5)
    closures = _closures(90, truth, [(1, 1), (3, 3)])
    for c in closures:
        graph.add_factor(*c)
    assert graph.representative("c1") == "c0"
    assert not graph.add_factor(*closures[1])
    with pytest.raises(InputError, match="different factor"):
        graph.add_factor("c1", closures[1][1], closures[1][2], gross_error(closures[1][3]),
                         closures[1][4])
    assert graph.factor_nodes("c1") == (f"{A}#3", f"{B}#3", False)
    assert graph.remove_factor(f"odom:{B}#1-2")  # c1's path from B#3 back to B#1 is cut
    assert graph.representative("c1") is None and graph.folded_count == 0
    assert set(graph.optimize().weights) >= {"c0", "c1"}


def test_folding_reads_factors_in_either_direction() -> None:
    """Closures stored A -> B and B -> A (the representative itself B -> A): they fold all the
    same, and the poses are those of the graph that solves them all, as in one direction."""
    graph, truth = _two_chains(95, 12, hops=10, odo_scale=1e-4)
    plain, _ = _two_chains(95, 12, hops=0, odo_scale=1e-4)
    for i, (fid, a, b, T, C) in enumerate(_closures(95, truth, [(k, k) for k in range(10)])):
        if i % 2 == 0:  # stored the other way: T_b_a with its covariance
            fid, a, b, (T, C) = fid, b, a, _inverse(T, C)
        graph.add_factor(fid, a, b, T, C)
        plain.add_factor(fid, a, b, T, C)
    assert graph.factor_nodes("c0") == (f"{B}#0", f"{A}#0", False)
    assert graph.folded_count == 9
    assert all(graph.representative(f"c{i}") == "c0" for i in range(1, 10))
    sol, ref = graph.optimize(), plain.optimize()
    worst_gap = max(pose_error(T, ref.T_anchor_frame[n])[1] for n, T in sol.T_anchor_frame.items())
    assert worst_gap < 0.1, worst_gap


def test_removing_a_representative_folds_the_rest_into_the_first_of_them() -> None:
    graph, truth = _two_chains(97, 8, hops=5, odo_scale=1e-4)
    for c in _closures(97, truth, [(k, k) for k in range(4)]):
        graph.add_factor(*c)
    assert [graph.representative(f"c{i}") for i in range(4)] == [None, "c0", "c0", "c0"]
    assert graph.remove_factor("c0")
    assert [graph.representative(f"c{i}") for i in (1, 2, 3)] == [None, "c1", "c1"]
    assert set(graph._fused) == {"c1"} and set(graph._deps) == {"c1"}
    assert graph.remove_factor("c2") and graph._deps == {"c1": ["c3"]}
    assert graph.remove_factor("c3") and graph._deps == {} and graph._fused == {}
    assert set(graph.optimize().weights) >= {"c1"}


def _fold_state(graph: PoseGraph) -> tuple:
    """What remove_factor may change: the factors, where each is folded, the fused measurements."""
    return (graph.revision, graph.factor_ids, [graph.representative(f) for f in graph.factor_ids],
            {r: (T.matrix().tolist(), C.tolist()) for r, (T, C) in graph._fused.items()})


def test_a_removal_that_fails_half_way_changes_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    """remove_factor raising leaves the graph as it was: a folded factor (its representative's
    measurement fused again), a representative (its folded ones folded again into the first of
    them) and the odometry they were carried along (every folded one judged again), each while
    the fusion fails; then each goes as it should."""
    import mergesvc.core.folding as folding

    graph, truth = _two_chains(97, 8, hops=5, odo_scale=1e-4)
    for c in _closures(97, truth, [(k, k) for k in range(4)]):
        graph.add_factor(*c)
    assert graph._deps == {"c0": ["c1", "c2", "c3"]}
    before = _fold_state(graph)

    def failing(items: Sequence[tuple[gtsam.Pose3, np.ndarray]]) -> Any:
        raise SolverError("fusion optimisation failed: (the test)")

    monkeypatch.setattr(folding, "_fuse", failing)
    for fid in ("c2", "c0", f"odom:{B}#1-2"):
        with pytest.raises(SolverError, match="the test"):
            graph.remove_factor(fid)
        assert _fold_state(graph) == before, fid
    monkeypatch.undo()
    assert graph.remove_factor("c2") and graph._deps == {"c0": ["c1", "c3"]}
    assert graph.remove_factor("c0")
    assert [graph.representative(f) for f in ("c1", "c3")] == [None, "c1"]
    assert graph.remove_factor(f"odom:{B}#1-2")  # c3's path back to B#1 is cut: solved
    assert graph.folded_count == 0 and "c3" in graph.optimize().weights


# -- rule 6: freezing ------------------------------------------------------------------------

STEP = gtsam.Pose3(gtsam.Rot3.Rz(0.2), np.array([2.0, 0.0, 0.0]))
ODO_COV = np.diag([1e-4] * 3 + [4e-3] * 3)
# what each graph was given (a sealed factor's measurement is not held by the graph, rule 6)
MEASURED: weakref.WeakKeyDictionary[PoseGraph, dict[str, tuple]] = weakref.WeakKeyDictionary()


def add(graph: PoseGraph, fid: str, a: str, b: str, T: gtsam.Pose3, C: np.ndarray,
        known_inlier: bool = False) -> bool:
    MEASURED.setdefault(graph, {})[fid] = (a, b, T, C, known_inlier)
    return graph.add_factor(fid, a, b, T, C, known_inlier=known_inlier)


def copy_into(graph: PoseGraph, source: PoseGraph, ids: Sequence[str]) -> None:
    for fid in ids:
        a, b, T, C, known = MEASURED[source][fid]
        add(graph, fid, a, b, T, C, known)


def grow(graph: PoseGraph, rng: np.random.Generator, truth: dict[str, gtsam.Pose3], k: int,
         closures: bool = True) -> None:
    """Step k of two sessions A and B driving side by side: keyframe k of each (noisy odometry
    from k - 1, a known inlier) and a closure A#k - B#k (and A#k - B#k-1)."""
    for s, start in ((A, gtsam.Pose3()), (B, gtsam.Pose3(gtsam.Rot3(), np.array([0, 3.0, 0])))):
        node = f"{s}#{k}"
        if k == 0:
            truth[node] = start
            graph.add_frame(node)
            continue
        truth[node] = truth[f"{s}#{k - 1}"].compose(STEP)
        meas = STEP.compose(gtsam.Pose3.Expmap(rng.multivariate_normal(np.zeros(6), ODO_COV)))
        add(graph, f"odom:{s}#{k}", f"{s}#{k - 1}", node, meas, ODO_COV, known_inlier=True)
    if closures:
        add(graph, f"c{k}", f"{A}#{k}", f"{B}#{k}", *closure(rng, truth, f"{A}#{k}", f"{B}#{k}"))
        if k:
            add(graph, f"d{k}", f"{A}#{k}", f"{B}#{k - 1}",
                *closure(rng, truth, f"{A}#{k}", f"{B}#{k - 1}"))


def driven(seed: int, cap: int, steps: int, *, solve: bool = True,
           closures: Callable[[int], bool] = lambda k: True,
           **config: Any) -> tuple[PoseGraph, dict[str, gtsam.Pose3], np.random.Generator]:
    """A graph of `steps` grow() steps with max_live_nodes=cap (and `config`), solved after
    each step unless solve=False; returns it, the truth and the random generator."""
    rng = np.random.default_rng(seed)
    graph = PoseGraph(anchor=f"{A}#0", config=GraphConfig(max_live_nodes=cap, **config))
    truth: dict[str, gtsam.Pose3] = {}
    for k in range(steps):
        grow(graph, rng, truth, k, closures=closures(k))
        if solve:
            graph.optimize(marginals=False)
    return graph, truth, rng


def least_squares_with_fixed(graph: PoseGraph, fixed: dict[str, gtsam.Pose3],
                             truth: dict[str, gtsam.Pose3]) -> dict[str, gtsam.Pose3]:
    """Reference for rule 6: plain GTSAM least squares over every node and factor of the graph,
    the anchor and the `fixed` nodes held by tight priors, started from the truth."""
    g = gtsam.NonlinearFactorGraph()
    tight = gtsam.noiseModel.Isotropic.Sigma(6, 1e-7)
    g.add(gtsam.PriorFactorPose3(graph.key(graph.anchor), gtsam.Pose3(), tight))
    for n, T in fixed.items():
        g.add(gtsam.PriorFactorPose3(graph.key(n), T, tight))
    for fid in graph.factor_ids:
        a, b, T, C, _ = MEASURED[graph][fid]
        g.add(gtsam.BetweenFactorPose3(graph.key(a), graph.key(b), T,
                                       gtsam.noiseModel.Gaussian.Covariance(C)))
    values = gtsam.Values()
    for n in graph.nodes:
        values.insert(graph.key(n), truth[n])
    est = gtsam.LevenbergMarquardtOptimizer(g, values, gtsam.LevenbergMarquardtParams()).optimize()
    return {n: est.atPose3(graph.key(n)) for n in graph.nodes}


def solve_sizes(monkeypatch: pytest.MonkeyPatch, *graphs: PoseGraph) -> list[int]:
    """The number of poses each least-squares solve of core.graph holds (recorded), in the
    graphs made from now on and in `graphs`."""
    import mergesvc.core.graph as core_graph

    sizes: list[int] = []
    real = core_graph.run_job

    def recording(job: SolveJob) -> SolveResult:
        if job.gnc_known is None:
            sizes.append(len(job.initial_keys))
        return real(job)

    monkeypatch.setattr(core_graph, "run_job", recording)  # graphs made from now on use it
    for g in graphs:
        g.optimizer = recording
    return sizes


@pytest.mark.parametrize("seed", range(2))
def test_frozen_nodes_keep_their_poses_and_the_rest_is_least_squares_with_them_fixed(
        seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """A graph growing by two keyframes a step, solved after each step with max_live_nodes=10:
    the oldest nodes freeze; a frozen node keeps its pose from then on, every other node is
    where plain least squares over the whole graph puts it with the frozen ones held fixed, and
    no solve holds more than the live nodes and the frozen ones their factors touch."""
    cap, steps = 10, 25
    sizes = solve_sizes(monkeypatch)
    rng = np.random.default_rng(600 + seed)
    graph = PoseGraph(anchor=f"{A}#0", config=GraphConfig(max_live_nodes=cap))
    truth: dict[str, gtsam.Pose3] = {}
    for k in range(steps):
        grow(graph, rng, truth, k)
        before = dict(graph._frozen)
        sol = graph.optimize(marginals=False)
        assert sol.frozen_nodes == len(before)
        for n, T in before.items():
            assert sol.T_anchor_frame[n].equals(T, 0.0), n
        ref = least_squares_with_fixed(graph, before, truth)
        for n, T in sol.T_anchor_frame.items():
            rot, trans = pose_error(T, ref[n])
            assert rot < 1e-6 and trans < 1e-5, (k, n, rot, trans)
        assert set(sol.weights) == set(graph.factor_ids)  # the frozen part's verdicts kept
        assert sol.outlier_factor_ids == [] and sol.ambiguous_factor_ids == []
    assert graph.frozen_count == 2 * steps - cap
    assert "c0" in graph._sealed and graph._factors["c0"].T_a_b is None  # not held any more
    assert not add(graph, "c0", *MEASURED[graph]["c0"][:4])  # a replay: a no-op
    assert max(sizes) <= cap + 2 + 3  # the live nodes, the new ones, frozen neighbours
    assert len(graph.nodes) > 3 * max(sizes)
    # the same graph without freezing: every node moves with every closure
    whole = least_squares_with_fixed(graph, {}, truth)
    moved = max(pose_error(sol.T_anchor_frame[n], whole[n])[1] for n in before)
    assert moved > 1e-4  # freezing is not free: what it gives up is measurable


def test_a_wrong_closure_to_the_frozen_part_is_confirmed_and_the_others_stay() -> None:
    """Rule 3 counts the frozen part's closures: a wrong closure from a live keyframe back to a
    frozen one is joined twice over by the closures on either side (frozen and live), so it is
    a confirmed outlier; removing it keeps the frozen poses."""
    graph, truth, rng = driven(610, 8, 20)
    assert f"{A}#2" in graph._frozen and f"{B}#19" not in graph._frozen
    frozen = dict(graph._frozen)
    graph.add_factor("wrong", f"{A}#2", f"{B}#19",
                     *closure(rng, truth, f"{A}#2", f"{B}#19", wrong=True))
    sol = graph.optimize(marginals=False)
    assert sol.gnc_ran and not sol.gnc_skipped
    assert sol.outlier_factor_ids == ["wrong"]
    assert sol.ambiguous_factor_ids == []
    assert graph.remove_factor("wrong")
    sol = graph.optimize(marginals=False)
    assert "wrong" not in sol.weights
    for n, T in frozen.items():
        assert sol.T_anchor_frame[n].equals(T, 0.0)
    # a factor between two frozen nodes is judged once (here: against the frozen poses alone)
    graph.add_factor("late", f"{A}#1", f"{B}#3", *closure(rng, truth, f"{A}#1", f"{B}#3"))
    sol = graph.optimize(marginals=False)
    assert sol.weights["late"] == 1.0 and "late" in graph._sealed
    graph.add_factor("late-wrong", f"{A}#1", f"{B}#4",
                     *closure(rng, truth, f"{A}#1", f"{B}#4", wrong=True))
    sol = graph.optimize(marginals=False)
    assert sol.outlier_factor_ids == ["late-wrong"]


def test_the_anchor_cannot_move_once_nodes_are_frozen() -> None:
    graph, _, _ = driven(620, 4, 5)
    assert graph.frozen_count == 6
    with pytest.raises(InputError, match="frozen"):
        graph.anchor = f"{B}#0"
    with pytest.raises(InputError, match="frozen"):
        graph.optimize(anchor=f"{B}#0")
    assert graph.optimize(marginals=False).anchor == f"{A}#0"


def test_settle_freezes_a_graph_loaded_at_once_as_it_grew(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A restart loads the whole graph at once: settle() solves it in insertion order, a few
    nodes more each time, so it freezes as the live graph did and no solve holds the whole."""
    cap, steps = 10, 25
    grown, truth, _ = driven(630, cap, steps)
    loaded = PoseGraph(anchor=f"{A}#0", config=GraphConfig(max_live_nodes=cap))
    for n in grown.nodes:
        loaded.add_frame(n)
    copy_into(loaded, grown, grown.factor_ids)
    sizes = solve_sizes(monkeypatch, loaded)
    sol = loaded.settle()
    assert loaded.frozen_count == grown.frozen_count == 2 * steps - cap
    assert max(sizes) <= cap + cap // 2 + 3
    assert set(sol.weights) == set(grown.factor_ids)
    ref = least_squares_with_fixed(loaded, {n: sol.T_anchor_frame[n] for n in loaded._frozen},
                                   truth)
    for n in loaded._frozen:  # frozen where the run that grew it froze them, near enough
        assert pose_error(sol.T_anchor_frame[n], grown._frozen[n])[1] < 0.05, n
    for n, T in sol.T_anchor_frame.items():
        assert pose_error(T, ref[n])[1] < 1e-5, n
    # without a bound: one solve of the whole graph
    whole = PoseGraph(anchor=f"{A}#0")
    copy_into(whole, grown, grown.factor_ids)
    sizes.clear()
    whole.settle()
    assert sizes == [len(whole.nodes)]
    for bad in (0, -3, 1.5, True, "2"):
        with pytest.raises(InputError, match="step"):
            loaded.settle(step=bad)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="step"):
        whole.settle(step=1.5)  # type: ignore[arg-type]  (without a bound too)


def late_session(cap: int) -> tuple[PoseGraph, dict[str, gtsam.Pose3]]:
    """A and B drive 12 keyframes each, solved at every step, with no closure between them;
    then B joins A's component on one wrong closure (a bridge: nothing can check it yet), then
    two correct closures between older keyframes arrive."""
    graph, truth, rng = driven(640, cap, 12, closures=lambda k: False)
    graph.add_factor("wrong", f"{A}#11", f"{B}#11",
                     *closure(rng, truth, f"{A}#11", f"{B}#11", wrong=True))
    sol = graph.optimize(marginals=False)
    assert sol.unchecked_factor_ids[-1] == "wrong"
    graph.add_factor("c1", f"{A}#2", f"{B}#2", *closure(rng, truth, f"{A}#2", f"{B}#2"))
    graph.add_factor("c2", f"{A}#5", f"{B}#5", *closure(rng, truth, f"{A}#5", f"{B}#5"))
    return graph, truth


def test_a_session_that_joins_late_stays_live_until_it_can_be_judged() -> None:
    """Freezing goes by when a node joined the anchor's component, not when it was added: B's
    keyframes, added early but joined late on one unchecked closure, are not frozen on it, so
    the two correct closures that come next confirm it as an outlier, as without freezing."""
    whole, truth = late_session(0)
    expected = whole.optimize(marginals=False)
    assert expected.outlier_factor_ids == ["wrong"] and expected.ambiguous_factor_ids == []
    bounded, _ = late_session(8)
    assert bounded.frozen_count == 12 and all(n.startswith(A) for n in bounded._frozen)
    sol = bounded.optimize(marginals=False)
    assert sol.outlier_factor_ids == ["wrong"] and sol.ambiguous_factor_ids == []
    assert "wrong" not in bounded._sealed
    for n in truth:
        # (A#0-11 frozen before the closures: within a few cm of where they would move)
        assert pose_error(sol.T_anchor_frame[n], expected.T_anchor_frame[n])[1] < 0.25, n


def test_chains_pulled_by_disputed_closures_stay_live_until_they_are_judged() -> None:
    """B is joined to A by two closures that disagree (ambiguous: GNC's pick between them is
    arbitrary, and both stay in the solve): neither chain freezes on that, the disputed closures
    are never sealed, and a third closure confirms the wrong one as an outlier, as without
    freezing; then both chains freeze."""
    graph, truth, rng = driven(650, 6, 4, closures=lambda k: False)
    frozen_alone = set(graph._frozen)  # A alone, odometry only: nothing to doubt
    graph.add_factor("c1", f"{A}#1", f"{B}#1", *closure(rng, truth, f"{A}#1", f"{B}#1"))
    graph.add_factor("wrong", f"{A}#2", f"{B}#2",
                     *closure(rng, truth, f"{A}#2", f"{B}#2", wrong=True))
    sol = graph.optimize(marginals=False)
    assert sol.ambiguous_factor_ids == ["wrong"] and sol.outlier_factor_ids == []
    for k in range(4, 12):  # A and B drive on, 20 nodes past the cap: none freezes
        grow(graph, rng, truth, k, closures=False)
        sol = graph.optimize(marginals=False)
        assert set(sol.ambiguous_factor_ids) & {"c1", "wrong"}
    assert set(graph._frozen) == frozen_alone
    assert not {"c1", "wrong"} & set(graph._sealed)
    graph.add_factor("c3", f"{A}#9", f"{B}#9", *closure(rng, truth, f"{A}#9", f"{B}#9"))
    sol = graph.optimize(marginals=False)
    assert sol.outlier_factor_ids == ["wrong"] and sol.ambiguous_factor_ids == []
    assert sol.weights["c1"] == 1.0 == sol.weights["c3"]
    assert {f"{A}#5", f"{B}#5"} <= set(graph._frozen)  # settled now: frozen
    assert "c1" in graph._sealed and "wrong" not in graph._sealed


def test_settle_with_an_anchor_added_after_other_nodes() -> None:
    grown, _, _ = driven(660, 10, 20, solve=False)
    loaded = PoseGraph(config=GraphConfig(max_live_nodes=10))
    copy_into(loaded, grown, grown.factor_ids[::-1])  # B's nodes first, the anchor near the end
    loaded.anchor = f"{A}#0"
    assert loaded.nodes.index(f"{A}#0") > 30
    sol = loaded.settle(step=5)
    assert sol.anchor == f"{A}#0" and sol.T_anchor_frame[f"{A}#0"].equals(gtsam.Pose3(), 1e-6)
    assert set(sol.weights) == set(grown.factor_ids)
    assert set(sol.T_anchor_frame) == set(grown.nodes)  # (joined at once: none frozen yet)
    with pytest.raises(InputError, match="anchor"):
        loaded._solve(f"{A}#0", False, limit=3)


def test_nothing_folds_into_a_sealed_factor() -> None:
    """Rule 5 with rule 6: a sealed factor is not solved again, so a closure that agrees with
    it is solved on its own (folded into it, its measurement would be used by no solve)."""
    graph, truth, rng = driven(670, 6, 10, closures=lambda k: k in (1, 2, 6), fold_hops=3,
                               fold_drift=100.0)
    assert "c1" in graph._sealed
    add(graph, "near-c1", f"{A}#1", f"{B}#2", *closure(rng, truth, f"{A}#1", f"{B}#2"))
    assert graph.representative("near-c1") != "c1"
    sol = graph.optimize(marginals=False)
    assert "near-c1" in sol.errors  # solved, not only listed
    unbounded = PoseGraph(anchor=f"{A}#0", config=GraphConfig(fold_hops=3, fold_drift=100.0))
    copy_into(unbounded, graph, [f for f in graph.factor_ids if f != "near-c1"])
    unbounded.add_factor("near-c1", *MEASURED[graph]["near-c1"][:4])
    assert unbounded.representative("near-c1") is not None  # it would fold, unsealed


def test_a_folded_factor_is_retracted_after_its_odometry_froze() -> None:
    """Rules 5 and 6 together: d1, c2 and d2 fold into c1, then the keyframes between them
    freeze and the odometry they were carried along is sealed (no longer held). Removing c2
    makes c1's fused measurement again from its own and the other two as they were carried
    (as a graph that never froze does, carrying them along its odometry again); removing c1
    then sends d1 and d2 back to the graph, solved (against the frozen poses) and kept."""
    graph, _, _ = driven(690, 6, 12, closures=lambda k: k in (1, 2, 6), fold_hops=3,
                         fold_drift=100.0)
    assert [graph.representative(f) for f in ("d1", "c2", "d2")] == ["c1"] * 3
    assert {f"{A}#2", f"{B}#2"} <= set(graph._frozen)
    assert graph._factors[f"odom:{B}#1"].T_a_b is None  # sealed: nothing is carried along it
    unfrozen = PoseGraph(anchor=f"{A}#0", config=GraphConfig(fold_hops=3, fold_drift=100.0))
    copy_into(unfrozen, graph, list(MEASURED[graph]))  # in the order they came
    assert [unfrozen.representative(f) for f in ("d1", "c2", "d2")] == ["c1"] * 3
    frozen = dict(graph._frozen)
    assert graph.remove_factor("c2") and unfrozen.remove_factor("c2")
    assert not graph.remove_factor("c2")
    with pytest.raises(InputError, match="unknown factor"):
        graph.representative("c2")
    assert graph.factor_ids == unfrozen.factor_ids
    T, C = graph._measurement(graph._factors["c1"])
    T_ref, C_ref = unfrozen._measurement(unfrozen._factors["c1"])
    assert T.equals(T_ref, 1e-9)
    np.testing.assert_allclose(C, C_ref, rtol=1e-9, atol=1e-15)
    sol = graph.optimize(marginals=False)
    assert "c2" not in sol.weights and sol.folded == {"d1": "c1", "d2": "c1", "d6": "c6"}
    assert sol.outlier_factor_ids == [] == sol.ambiguous_factor_ids
    assert graph.remove_factor("c1")
    assert graph.representative("d1") is None and graph.representative("d2") is None
    sol = graph.optimize(marginals=False)
    assert "c1" not in sol.weights and {"d1", "d2"} <= set(sol.errors)  # solved
    assert sol.outlier_factor_ids == [] == sol.ambiguous_factor_ids
    assert {"d1", "d2"} <= set(graph._sealed)  # kept, between frozen nodes: settled
    for n, T_n in frozen.items():
        assert sol.T_anchor_frame[n].equals(T_n, 0.0), n


def test_a_chain_joined_by_one_closure_does_not_freeze_on_it() -> None:
    """B joined to A by one closure (a bridge: nothing can check it) stays live however many
    nodes join after it, while A (the anchor's chain) freezes; a second closure that agrees
    places B twice over, and B freezes too."""
    rng = np.random.default_rng(680)
    graph = PoseGraph(anchor=f"{A}#0", config=GraphConfig(max_live_nodes=6))
    truth: dict[str, gtsam.Pose3] = {}
    for k in range(12):
        grow(graph, rng, truth, k, closures=False)
        if k == 1:
            graph.add_factor("c1", f"{A}#1", f"{B}#1", *closure(rng, truth, f"{A}#1", f"{B}#1"))
        sol = graph.optimize(marginals=False)
    assert "c1" in sol.unchecked_factor_ids
    assert f"{A}#4" in graph._frozen and not any(n.startswith(B) for n in graph._frozen)
    graph.add_factor("c5", f"{A}#5", f"{B}#5", *closure(rng, truth, f"{A}#5", f"{B}#5"))
    sol = graph.optimize(marginals=False)
    assert sol.outlier_factor_ids == [] == sol.ambiguous_factor_ids
    assert f"{B}#4" in graph._frozen
