"""The pose graph that joins a drive's 6-DoF registrations by its odometry (mapkit.localization.sequence), on a
known drive: a camera along a street that turns, registrations scattered about its true poses, two consecutive
ones at a look-alike place 270 m away, a stretch without any, and odometry from the true motion."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapkit.core.geometry import invert_pose, make_pose, rotation_angle_rad
from mapkit.localization.localize import sequence_noise, with_sequence_poses
from mapkit.localization.sequence import smooth_sequence
from mapkit.localization.sixdof import SixDofConfig, SixDofResult

#: queries 2 m apart, a quarter turn in the middle
N = 80
#: the 6-DoF localizer's defaults
NOISE = sequence_noise(SixDofConfig())
#: the look-alike place: the two queries registered there, and the stretch with no registration
WRONG, MISSING = (40, 41), range(55, 63)


def _drive() -> np.ndarray:
    """(N, 4, 4) true world_from_camera: forward along x, then a quarter turn to the left over 20 queries."""
    heading = np.clip((np.arange(N) - 30) / 20, 0, 1) * np.pi / 2
    xy = np.zeros((N, 2))
    for t in range(1, N):
        xy[t] = xy[t - 1] + 2.0 * np.array([np.cos(heading[t]), np.sin(heading[t])])
    base_from_cam = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # optical z forward, x right, y down
    return np.array(
        [
            make_pose(Rotation.from_euler("z", h).as_matrix() @ base_from_cam, np.array([x, y, 1.5]))
            for h, (x, y) in zip(heading, xy, strict=True)
        ]
    )


def _noisy(T: np.ndarray, rng: np.random.Generator, sigma_m: float, sigma_deg: float) -> np.ndarray:
    R = Rotation.from_rotvec(np.radians(sigma_deg) * rng.standard_normal(3)).as_matrix()
    return make_pose(T[:3, :3] @ R, T[:3, 3] + sigma_m * rng.standard_normal(3))


def _case(seed: int = 3):
    """(truth, registered, odometry, fallback) of the drive."""
    rng = np.random.default_rng(seed)
    truth = _drive()
    registered: list[np.ndarray | None] = [_noisy(T, rng, 0.1, 0.5) for T in truth]
    registered[0] = None  # the drive starts before its first registration
    for t in WRONG:
        registered[t] = make_pose(Rotation.from_euler("z", 0.7).as_matrix() @ truth[t][:3, :3], truth[t][:3, 3] + 270)
    for t in MISSING:
        registered[t] = None
    odometry = [None] + [invert_pose(a) @ b for a, b in zip(truth[:-1], truth[1:], strict=True)]
    fallback = [make_pose(T[:3, :3], T[:3, 3] + [3.0, -2.0, 0.0]) for T in truth]  # the filter, metres off
    return truth, registered, odometry, fallback


def _errors(estimates, truth) -> tuple[np.ndarray, np.ndarray]:
    m = np.array([np.linalg.norm(E[:3, 3] - T[:3, 3]) for E, T in zip(estimates, truth, strict=True)])
    deg = np.degrees([rotation_angle_rad(E[:3, :3].T @ T[:3, :3]) for E, T in zip(estimates, truth, strict=True)])
    return m, deg


@pytest.mark.parametrize("mode", ["causal", "batch"])
def test_odometry_carries_the_registrations_accuracy_across_outliers_and_gaps(mode):
    """Every query from the fifth on ends within the benchmarks' finest band (0.25 m, 2 deg) of its true pose, the
    two registrations 270 m away and the stretch without any included (with the whole drive, every query from the
    second within (0.1 m, 1 deg)), and the median position error is below half the registrations' own."""
    truth, registered, odometry, fallback = _case()
    out = smooth_sequence(registered, odometry, fallback, NOISE, mode)
    # the first query has only the filter's pose (the next test); online, the next few have little to average
    first = 5 if mode == "causal" else 1
    m, deg = _errors(out[first:], truth[first:])
    good = [t for t in range(1, N) if t not in WRONG and t not in MISSING]
    raw, _ = _errors([registered[t] for t in good], truth[good])
    limit_m, limit_deg = (0.25, 2.0) if mode == "causal" else (0.1, 1.0)
    assert m.max() < limit_m and deg.max() < limit_deg, (m.argmax() + first, m.max(), deg.max())
    assert np.median(m) < 0.5 * np.median(raw), (np.median(m), np.median(raw))


