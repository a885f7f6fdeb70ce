"""Match result -> inter-robot factor (mergesvc.core.factors) and frame ids (FrameId): the
covariance inflation in GTSAM's tangent order, frame ids carried through, rejected matches
refused, and the factor exactly as the service built it inline before (same id, same JSON)."""

from __future__ import annotations

from urllib.parse import unquote

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import mergesvc
from mergesvc.core.factors import (
    anchoring_keyframe,
    factor_frames,
    factor_from_match,
    factor_nodes,
    inflate_covariance,
    match_factor_id,
    odometry_edge,
    yields_factor,
)
from mergesvc.core.frames import FrameId, KeyframeId, frame_name, keyframe_name, split_frame
from mergesvc.core.model import (
    Correspondence,
    Factor,
    FactorStatus,
    Match,
    MatchResult,
    ObjectNode,
    Odometry,
    RejectReason,
    Submap,
    Transform,
)
from mergesvc.core.poses import pose3_from_model, transform_from_pose3
from mergesvc.errors import InputError, one_line

DRIFT = (0.05, 0.5)


def spd(rng: np.random.Generator) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    return A @ A.T * 1e-3 + np.eye(6) * 1e-4


def result(rng: np.random.Generator, accepted: bool = True, **kw) -> MatchResult:
    q = rng.normal(size=4)
    fields = dict(
        accepted=accepted,
        reason=RejectReason.VERIFIED if accepted else RejectReason.AMBIGUOUS,
        matches=[Match(submap_object=f"s{i}", map_object=f"m{i}", score=0.9 - 0.1 * i)
                 for i in range(4)],
        transform=Transform(translation=tuple(rng.normal(size=3).tolist()),
                            quaternion_wxyz=tuple((q / np.linalg.norm(q)).tolist())),
        covariance=spd(rng).tolist(),
        timings_ms={"total": 1.0},
    )
    fields.update(kw)
    return MatchResult(**fields)


# --------------------------------------------------------------------------------------------
# Covariance inflation
# --------------------------------------------------------------------------------------------


def test_inflation_adds_the_drift_variances_rotation_first() -> None:
    rng = np.random.default_rng(0)
    cov = spd(rng)
    r, t = DRIFT
    expected = cov.copy()
    for i in range(6):
        expected[i, i] += (r if i < 3 else t) ** 2
    out = inflate_covariance(cov, DRIFT)
    np.testing.assert_array_equal(out, expected)
    np.testing.assert_array_equal(out - out.T, 0.0)  # stays symmetric
    # nothing but the diagonal changes
    off = ~np.eye(6, dtype=bool)
    np.testing.assert_array_equal(out[off], cov[off])


def test_inflation_order_is_gtsams_pose3_tangent_order() -> None:
    """GTSAM's Pose3 tangent is (rotation, translation): a pure rotation lands in the first
    three coordinates, a pure translation in the last three; the rotation sigma must go there."""
    rot = gtsam.Pose3.Logmap(gtsam.Pose3(gtsam.Rot3.Rx(0.1), np.zeros(3)))
    trans = gtsam.Pose3.Logmap(gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0, 0])))
    assert np.abs(rot[:3]).max() > 0 and np.abs(rot[3:]).max() == 0
    assert np.abs(trans[:3]).max() == 0 and np.abs(trans[3:]).max() > 0
    r, t = DRIFT
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([r, r, r, t, t, t]))
    np.testing.assert_allclose(inflate_covariance(np.zeros((6, 6)), DRIFT), noise.covariance(),
                               rtol=1e-12)


def test_inflation_accepts_lists_and_refuses_other_shapes() -> None:
    out = inflate_covariance(np.eye(6).tolist(), (0.0, 0.0))
    np.testing.assert_array_equal(out, np.eye(6))
    with pytest.raises(InputError):
        inflate_covariance(np.eye(3), DRIFT)


# --------------------------------------------------------------------------------------------
# Factor from a match
# --------------------------------------------------------------------------------------------


