"""A map sent in parts across profiles (full, f16, int8, compact), and submaps of every profile
against it: the service matches each one as well as a copy in the map's own profile would
(fleet/mixed.py), also after a restart. The map's objects near the submap came compact, coded
on a fleet projection fitted on other data (a survey): a full-precision submap compared with
those compact objects used to lose them to full-precision look-alikes (no_match, 4-6 matches)
while its compact copy was verified with 20 (docs/wire.md §5.4)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mergesvc.core.model import Submap
from mergesvc.core.pipeline import match
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.replies import SubmapResult
from mergesvc.fleet.service import MergeService
from mergesvc.sim import Family, make_scenario
from mergesvc.wire import Profile, Projection, encode_message

NEAR_M = 60.0  # map objects this close to the submap's true objects are sent compact
FAR_M = 250.0  # the rest of the map kept in the test, in the three other profiles


@pytest.fixture(scope="module")
def world():
    """The KITTI-like scenario's map split in four parts, its submap, a survey projection."""
    sc = make_scenario(Family.KITTI, 0)
    pos = {o.id: np.asarray(o.position) for o in sc.map.objects}
    true_xyz = np.array([pos[m] for m in sc.truth.values() if m is not None])
    dist = {k: float(np.linalg.norm(true_xyz - p, axis=1).min()) for k, p in pos.items()}
    near = [o for o in sc.map.objects if dist[o.id] <= NEAR_M]
    far = [o for o in sc.map.objects if NEAR_M < dist[o.id] <= FAR_M]
    survey = make_scenario(Family.KITTI, 100).map.arrays().embeddings_nd[:300]
    parts = [(far[0::3], Profile.FULL), (far[1::3], Profile.F16), (far[2::3], Profile.INT8),
             (near, Profile.COMPACT)]
    return sc, parts, Projection.fit(survey)


def _put(svc: MergeService, sub: Submap, profile: Profile, proj: Projection) -> None:
    data = encode_message(sub, profile, sub.robot_id, sub.seq, projection=proj)
    row, created = svc.store.put_submap(sub.robot_id, sub.session_id, sub.seq, data, 0.0)
    assert created
    svc._process(row)  # the worker's own path: decode the stored payload, match, store


def test_submaps_of_every_profile_match_a_map_sent_in_parts_across_profiles(
    world, tmp_path: Path
) -> None:
    sc, parts, proj = world
    store, m = str(tmp_path / "mixed.db"), sc.map
    svc = MergeService(ServiceConfig(store=store), None, [proj])
    try:
        for seq, (objects, profile) in enumerate(parts):
            _put(svc, Submap(robot_id=m.robot_id, session_id=m.session_id, seq=seq,
                             objects=objects, up=m.up), profile, proj)
        held = svc.sessions.session_map(f"{m.robot_id}/{m.session_id}").arrays
        # the case the views are for: matched as it is, a full-precision submap loses the
        # compact objects to look-alikes
        raw = match(held, sc.submap, svc.config.match).result
        assert not raw.accepted or len(raw.matches) < 10, (raw.reason, len(raw.matches))
    finally:
        svc.close()
    svc = MergeService(ServiceConfig(store=store), None, [proj])  # a restart: restored
    results: list[SubmapResult] = []
    svc.outbox.result = results.append
    try:
        svc.restore()
        for profile in Profile:  # one session each: at most two of robot q are tried
            _put(svc, sc.submap.model_copy(update={"robot_id": "q", "session_id": profile.value,
                                                   "seq": 0}), profile, proj)
            tried = {t.frame: t for t in results[-1].tried}
            car = tried[f"{m.robot_id}/{m.session_id}"]
            assert (car.reason.value, car.matches >= 18) == ("verified", True), (profile, car)
            pairs = svc.factors[car.factor_id].correspondences
            assert sum(sc.is_correct(c.object_b, c.object_a) for c in pairs) >= 18, profile
    finally:
        svc.close()


def test_views_leave_a_pair_without_compact_alone_and_give_compact_embeddings_back(world) -> None:
    from mergesvc.fleet.mixed import ProfileViews
    from mergesvc.wire import decode_message

    sc, _, proj = world
    views = ProfileViews({proj.id: proj})
    sub = sc.submap.model_copy(update={"seq": 3})
    arrays = sc.map.arrays()
    full = encode_message(sub, Profile.F16, sub.robot_id, 3)
    assert views.note("car2/s0", full) is None
    assert views.pair("car1/s0", arrays, sub, None) == (arrays, sub)  # as they are
    data = encode_message(sub, Profile.COMPACT, sub.robot_id, 3, projection=proj)
    code = views.note("car2/s0", data)
    assert (code.projection_id, code.budget_bits, code.step16) == (proj.id, 400, 24)
    decoded = decode_message(data, proj)[1]
    m_view, s_view = views.pair("car1/s0", decoded.arrays(), decoded, code)
    np.testing.assert_allclose(s_view.embeddings_nd, decoded.arrays().embeddings_nd, atol=1e-9)
    np.testing.assert_allclose(m_view.embeddings_nd, decoded.arrays().embeddings_nd, atol=1e-9)
    assert m_view.ids == decoded.arrays().ids
    # a full submap against a session that holds compact objects: both sides in its code
    m_view, s_view = views.pair("car2/s0", arrays, sub, None)
    assert not np.allclose(s_view.embeddings_nd, sub.arrays().embeddings_nd)
    np.testing.assert_array_equal(m_view.position_xyz_m, arrays.position_xyz_m)
    assert views.pair("car2/s0", arrays, sub, None)[0] is m_view  # cached per session map