def test_causal_poses_depend_only_on_the_queries_before_them():
    """Online, query t's pose is fixed once it is added: changing every registration after it leaves poses 0..t
    as they were; the first query, before any registration, is the fallback's; the batch reading moves it."""
    truth, registered, odometry, fallback = _case()
    out = smooth_sequence(registered, odometry, fallback, NOISE, "causal")
    later = registered[:30] + [None if T is None else make_pose(T[:3, :3], T[:3, 3] + 1.0) for T in registered[30:]]
    again = smooth_sequence(later, odometry, fallback, NOISE, "causal")
    np.testing.assert_allclose(np.array(again[:30]), np.array(out[:30]), atol=1e-9)
    # and it does move the later ones, once the moved registrations outnumber the earlier ones
    assert np.linalg.norm(again[79][:3, 3] - out[79][:3, 3]) > 0.5
    np.testing.assert_allclose(out[0], fallback[0], atol=1e-6)
    batch = smooth_sequence(registered, odometry, fallback, NOISE, "batch")
    assert np.linalg.norm(batch[0][:3, 3] - truth[0][:3, 3]) < 0.1  # the whole drive places its first query too


def test_a_query_nothing_places_has_no_pose_and_a_gap_starts_again_from_the_fallback():
    """Without odometry into it, a registration or a fallback, a query gets None; the query after a gap in the
    odometry without a registration starts from its fallback pose, 3.6 m off, and the registrations after it bring
    the stretch back within 0.25 m of the truth."""
    truth, registered, odometry, fallback = _case()
    registered[10], fallback[10], odometry[10], odometry[11] = None, None, None, None
    registered[11] = None
    out = smooth_sequence(registered, odometry, fallback, NOISE, "causal")
    assert out[10] is None
    np.testing.assert_allclose(out[11], fallback[11], atol=1e-6)
    m, _ = _errors(out[12:30], truth[12:30])
    assert m.max() < 0.25, m


def test_lengths_and_mode_are_checked():
    truth, registered, odometry, fallback = _case()
    with pytest.raises(ValueError, match="80 registered poses, 79 odometry steps"):
        smooth_sequence(registered, odometry[:-1], fallback, NOISE)
    with pytest.raises(ValueError, match="choose causal or batch"):
        smooth_sequence(registered, odometry, fallback, NOISE, "off")  # type: ignore[arg-type]


@pytest.mark.parametrize("mode", ["causal", "batch"])
def test_one_wrong_registration_does_not_capture_the_track(mode):
    """The drive starts with the filter 40 m off and turned 20 deg; the first registration is 4 m off, and every
    one after it is right. The track does not stay with the wrong one (a robust kernel started there would take the
    right ones for outliers): from the second right registration on, every query lies within (0.25 m, 2 deg), and
    until then each keeps its own registration or the filter's pose."""
    truth, registered, odometry, _ = _case()
    turn = Rotation.from_euler("z", 20, degrees=True).as_matrix()
    fallback = [make_pose(turn @ T[:3, :3], T[:3, 3] + [40.0, 0.0, 0.0]) for T in truth]
    registered = [None] * 5 + [make_pose(turn[:3, :3].T @ truth[5][:3, :3], truth[5][:3, 3] + 4.0)] + [None] * 4
    registered += [_noisy(T, np.random.default_rng(t), 0.1, 0.5) for t, T in enumerate(truth[10:], 10)]
    out = smooth_sequence(registered, odometry, fallback, NOISE, mode)
    m, deg = _errors(out[11:], truth[11:])
    assert m.max() < 0.25 and deg.max() < 2.0, (m.argmax() + 11, m.max(), deg.max())
    if mode == "causal":
        np.testing.assert_allclose(np.array(out[:5]), np.array(fallback[:5]))
        np.testing.assert_allclose(out[5], registered[5])


@pytest.mark.parametrize("mode", ["causal", "batch"])
def test_a_run_of_agreeing_wrong_registrations_is_outvoted(mode):
    """The first six registrations agree with each other at a place 20 m off; the right ones from query 10 on
    outnumber them from query 16. Online, every query from there lies within (0.25 m, 2 deg); with the whole drive,
    every query does, the first six placed by the odometry from the right ones."""
    truth, registered, odometry, fallback = _case()
    registered = list(registered)
    for t in range(1, 10):
        registered[t] = make_pose(truth[t][:3, :3], truth[t][:3, 3] + [20.0, 3.0, 0.0]) if t <= 6 else None
    out = smooth_sequence(registered, odometry, fallback, NOISE, mode)
    first = 16 if mode == "causal" else 1
    m, deg = _errors(out[first:], truth[first:])
    assert m.max() < 0.25 and deg.max() < 2.0, (m.argmax() + first, m.max(), deg.max())


