"""Honest covariances of the multi-session pose graph: a session that registrations do not tie to the others, or
tie only by a few wrong registrations, keeps the uncertainty of what does place it (its GPS bias, its odometry);
and ``mapkit eval align`` names a session whose truth lies outside its 95% ellipsoids."""

import json

import numpy as np
from scipy.spatial import cKDTree

from mapkit.core.geometry import make_pose
from mapkit.core.workspace import Workspace
from mapkit.evaluation.evaluate import _consistency, _SessionError, format_align_truth
from mapkit.multisession.align import AlignConfig
from mapkit.multisession.posegraph import Edge, PoseGraph, support_points
from mapkit.report.html import markdown_to_html

CHI2_95_3DOF = 7.815
N_SUB = 4  # submaps per session, 50 m apart along x


def _graph(
    rng: np.random.Generator,
    n_sessions: int = 3,
    untied: int = 1,
    wrong_ties: int = 0,
    wrong_m: float = 3.0,
    n_sub: int = N_SUB,
    tie_sigma_m: float | None = None,
) -> tuple[PoseGraph, np.ndarray]:
    """Sessions of ``n_sub`` submaps, each displaced by its GPS bias (drawn from the graph's prior; the last
    session's horizontal bias is 2 m long, in a drawn direction), exact odometry, exact ICP edges between every
    pair of the first sessions at every place; the last ``untied`` sessions have none, except ``wrong_ties``
    registrations of the last session onto the first that agree with each other but are ``wrong_m`` off.
    ``tie_sigma_m``: the graph's, if not its default. Returns the graph and the true corrections (n, 3)."""
    cfg = AlignConfig().graph
    if tie_sigma_m is not None:
        cfg = cfg.model_copy(update={"tie_sigma_m": tie_sigma_m})
    bias = rng.standard_normal((n_sessions, 3)) * np.asarray(cfg.gps_bias_sigma_m)
    heading = rng.uniform(0, 2 * np.pi)
    bias[-1, :2] = 2.0 * np.array([np.cos(heading), np.sin(heading)])
    true_t = -np.repeat(bias, n_sub, axis=0)  # the corrections that undo each session's bias
    centres = np.array([[25.0 + 50 * k, 0, 0] for k in range(n_sub)] * n_sessions) + np.repeat(bias, n_sub, axis=0)
    tied = n_sessions - untied
    x0 = np.zeros((len(centres), 6))
    x0[: tied * n_sub, 3:] = true_t[: tied * n_sub] + bias[:tied].mean(axis=0)  # session_offsets' start
    g = PoseGraph(centres, cfg, initial=x0, session_of=np.repeat(np.arange(n_sessions), n_sub))
    x_axis = np.array([1.0, 0, 0])
    for s in range(n_sessions):
        for k in range(n_sub - 1):
            sup = support_points(np.array([50.0 * (k + 1), 0, 0]) + bias[s], x_axis, cfg.lever_m)
            g.add(Edge("odometry", s * n_sub + k, s * n_sub + k + 1, sup, np.eye(4), cfg.odometry_sigma_fused_m))

    def icp(sa: int, sb: int, k: int, error: np.ndarray) -> None:
        T = make_pose(np.eye(3), bias[sb] - bias[sa] + error)  # session a's points onto session b's
        a = sa * n_sub + k
        g.add(Edge("icp", a, sb * n_sub + k, support_points(centres[a], x_axis, cfg.lever_m), T, cfg.icp_sigma_m, 0))

    for sa in range(tied):
        for sb in range(sa + 1, tied):
            for k in range(n_sub):
                icp(sa, sb, k, np.zeros(3))
    wrong = wrong_m * np.array([np.cos(heading + 1.0), np.sin(heading + 1.0), 0.0])
    for k in range(wrong_ties):
        icp(n_sessions - 1, 0, k, wrong)
    return g, true_t


def _inside_last_session(g: PoseGraph, true_t: np.ndarray) -> np.ndarray:
    """Whether each submap of the last session has its true correction inside its 95% position ellipsoid."""
    x = g.solve()
    cov = g.covariances()[-N_SUB:, 3:, 3:]
    e = x[-N_SUB:, 3:] - true_t[-N_SUB:]
    return np.einsum("ki,ki->k", e, np.linalg.solve(cov, e[..., None])[..., 0]) <= CHI2_95_3DOF


