"""Noise calibration of a pose graph from its own residuals: variance-component estimation.

Factors fall into groups (a robot's odometry, the inter-robot closures); each group's declared
covariances are scaled per axis (GTSAM order: rotation, then translation) in decorrelated
coordinates: the rotation error, and the translation error less the part the rotation error
explains (`scale_covariance`). After a solve, each group and axis gets the REML fixed point of
a per-axis variance component (Foerstner's estimator), in those coordinates:

    s_a^2 <- (s_a^2 * sum_i e_ia (W_i e_i)_a + nu) / (sum_i (W_i Q_i)_aa + nu)

with the redundancies from a seeded Monte-Carlo trace estimate (one sparse factorisation and a
few solves) and nu pseudo-observations at the declared scale. Factors whose NEES is beyond
`gross_quantile` are left out. Nothing here uses the truth. Pure: no I/O. docs/uncertainty.md.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from pydantic import BaseModel, ConfigDict, Field

from mergesvc.core.chi2 import chi2_quantile
from mergesvc.errors import SolverError

# draws the redundancy's square is estimated from (at most): its Gram matrix holds k^2 numbers
# per group and axis, and each factor adds k^2 products to it
GRAM_DRAWS = 64


class CalibrationConfig(BaseModel):
    """Settings of the noise calibration (variance-component estimation)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(True, description="scale each group's covariances per axis to what "
                          "the residuals show (variance-component estimation)")
    samples: int = Field(32, ge=4, le=1024, description="Monte-Carlo draws of the redundancy "
                         "numbers' estimate")
    prior_redundancy: float = Field(
        2.0, ge=0.0, description="pseudo-observations at the current scale: an axis the graph "
        "checks less than this keeps most of its declared scale")
    min_scale: float = Field(0.05, gt=0.0, description="smallest sigma scale of an axis")
    max_scale: float = Field(20.0, gt=0.0, description="largest sigma scale of an axis")
    gross_quantile: float = Field(
        0.999, gt=0.0, lt=1.0, description="a factor whose NEES exceeds this chi-square "
        "quantile (6 dof) is left out of the estimate (a gross error, not noise)")
    seed: int = Field(0, description="the Monte-Carlo draws' seed")
    groups: tuple[str, ...] = Field(
        ("odometry",), description="the noise groups calibrated, by the name before any ':' "
        "(odometry:auv1 is odometry); the others keep their declared scale. Inter-robot "
        "factors ('closures') are left out by default: successive ones share objects, and "
        "their residuals understate their errors (docs/uncertainty.md)")
    every_growth: float = Field(
        0.25, ge=0.0, description="calibrate again once the solved graph holds this fraction "
        "more factors than at the last calibration (0: at every solve); each calibration is "
        "a pass over the whole graph and moves every noise model, so a large graph would pay "
        "it at every solve")
    resolves: int = Field(2, ge=0, le=10, description="solves again at most this many times "
                          "after one that moved a scale by more than resolve_change")
    resolve_change: float = Field(0.1, gt=0.0, description="relative change of a sigma "
                                  "scale that makes the graph solve again with it")


@dataclass
class Component:
    """One group's sums for one estimate: per axis, the residual part and the redundancy."""

    residual: np.ndarray = field(default_factory=lambda: np.zeros(6))
    redundancy: np.ndarray = field(default_factory=lambda: np.zeros(6))
    # per axis, the sum of the squared eigenvalues of the residuals' share of the axis (each
    # in [0, 1], summing to the redundancy): the residual sum's variance is twice this
    redundancy_sq: np.ndarray = field(default_factory=lambda: np.zeros(6))
    factors: int = 0
    left_out: int = 0


def decorrelation(C: np.ndarray) -> np.ndarray:
    """L (6, 6) with L x = (r, t - B r), B = C_tr C_rr^-1: the translation error less the part
    the rotation error explains (a heading error moved the position sideways along the path),
    so that L C L^T is block diagonal. Identity for a covariance without cross terms."""
    L = np.eye(6)
    C_rr, C_tr = C[:3, :3], C[3:, :3]
    if np.any(C_tr):
        L[3:, :3] = -np.linalg.solve(C_rr, C_tr.T).T
    return L