def test_a_long_drive_with_drifting_odometry_stays_on_its_registrations():
    """600 m of straight drive whose odometry over-reads every step by 0.4 % (2.4 m over the drive, more than two
    registrations far apart could agree by): each query is solved from the 200 m of driving before it, where the
    drift stays within the band, and lies within (0.25 m, 2 deg) of its true pose; one window over the whole drive
    would hold only part of the drive's registrations and carry the drift into the rest."""
    rng = np.random.default_rng(5)
    base_from_cam = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    truth = np.array([make_pose(base_from_cam, np.array([2.0 * t, 0.0, 1.5])) for t in range(300)])
    registered = [_noisy(T, rng, 0.1, 0.5) for T in truth]
    odometry = [None] + [make_pose(np.eye(3), np.array([0.0, 0.0, 2.0 * 1.004])) for _ in range(299)]
    fallback = [None] * 300
    out = smooth_sequence(registered, odometry, fallback, NOISE, "causal")
    m, deg = _errors(out[5:], truth[5:])
    assert m.max() < 0.25 and deg.max() < 2.0, (m.argmax() + 5, m.max(), deg.max())
    whole = smooth_sequence(registered, odometry, fallback, replace(NOISE, window_m=1e6), "causal")
    assert _errors(whole[5:], truth[5:])[0].max() > 0.5


def _loose_case():
    """(truth, registered, odometry, covariances): queries 30-49 register from points far ahead, up to 0.6 m off
    along the view, and their covariance says so (0.5 m std along the optical axis); the rest within 1 cm."""
    rng = np.random.default_rng(11)
    truth = _drive()
    odometry = [None] + [invert_pose(a) @ b for a, b in zip(truth[:-1], truth[1:], strict=True)]
    sharp = np.diag(np.r_[np.full(3, np.radians(0.05)), 0.01, 0.01, 0.01] ** 2)
    loose = np.diag(np.r_[np.full(3, np.radians(0.05)), 0.02, 0.02, 0.5] ** 2)
    registered, covariances = [], []
    for t, T in enumerate(truth):
        off = 0.6 * np.sin(np.pi * (t - 29) / 21) if 30 <= t < 50 else 0.0  # along the camera's z
        along = T[:3, :3] @ np.array([0.0, 0.0, off])
        registered.append(make_pose(T[:3, :3], T[:3, 3] + along + 0.01 * rng.standard_normal(3)))
        covariances.append(loose if off else sharp)
    return truth, registered, odometry, covariances


def test_a_registration_that_says_it_is_loose_yields_to_the_odometry():
    """Given the covariances, the odometry from the sharp registrations on either side of the loose ones carries
    their accuracy across; without them the graph follows the loose ones."""
    truth, registered, odometry, covariances = _loose_case()
    fallback = [None] * N
    for mode in ("causal", "batch"):
        given = _errors(smooth_sequence(registered, odometry, fallback, NOISE, mode, covariances), truth)[0]
        alone = _errors(smooth_sequence(registered, odometry, fallback, NOISE, mode), truth)[0]
        assert given[30:50].max() < 0.15, (mode, given[30:50].max())
        assert alone[30:50].max() > 0.25, (mode, alone[30:50].max())  # outside the finest band


def test_the_localizer_passes_its_registrations_covariances_unless_told_not_to():
    """``with_sequence_poses`` (the 6-DoF localizer's pose graph) gives the accepted registrations' covariances to
    the graph; ``smoothing_covariance: false`` leaves them out; a rejected registration's covariance never counts."""
    truth, registered, odometry, covariances = _loose_case()
    results = [
        SixDofResult(f"q{t}", invert_pose(T), T, True, "", 50, 60, covariance=C)
        for t, (T, C) in enumerate(zip(registered, covariances, strict=True))
    ]
    fallback = [None] * N
    on = with_sequence_poses(results, odometry, fallback, SixDofConfig())
    off = with_sequence_poses(results, odometry, fallback, SixDofConfig(smoothing_covariance=False))
    assert _errors([r.sequence_world_from_cam for r in on], truth)[0][30:50].max() < 0.15
    expected = smooth_sequence(registered, odometry, fallback, NOISE, "causal")
    for r, T in zip(off, expected, strict=True):
        np.testing.assert_allclose(r.sequence_world_from_cam, T)
    # a rejected query keeps its covariance in the result, but the graph neither takes its pose nor its covariance
    rejected = [replace(r, accepted=False) if t == 40 else r for t, r in enumerate(results)]
    got = with_sequence_poses(rejected, odometry, fallback, SixDofConfig())
    dropped = smooth_sequence(
        [None if t == 40 else T for t, T in enumerate(registered)],
        odometry,
        fallback,
        NOISE,
        "causal",
        [None if t == 40 else C for t, C in enumerate(covariances)],
    )
    for r, T in zip(got, dropped, strict=True):
        np.testing.assert_allclose(r.sequence_world_from_cam, T)


def test_covariances_must_match_the_queries():
    truth, registered, odometry, fallback = _case()
    with pytest.raises(ValueError, match="covariances"):
        smooth_sequence(registered, odometry, fallback, NOISE, "causal", [None] * (N - 1))