def test_factor_id() -> None:
    a, b = FrameId("auv1", "s0"), FrameId("auv2", "s1")
    assert match_factor_id(a, b, 7) == "auv1.s0-auv2.s1-7"


def test_frame_ids_are_carried_through() -> None:
    rng = np.random.default_rng(1)
    a, b = FrameId("auv1", "s0"), FrameId("auv2", "2024/05")
    res = result(rng)
    f = factor_from_match(res, a, b, factor_id="x", drift_sigma=DRIFT)
    assert (f.robot_a, f.session_a, f.robot_b, f.session_b) == ("auv1", "s0", "auv2", "2024/05")
    assert factor_frames(f) == (a, b)
    assert f.factor_id == "x" and f.status is FactorStatus.ACCEPTED
    assert f.T_a_b == res.transform
    assert [(c.object_a, c.object_b, c.score) for c in f.correspondences] == [
        (m.map_object, m.submap_object, m.score) for m in res.matches
    ]
    np.testing.assert_array_equal(f.covariance, inflate_covariance(res.covariance, DRIFT))


def test_a_rejected_match_is_refused() -> None:
    rng = np.random.default_rng(2)
    a, b = FrameId("a", "s"), FrameId("b", "s")
    rejected = result(rng, accepted=False)
    assert not yields_factor(rejected)
    with pytest.raises(InputError, match="ambiguous"):
        factor_from_match(rejected, a, b, factor_id="x", drift_sigma=DRIFT)
    for missing in ({"transform": None}, {"covariance": None}):
        res = result(rng, **missing)
        assert not yields_factor(res)
        with pytest.raises(InputError):
            factor_from_match(res, a, b, factor_id="x", drift_sigma=DRIFT)


def _inline_before(res: MatchResult, other: str, sub_robot: str, sub_session: str, seq: int,
                   drift_sigma: tuple[float, float]) -> Factor:
    """The service's inline code before core/factors.py, verbatim (the oracle)."""
    robot, session = other.split("/", 1)
    r_sig, t_sig = drift_sigma
    cov = np.asarray(res.covariance) + np.diag([r_sig**2] * 3 + [t_sig**2] * 3)
    return Factor(
        factor_id=f"{robot}.{session}-{sub_robot}.{sub_session}-{seq}",
        robot_a=robot, session_a=session, robot_b=sub_robot, session_b=sub_session,
        T_a_b=res.transform, covariance=cov.tolist(),
        correspondences=[Correspondence(object_a=m.map_object, object_b=m.submap_object,
                                        score=m.score) for m in res.matches],
        status=FactorStatus.ACCEPTED,
    )


def _real_match() -> MatchResult:
    rng = np.random.default_rng(0)
    objs = [
        mergesvc.ObjectNode(id=f"o{i}", embedding=rng.normal(size=8).tolist(), variance=0.01,
                            position=tuple(rng.uniform(-5, 5, size=3).tolist()))
        for i in range(6)
    ]
    m = mergesvc.ObjectMap(robot_id="auv1", session_id="s0", objects=objs)
    sub = mergesvc.Submap(robot_id="auv2", session_id="s1", objects=objs, seq=3)
    out = mergesvc.match(m, sub)
    assert yields_factor(out) and yields_factor(out.result)
    return out.result


@pytest.mark.parametrize("seed", [None, 3, 4])
def test_the_factor_is_the_one_the_service_built_before(seed: int | None) -> None:
    res = _real_match() if seed is None else result(np.random.default_rng(seed))
    other, me = "auv1/s0", FrameId("auv2", "s1")
    before = _inline_before(res, other, me.robot, me.session, 3, DRIFT)
    a = FrameId.parse(other)
    now = factor_from_match(res, a, me, factor_id=match_factor_id(a, me, 3), drift_sigma=DRIFT)
    assert now.factor_id == before.factor_id == "auv1.s0-auv2.s1-3"
    assert now.model_dump_json() == before.model_dump_json()  # what the store keeps
    assert mergesvc.encode_message(now, "compact", "mergesvc", 1) == mergesvc.encode_message(
        before, "compact", "mergesvc", 1
    )