def scale_covariance(C: np.ndarray, sigma_scale: np.ndarray) -> np.ndarray:
    """C scaled per axis in the decorrelated coordinates (`decorrelation`): rotation errors by
    s[:3], and with them the position error they cause; the rest of the translation error by
    s[3:]. M C M^T with M = L^-1 diag(s) L."""
    return scale_covariances(np.asarray(C, dtype=np.float64)[None], sigma_scale)[0]


def scale_covariances(Cs: np.ndarray, sigma_scale: np.ndarray) -> np.ndarray:
    """`scale_covariance` of a stack (n, 6, 6) of covariances by one scale, at once (L as
    `decorrelation` builds it, for each)."""
    Cs = np.asarray(Cs, dtype=np.float64).reshape(-1, 6, 6)
    L = np.broadcast_to(np.eye(6), Cs.shape).copy()
    cross = np.any(Cs[:, 3:, :3] != 0, axis=(1, 2))
    if np.any(cross):
        C = Cs[cross]
        L[cross, 3:, :3] = -np.swapaxes(np.linalg.solve(C[:, :3, :3],
                                                        np.swapaxes(C[:, 3:, :3], 1, 2)), 1, 2)
    M = np.linalg.solve(L, np.asarray(sigma_scale)[None, :, None] * L)
    out = M @ Cs @ np.swapaxes(M, 1, 2)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def factor_normal_matrix(H: sp.csc_matrix) -> sla.SuperLU:
    """LU of a normal matrix H = A^T A (symmetric positive definite) in a fill-reducing order,
    each pivot on the diagonal (rows permuted as the columns): what a Cholesky factorisation
    would keep. SuperLU's default partial pivoting permutes the rows away from that order, and
    on a fleet's loop-closed pose graph fills the factor several times over
    (docs/benchmarks/soak.md). RuntimeError when H is singular."""
    return sla.splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                    options={"SymmetricMode": True})


