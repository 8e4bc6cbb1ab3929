"""Patches against known answers: brute-force extraction, known yaw, hand-built voxel grids."""

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mapkit.core.errors import InputError
from mapkit.core.geometry import yaw_rotation
from mapkit.places import patches as pa


def _scene(rng, n_wall=1500, n_ground=800, n_pole=150):
    """A patch-sized structured scene about the origin: a long wall, a strip of ground, a pole.

    Deliberately anisotropic, so that the smallest-eigenvalue axis is well defined (the wall's
    normal, here along (cos 20 deg, sin 20 deg))."""
    d = np.array([math.cos(math.radians(110)), math.sin(math.radians(110))])  # along the wall
    nrm = np.array([d[1], -d[0]])
    t = rng.uniform(-9, 9, n_wall)
    wall = np.column_stack([4 * nrm[0] + t * d[0], 4 * nrm[1] + t * d[1], rng.uniform(-1.5, 8, n_wall)])
    g = rng.uniform(-9, 9, (n_ground, 2)) * [1, 0.3]
    ground = np.column_stack(
        [g[:, 0] * d[0] + g[:, 1] * nrm[0], g[:, 0] * d[1] + g[:, 1] * nrm[1], rng.normal(-1.5, 0.02, n_ground)]
    )
    pole = np.column_stack([np.full(n_pole, -3.0), np.full(n_pole, 2.0), rng.uniform(-1.5, 5, n_pole)])
    return np.vstack([wall, ground, pole]) + rng.normal(0, 0.01, (n_wall + n_ground + n_pole, 3))


def test_select_keypoints_is_a_random_five_percent(rng):
    idx = pa.select_keypoints(10_000, rng=rng)
    assert len(idx) == 500 and len(np.unique(idx)) == 500
    assert np.all(np.diff(idx) > 0) and idx[0] >= 0 and idx[-1] < 10_000
    np.testing.assert_array_equal(
        pa.select_keypoints(10_000, rng=np.random.default_rng(3)),
        pa.select_keypoints(10_000, rng=np.random.default_rng(3)),
    )
    assert len(pa.select_keypoints(7, rng=rng)) == 1
    with pytest.raises(InputError):
        pa.select_keypoints(100, fraction=0.0)


def test_domain_presets_and_validation():
    assert pa.NBLD_DOMAIN.bounding_radius == pytest.approx(math.hypot(10, 10))
    assert pa.M2DP_DOMAIN.patch_half_height == math.inf
    assert pa.CNN_DOMAIN.patch_radius == pytest.approx(10 * math.sqrt(2))  # holds the cube under any yaw
    with pytest.raises(ValueError):
        pa.PatchDomain(kind="cylinder", radius=10.0)  # no height
    with pytest.raises(ValueError):
        pa.PatchDomain(kind="cube", half_size=10.0, radius=3.0)


@pytest.mark.parametrize(
    "domain",
    [pa.NBLD_DOMAIN, pa.M2DP_DOMAIN, pa.CNN_DOMAIN, pa.PatchDomain(kind="cylinder", radius=3.0, height=2.0)],
    ids=["nbld", "m2dp", "cube", "small"],
)
def test_extract_patches_matches_brute_force(rng, domain):
    points = rng.uniform([-30, -30, -20], [30, 30, 20], (4000, 3))
    keypoints = np.vstack([points[:15], rng.uniform(-30, 30, (5, 3))])
    tree = pa.xy_tree(points)
    indptr, indices = pa.extract_patches(points, keypoints, domain, tree=tree)
    assert indptr[0] == 0 and indptr[-1] == len(indices)
    for k, kp in enumerate(keypoints):
        d = points - kp
        if domain.kind == "cube":
            r, hh = domain.half_size * math.sqrt(2), domain.half_size
        else:
            r, hh = domain.radius, (domain.height / 2 if domain.kind == "cylinder" else math.inf)
        expected = np.flatnonzero((d[:, 0] ** 2 + d[:, 1] ** 2 <= r * r) & (np.abs(d[:, 2]) <= hh))
        np.testing.assert_array_equal(np.sort(indices[indptr[k] : indptr[k + 1]]), expected)
    # without a tree: the same; a 3-D tree is refused
    np.testing.assert_array_equal(pa.extract_patches(points, keypoints, domain)[1], indices)
    with pytest.raises(InputError):
        pa.extract_patches(points, keypoints, domain, tree=cKDTree(points))


def test_yaw_axis_is_wall_normal_towards_observer(rng):
    pts = _scene(rng, n_ground=0, n_pole=0)  # a wall alone: its normal is the least-spread axis
    yaw, out = pa.yaw_normalise(pts, np.array([1.0, 0.0]))  # observer on the wall's side
    assert yaw == pytest.approx(math.radians(20), abs=math.radians(0.5))
    yaw_b, out_b = pa.yaw_normalise(pts, np.array([-1.0, 0.0]))  # the other side: x flips
    assert yaw_b == pytest.approx(math.radians(20 - 180), abs=math.radians(0.5))
    np.testing.assert_allclose(out_b[:, :2], -out[:, :2], atol=1e-9)
    np.testing.assert_allclose(out_b[:, 2], pts[:, 2])
    # the wall (4 m along the normal) ends up at x = +4 when the observer is on its side
    assert np.median(out[:, 0]) == pytest.approx(4.0, abs=0.05)