def test_a_match_outcome_is_taken_as_its_result() -> None:
    rng = np.random.default_rng(0)
    objs = [
        mergesvc.ObjectNode(id=f"o{i}", embedding=rng.normal(size=8).tolist(), variance=0.01,
                            position=tuple(rng.uniform(-5, 5, size=3).tolist()))
        for i in range(6)
    ]
    out = mergesvc.match(mergesvc.ObjectMap(robot_id="a", session_id="s", objects=objs),
                         mergesvc.Submap(robot_id="b", session_id="s", objects=objs))
    a, b = FrameId("a", "s"), FrameId("b", "s")
    assert factor_from_match(out, a, b, factor_id="f", drift_sigma=DRIFT) == factor_from_match(
        out.result, a, b, factor_id="f", drift_sigma=DRIFT
    )


# --------------------------------------------------------------------------------------------
# Pose-level factors (keyframes)
# --------------------------------------------------------------------------------------------


def test_a_pose_level_factor_is_re_anchored_at_keyframe_a() -> None:
    """The match gives T_{a,Kb} (map in a's session frame, submap in keyframe Kb's body frame);
    the factor is T_{Ka,Kb} = inv(T_{a,Ka}) T_{a,Kb}, its covariance the match's (left
    multiplication by a constant keeps a right perturbation) inflated."""
    rng = np.random.default_rng(5)
    res = result(rng)
    a, b = FrameId("auv1", "s0"), FrameId("auv2", "s0")
    T_a_ka = gtsam.Pose3(gtsam.Rot3.Rz(0.7), np.array([4.0, -2.0, 0.5]))
    f = factor_from_match(res, a, b, factor_id="p", drift_sigma=DRIFT, keyframe_a=12,
                          keyframe_b=30, T_a_keyframe_a=T_a_ka)
    assert (f.keyframe_a, f.keyframe_b) == (12, 30)
    expected = T_a_ka.inverse().compose(pose3_from_model(res.transform))
    assert pose3_from_model(f.T_a_b).equals(expected, 1e-9)
    np.testing.assert_array_equal(f.covariance, inflate_covariance(res.covariance, DRIFT))
    # a right perturbation of the match maps to the same right perturbation of the factor
    xi = np.r_[0.01, -0.02, 0.03, 0.1, 0.2, -0.1]
    perturbed = pose3_from_model(res.transform).compose(gtsam.Pose3.Expmap(xi))
    d = expected.between(T_a_ka.inverse().compose(perturbed))
    np.testing.assert_allclose(gtsam.Pose3.Logmap(d), xi, atol=1e-12)
    assert factor_nodes(f) == (KeyframeId(a, 12), KeyframeId(b, 30))
    # a (4, 4) pose works as well; identity (keyframe 0 of a map in its own frame) keeps T
    same = factor_from_match(res, a, b, factor_id="p", drift_sigma=DRIFT, keyframe_a=12,
                             keyframe_b=30, T_a_keyframe_a=T_a_ka.matrix())
    assert pose3_from_model(same.T_a_b).equals(expected, 1e-9)
    at0 = factor_from_match(res, a, b, factor_id="q", drift_sigma=DRIFT, keyframe_a=0,
                            keyframe_b=4)
    assert pose3_from_model(at0.T_a_b).equals(pose3_from_model(res.transform), 1e-9)
    # the wire format carries the keyframes
    back = mergesvc.decode_message(mergesvc.encode_message(f, "full", "mergesvc", 1))[1]
    assert (back.keyframe_a, back.keyframe_b) == (12, 30)