def variance_components(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    groups: Sequence[str | None],
    config: CalibrationConfig,
) -> dict[str, Component]:
    """Per group, the per-axis sums of the estimator (module docstring) at `values`.

    groups[i] names the group of graph factor i (None: not calibrated, e.g. a prior; it still
    counts in the solve). Every factor must be 6-dimensional (Pose3). Raises SolverError when
    the linearised system is singular."""
    if len(groups) != graph.size():
        raise SolverError(f"{len(groups)} groups for {graph.size()} factors")
    cols: dict[int, int] = {}
    rows, cs, vals = [], [], []
    b_all = np.zeros(6 * graph.size())
    sqrt_info: list[np.ndarray] = []
    for i in range(graph.size()):
        f = graph.at(i)
        jf = f.linearize(values)
        A, b = jf.jacobian()
        if A.shape[0] != 6:
            raise SolverError(f"factor {i} is {A.shape[0]}-dimensional, not a Pose3 factor")
        b_all[6 * i:6 * i + 6] = b
        for j, key in enumerate(jf.keys()):
            c0 = cols.setdefault(key, 6 * len(cols))
            blk = A[:, 6 * j:6 * j + 6]
            r, c = np.nonzero(blk)
            rows.append(6 * i + r)
            cs.append(c0 + c)
            vals.append(blk[r, c])
        sqrt_info.append(np.asarray(f.noiseModel().R(), dtype=np.float64)
                         if groups[i] is not None else np.eye(6))
    A_s = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cs))),
                        shape=(6 * graph.size(), 6 * len(cols)))
    try:
        lu = factor_normal_matrix((A_s.T @ A_s).tocsc())
    except RuntimeError as exc:  # singular: a direction no factor fixes
        raise SolverError(f"calibration: the linearised system is singular: {exc}") from exc
    rng = np.random.default_rng(config.seed)
    Z = rng.standard_normal((A_s.shape[0], config.samples))
    res = Z - A_s @ lu.solve(np.asarray(A_s.T @ Z))  # residuals of pure noise: I - A H^-1 A^T
    gross = chi2_quantile(config.gross_quantile, 6)
    out: dict[str, Component] = defaultdict(Component)
    k = min(config.samples, GRAM_DRAWS)
    gram: dict[str, np.ndarray] = defaultdict(lambda: np.zeros((6, k, k)))
    for i, g in enumerate(groups):
        if g is None:
            continue
        comp = out[g]
        r_w = -b_all[6 * i:6 * i + 6]  # whitened residual R e
        if float(r_w @ r_w) > gross:
            comp.left_out += 1
            continue
        R = sqrt_info[i]
        R_inv = np.linalg.inv(R)
        e = R_inv @ r_w
        We = R.T @ r_w
        blk = res[6 * i:6 * i + 6]
        Q_w = blk @ blk.T / config.samples  # whitened residual covariance, R Q R^T
        WQ = R.T @ Q_w @ R_inv.T  # W Q = R^T (R Q R^T) R^-T
        # per axis of the decorrelated coordinates z = L e (scale_covariance's axes):
        # e_z (W_z e_z) and (W_z Q_z), with W_z = L^-T W L^-1, Q_z = L Q L^T
        L = decorrelation(R_inv @ R_inv.T)
        L_invT = np.linalg.inv(L).T
        comp.residual += (L @ e) * (L_invT @ We)
        comp.redundancy += np.diag(L_invT @ WQ @ L.T)
        comp.factors += 1
        # the first k draws, per axis: its share of the residuals' projection is (1/k) U_a V_a^T
        # over the group's factors; sum_ij U V^T U V^T through the (k, k) Gram V^T U
        gram[g] += np.einsum("as,at->ast", L @ R_inv @ blk[:, :k], L_invT @ R.T @ blk[:, :k])
    for g, G in gram.items():
        # trace(M^2) of the estimate less its sampling bias (trace(M)^2 / k of k draws)
        raw = np.einsum("ast,ats->a", G, G) / k**2
        r = np.einsum("ass->a", G) / k  # trace(M) from the same draws
        out[g].redundancy_sq = np.maximum((raw - r * r / k) / (1.0 + 1.0 / k), 0.0)
    return dict(out)


def scale_standard_error(comp: Component) -> np.ndarray:
    """Relative standard error (6,) of each axis's sigma scale from one estimate's residuals:
    the residual sum is a sum of chi-square(1) terms weighted by the eigenvalues l of the
    axis's share of the residuals (sum l = r, the redundancy), so the variance estimate
    has a relative variance 2 sum l^2 / r^2 and the sigma half its relative deviation,
    sqrt(sum l^2 / 2) / r; at most 1 / sqrt(2 r) (every l <= 1). What the residuals alone give
    (the prior's pull aside, the other groups' covariances taken as right); inf where nothing
    checks the axis (r <= 0)."""
    r = np.asarray(comp.redundancy, dtype=np.float64)
    q = np.minimum(np.asarray(comp.redundancy_sq, dtype=np.float64), np.maximum(r, 0.0))
    out = np.full(r.shape, np.inf)
    np.divide(np.sqrt(0.5 * q), r, out=out, where=r > 0)
    return out


def updated_scale(scale: np.ndarray, comp: Component, config: CalibrationConfig) -> np.ndarray:
    """A group's sigma scale (6,) after one estimate at `scale`: the fixed-point step with
    `prior_redundancy` pseudo-observations at the declared scale (1), so an axis the graph
    checks little stays near what was declared; clamped to [min_scale, max_scale]."""
    nu = config.prior_redundancy
    s2 = np.square(np.asarray(scale, dtype=np.float64))
    num = s2 * np.maximum(comp.residual, 0.0) + nu  # the residuals at the declared scale
    den = np.maximum(comp.redundancy, 0.0) + nu
    var = np.divide(num, den, out=s2.copy(), where=den > 0)
    return np.clip(np.sqrt(var), config.min_scale, config.max_scale)


__all__ = ["CalibrationConfig", "Component", "decorrelation", "factor_normal_matrix",
           "scale_covariance", "scale_covariances", "scale_standard_error", "updated_scale",
           "variance_components"]