def test_yaw_normalisation_invariant_to_rotation_about_z(rng):
    pts = _scene(rng)
    observer = np.array([0.3, 0.5])
    _, out = pa.yaw_normalise(pts, observer)
    occ, dcg = pa.voxelise(out, pa.CNN_DOMAIN)
    for psi in (0.7, 2.5, -1.9):
        Rz = yaw_rotation(psi)
        yaw_r, out_r = pa.yaw_normalise(pts @ Rz.T, Rz[:2, :2] @ observer)
        occ_r, dcg_r = pa.voxelise(out_r, pa.CNN_DOMAIN)
        assert np.mean(occ_r != occ) < 1e-3 and np.mean(dcg_r != dcg) < 1e-3
        np.testing.assert_allclose(out_r, out, atol=1e-9)


def test_degenerate_patch_falls_back_to_middle_eigenvector(rng):
    # flat ground only, a road strip 18 m long, 3 m wide along 30 deg: e0 is vertical, so the
    # axis is the middle eigenvector, across the strip (120 deg or -60 deg)
    t, w = rng.uniform(-9, 9, 2000), rng.uniform(-1.5, 1.5, 2000)
    a = math.radians(30)
    pts = np.column_stack(
        [t * math.cos(a) - w * math.sin(a), t * math.sin(a) + w * math.cos(a), rng.normal(0, 0.01, 2000)]
    )
    yaw, _ = pa.yaw_normalise(pts, np.array([-1.0, 1.0]))
    assert yaw == pytest.approx(math.radians(120), abs=math.radians(1))


@pytest.mark.parametrize("block_points", [1 << 18, 600], ids=["one-block", "blocks"])
def test_batch_yaw_normalisation_equals_single(rng, monkeypatch, block_points):
    monkeypatch.setattr(pa, "_BLOCK_POINTS", block_points)
    patches = [_scene(rng, 300, 200, 30) for _ in range(3)] + [np.zeros((0, 3))]
    obs = rng.normal(size=(4, 2))
    indptr = np.cumsum([0] + [len(p) for p in patches])
    yaw, out = pa.yaw_normalise_patches(np.vstack(patches), indptr, obs)
    for k, p in enumerate(patches[:3]):
        y1, o1 = pa.yaw_normalise(p, obs[k])
        assert yaw[k] == pytest.approx(y1)
        np.testing.assert_allclose(out[indptr[k] : indptr[k + 1]], o1)
    assert yaw[3] == 0.0


def test_density_comparison_of_hand_built_grid():
    # grid 4 over a cube of half size 2: voxel (i, j, k) has its centre at (i - 1.5, j - 1.5, k - 1.5)
    cube = pa.PatchDomain(kind="cube", half_size=2.0)
    counts = {(0, 0, 0): 2, (1, 0, 0): 1, (3, 0, 0): 3, (0, 1, 0): 4, (0, 0, 3): 1}
    pts = np.array([[i - 1.5, j - 1.5, k - 1.5] for (i, j, k), c in counts.items() for _ in range(c)])
    occ, dcg = pa.voxelise(pts, cube, grid=4)
    expected_occ = np.zeros((4, 4, 4), np.uint8)
    for ijk in counts:
        expected_occ[ijk] = 1
    np.testing.assert_array_equal(occ, expected_occ)
    expected = np.zeros((3, 4, 4, 4), np.uint8)
    # x: (0,0,0)=2 > (1,0,0)=1; (1,0,0)=1 > (2,0,0)=0; (3,0,0)=3 is the last cell, > 0;
    #    (0,1,0)=4 > (1,1,0)=0; (0,0,3)=1 > (1,0,3)=0
    for ijk in [(0, 0, 0), (1, 0, 0), (3, 0, 0), (0, 1, 0), (0, 0, 3)]:
        expected[0][ijk] = 1
    # y: (0,0,0)=2 < (0,1,0)=4 -> 0; (1,0,0)=1 > (1,1,0)=0; (3,0,0) > (3,1,0); (0,1,0)=4 > (0,2,0)=0; (0,0,3) > (0,1,3)
    for ijk in [(1, 0, 0), (3, 0, 0), (0, 1, 0), (0, 0, 3)]:
        expected[1][ijk] = 1
    # z: (0,0,0)=2 > (0,0,1)=0; (1,0,0); (3,0,0); (0,1,0); (0,0,3) is the last cell, > 0
    for ijk in [(0, 0, 0), (1, 0, 0), (3, 0, 0), (0, 1, 0), (0, 0, 3)]:
        expected[2][ijk] = 1
    np.testing.assert_array_equal(dcg, expected)
    # points outside the cube are left out; a point exactly on the far face is in the last cell
    occ2, _ = pa.voxelise(np.array([[2.0, 2.0, 2.0], [2.5, 0, 0]]), cube, grid=4)
    assert occ2.sum() == 1 and occ2[3, 3, 3] == 1


