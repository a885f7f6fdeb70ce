"""File formats other tools read (mergesvc.wire.formats): TUM trajectories and g2o pose graphs.

The conventions are pinned against the tools themselves: TUM's quaternion order against a
hand-written line, g2o's (translation, rotation) information order against gtsam.readG2o (what
comes back must be what we meant, in GTSAM's order) and against gtsam.writeG2o's own text."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mergesvc.errors import DecodeError, InputError
from mergesvc.wire.formats import read_tum, write_g2o, write_tum


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.stack([
        _pose(Rotation.random(random_state=rng).as_matrix(), rng.normal(0.0, 20.0, 3))
        for _ in range(n)
    ])


def _random_covariance(rng: np.random.Generator) -> np.ndarray:
    """A full 6x6 SPD covariance in GTSAM order whose rotation block (~1e-4) and translation
    block (~1e-2) differ in size, with rotation-translation cross terms that are NOT a
    symmetric block (so a transposed cross block would be caught)."""
    A = rng.normal(size=(6, 6)) * np.array([0.01, 0.01, 0.01, 0.1, 0.1, 0.1])[:, None]
    return A @ A.T + np.diag([1e-5] * 3 + [1e-3] * 3)


# ---- TUM


def test_tum_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    poses = _random_poses(rng, 50)
    stamps = 1305031102.175304 + np.cumsum(rng.uniform(0.01, 0.05, 50))
    path = write_tum(tmp_path / "traj.txt", stamps, poses)
    got_stamps, got_poses = read_tum(path)
    np.testing.assert_array_equal(got_stamps, stamps)  # repr round-trips floats exactly
    np.testing.assert_array_equal(got_poses[:, :3, 3], poses[:, :3, 3])
    np.testing.assert_allclose(got_poses, poses, atol=1e-14)
    assert [p.name for p in tmp_path.iterdir()] == ["traj.txt"]  # no temporary file left


def test_tum_quaternion_order_is_x_y_z_w(tmp_path: Path) -> None:
    """A hand-written TUM line: 60 degrees about x is qx = sin 30 = 0.5, qw = cos 30."""
    qw = float(np.cos(np.radians(30.0)))
    path = tmp_path / "hand.txt"
    path.write_text(f"# timestamp tx ty tz qx qy qz qw\n\n1.5 1 2 3 0.5 0 0 {qw!r}\n")
    stamps, poses = read_tum(path)
    expected = gtsam.Pose3(gtsam.Rot3.Quaternion(qw, 0.5, 0.0, 0.0), gtsam.Point3(1, 2, 3))
    np.testing.assert_array_equal(stamps, [1.5])
    np.testing.assert_allclose(poses[0], expected.matrix(), atol=1e-15)
    np.testing.assert_allclose(poses[0, :3, :3], gtsam.Rot3.Rx(np.radians(60.0)).matrix(),
                               atol=1e-15)
    # and writing gives the same numbers in the same order
    out = write_tum(tmp_path / "out.txt", stamps, poses)
    fields = [float(x) for x in out.read_text().splitlines()[1].split()]
    np.testing.assert_allclose(fields, [1.5, 1, 2, 3, 0.5, 0, 0, qw], atol=1e-15)
    assert out.read_text().startswith("# timestamp tx ty tz qx qy qz qw\n")


def test_tum_writes_qw_non_negative(tmp_path: Path) -> None:
    R = Rotation.from_quat([0.1, 0.2, 0.3, -0.9]).as_matrix()  # scipy: x y z w
    out = write_tum(tmp_path / "t.txt", [0.0], _pose(R, np.zeros(3))[None])
    q = np.array([float(x) for x in out.read_text().splitlines()[1].split()[4:]])
    np.testing.assert_allclose(q, -np.array([0.1, 0.2, 0.3, -0.9]) / np.linalg.norm(
        [0.1, 0.2, 0.3, -0.9]), atol=1e-15)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("0 1 2 3 0 0 0 1\n# ok\n1 1 2 3 0 0 1\n", r"line 3: expected 8 numbers"),
        ("\n\n0 1 2 3 0 0 0 1 9\n", r"line 3: expected 8 numbers .*found 9"),
        ("0,1,2,3,0,0,0,1\n", r"line 1: expected 8 numbers .*found 1"),
        ("0 1 2 x 0 0 0 1\n", r"line 1: 'x' is not a number"),
        ("0 1 2 nan 0 0 0 1\n", r"line 1: NaN or inf"),
        ("0 1 2 3 0 0 0 0\n", r"line 1: the quaternion .* has norm 0"),
        ("0 1 2 3 0.1 0.2 0.3 2\n", r"line 1: the quaternion .*not 1"),
        ("# only a comment\n\n", r"no pose lines"),
        ("", r"no pose lines"),
    ],
)
def test_malformed_tum_is_refused_naming_the_line(
    tmp_path: Path, text: str, message: str
) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(DecodeError, match=message) as err:
        read_tum(path)
    assert str(path) in str(err.value)


def test_tum_unreadable_files_are_decode_errors(tmp_path: Path) -> None:
    with pytest.raises(DecodeError, match="cannot read"):
        read_tum(tmp_path / "missing.txt")
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(DecodeError, match="not a text file"):
        read_tum(tmp_path / "bin.txt")


def test_write_tum_refuses_bad_input(tmp_path: Path) -> None:
    poses = _random_poses(np.random.default_rng(1), 3)
    out = tmp_path / "t.txt"
    with pytest.raises(InputError, match="timestamp 1 is NaN"):
        write_tum(out, [0.0, np.nan, 2.0], poses)
    bad = poses.copy()
    bad[2, 1, 3] = np.inf
    with pytest.raises(InputError, match="pose 2 holds NaN or inf"):
        write_tum(out, [0.0, 1.0, 2.0], bad)
    with pytest.raises(InputError, match="3 poses need 3 timestamps"):
        write_tum(out, [0.0, 1.0], poses)
    with pytest.raises(InputError, match="no poses"):
        write_tum(out, [], np.zeros((0, 4, 4)))
    assert not out.exists()
    with pytest.raises(InputError, match="cannot write"):
        write_tum(tmp_path / "no" / "such" / "dir.txt", [0.0, 1.0, 2.0], poses)


def test_write_replaces_an_existing_file(tmp_path: Path) -> None:
    out = tmp_path / "t.txt"
    out.write_text("old\n")
    write_tum(out, [0.0], np.eye(4)[None])
    assert read_tum(out)[0].tolist() == [0.0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.txt"]


def test_tum_reads_in_evo_when_installed(tmp_path: Path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    rng = np.random.default_rng(2)
    poses = _random_poses(rng, 10)
    stamps = np.arange(10) * 0.1
    traj = file_interface.read_tum_trajectory_file(str(write_tum(tmp_path / "t.txt", stamps,
                                                                 poses)))
    np.testing.assert_allclose(traj.timestamps, stamps)
    np.testing.assert_allclose(np.stack(traj.poses_se3), poses, atol=1e-12)


# ---- g2o


def _graph(rng: np.random.Generator) -> tuple[dict[int, np.ndarray], list]:
    vertices = {k: _random_poses(rng, 1)[0] for k in (0, 1, 2, 7)}
    edges = []
    for i, j in [(0, 1), (1, 2), (2, 7), (0, 7), (7, 1)]:
        T_ij = np.linalg.inv(vertices[i]) @ vertices[j]
        T_ij = T_ij @ _pose(Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix(),
                            rng.normal(0, 0.05, 3))  # a measurement, not exactly consistent
        edges.append((i, j, T_ij, _random_covariance(rng)))
    return vertices, edges


def test_g2o_reads_back_in_gtsam_with_the_covariance_in_gtsam_order(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    vertices, edges = _graph(rng)
    path = write_g2o(tmp_path / "graph.g2o", vertices, edges)
    graph, initial = gtsam.readG2o(str(path), True)
    assert sorted(initial.keys()) == sorted(vertices)
    for k, T in vertices.items():
        np.testing.assert_allclose(initial.atPose3(k).matrix(), T, atol=1e-12)
    assert graph.size() == len(edges)
    for n, (i, j, T_ij, cov) in enumerate(edges):
        factor = graph.at(n)
        assert isinstance(factor, gtsam.BetweenFactorPose3)
        assert list(factor.keys()) == [i, j]
        np.testing.assert_allclose(factor.measured().matrix(), T_ij, atol=1e-12)
        model = factor.noiseModel()
        np.testing.assert_allclose(model.covariance(), cov, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(model.information(), np.linalg.inv(cov), rtol=1e-9,
                                   atol=1e-6)


def test_g2o_information_order_is_translation_first(tmp_path: Path) -> None:
    """Rotation sigma 0.01 rad, translation sigma 1 m (GTSAM order): the file's information
    starts with the translation's 1, and gtsam reads back the same sigmas in its order."""
    cov = np.diag([1e-4] * 3 + [1.0] * 3)
    vertices = {0: np.eye(4), 1: _pose(np.eye(3), np.array([1.0, 0.0, 0.0]))}
    path = write_g2o(tmp_path / "g.g2o", vertices, [(0, 1, vertices[1], cov)])
    line = path.read_text().splitlines()[-1].split()
    assert line[:3] == ["EDGE_SE3:QUAT", "0", "1"]
    info = [float(x) for x in line[10:]]
    assert len(info) == 21
    # upper triangle row by row: the diagonal sits at 0, 6, 11, 15, 18, 20
    assert [info[k] for k in (0, 6, 11, 15, 18, 20)] == pytest.approx([1.0] * 3 + [1e4] * 3)
    graph, _ = gtsam.readG2o(str(path), True)
    np.testing.assert_allclose(graph.at(0).noiseModel().sigmas(), [0.01] * 3 + [1.0] * 3)