def test_keyframe_arguments_are_checked() -> None:
    rng = np.random.default_rng(6)
    a, b = FrameId("a", "s"), FrameId("b", "s")
    res = result(rng)
    with pytest.raises(InputError, match="together"):
        factor_from_match(res, a, b, factor_id="x", drift_sigma=DRIFT, keyframe_a=1)
    with pytest.raises(InputError, match="needs"):
        factor_from_match(res, a, b, factor_id="x", drift_sigma=DRIFT,
                          T_a_keyframe_a=np.eye(4))
    frame_level = factor_from_match(res, a, b, factor_id="x", drift_sigma=DRIFT)
    assert frame_level.keyframe_a is None and frame_level.keyframe_b is None
    assert factor_nodes(frame_level) == (KeyframeId(a, 0), KeyframeId(b, 0))


def test_anchoring_keyframe_is_the_majority_of_the_matched_objects() -> None:
    rng = np.random.default_rng(7)
    res = result(rng)  # matched map objects m0..m3
    assert anchoring_keyframe(res, {"m0": 5, "m1": 5, "m2": 9, "m3": 2}) == 5
    assert anchoring_keyframe(res, {"m0": 5, "m1": 9, "m2": 9, "m3": 5}) == 9  # tie: latest
    assert anchoring_keyframe(res, {"m0": 3, "x": 1}) == 3  # unknown objects do not vote
    with pytest.raises(InputError):
        anchoring_keyframe(res, {"x": 1})


def test_odometry_edge_of_a_keyframe_submap() -> None:
    obj = [ObjectNode(id="o", position=(0, 0, 0), embedding=[1.0], variance=1.0)]
    T = gtsam.Pose3(gtsam.Rot3.Ry(0.2), np.array([1.0, 2.0, 3.0]))
    cov = np.diag([1e-4] * 3 + [1e-2] * 3)
    sub = Submap(robot_id="r", session_id="s", seq=2, objects=obj, keyframe=9,
                 odometry=Odometry(from_keyframe=4, T_from_to=transform_from_pose3(T),
                                   covariance=cov.tolist()))
    edge = odometry_edge(sub)
    assert edge is not None
    assert (str(edge.from_), str(edge.to)) == ("r/s#4", "r/s#9")
    assert edge.edge_id == "odom:r/s#4-9"
    assert edge.T_from_to.equals(T, 1e-9)
    np.testing.assert_array_equal(edge.covariance, cov)
    assert odometry_edge(Submap(robot_id="r", session_id="s", objects=obj, keyframe=0)) is None
    assert odometry_edge(Submap(robot_id="r", session_id="s", objects=obj)) is None


def test_keyframe_ids() -> None:
    f = FrameId("auv1", "s0")
    k = KeyframeId(f, 12)
    assert str(k) == "auv1/s0#12" == keyframe_name(f, 12) == keyframe_name("auv1/s0", 12)
    assert KeyframeId.parse("auv1/s0#12") == k
    assert KeyframeId.parse("auv1/s#2#0") == KeyframeId(FrameId("auv1", "s#2"), 0)
    assert KeyframeId.origin(f) == KeyframeId(f, 0)
    assert sorted([KeyframeId(f, 10), KeyframeId(f, 9)])[0].k == 9
    for bad in ("auv1/s0", "auv1/s0#", "auv1/s0#-1", "auv1/s0#x", "auv1#3", "auv1/s0#\u00b2"):
        with pytest.raises(InputError):
            KeyframeId.parse(bad)
    for k_bad in (-1, 1.0, True):
        with pytest.raises(InputError):
            KeyframeId(f, k_bad)
    with pytest.raises(InputError):
        KeyframeId("auv1/s0", 1)


def test_transform_round_trip() -> None:
    T = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.2, 0.1), np.array([1.0, -2.0, 3.0]))
    assert pose3_from_model(transform_from_pose3(T)).equals(T, 1e-12)
    assert pose3_from_model(transform_from_pose3(T.matrix())).equals(T, 1e-12)


# --------------------------------------------------------------------------------------------
# Frame ids
# --------------------------------------------------------------------------------------------


def test_frame_id_string_and_parse() -> None:
    f = FrameId("auv1", "s0")
    assert str(f) == "auv1/s0" == frame_name("auv1", "s0")
    assert FrameId.parse("auv1/s0") == f
    assert FrameId.parse("auv1/s/2") == FrameId("auv1", "s/2")
    assert split_frame("auv1/s/2") == ("auv1", "s/2")
    assert {f: 1}[FrameId.parse(str(f))] == 1  # hashable, equal by value
    assert sorted([FrameId("b", "s"), FrameId("a", "t")])[0] == FrameId("a", "t")


