"""`mapkit eval align` on two synthetic drives down the same street with independent GPS biases."""

import warnings

import numpy as np
import pytest

from mapkit.core.errors import InputWarning
from mapkit.evaluation.evaluate import evaluate_align, format_align_truth
from mapkit.mapping.build import build
from mapkit.multisession.align import align_workspace
from mapkit.synth import session_logs, synthesize

# two 90 m drives, the second following the first one's route; GPS biased (1 m per axis; the
# demo's 2 m can put two short drives further apart than alignment's plausibility gate) but
# without multipath or dropouts, so that each session is georeferenced with its own offset and
# alignment has something to remove
OVERRIDES = {
    "sessions": [
        {
            "name": "first",
            "role": "train",
            "date": "2014-06-26",
            "time": "11:00",
            "weather": "overcast",
            "length_m": 90.0,
            "speed_mps": 8.0,
            "lane_offset_m": 0.0,
        },
        {
            "name": "second",
            "role": "train",
            "date": "2014-06-27",
            "time": "14:00",
            "weather": "sunny",
            "length_m": 90.0,
            "speed_mps": 8.0,
            "lane_offset_m": 0.3,
            "follow": "first",
        },
    ],
    "lidar": {"beams": 64, "vertical_fov_deg": [-24.9, 2.0], "azimuth_steps": 512},
    "motion": {"start_from_rest": False},  # what these figures were measured with (the tiny preset starts from rest)
    "gps": {
        "rate_hz": 5.0,
        "bias_sigma_m": 1.0,
        "white_sigma_m": 0.5,
        "multipath_rate_hz": 0.0,
        "dropout_rate_hz": 0.0,
    },
}


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval-align")
    town = synthesize(preset="tiny", out=root / "town", overrides=OVERRIDES, seed=3, progress=False)
    cfg = root / "build.yaml"
    cfg.write_text("lidar_map: false\n")  # align registers the semi-dense maps
    ws = build(session_logs(town), root / "ws", config=cfg, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        align_workspace(ws, progress=False)
    return evaluate_align(ws, town)


def test_alignment_brings_the_same_surface_together(evaluated):
    r = evaluated
    assert r["pairs_evaluated"] == 1
    assert r["before_median_m"] > 0.5 and r["after_median_m"] < 0.4 and r["after_median_m"] < r["before_median_m"] / 3


def test_aligned_sessions_share_one_offset_the_mean_of_their_biases(evaluated):
    t = evaluated["trajectories"]
    assert set(t) == {"first", "second"}
    before = np.array([t[n]["gps"]["mean_offset_enu_m"] for n in ("first", "second")])
    after = np.array([t[n]["aligned"]["mean_offset_enu_m"] for n in ("first", "second")])
    # before: each session carries its own GPS bias; after: one common offset, between the two
    assert np.linalg.norm(after[0] - after[1]) < 0.5 < 2.0 < np.linalg.norm(before[0] - before[1])
    assert np.all(np.minimum(before[0], before[1]) - 0.5 <= after[0]) and np.all(
        after[0] <= np.maximum(before[0], before[1]) + 0.5
    )
    for n in t:
        for w in ("gps", "aligned"):
            assert t[n][w]["horizontal_rmse_m"] <= t[n][w]["ate_rmse_m"]
            # removing the offset by a least-squares rigid fit never makes the error larger, and
            # what is left splits into horizontal and vertical parts
            o = t[n][w]["offset_removed"]
            assert o["ate_rmse_m"] <= t[n][w]["ate_rmse_m"] + 1e-9
            assert o["horizontal_rmse_m"] ** 2 + o["vertical_rmse_m"] ** 2 == pytest.approx(o["ate_rmse_m"] ** 2)
            assert abs(o["scale_vs_truth"] - 1.0) < 0.02  # LiDAR odometry is metric: about 1% over these 90 m drives
    rows = {
        line.split("|")[1].strip(): line
        for line in format_align_truth(evaluated).splitlines()
        if line.startswith("| first")
    }
    o = t["first"]["aligned"]["offset_removed"]
    assert (
        rows["first"]
        .rstrip(" |")
        .endswith(f"{o['ate_rmse_m']:.2f} / {o['horizontal_rmse_m']:.2f} / {o['vertical_rmse_m']:.2f} m")
    )


def test_eval_align_states_the_gps_bound_and_checks_the_covariances(evaluated):
    b, t = evaluated["gps_bias_bound"], evaluated["trajectories"]
    mean = np.mean([t[n]["gps"]["mean_offset_enu_m"] for n in t], axis=0)
    assert b["sessions"] == 2 and b["allowed_horizontal_m"] == pytest.approx(np.linalg.norm(mean[:2]))
    # one common offset at the mean of the two biases, give or take what the drives' shapes add
    shape = max(t[n]["aligned"]["offset_removed"]["horizontal_rmse_m"] for n in t)
    assert b["aligned_horizontal_rmse_median_m"] <= b["allowed_horizontal_m"] + shape + 0.3
    # the covariances are not overconfident: the graph knows two sessions pin the frame to
    # about 2 m / sqrt(2), so every submap's true position lies inside its 95% ellipsoid
    c = evaluated["consistency"]
    assert c["submaps"] >= 2 and set(c["sessions"]) == {"first", "second"}
    assert c["inside_95"] >= 0.9 and 0.0 < c["nees_mean"] < 7.815
    md = format_align_truth(evaluated)
    assert "GPS bound" in md and f"{100 * c['inside_95']:.0f}% of {c['submaps']} submap centres" in md