def _numbers(line: str) -> tuple[str, np.ndarray]:
    tag, *rest = line.split()
    return tag, np.array([float(x) for x in rest])


def test_g2o_text_matches_gtsams_own_writer(tmp_path: Path) -> None:
    """gtsam.writeG2o on the same graph writes the same numbers (to its 6 significant
    digits): same vertex and edge layout, same quaternion order, same information order."""
    rng = np.random.default_rng(4)
    vertices, edges = _graph(rng)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, T in vertices.items():
        values.insert(k, gtsam.Pose3(T))
    for i, j, T_ij, cov in edges:
        graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(T_ij),
                                           gtsam.noiseModel.Gaussian.Covariance(cov)))
    theirs = tmp_path / "gtsam.g2o"
    gtsam.writeG2o(graph, values, str(theirs))
    ours = write_g2o(tmp_path / "ours.g2o", vertices, edges)
    their_lines = [_numbers(x) for x in theirs.read_text().splitlines() if x.strip()]
    our_lines = [_numbers(x) for x in ours.read_text().splitlines() if x.strip()]
    assert [t for t, _ in their_lines] == [t for t, _ in our_lines]
    for (tag, a), (_, b) in zip(their_lines, our_lines):
        assert len(a) == len(b), tag
        head = 1 if tag == "VERTEX_SE3:QUAT" else 2
        np.testing.assert_array_equal(a[:head], b[:head])  # ids
        q_a, q_b = a[head + 3 : head + 7], b[head + 3 : head + 7]
        if np.dot(q_a, q_b) < 0:  # q and -q are the same rotation
            q_a = -q_a
        np.testing.assert_allclose(q_a, q_b, rtol=1e-5, atol=1e-6)
        rest_a = np.concatenate([a[head : head + 3], a[head + 7 :]])
        rest_b = np.concatenate([b[head : head + 3], b[head + 7 :]])
        np.testing.assert_allclose(rest_a, rest_b, rtol=2e-5, atol=1e-5 * np.abs(rest_b).max())


