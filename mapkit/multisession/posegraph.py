"""The pose graph over all submaps: odometry edges inside a session, ICP edges between sessions and
weak GPS priors, solved with scipy's robust least squares (:class:`PoseGraph`); and the
session-level offsets that start it inside the right basin (:func:`session_offsets`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from mapkit.core.config import MapkitConfig
from mapkit.multisession.registration import PairResult


class GraphConfig(MapkitConfig):
    prior_sigma_m: list[float] = Field([3.0, 3.0, 3.0], description="GPS prior on each submap's correction, east/north/up (m): weak, GPS drifts by metres.")
    prior_sigma_deg: float = Field(3.0, gt=0, description="Prior on each submap's rotation correction (deg).")
    odometry_sigma_m: float = Field(0.10, gt=0, description="How much two consecutive submaps of a session may disagree at their boundary (m).")
    icp_sigma_m: float = Field(0.10, gt=0, description="Uncertainty of an accepted ICP registration at its support points (m).")
    lever_m: float = Field(10.0, gt=0, description="Support points of an edge lie this far from its centre, so rotations are constrained too (m).")
    robust_scale: float = Field(3.0, gt=0, description="Cauchy loss scale, in sigmas, of the robust solve (applied to every whitened residual).")
    reject_sigmas: float = Field(6.0, gt=0, description="After the solve, an ICP edge whose RMS residual exceeds this many sigmas is rejected and the graph solved again.")
    max_rounds: int = Field(3, ge=1, description="Solve / reject rounds.")


@dataclass
class Edge:
    kind: str  # "odometry" | "icp"
    a: int  # node whose (current) frame the measurement starts from
    b: int
    support: np.ndarray  # (P, 3) support points in a's current frame
    target_from_source: np.ndarray  # (4, 4): a's current frame -> b's current frame
    sigma_m: float
    pair: Optional[int] = None  # index into the pair list (ICP edges)


def support_points(centre: np.ndarray, direction: np.ndarray, lever: float) -> np.ndarray:
    """Six points about ``centre`` (along and across the horizontal ``direction``, and up) where an
    edge's two frames are compared, ``lever`` from it so that rotations are constrained too."""
    d = np.array([direction[0], direction[1], 0.0])
    d = d / max(np.linalg.norm(d), 1e-9)
    lateral = np.array([-d[1], d[0], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    return np.stack([centre, centre + lever * d, centre - lever * d, centre + lever * lateral, centre - lever * lateral, centre + 0.5 * lever * up])


def _apply_node(x: np.ndarray, centres: np.ndarray, node: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Corrected positions of ``pts`` (E, P, 3) under nodes ``node`` (E,): p' = R (p - c) + c + t."""
    rv, t = x[node, :3], x[node, 3:]
    R = Rotation.from_rotvec(rv).as_matrix()  # (E, 3, 3)
    c = centres[node][:, None, :]
    return np.einsum("eij,epj->epi", R, pts - c) + c + t[:, None, :]


class PoseGraph:
    """Corrections of submaps: node k moves its submap's points by p' = R_k (p - c_k) + c_k + t_k.

    Residuals are distances at support points (so rotation and translation share one unit):
    odometry edges ask consecutive submaps of a session to move their common boundary alike,
    ICP edges ask T_a(p) = T_b(T_ab p), priors keep every correction near zero (GPS).
    """

    def __init__(self, centres: np.ndarray, cfg: GraphConfig, fixed: Optional[np.ndarray] = None, initial: Optional[np.ndarray] = None):
        self.centres = np.asarray(centres, np.float64)
        self.cfg = cfg
        n = len(self.centres)
        self.fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
        self.x0 = np.zeros((n, 6)) if initial is None else np.asarray(initial, np.float64).copy()
        self.edges: list[Edge] = []

    def add(self, edge: Edge) -> None:
        self.edges.append(edge)

    @staticmethod
    def _stack(edges: list[Edge]) -> Optional[tuple]:
        """Node indices, support points in both frames and sigmas of ``edges``, as arrays (built
        once per solve, not at every evaluation of the residuals)."""
        if not edges:
            return None
        a = np.array([e.a for e in edges])
        b = np.array([e.b for e in edges])
        P = np.stack([e.support for e in edges])  # (E, P, 3), in a's current frame
        Tab = np.stack([e.target_from_source for e in edges])
        Pb = np.einsum("eij,epj->epi", Tab[:, :3, :3], P) + Tab[:, None, :3, 3]  # the same points in b's frame
        return a, b, P, Pb, np.array([e.sigma_m for e in edges])

    def _edge_displacements(self, x: np.ndarray, stacked: tuple) -> np.ndarray:
        """(E, P, 3) disagreement T_a(p) - T_b(T_ab p) at every support point, in metres."""
        a, b, P, Pb, _ = stacked
        return _apply_node(x, self.centres, a, P) - _apply_node(x, self.centres, b, Pb)

    def _residuals(self, x_free: np.ndarray, stacked: Optional[tuple]) -> np.ndarray:
        x = self.x0.copy()
        x[~self.fixed] = x_free.reshape(-1, 6)
        free = np.flatnonzero(~self.fixed)
        out = [(x[free, 3:] / np.asarray(self.cfg.prior_sigma_m)).ravel(), (x[free, :3] / np.radians(self.cfg.prior_sigma_deg)).ravel()]
        if stacked is not None:
            out.append((self._edge_displacements(x, stacked) / stacked[4][:, None, None]).ravel())
        return np.concatenate(out)

    def solve(self, edges: Optional[list[Edge]] = None) -> np.ndarray:
        """Corrections (n, 6) = [rotation vector, translation at the centre]."""
        from scipy.optimize import least_squares
        from scipy.sparse import lil_matrix

        edges = self.edges if edges is None else edges
        free = np.flatnonzero(~self.fixed)
        if len(free) == 0:
            return self.x0.copy()
        col = -np.ones(len(self.centres), np.int64)
        col[free] = np.arange(len(free))
        stacked = self._stack(edges)
        n_res = len(self._residuals(self.x0[free].ravel(), stacked))
        S = lil_matrix((n_res, 6 * len(free)), dtype=np.int8)
        row = 0
        for k in range(len(free)):  # translation priors, then rotation priors
            S[row + 3 * k : row + 3 * k + 3, 6 * k + 3 : 6 * k + 6] = 1
        row += 3 * len(free)
        for k in range(len(free)):
            S[row + 3 * k : row + 3 * k + 3, 6 * k : 6 * k + 3] = 1
        row += 3 * len(free)
        for e in edges:
            m = 3 * len(e.support)
            for node in (e.a, e.b):
                if col[node] >= 0:
                    S[row : row + m, 6 * col[node] : 6 * col[node] + 6] = 1
            row += m
        # one Cauchy loss on every whitened row (scipy applies it to all residuals): rows within
        # a few sigmas stay nearly quadratic, a wrong ICP edge far out loses its pull
        res = least_squares(self._residuals, self.x0[free].ravel(), jac_sparsity=S.tocsr(), args=(stacked,),
                            loss="cauchy", f_scale=self.cfg.robust_scale, method="trf", x_scale="jac", max_nfev=200)
        x = self.x0.copy()
        x[free] = res.x.reshape(-1, 6)
        return x

    def edge_rms_sigmas(self, x: np.ndarray, edges: list[Edge]) -> np.ndarray:
        """RMS residual of each edge, in its sigmas."""
        stacked = self._stack(edges)
        if stacked is None:
            return np.zeros(0)
        d = np.linalg.norm(self._edge_displacements(x, stacked), axis=2)
        return np.sqrt(np.mean(d**2, axis=1)) / stacked[4]


# --- session offsets -------------------------------------------------------------------------------


def session_offsets(pairs: list[PairResult], names: list[str], fixed: Optional[dict[str, np.ndarray]] = None,
                    iterations: int = 10, huber_m: float = 0.5) -> dict[str, np.ndarray]:
    """One translation per session from the accepted registrations: o_a - o_b = d_ab, where d_ab
    moves source a onto target b at the pair centre; iteratively reweighted (Huber) least squares,
    sessions in ``fixed`` held, otherwise the mean offset is zero (the GPS frame on average)."""
    fixed = fixed or {}
    idx = {n: k for k, n in enumerate(names)}
    rows = [(idx[p.source[0]], idx[p.target[0]], p.target_from_source[:3, :3] @ p.centre + p.target_from_source[:3, 3] - p.centre)
            for p in pairs if p.source[0] in idx and p.target[0] in idx]
    out = {n: np.asarray(fixed.get(n, np.zeros(3)), np.float64) for n in names}
    if not rows:
        return out
    n = len(names)
    free = [k for k in range(n) if names[k] not in fixed]
    w = np.ones(len(rows))
    o = np.array([out[nm] for nm in names])
    for _ in range(iterations):
        A = np.zeros((len(rows) + 1, n))
        b = np.zeros((len(rows) + 1, 3))
        for r, (ia, ib, d) in enumerate(rows):
            A[r, ia], A[r, ib], b[r] = w[r], -w[r], w[r] * d
        if fixed:  # fixed sessions: move their terms to the right-hand side
            for k in range(n):
                if k not in free:
                    b -= np.outer(A[:, k], o[k])
                    A[:, k] = 0
        else:
            A[-1, :] = 1.0  # gauge: zero mean
        sol, *_ = np.linalg.lstsq(A[:, free], b, rcond=None)
        o[free] = sol
        res = np.linalg.norm(np.array([o[ia] - o[ib] - d for ia, ib, d in rows]), axis=1)
        w = np.where(res <= huber_m, 1.0, huber_m / np.maximum(res, 1e-12)) ** 0.5
    return {nm: o[k] for k, nm in enumerate(names)}