def test_pack_unpack_round_trip(rng):
    bits = (rng.random((5, 3, 32, 32, 32)) < 0.3).astype(np.uint8)
    packed = pa.pack_bits(bits)
    assert packed.shape == (5, 3, 32, 32, 4) and packed.dtype == np.uint8
    np.testing.assert_array_equal(pa.unpack_bits(packed, 32), bits)
    odd = (rng.random((7, 13)) < 0.5).astype(np.uint8)
    np.testing.assert_array_equal(pa.unpack_bits(pa.pack_bits(odd), 13), odd)


def test_voxelise_patches_equals_single_and_packs(rng):
    patches = [rng.uniform(-12, 12, (n, 3)) for n in (50, 0, 400)]
    indptr = np.cumsum([0] + [len(p) for p in patches])
    occ, dcg = pa.voxelise_patches(np.vstack(patches), indptr, pa.CNN_DOMAIN)
    assert occ.shape == (3, 32, 32, 32) and dcg.shape == (3, 3, 32, 32, 32)
    for k, p in enumerate(patches):
        o1, d1 = pa.voxelise(p, pa.CNN_DOMAIN)
        np.testing.assert_array_equal(occ[k], o1)
        np.testing.assert_array_equal(dcg[k], d1)
    assert occ[1].sum() == 0
    occ_p, dcg_p = pa.voxelise_patches(np.vstack(patches), indptr, pa.CNN_DOMAIN, packed=True)
    np.testing.assert_array_equal(pa.unpack_bits(occ_p, 32), occ)
    np.testing.assert_array_equal(pa.unpack_bits(dcg_p, 32), dcg)
    with pytest.raises(InputError):
        pa.voxelise(patches[0], pa.M2DP_DOMAIN)


def test_first_observer_positions():
    # point 0 seen by frames 5, 7 (keyframes); point 1 by 2 (not a keyframe), 4, 9; point 2 by 3 only (no pose)
    obs_indptr = np.array([0, 2, 5, 6])
    obs_frame_ids = np.array([5, 7, 2, 4, 9, 3])
    frame_ids = np.array([9, 4, 7, 5])  # any order
    frame_positions = np.array([[9.0, 0, 0], [4.0, 0, 0], [7.0, 0, 0], [5.0, 0, 0]])
    pos = pa.first_observer_positions(np.array([1, 0]), obs_indptr, obs_frame_ids, frame_ids, frame_positions)
    np.testing.assert_array_equal(pos, [[4.0, 0, 0], [5.0, 0, 0]])
    with pytest.raises(InputError):
        pa.first_observer_positions(np.array([2]), obs_indptr, obs_frame_ids, frame_ids, frame_positions)


def test_voxel_grids_chain_equals_its_stages(rng):
    points = np.vstack([_scene(rng) + [20.0 * k, 0, 0] for k in range(3)])
    keypoints = points[rng.choice(len(points), 5, replace=False)]
    obs = rng.normal(size=(5, 2))
    occ, dcg, yaw = pa.voxel_grids(points, keypoints, obs)
    assert occ.shape == (5, 32, 32, 4) and dcg.shape == (5, 3, 32, 32, 4)
    indptr, indices = pa.extract_patches(points, keypoints, pa.CNN_DOMAIN)
    yaw2, normalised = pa.yaw_normalise_patches(pa.gather_local(points, keypoints, indptr, indices), indptr, obs)
    occ2, dcg2 = pa.voxelise_patches(normalised, indptr, pa.CNN_DOMAIN)
    np.testing.assert_allclose(yaw, yaw2)
    np.testing.assert_array_equal(pa.unpack_bits(occ, 32), occ2)
    np.testing.assert_array_equal(pa.unpack_bits(dcg, 32), dcg2)
    assert occ2.reshape(5, -1).sum(axis=1).min() > 50  # the grids hold the scene


def test_keypoint_blocks_cover_all_keypoints_within_the_budget(rng):
    points = rng.uniform([-50, -50, -5], [50, 50, 5], (5000, 3))
    keypoints = points[:40]
    tree = pa.xy_tree(points)
    blocks = list(pa.keypoint_blocks(tree, keypoints, pa.NBLD_DOMAIN, max_points=500))
    assert blocks[0][0] == 0 and blocks[-1][1] == 40
    assert all(a1 == b0 for (_, a1), (b0, _) in zip(blocks, blocks[1:], strict=False))
    lengths = tree.query_ball_point(keypoints[:, :2], 10.0, return_length=True)
    assert all(lengths[k0:k1].sum() <= 500 or k1 - k0 == 1 for k0, k1 in blocks)
    assert len(blocks) > 1