def test_write_g2o_refuses_bad_graphs(tmp_path: Path) -> None:
    out = tmp_path / "g.g2o"
    V = {0: np.eye(4), 1: np.eye(4)}
    good = np.eye(6) * 0.01
    cases = [
        (V, [(0, 2, np.eye(4), good)], "names vertex 2, which is not among the vertices"),
        (V, [(0, 0, np.eye(4), good)], "from vertex 0 to itself"),
        (V, [(0, 1, np.eye(4), good * np.nan)], "NaN or inf"),
        (V, [(0, 1, np.eye(4), -good)], "not positive definite"),
        (V, [(0, 1, np.eye(4), good + np.triu(np.ones((6, 6)), 1) * 1e-3)], "not symmetric"),
        (V, [(0, 1, np.eye(4), np.eye(3))], "6x6"),
        (V, [(0, 1, np.eye(4))], "got 3 items"),
        (V, [(0, 1, np.diag([1.0, 1.0, -1.0, 1.0]), good)], "not a proper rotation"),
        ({-1: np.eye(4)}, [], "negative"),
        ({"a": np.eye(4)}, [], "not an integer"),
        ({0: np.full((4, 4), np.nan)}, [], "vertex 0: pose 0 holds NaN"),
    ]
    for vertices, edges, message in cases:
        with pytest.raises(InputError, match=message):
            write_g2o(out, vertices, edges)
        assert not out.exists()
    assert list(tmp_path.iterdir()) == []
