"""core/retrieval.py: one index over the fleet's objects ranks the frames a submap is worth
matching against. Checked against a loop-by-loop reference of the score, on look-alike worlds
(every frame sees the same classes) and on the real DINO centroids when ../shared/data has them."""

from __future__ import annotations

import numpy as np
import pytest

from mergesvc.core.retrieval import FleetIndex
from mergesvc.errors import InputError
from mergesvc.sim.runs import Family, world_embedding_model


def reference_scores(frames: dict[str, np.ndarray], q: np.ndarray, exclude: str | None
                     ) -> dict[str, float]:
    """The module docstring's score, one frame and one object at a time."""
    def cos(a, b):
        return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))

    names = [f for f, e in frames.items() if f != exclude and len(e) and e.shape[1] == q.shape[1]]
    best = {f: [max(cos(qi, o) for o in frames[f]) for qi in q] for f in names}
    typical = [float(np.median([best[f][i] for f in names])) for i in range(len(q))]
    return {f: sum(max(0.0, best[f][i] - typical[i]) for i in range(len(q))) for f in names}


def fleet(seed: int, n_frames: int, per_frame: int, dim: int = 64):
    """Frames of look-alike objects: 6 classes shared by every frame."""
    rng = np.random.default_rng(seed)
    model = world_embedding_model(Family.UNDERWATER, seed)
    frames = {}
    for k in range(n_frames):
        classes = rng.integers(0, 6, size=per_frame)
        frames[f"auv{k}/s0"] = model.instances(classes, rng)[:, :dim]
    return model, frames, rng


def test_scores_equal_the_reference() -> None:
    _, frames, rng = fleet(0, 7, 15)
    frames["empty/s0"] = np.zeros((0, 64))
    frames["other/s0"] = rng.normal(size=(5, 32))  # another embedding size
    idx = FleetIndex()
    for f, e in frames.items():
        idx.update(f, e)
    q = frames["auv3/s0"][:6] + 0.3 * rng.normal(size=(6, 64))
    got = {s.frame: s.score for s in idx.rank(q, exclude="auv1/s0")}
    ref = reference_scores(frames, q, "auv1/s0")
    assert set(got) == set(ref) and "other/s0" not in got and "auv1/s0" not in got
    for f in ref:
        assert got[f] == pytest.approx(ref[f], abs=1e-9), f
    assert [s.frame for s in idx.rank(q, keep=2)] == sorted(ref, key=lambda f: -ref[f])[:2]


@pytest.mark.parametrize("seed", range(5))
def test_the_frame_that_saw_the_objects_ranks_first_among_look_alikes(seed: int) -> None:
    """20 frames of 40 objects of the same 6 classes; the submap is 8 noisy views of one
    frame's objects (noise of a mid-range view, s = 0.3)."""
    model, frames, rng = fleet(seed, 20, 40, dim=384)
    idx = FleetIndex()
    for f, e in frames.items():
        idx.update(f, e)
    target = f"auv{seed + 3}/s0"
    picked = rng.choice(40, size=8, replace=False)
    q = model.observe(frames[target][picked], np.full(8, 0.3), rng)
    ranked = idx.rank(q, keep=3)
    assert ranked[0].frame == target, ranked
    assert ranked[0].score > 2.0 * ranked[1].score


def test_update_replaces_remove_drops_and_order_breaks_ties() -> None:
    idx = FleetIndex()
    e = np.eye(4)
    idx.update("a", e[:2])
    idx.update("b", e[:2])
    idx.update("c", e[2:])
    q = e[:1]
    assert [s.frame for s in idx.rank(q)] == ["a", "b", "c"]  # a, b tie: arrival order
    idx.update("a", e[2:])  # a's objects changed: it keeps its place in the order
    assert [s.frame for s in idx.rank(q)] == ["b", "a", "c"]
    idx.remove("b")
    assert "b" not in idx and len(idx) == 2
    assert [s.frame for s in idx.rank(q, exclude="a")] == ["c"]
    assert idx.rank(np.zeros((0, 4))) == [] or all(s.score == 0 for s in idx.rank(
        np.zeros((0, 4))))


@pytest.mark.parametrize("bad", [np.full((2, 4), np.nan), np.ones(4), np.ones((2, 0))])
def test_bad_embeddings_are_refused(bad) -> None:
    idx = FleetIndex()
    with pytest.raises(InputError):
        idx.update("a", bad)
    idx.update("a", np.eye(4))
    with pytest.raises(InputError):
        idx.rank(bad)
    with pytest.raises(InputError, match="keep"):
        idx.rank(np.eye(4), keep=-1)
