"""The pose graph over all submaps, on GTSAM: odometry edges inside a session, ICP edges between
sessions as robust between factors, and GPS through one bias state per session, solved
incrementally with iSAM2 (:class:`PoseGraph`); and the session-level offsets that start it inside
the right basin (:func:`session_offsets`).

Node k is the pose ``X_k = (R_k, c_k + t_k)`` of submap k's frame (origin at its centre c_k, axes
ENU), so its correction moves a point by ``p' = R_k (p - c_k) + c_k + t_k``. An edge asks two
submaps to agree on the points both hold (``T_a p = T_b T_ab p``); its information is that of its
support points (distances in metres, so rotation and translation share one unit). The GPS model
is the receiver's: every fix of a drive carries one slowly varying bias, so a session's submaps
share a bias state ``b_s`` (prior ``gps_bias_sigma_m``) and each submap's correction is
``t_k = -b_s`` up to ``gps_submap_sigma_m``. N sessions that ICP ties together then sit at the
mean of their N biases, and the marginal covariances say so: a submap's position is known to
about ``gps_bias_sigma_m / sqrt(N)``, not to the GPS noise averaged over thousands of fixes.
Registrations that are wrong together (a sparse map registered onto the wrong wall at the few
places that tie its session) are an error the graph cannot see: the covariances consider one per
session (``tie_sigma_m``), so a session that few registrations tie keeps about the uncertainty of
its own GPS bias and odometry, and one that many tie keeps nearly the graph's marginals.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from mapkit.core.config import MapkitConfig
from mapkit.core.geometry import skew
from mapkit.multisession.registration import PairResult

if TYPE_CHECKING:
    import gtsam


class GraphConfig(MapkitConfig):
    gps_bias_sigma_m: list[float] = Field(
        [2.0, 2.0, 4.0],
        min_length=3,
        max_length=3,
        description="Prior on each session's GPS bias, east/north/up (m): the offset all fixes "
        "of one drive share (a receiver's bias wanders over minutes). 2 m horizontal, twice "
        "that vertical: a consumer receiver's order, and the synthetic town's GPS model.",
    )
    gps_submap_sigma_m: float = Field(
        1.0,
        gt=0,
        description="How far one submap's correction may depart from its session's "
        "bias (m): what the session's rigid GPS fit leaves along the drive.",
    )
    prior_sigma_deg: float = Field(3.0, gt=0, description="Prior on each submap's rotation correction (deg).")
    odometry_sigma_m: float = Field(
        0.10,
        gt=0,
        description="How much two consecutive submaps of a session may disagree at their boundary (m), "
        "on a trajectory of kiss-icp fitted rigidly to GPS (the build's default).",
    )
    odometry_sigma_fused_m: float = Field(
        0.02,
        gt=0,
        description="... on the factor graph's trajectory (georef.fuse: IMU, GPS and kiss-icp), "
        "which holds a drive together to centimetres (offset-removed ATE 0.03-0.08 m on the tiny town). "
        "Misalignment between drives (eval_align's median) on tiny towns of seeds 7, 8 and 9: 0.053, "
        "0.058, 0.051 m at 0.02 against 0.058, 0.051, 0.073 m at 0.10 (towns of `mapkit synth --preset tiny "
        "--seed S` built with configs/build/demo.yaml; `mapkit align WS -c V.yaml`, V.yaml setting this "
        "field, then `mapkit eval align WS --truth TOWN`). One demo town gave the opposite order (0.058 m "
        "against 0.053 m), a difference inside the spread between towns.",
    )
    icp_sigma_m: float = Field(
        0.10, gt=0, description="Uncertainty of an accepted ICP registration at its support points (m)."
    )
    tie_sigma_m: float = Field(
        3.0,
        ge=0,
        description="How far the accepted registrations of one session may be wrong together (m, per axis): a "
        "sparse or repetitive map registers onto the wrong surface the same way at neighbouring places, an error "
        "no residual shows. The covariances consider it, tie_sigma_m / sqrt(n) with n the session's submaps tied "
        "to each other session by a kept registration (independent places and maps); the estimate still follows the "
        "registrations. 0 = off. 3 m: a wrong registration lands within ICP's first-level reach (4 m) of the right "
        "one. Its cost where registrations are right, on the tiny town of seed 7 (`mapkit synth --preset tiny "
        "--seed 7`, built with configs/build/demo.yaml; every accepted registration within 0.37 m of the truth): "
        "horizontal position sigmas 1.2 -> 1.45 m, median NEES 1.9 -> 1.4, every submap inside its 95% ellipsoid "
        "either way.",
    )
    lever_m: float = Field(
        10.0,
        gt=0,
        description="Support points of an edge lie this far from its centre, so rotations are constrained too (m).",
    )
    robust_scale: float = Field(
        3.0, gt=0, description="Cauchy kernel width, in sigmas (Mahalanobis), of every edge factor."
    )
    reject_sigmas: float = Field(
        6.0,
        gt=0,
        description="After the solve, an ICP edge whose RMS residual exceeds this many sigmas is rejected and its "
        "factor removed from the graph.",
    )
    max_rounds: int = Field(3, ge=1, description="Solve / reject rounds.")
    relinearize_threshold: float = Field(
        1e-3, gt=0, description="iSAM2 relinearises a variable whose update exceeds this (rad or m)."
    )
    max_updates: int = Field(
        20,
        ge=1,
        description="iSAM2 updates after the last factor was added, until the estimate moves less than the threshold.",
    )


@dataclass
class Edge:
    kind: str  # "odometry" | "icp"
    a: int  # node whose (current) frame the measurement starts from
    b: int
    support: np.ndarray  # (P, 3) support points in a's current frame
    target_from_source: np.ndarray  # (4, 4): a's current frame -> b's current frame
    sigma_m: float
    pair: int | None = None  # index into the pair list (ICP edges)


def support_points(centre: np.ndarray, direction: np.ndarray, lever: float) -> np.ndarray:
    """Six points about ``centre`` (along and across the horizontal ``direction``, and up) where an
    edge's two frames are compared, ``lever`` from it so that rotations are constrained too."""
    d = np.array([direction[0], direction[1], 0.0])
    d = d / max(np.linalg.norm(d), 1e-9)
    lateral = np.array([-d[1], d[0], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    return np.stack(
        [
            centre,
            centre + lever * d,
            centre - lever * d,
            centre + lever * lateral,
            centre - lever * lateral,
            centre + 0.5 * lever * up,
        ]
    )


def _apply_node(x: np.ndarray, centres: np.ndarray, node: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Corrected positions of ``pts`` (E, P, 3) under nodes ``node`` (E,): p' = R (p - c) + c + t."""
    rv, t = x[node, :3], x[node, 3:]
    R = Rotation.from_rotvec(rv).as_matrix()  # (E, 3, 3)
    c = centres[node][:, None, :]
    return np.einsum("eij,epj->epi", R, pts - c) + c + t[:, None, :]


def support_information(local: np.ndarray, sigma_m: float) -> np.ndarray:
    """(6, 6) information, in gtsam's Pose3 tangent (rotation, translation), of comparing the points
    ``local`` (P, 3; relative to the node's origin, in its axes) to ``sigma_m`` each: a right
    perturbation (w, v) moves q by w x q + v, so the Jacobian of each point is [-[q]x, I]."""
    J = np.concatenate([np.hstack([-skew(q), np.eye(3)]) for q in local])
    return J.T @ J / sigma_m**2


def _shift(c: np.ndarray) -> np.ndarray:
    S = np.eye(4)
    S[:3, 3] = c
    return S


def _bias_error(centre: np.ndarray):
    """Submap correction plus its session's GPS bias: ``(t(X) - c) + b``; d t(X) / d(w, v) = [0, R]."""

    def error(this, values, H):
        pose = values.atPose3(this.keys()[0])
        bias = values.atPoint3(this.keys()[1])
        if H is not None:
            H[0] = np.hstack([np.zeros((3, 3)), pose.rotation().matrix()])
            H[1] = np.eye(3)
        return pose.translation() - centre + bias

    return error


class PoseGraph:
    """Corrections of submaps on a GTSAM factor graph solved by iSAM2 (see the module's docstring).

    Sessions enter one at a time, each with its own nodes, odometry, GPS and the ICP edges to the
    sessions before it, as iSAM2 updates; rejected ICP edges leave by factor removal, not by a new
    solve. Nodes in ``fixed`` (sessions aligned by an earlier run) are not variables: an edge to one
    becomes a prior on the other end. ``session_of`` (n,) groups nodes into sessions (one GPS bias
    each); by default every node is its own session.
    """

    def __init__(
        self,
        centres: np.ndarray,
        cfg: GraphConfig,
        fixed: np.ndarray | None = None,
        initial: np.ndarray | None = None,
        session_of: np.ndarray | None = None,
    ):
        self.centres = np.asarray(centres, np.float64)
        self.cfg = cfg
        n = len(self.centres)
        self.fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
        self.x0 = np.zeros((n, 6)) if initial is None else np.asarray(initial, np.float64).copy()
        self.session_of = np.arange(n) if session_of is None else np.asarray(session_of, np.int64)
        self.edges: list[Edge] = []
        self._active: list[Edge] = []  # the edges of the solved graph (solve's, less those removed)
        self._considered: tuple[np.ndarray, dict[int, np.ndarray]] | None = None
        self._isam: gtsam.ISAM2 | None = None
        self._factor_of: dict[int, int] = {}  # id(edge) -> iSAM2 factor index
        self.updates = 0

    def add(self, edge: Edge) -> None:
        self.edges.append(edge)

    # -- conversions -------------------------------------------------------------------------------

    def _pose(self, x: np.ndarray, k: int):
        import gtsam

        return gtsam.Pose3(gtsam.Rot3(Rotation.from_rotvec(x[k, :3]).as_matrix()), self.centres[k] + x[k, 3:])

    def _x_of(self, values) -> np.ndarray:
        import gtsam

        x = self.x0.copy()
        for k in np.flatnonzero(~self.fixed):
            p = values.atPose3(gtsam.symbol("x", int(k)))
            x[k, :3] = Rotation.from_matrix(p.rotation().matrix()).as_rotvec()
            x[k, 3:] = p.translation() - self.centres[k]
        return x

    # -- factors -----------------------------------------------------------------------------------

    def _edge_factor(self, e: Edge):
        """``e`` as a robust factor on its free end(s): BetweenFactor(X_b, X_a, M) with
        ``M = S_b T_ab S_a^-1`` (S_k moves c_k to the origin), its error in a's frame; with a fixed,
        the reverse (error in b's frame); with one end fixed, a prior on the other. None if both are fixed."""
        import gtsam

        if self.fixed[e.a] and self.fixed[e.b]:
            return None
        M = _shift(-self.centres[e.b]) @ e.target_from_source @ _shift(self.centres[e.a])
        if not self.fixed[e.a]:
            this, other, meas = e.a, e.b, M
            local = e.support - self.centres[e.a]
        else:
            this, other, meas = e.b, e.a, np.linalg.inv(M)
            local = e.support @ e.target_from_source[:3, :3].T + e.target_from_source[:3, 3] - self.centres[e.b]
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(self.cfg.robust_scale),
            gtsam.noiseModel.Gaussian.Information(support_information(local, e.sigma_m)),
        )
        X = lambda k: gtsam.symbol("x", int(k))  # noqa: E731 (a one-line helper local to this function)
        if self.fixed[other]:
            return gtsam.PriorFactorPose3(X(this), self._pose(self.x0, other).compose(gtsam.Pose3(meas)), noise)
        return gtsam.BetweenFactorPose3(X(other), X(this), gtsam.Pose3(meas), noise)

    def _session_block(self, s: int, edges: list[Edge], x_init: np.ndarray):
        """Values and factors of session ``s``'s free nodes: poses, its bias, GPS and rotation
        priors, and ``edges`` (those that are now fully inside the graph)."""
        import gtsam

        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        nodes = [int(k) for k in np.flatnonzero((self.session_of == s) & ~self.fixed)]
        owned: list[Edge] = []
        if nodes:
            b = gtsam.symbol("b", s)
            values.insert(b, -x_init[nodes, 3:].mean(axis=0))
            graph.add(
                gtsam.PriorFactorPoint3(
                    b, np.zeros(3), gtsam.noiseModel.Diagonal.Sigmas(np.asarray(self.cfg.gps_bias_sigma_m, float))
                )
            )
            rot_prior = gtsam.noiseModel.Diagonal.Sigmas(
                np.r_[np.full(3, np.radians(self.cfg.prior_sigma_deg)), np.full(3, 1e4)]
            )
            gps = gtsam.noiseModel.Isotropic.Sigma(3, self.cfg.gps_submap_sigma_m)
            for k in nodes:
                xk = gtsam.symbol("x", k)
                values.insert(xk, self._pose(x_init, k))
                graph.add(gtsam.PriorFactorPose3(xk, gtsam.Pose3(gtsam.Rot3(), self.centres[k]), rot_prior))
                graph.add(gtsam.CustomFactor(gps, [xk, b], _bias_error(self.centres[k])))
        for e in edges:
            f = self._edge_factor(e)
            if f is not None:
                owned.append(e)
                graph.add(f)
        return graph, values, owned

    # -- solving -----------------------------------------------------------------------------------

    def solve(self, edges: list[Edge] | None = None) -> np.ndarray:
        """Corrections (n, 6) = [rotation vector, translation at the centre], sessions added one
        iSAM2 update at a time (each with the edges to the sessions already in)."""
        import gtsam

        edges = self.edges if edges is None else edges
        self._active, self._considered = list(edges), None
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.cfg.relinearize_threshold)
        params.relinearizeSkip = 1
        self._isam, self._factor_of, self.updates = gtsam.ISAM2(params), {}, 0
        if self.fixed.all():
            return self.x0.copy()
        sessions = list(dict.fromkeys(self.session_of.tolist()))  # in node order
        rank = {s: r for r, s in enumerate(sessions)}
        entered = lambda e: max(rank[self.session_of[e.a]], rank[self.session_of[e.b]])  # noqa: E731 (a one-line helper local to this function)
        for r, s in enumerate(sessions):
            graph, values, owned = self._session_block(s, [e for e in edges if entered(e) == r], self.x0)
            if graph.size() == 0 and values.size() == 0:
                continue
            res = self._isam.update(graph, values)
            self.updates += 1
            for e, idx in zip(owned, list(res.getNewFactorsIndices())[graph.size() - len(owned) :], strict=True):
                self._factor_of[id(e)] = int(idx)
        return self._converge()

    def remove(self, edges: list[Edge]) -> np.ndarray:
        """Take ``edges`` out of the solved graph (iSAM2 factor removal) and return the new corrections."""
        import gtsam

        idx = [self._factor_of.pop(id(e)) for e in edges if id(e) in self._factor_of]
        gone = {id(e) for e in edges}
        self._active, self._considered = [e for e in self._active if id(e) not in gone], None
        if idx:
            assert self._isam is not None  # factor indices come from solve's iSAM2
            self._isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), idx)
            self.updates += 1
        return self._converge()

    def _converge(self) -> np.ndarray:
        if self._isam is None or self.fixed.all():
            return self.x0.copy()
        x = self._x_of(self._isam.calculateEstimate())
        for _ in range(self.cfg.max_updates):
            self._isam.update()
            self.updates += 1
            x_new = self._x_of(self._isam.calculateEstimate())
            moved = np.abs(x_new - x).max()
            x = x_new
            if moved < self.cfg.relinearize_threshold:
                break
        return x

    def covariances(self) -> np.ndarray:
        """(n, 6, 6) covariance of every node's correction, (rotation rad, translation m) in ENU axes
        at the submap's centre: its marginal covariance in the graph plus what an error shared by a
        session's registrations would move it (:meth:`_tie_covariances`); zeros for fixed nodes
        (they are not estimated here)."""
        import gtsam

        n = len(self.centres)
        out = np.zeros((n, 6, 6))
        if self._isam is None:
            return out
        est = self._isam.calculateEstimate()
        ties, _ = self._tie_covariances()
        for k in np.flatnonzero(~self.fixed):
            xk = gtsam.symbol("x", int(k))
            R = est.atPose3(xk).rotation().matrix()
            A = np.kron(np.eye(2), R)  # body (rotation, translation) -> ENU axes
            out[k] = A @ (self._isam.marginalCovariance(xk) + ties[k]) @ A.T
        return out

    def biases(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Each session with free nodes: its GPS bias estimate (ENU, m) and covariance (3, 3), the
        latter with the registrations' shared errors considered as in :meth:`covariances`."""
        import gtsam

        out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        if self._isam is None:
            return out
        est = self._isam.calculateEstimate()
        _, ties = self._tie_covariances()
        for s in sorted(set(self.session_of[~self.fixed].tolist())):
            b = gtsam.symbol("b", int(s))
            out[int(s)] = (np.asarray(est.atPoint3(b)), np.asarray(self._isam.marginalCovariance(b)) + ties[int(s)])
        return out

    def _tie_covariances(self) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """The covariance that errors shared by each session's registrations add: (n, 6, 6) per node
        (gtsam's tangent: rotation, translation in the node's axes) and (3, 3) per session's bias.

        The graph takes every accepted registration as independent, right to ``icp_sigma_m``, so a
        session tied by a few registrations that are wrong the same way (metres off, agreeing with each
        other) is placed by them as confidently as by many right ones. A consider covariance (Schmidt)
        keeps the estimate and adds the error such a shared offset r_s of session s's registrations
        would cause, r_s ~ N(0, tie_sigma_m^2 / n_s I), n_s the pairs (own submap, other session) that a
        registration ties: S_s Sigma_r S_s^T, with S_s the estimate's sensitivity to r_s, from GTSAM's solve of the
        graph linearised at the estimate with the registrations shifted (their robust weights kept).
        A session that many places tie keeps nearly the graph's covariance; one that few places tie
        gets back about what its GPS bias and odometry alone allow."""
        import gtsam

        if self._considered is not None:
            return self._considered
        n = len(self.centres)
        nodes, biases = np.zeros((n, 6, 6)), {int(s): np.zeros((3, 3)) for s in set(self.session_of.tolist())}
        self._considered = (nodes, biases)
        icp = [e for e in self._active if e.kind == "icp" and not (self.fixed[e.a] and self.fixed[e.b])]
        if self._isam is None or self.cfg.tie_sigma_m <= 0 or not icp:
            return self._considered
        est = self._isam.calculateEstimate()
        free = np.flatnonzero(~self.fixed)
        sessions = sorted(set(self.session_of[free].tolist()))
        base = self._batch(self._active).linearize(est).optimize()
        step = 0.01  # m; small, so that the robust kernels weigh the shifted residuals as the estimate's own
        for s in sessions:
            mine = [e for e in icp if (self.session_of[e.a] == s) != (self.session_of[e.b] == s)]
            # independent evidence: each of the session's submaps tied to each other session (one map onto another)
            tied = {
                (e.a, int(self.session_of[e.b])) if self.session_of[e.a] == s else (e.b, int(self.session_of[e.a]))
                for e in mine
            }
            if not tied:
                continue
            var = self.cfg.tie_sigma_m**2 / len(tied)
            S_x, S_b = np.zeros((n, 6, 3)), {t: np.zeros((3, 3)) for t in sessions}
            for j in range(3):
                shift = _shift(step * np.eye(3)[j])
                moved = {
                    id(e): Edge(
                        e.kind,
                        e.a,
                        e.b,
                        e.support,
                        (shift if self.session_of[e.a] == s else np.linalg.inv(shift)) @ e.target_from_source,
                        e.sigma_m,
                        e.pair,
                    )
                    for e in mine
                }
                d = self._batch([moved.get(id(e), e) for e in self._active]).linearize(est).optimize()
                for k in free:
                    xk = gtsam.symbol("x", int(k))
                    S_x[k, :, j] = (d.at(xk) - base.at(xk)) / step
                for t in sessions:
                    b = gtsam.symbol("b", t)
                    S_b[t][:, j] = (d.at(b) - base.at(b)) / step
            nodes += var * np.einsum("kij,klj->kil", S_x, S_x)
            for t in sessions:
                biases[t] += var * S_b[t] @ S_b[t].T
        return self._considered

    def _batch(self, edges: list[Edge]):
        """The whole graph as one NonlinearFactorGraph (what iSAM2 holds after its updates, with ``edges``)."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for s in dict.fromkeys(self.session_of.tolist()):
            block, _, _ = self._session_block(s, [], self.x0)
            graph.push_back(block)
        for e in edges:
            f = self._edge_factor(e)
            if f is not None:
                graph.add(f)
        return graph

    def edge_rms_sigmas(self, x: np.ndarray, edges: list[Edge]) -> np.ndarray:
        """RMS residual of each edge at its support points, in its sigmas."""
        stacked = self._stack(edges)
        if stacked is None:
            return np.zeros(0)
        a, b, P, Pb, sigma = stacked
        d = np.linalg.norm(_apply_node(x, self.centres, a, P) - _apply_node(x, self.centres, b, Pb), axis=2)
        return np.sqrt(np.mean(d**2, axis=1)) / sigma

    @staticmethod
    def _stack(edges: list[Edge]) -> tuple | None:
        """Node indices, support points in both frames and sigmas of ``edges``, as arrays."""
        if not edges:
            return None
        a = np.array([e.a for e in edges])
        b = np.array([e.b for e in edges])
        P = np.stack([e.support for e in edges])  # (E, P, 3), in a's current frame
        Tab = np.stack([e.target_from_source for e in edges])
        Pb = np.einsum("eij,epj->epi", Tab[:, :3, :3], P) + Tab[:, None, :3, 3]  # the same points in b's frame
        return a, b, P, Pb, np.array([e.sigma_m for e in edges])


# --- session offsets -------------------------------------------------------------------------------


def session_offsets(
    pairs: list[PairResult],
    names: list[str],
    fixed: dict[str, np.ndarray] | None = None,
    iterations: int = 10,
    huber_m: float = 0.5,
) -> dict[str, np.ndarray]:
    """One translation per session from the accepted registrations: o_a - o_b = d_ab, where d_ab
    moves source a onto target b at the pair centre; iteratively reweighted (Huber) least squares,
    sessions in ``fixed`` held, otherwise the mean offset is zero (the GPS frame on average)."""
    fixed = fixed or {}
    idx = {n: k for k, n in enumerate(names)}
    rows = [
        (
            idx[p.source[0]],
            idx[p.target[0]],
            p.target_from_source[:3, :3] @ p.centre + p.target_from_source[:3, 3] - p.centre,
        )
        for p in pairs
        if p.source[0] in idx and p.target[0] in idx
    ]
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