def test_a_session_without_registrations_keeps_its_gps_uncertainty_over_50_draws():
    rng = np.random.default_rng(11)
    inside = np.array([_inside_last_session(*_graph(rng)) for _ in range(50)])
    assert inside.mean() >= 0.9, inside.mean()


def test_a_session_tied_by_a_few_wrong_registrations_is_not_made_confident():
    # two registrations of the last session, 3 m off and agreeing with each other: the graph cannot tell them from
    # right ones, so it may follow them, but its covariance must then say metres, not decimetres
    rng = np.random.default_rng(12)
    inside = np.array([_inside_last_session(*_graph(rng, wrong_ties=2)) for _ in range(50)])
    assert inside.mean() >= 0.9, inside.mean()


def test_many_right_registrations_still_pin_a_session_to_the_others():
    # considering shared errors keeps the estimate and costs little where many places tie: two sessions tied at
    # 20 places sit at the mean of their biases, known to about 2 m / sqrt(2), and the untied one keeps its 2 m
    sig, x = {}, {}
    for tie in (0.0, None):
        g, true_t = _graph(np.random.default_rng(13), n_sub=20, tie_sigma_m=tie)
        x[tie] = g.solve()
        sig[tie] = np.sqrt(g.covariances()[:, 3, 3])
    assert np.abs(x[None] - x[0.0]).max() < 1e-9
    assert np.allclose(sig[0.0][:40], 2.0 / np.sqrt(2), atol=0.05)
    assert np.all(sig[None][:40] < 1.1 * sig[0.0][:40]) and np.all(sig[None][:40] > sig[0.0][:40])
    assert np.all(sig[None][40:] > 2.0)
    rel = (x[None][:40, 3:] - true_t[:40]).reshape(2, 20, 3)
    assert np.abs(rel[1] - rel[0]).max() < 0.02  # the tied sessions agree to centimetres


# --- eval align's flag ------------------------------------------------------------------------------


def _aligned_session(ws: Workspace, name: str, error_m: np.ndarray, sigma_m: float) -> _SessionError:
    """A session of ``N_SUB`` submaps whose aligned trajectory is off the truth by ``error_m`` everywhere, its
    submaps.json claiming ``sigma_m`` per axis."""
    centres = np.array([[25.0 + 50 * k, 0, 0] for k in range(N_SUB)])
    cov = np.zeros((6, 6))
    cov[3:, 3:] = np.eye(3) * sigma_m**2
    cov[:3, :3] = np.eye(3) * 1e-4
    path = ws.aligned(name).submaps
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"submaps": [{"centre_enu": c.tolist(), "covariance": cov.tolist()} for c in centres]}))
    E = np.repeat(make_pose(np.eye(3), error_m)[None], N_SUB, axis=0)
    return _SessionError(cKDTree(centres[:, :2]), E, E, np.zeros((0, 3)))


def test_eval_align_flags_an_overconfident_session_and_not_an_honest_one(tmp_path):
    ws = Workspace(tmp_path)
    sess = {
        "honest": _aligned_session(ws, "honest", np.array([1.5, -1.0, 0.5]), 1.0),  # NEES 3.5
        "foggy": _aligned_session(ws, "foggy", np.array([3.0, 1.0, 0.0]), 0.5),  # NEES 40
    }
    c = _consistency(ws, sess)
    assert c["overconfident"] == ["foggy"]
    assert c["sessions"]["foggy"]["overconfident"] and not c["sessions"]["honest"]["overconfident"]
    md = format_align_truth(
        {
            "pairs": {},
            "before_median_m": 1.0,
            "after_median_m": 0.1,
            "accepted_pairs_true_error_above_1m": 0,
            "accepted_pairs": 1,
            "accepted_pair_true_error_max_m": 0.1,
            "consistency": c,
        }
    )
    assert "**Overconfident: foggy**" in md and "foggy 100%" in md and "honest" not in md.split("Overconfident")[1]
    assert "<b>Overconfident: foggy</b>" in markdown_to_html(md)  # as the demo report shows eval_align.md