@pytest.mark.parametrize("robot,session", [("", "s"), ("a", ""), ("a/b", "s")])
def test_invalid_frame_ids_are_refused(robot: str, session: str) -> None:
    with pytest.raises(InputError):
        FrameId(robot, session)
    with pytest.raises(InputError):
        frame_name(robot, session)


@pytest.mark.parametrize("name", ["", "nosession", "/s", "a/"])
def test_unparseable_frame_names_are_refused(name: str) -> None:
    with pytest.raises(InputError):
        FrameId.parse(name)
    with pytest.raises(InputError):
        split_frame(name)


# --------------------------------------------------------------------------------------------
# One line of error text (mergesvc.errors.one_line)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "exc,line",
    [
        (ValueError("bad value"), "bad value"),
        (ValueError("  first\nsecond\n"), "first"),
        (ValueError("\n\nafter blank lines\nmore"), "after blank lines"),
        (KeyError(), "KeyError"),
        (RuntimeError("   "), "RuntimeError"),
        ("text\nmore", "text"),
        ("", ""),
    ],
)
def test_one_line(exc: BaseException | str, line: str) -> None:
    assert one_line(exc) == line


def test_one_line_is_what_the_wire_and_store_use() -> None:
    from mergesvc.cli import errors as cli_errors
    from mergesvc.core import graph
    from mergesvc.store import database as store
    from mergesvc.wire import envelope, files, projection

    for module in (envelope, files, projection, store, graph, cli_errors):
        assert module.one_line is one_line, module.__name__


# -------------------------------------------------------------------------- factor ids


def test_factor_ids_of_the_review_collide_no_more() -> None:
    """("p","q-r")+("s","t") and ("p","q")+("r-s","t") once both gave p.q-r-s.t-5."""
    one = match_factor_id(FrameId("p", "q-r"), FrameId("s", "t"), 5)
    two = match_factor_id(FrameId("p", "q"), FrameId("r-s", "t"), 5)
    assert one != two
    assert (one, two) == ("p.q%2Dr-s.t-5", "p.q-r%2Ds.t-5")  # docs/wire.md §6.3's vectors
    assert match_factor_id(FrameId("auv1", "s0"), FrameId("auv2", "s0"), 12) == "auv1.s0-auv2.s0-12"
    assert match_factor_id(FrameId("r" * 70, "s" * 60), FrameId("x", "y"), 7) == (
        "h-55689ed34e0cea41a457d44505c56e32")


_HOSTILE = st.text(alphabet=st.sampled_from(list("ab.-%2DE5_水")), min_size=1, max_size=70)
_SESSION = st.text(alphabet=st.sampled_from(list("ab.-%2DE5_/水")), min_size=1, max_size=70)


@settings(max_examples=400, deadline=None)
@given(st.lists(st.tuples(_HOSTILE, _SESSION, _HOSTILE, _SESSION,
                          st.integers(0, 12)), min_size=2, max_size=6, unique=True))
def test_factor_ids_never_collide_for_hostile_names(tuples: list) -> None:
    """Names made of the separators and the escape itself: distinct tuples, distinct ids, each
    at most 128 characters, and an escaped id gives back its tuple."""
    ids = [match_factor_id(FrameId(ra, sa), FrameId(rb, sb), seq)
           for ra, sa, rb, sb, seq in tuples]
    assert len(set(ids)) == len(ids)
    for fid, (ra, sa, rb, sb, seq) in zip(ids, tuples, strict=True):
        assert 1 <= len(fid) <= 128
        if fid.startswith("h-"):
            continue
        a, b, s = fid.split("-")
        back = [unquote(x) for x in (*a.split("."), *b.split("."))]
        assert back == [ra, sa, rb, sb] and int(s) == seq
