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
    for f in ref:  # the index holds and multiplies float32 rows: cosines to about 1e-7
        assert got[f] == pytest.approx(ref[f], abs=1e-5), f
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


class StackedReference:
    """The index as it was (before its rows were held once): each frame's unit rows kept apart,
    stacked again for every ranking, in float32 as the index holds them. `rank` must give
    exactly what this gives."""

    def __init__(self) -> None:
        self.frames: dict[str, np.ndarray] = {}

    def update(self, frame: str, e: np.ndarray) -> None:
        a = np.asarray(e, dtype=np.float64)
        norm = np.linalg.norm(a, axis=1, keepdims=True)
        self.frames[frame] = (a / np.where(norm > 0, norm, 1.0)).astype(np.float32)

    def remove(self, frame: str) -> None:
        self.frames.pop(frame, None)

    def rank(self, e: np.ndarray, exclude: str | None = None, keep: int | None = None):
        a = np.asarray(e, dtype=np.float64)
        norm = np.linalg.norm(a, axis=1, keepdims=True)
        q = a / np.where(norm > 0, norm, 1.0)
        names = [f for f, r in self.frames.items() if r.shape[1] == q.shape[1] and len(r)]
        blocks = [self.frames[f] for f in names]
        rows = np.vstack(blocks) if blocks else np.zeros((0, q.shape[1]))
        starts = np.cumsum([0] + [len(b) for b in blocks[:-1]]).astype(np.int64)
        pick = [i for i, f in enumerate(names) if f != exclude]
        if not pick or not len(q):
            return [(names[i], 0.0) for i in pick][:keep]
        best = np.maximum.reduceat(q.astype(np.float32) @ rows.T, starts, axis=1)[:, pick]
        score = np.maximum(best - np.median(best, axis=1, keepdims=True), 0.0).sum(
            axis=0, dtype=np.float64)
        order = np.argsort(-score, kind="stable")
        out = [(names[pick[i]], float(score[i])) for i in order]
        return out if keep is None else out[:keep]


@pytest.mark.parametrize("seed", range(6))
def test_rank_is_exactly_the_stacked_reference_through_replacements_and_removals(
        seed: int) -> None:
    """Random updates (new frames, blocks grown, shrunk, emptied, replaced at the same size),
    removals and re-additions, a frame moving to another embedding size, two sizes at once:
    after every change the ranking (order and every score, bit for bit) is the reference's,
    and the rows are held once (N x d float32 per size)."""
    rng = np.random.default_rng(seed)
    idx, ref = FleetIndex(), StackedReference()
    names = [f"auv{k}/s{j}" for k in range(5) for j in range(4)]
    dims = (16, 16, 16, 7)  # mostly one size
    for step in range(150):
        f = names[int(rng.integers(len(names)))]
        if step % 11 == 5 and f in idx:
            idx.remove(f)
            ref.remove(f)
            assert f not in idx
        else:
            n = int(rng.choice([0, 1, 2, 3, 5, 8, 13]))
            d = int(rng.choice(dims))
            e = rng.normal(size=(n, d))
            if n and rng.random() < 0.2:
                e[0] = 0.0  # a zero row stays zero
            idx.update(f, e)
            ref.update(f, e)
        assert len(idx) == len(ref.frames)
        for d in (16, 7):
            q = rng.normal(size=(int(rng.integers(1, 6)), d))
            exclude = names[int(rng.integers(len(names)))]
            keep = None if step % 3 else int(rng.integers(0, 4))
            got = [(s.frame, s.score) for s in idx.rank(q, exclude=exclude, keep=keep)]
            assert got == ref.rank(q, exclude, keep), (seed, step, d)
    held = sum(r.size * 4 for r in ref.frames.values())
    assert idx.nbytes() == held


def test_rank_is_exactly_the_stacked_reference_on_a_served_fleet() -> None:
    """A fleet's sessions as the service updates them (a session's block grows submap after
    submap, sessions in time order), 384-d look-alike objects."""
    model, frames, rng = fleet(7, 12, 30, dim=384)
    idx, ref = FleetIndex(), StackedReference()
    for f, e in frames.items():
        for n in range(0, len(e) + 1, 4):  # grown 4 objects at a time, as submaps come in
            idx.update(f, e[:n])
            ref.update(f, e[:n])
            q = model.observe(e[:3], np.full(3, 0.3), rng) if n else rng.normal(size=(2, 384))
            assert [(s.frame, s.score) for s in idx.rank(q, exclude=f)] == ref.rank(q, f)
