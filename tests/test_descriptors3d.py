"""NBLD and M2DP against known answers and slow references; the chain's yaw invariance; PCA."""

import math
from pathlib import Path

import numpy as np
import pytest

from mapkit.core.errors import InputError
from mapkit.core.geometry import yaw_rotation
from mapkit.places import descriptors3d as d3


def _cell_centres(cfg, counts):
    """Points at the centres of NBLD cells, ``counts[i, j, k]`` of them in ring i, sector j, layer k."""
    R, H = cfg.domain.radius, cfg.domain.height
    out = []
    for (i, j, k), c in np.ndenumerate(counts):
        r = (i + 0.5) * R / cfg.n_radial
        a = (j + 0.5) * 2 * math.pi / cfg.n_azimuth
        z = -H / 2 + (k + 0.5) * H / cfg.n_vertical
        out += [[r * math.cos(a), r * math.sin(a), z]] * int(c)
    return np.array(out, np.float64).reshape(-1, 3)


def test_nbld_density_step_gives_expected_bits():
    cfg = d3.NBLDConfig()
    nr, na, nz = cfg.n_radial, cfg.n_azimuth, cfg.n_vertical
    # equal-width rings: cell volumes grow as 1 : 3 : 5, so counts 20, 6, 5 are densities
    # 20, 2, 1 (in units of 1 / inner cell volume): dense inside, sparse outside
    counts = np.zeros((nr, na, nz), int)
    counts[0], counts[1], counts[2] = 20, 6, 5
    desc = d3.nbld_patches(_cell_centres(cfg, counts), np.array([0, counts.sum()]), cfg)
    assert desc.shape == (1, 3 * nr * na * nz) and desc.dtype == np.float32
    bits = desc.reshape(3, nr, na, nz)
    assert np.all(bits[0] == 1)  # radial: each ring denser than the next; the outer one than 0
    assert np.all(bits[1] == 0)  # azimuthal: equal neighbours
    assert np.all(bits[2][:, :, :-1] == 0) and np.all(bits[2][:, :, -1] == 1)  # vertical: only the top layer (> 0)

    # sector 0 made denser in every ring: its azimuthal bit is 1, the sector before it (which
    # wraps around to sector 0) stays 0, every other azimuthal bit stays 0
    counts[:, 0] += 1
    bits = d3.nbld_patches(_cell_centres(cfg, counts), np.array([0, counts.sum()]), cfg).reshape(3, nr, na, nz)
    assert np.all(bits[1][:, 0] == 1) and np.all(bits[1][:, 1:] == 0)
    assert np.all(bits[0] == 1)
    packed = d3.nbld_patches(_cell_centres(cfg, counts), np.array([0, counts.sum()]), cfg, packed=True)
    np.testing.assert_array_equal(packed[0], np.packbits(bits.ravel().astype(np.uint8)))


def test_nbld_counts_cells_and_leaves_out_the_outside():
    cfg = d3.NBLDConfig(n_vertical=4)  # 5 m layers: the layers named below
    pts = np.array(
        [
            [-0.0, -0.0, 0.0],  # the keypoint (signed zeros): ring 0, sector 0, layer 2
            [1.0, 0.1, 0.1],  # ring 0, sector 0, layer 2
            [-0.1, 9.0, -9.0],  # ring 2, sector 2 (90-135 deg), layer 0
            [10.0, 0.0, 10.0],  # on the outer boundary: last ring and layer
            [10.5, 0.0, 0.0],  # outside the radius
            [0.0, 1.0, 10.5],  # above the top
        ]
    )
    c = d3.nbld_counts(pts, np.array([0, 6]), cfg)[0]
    assert c.sum() == 4
    assert c[0, 0, 2] == 2 and c[2, 2, 0] == 1 and c[2, 0, 3] == 1


def _m2dp_loop(points, cfg):
    """M2DP written out point by point and plane by plane (float64, math.atan2)."""
    R, L, T = cfg.domain.radius, cfg.n_radial, cfg.n_angular
    A = np.zeros((cfg.n_planes, L * T))
    row = 0
    for az in np.linspace(-math.pi / 2, math.pi / 2, cfg.n_plane_azimuths):
        for el in np.linspace(0, math.pi / 2, cfg.n_plane_elevations):
            n = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            px = np.array([1.0, 0, 0]) - n[0] * n
            px /= np.linalg.norm(px)
            py = np.cross(n, px)
            for p in points:
                X, Y = p @ px, p @ py
                rho = math.hypot(X, Y)
                if rho >= R:
                    continue
                theta = math.atan2(Y, X) if np.any(p != 0) else 0.0  # the keypoint: theta = 0
                sector = min(int((theta + math.pi) / (2 * math.pi) * T), T - 1)
                ring = int(L * math.sqrt(rho / R))  # radii R (i / L)^2
                A[row, ring * T + sector] += 1
            row += 1
    if not A.any():
        return np.zeros(cfg.dim)
    U, _, Vt = np.linalg.svd(A)
    u, v = U[:, 0], Vt[0]
    return np.concatenate([u, v]) * (1.0 if v.sum() >= 0 else -1.0)


def _off_bin_edges(points, cfg, eps=1e-5):
    """The points that lie farther than ``eps`` (in ring or sector units) from every M2DP bin
    edge on every plane: the library bins in float32, so a point within float32 precision of an
    edge may fall on either side (module docstring); the reference must not depend on it."""
    _, ax, ay = d3.m2dp_planes(cfg)
    x, y = points @ ax.T, points @ ay.T
    ring = cfg.n_radial * np.sqrt(np.hypot(x, y) / cfg.domain.radius)
    sector = (np.arctan2(y, x) + math.pi) / (2 * math.pi) * cfg.n_angular
    inside = ring < cfg.n_radial + eps  # edges beyond the grid have the outside on both sides
    near = inside & ((np.abs(ring - np.round(ring)) < eps) | (np.abs(sector - np.round(sector)) < eps))
    return points[~near.any(axis=1)]


def test_m2dp_equals_loop_reference(rng):
    cfg = d3.M2DPConfig()
    p1 = np.column_stack([rng.uniform(-10, 10, (400, 2)), rng.normal(0, 4, 400)])
    p1 = _off_bin_edges(p1[np.hypot(p1[:, 0], p1[:, 1]) <= 10], cfg)
    assert len(p1) > 300  # edge points are rare: a few in a thousand at most
    p1 = np.vstack([np.zeros(3), p1])  # with the keypoint itself
    p2 = _off_bin_edges(
        np.vstack([rng.normal([3, -2, 0], [0.3, 3, 2], (150, 3)), [[0.7, 0.4, 40.0]]]), cfg
    )  # one point far above: outside on most planes
    assert p2[-1, 2] == 40.0
    patches = [p1, np.zeros((0, 3)), p2]
    indptr = np.cumsum([0] + [len(p) for p in patches])
    desc = d3.m2dp_patches(np.vstack(patches), indptr, cfg)
    assert desc.shape == (3, 192) and desc.dtype == np.float32
    for k, p in enumerate(patches):
        np.testing.assert_allclose(desc[k], _m2dp_loop(p, cfg), atol=2e-5)
    assert np.all(desc[1] == 0)
    assert np.all(desc[[0, 2]] >= -1e-6)  # non-negative counts: sign fixed to the non-negative pair
    # an outlier 500 m up (outside on every plane but the vertical ones) changes nothing here
    p3 = np.vstack([p2, [[0.5, 0.2, 500.0]]])
    np.testing.assert_allclose(d3.m2dp_patches(p3, np.array([0, len(p3)]), cfg)[0], _m2dp_loop(p3, cfg), atol=2e-5)
    # a finer grid than one byte per plane holds (9 rings x 34 sector columns): two-byte bin ids
    fine = d3.M2DPConfig(n_angular=32, n_plane_elevations=5)
    p4 = np.vstack([np.zeros(3), _off_bin_edges(p1[1:], fine)])
    np.testing.assert_allclose(d3.m2dp_patches(p4, np.array([0, len(p4)]), fine)[0], _m2dp_loop(p4, fine), atol=2e-5)
    with pytest.raises(InputError):
        d3.m2dp_patches(p4, np.array([0, len(p4)]), d3.M2DPConfig(n_radial=300))


# --- M2DP as the authors' M2DP.m computes it ----------------------------------------------------------

M2DP_REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "data" / "m2dp-reference"


def _half_cosines(a: np.ndarray, b: np.ndarray, P: int = 64) -> tuple[float, float]:
    """|cosine| of the u1 halves and of the v1 halves (each half's SVD sign is arbitrary)."""
    return tuple(
        abs(float(x @ y)) / (np.linalg.norm(x) * np.linalg.norm(y)) for x, y in ((a[:P], b[:P]), (a[P:], b[P:]))
    )


@pytest.mark.realdata
def test_m2dp_reference_reproduces_the_authors_m2dp_on_a_kitti_scan():
    scan, expected = M2DP_REFERENCE / "kitti-000000.bin", M2DP_REFERENCE / "kitti-000000.m2dp.txt"
    if not (scan.is_file() and expected.is_file()):
        pytest.skip(
            f"M2DP reference not found at {M2DP_REFERENCE} (expected ../shared/data/m2dp-reference beside the project)"
        )
    pts = np.fromfile(scan, np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    ref = np.loadtxt(expected).ravel()
    assert pts.shape == (124668, 3) and ref.shape == (192,)
    A = d3.m2dp_reference_signature(pts)
    assert A.shape == (64, 128) and np.all(A.sum(axis=1) == len(pts))  # the farthest-point grid holds every point
    desc = d3.m2dp_reference(pts)
    assert min(_half_cosines(desc, ref)) >= 0.9999  # measured: 1 - cos < 1e-15
    assert (
        desc[64:].sum() >= 0 and np.isclose(np.linalg.norm(desc[:64]), 1) and np.isclose(np.linalg.norm(desc[64:]), 1)
    )
    # the batched patch descriptor with the authors' settings, on the scan as one patch (float32
    # binning: ~10 of its 8 M point-plane counts sit on a bin edge to float32 precision)
    authors = d3.m2dp_patches(pts, np.array([0, len(pts)]), d3.M2DPConfig.authors())[0]
    assert min(_half_cosines(authors.astype(np.float64), ref)) >= 0.9999  # measured: 1 - cos ~ 5e-12
    np.testing.assert_allclose(authors, desc, atol=2e-5)


def _authors_cfg(**kw):
    return d3.M2DPConfig.authors(**kw)


def _off_authors_bin_edges(points: np.ndarray, cfg, eps: float = 1e-5) -> np.ndarray:
    """The points of one cloud, less those within ``eps`` (in ring or sector units) of an M2DP
    bin edge on some plane in the authors' frame and grid (float32 binning in the library: such
    a point may fall on either side). Dropping points moves the mean, the axes and the farthest
    point, so this repeats until no point is near an edge (each round finds ~1e-5 x 4 x 64 planes of
    the points anew: a few in a patch of a thousand, which then may not settle)."""
    _, ax, ay = d3.m2dp_planes(cfg)
    for _ in range(50):
        if len(points) < 2:
            return points
        d = d3.m2dp_pca_frame(points, np.array([0, len(points)]))
        R = np.sqrt(np.max(np.einsum("ij,ij->i", d, d)))
        x, y = d @ ax.T, d @ ay.T
        ring = cfg.n_radial * np.sqrt(np.hypot(x, y) / R)
        sector = (np.arctan2(y, x) + math.pi) / (2 * math.pi) * cfg.n_angular
        # ring edges 1 .. l - 1 only: nothing lies below 0, and the last ring has no outer edge
        near_ring = (np.abs(ring - np.round(ring)) < eps) & (np.round(ring) >= 1) & (np.round(ring) <= cfg.n_radial - 1)
        near = near_ring | (np.abs(sector - np.round(sector)) < eps)
        keep = ~near.any(axis=1)
        if keep.all():
            return points
        points = points[keep]
    raise AssertionError("points near M2DP bin edges did not settle")


def test_m2dp_patches_with_the_authors_settings_equal_m2dp_reference_on_each_patch(rng):
    cfg = d3.M2DPConfig.authors()
    street = _street(rng)
    patches = [
        rng.normal(0, [4.0, 2.0, 0.7], (600, 3)) @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
        + [3.0, -1.0, 2.0],  # tilted ellipsoid, off the origin
        street[np.hypot(street[:, 0] - 30, street[:, 1]) < 10][
            ::4
        ],  # a street patch about (30, 0): facades, road markings
        np.zeros((0, 3)),
        np.array([[1.0, 2.0, 3.0]]),  # one point: at the mean, R = 0
        # three points at one place, one far above, two aside (not coplanar: in the PCA frame a plane
        # is z = 0, which puts every point on a sector edge of the vertical M2DP planes)
        np.array([[0.5, 0.5, 0.5]] * 3 + [[0.5, 0.6, 40.0], [3.0, -1.0, 2.0], [1.0, 2.0, 0.0]]),
        np.vstack([rng.normal([0, 0, 0], [0.3, 3.0, 1.0], (300, 3)), [[80.0, 1.0, 1.0]]]),  # an outlier sets the radius
    ]
    patches = [_off_authors_bin_edges(p, cfg) for p in patches]
    assert len(patches[1]) > 450 and len(patches[0]) > 550 and len(patches[5]) > 280  # edge points are rare
    indptr = np.cumsum([0] + [len(p) for p in patches])
    counts = d3.m2dp_signature_matrices(np.vstack(patches), indptr, cfg)
    desc = d3.m2dp_patches(np.vstack(patches), indptr, cfg)
    assert desc.shape == (len(patches), 192) and desc.dtype == np.float32
    for k, p in enumerate(patches):
        # the same counts exactly, so the same descriptor up to the singular-vector solver: float64
        # SVD of the library's counts is the reference to 1e-9; its float32 power iteration to 2e-5
        A = d3.m2dp_reference_signature(p)
        np.testing.assert_array_equal(counts[k], A, err_msg=f"patch {k}")
        ref = d3.m2dp_reference(p)
        np.testing.assert_allclose(desc[k], ref, atol=2e-5, err_msg=f"patch {k}")
        if A.any():
            U, _, Vt = np.linalg.svd(counts[k].astype(np.float64))
            exact = np.concatenate([U[:, 0], Vt[0]]) * (1.0 if Vt[0].sum() >= 0 else -1.0)
            np.testing.assert_allclose(exact, ref, atol=1e-9, err_msg=f"patch {k}")
    assert np.all(desc[2] == 0)
    assert counts[3].sum() == 64 and np.all(counts[3][:, 7 * 16 + 8] == 1)  # R = 0: the original's last ring, angle 0
    assert np.all(counts[5].sum(axis=1) == len(patches[5]))  # nothing outside the farthest-point grid
    # the defaults are not the authors': on the ellipsoid the descriptor is far from the reference
    default = d3.m2dp_patches(patches[0], np.array([0, len(patches[0])]))[0]
    assert min(_half_cosines(default.astype(np.float64), d3.m2dp_reference(patches[0]))) < 0.99


def test_m2dp_variants_do_what_they_say(rng):
    p = np.vstack(
        [
            rng.normal([2.0, 1.0, 0.0], [5.0, 1.5, 2.0], (500, 3)),
            rng.normal([-4.0, 3.0, 1.0], [0.5, 0.5, 4.0], (200, 3)),
        ]
    )
    ip = np.array([0, len(p)])
    # unnormalised in-plane axes: length sqrt(1 - n_x^2), orthogonal to the normal, y = n x x
    n, ax, ay = d3.m2dp_planes(d3.M2DPConfig(normalise_axes=False))
    np.testing.assert_allclose(np.linalg.norm(ax, axis=1), np.sqrt(1 - n[:, 0] ** 2), atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", ax, n), 0, atol=1e-12)
    np.testing.assert_allclose(ay, np.cross(n, ax), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(d3.m2dp_planes()[1], axis=1), 1, atol=1e-12)
    # the PCA frame: centred, uncorrelated, variances decreasing, each axis's largest coefficient
    # positive (checked against numpy's SVD of each patch), and batched = one patch at a time;
    # patches of 256 points or more go one by one, smaller ones all at once
    q = rng.normal(0, [1.0, 3.0, 0.2], (300, 3)) + 7.0
    r = rng.normal(0, [2.0, 0.5, 1.0], (100, 3)) - 3.0
    ip3 = np.cumsum([0, len(p), len(q), len(r)])
    frames = d3.m2dp_pca_frame(np.vstack([p, q, r]), ip3)
    for k, pts in enumerate((p, q, r)):
        f = frames[ip3[k] : ip3[k + 1]]
        np.testing.assert_array_equal(d3.m2dp_pca_frame(pts, np.array([0, len(pts)])), f)
        c = pts - pts.mean(axis=0)
        V = np.linalg.svd(c, full_matrices=False)[2].T
        V *= np.where(V.max(axis=0) < -V.min(axis=0), -1.0, 1.0)
        np.testing.assert_allclose(f, c @ V, atol=1e-9)
        cov = f.T @ f
        assert np.all(np.abs(cov - np.diag(np.diag(cov))) < 1e-8 * cov[0, 0]) and np.all(np.diff(np.diag(cov)) < 0)
    # each setting on its own changes the descriptor
    base = d3.m2dp_patches(p, ip)[0]
    for kw in ({"radius": "farthest"}, {"normalise_axes": False}, {"frame": "pca"}):
        assert np.abs(d3.m2dp_patches(p, ip, d3.M2DPConfig(**kw))[0] - base).max() > 0.01, kw
    # the farthest-point radius makes it scale-invariant; the PCA frame, translation-invariant
    far = d3.M2DPConfig(radius="farthest")
    np.testing.assert_allclose(d3.m2dp_patches(3.0 * p, ip, far)[0], d3.m2dp_patches(p, ip, far)[0], atol=1e-4)
    authors = d3.M2DPConfig.authors()
    np.testing.assert_allclose(
        d3.m2dp_patches(p + [40.0, -7.0, 3.0], ip, authors)[0], d3.m2dp_patches(p, ip, authors)[0], atol=1e-4
    )
    assert authors.dim == 192 and (authors.radius, authors.normalise_axes, authors.frame) == ("farthest", False, "pca")
    assert (d3.M2DPConfig().radius, d3.M2DPConfig().normalise_axes, d3.M2DPConfig().frame) == ("domain", True, "yaw")


def test_leading_singular_vectors_match_svd_and_fallback(rng):
    A = rng.random((20, 12, 30)).astype(np.float32) ** 3
    U, _, Vt = np.linalg.svd(A.astype(np.float64))
    ref_u, ref_v = U[:, :, 0], Vt[:, 0, :]
    flip = np.where(ref_v.sum(axis=1) < 0, -1.0, 1.0)[:, None]
    for max_iter in (64, 0):  # 0: everything goes through the exact fallback
        u, v = d3.leading_singular_vectors(A, max_iter=max_iter)
        np.testing.assert_allclose(u, ref_u * flip, atol=1e-5)
        np.testing.assert_allclose(v, ref_v * flip, atol=1e-5)


def _street(rng):
    """A 60 m street: two facades with window edges, road markings, poles; +z up."""
    parts = []
    for side in (-9.0, 9.0):
        x = rng.uniform(0, 60, 6000)
        z = rng.uniform(0, 12, 6000)
        on_edge = (np.mod(x, 4.0) < 0.3) | (np.mod(z, 3.0) < 0.3)
        parts.append(np.column_stack([x, side + 0.5 * np.sin(x / 7) + rng.normal(0, 0.03, 6000), z])[on_edge])
    for y0 in (-3.5, 0.0, 3.5):
        x = rng.uniform(0, 60, 1500)
        parts.append(np.column_stack([x, y0 + rng.normal(0, 0.05, 1500), rng.normal(0, 0.02, 1500)]))
    for x0 in range(5, 60, 12):
        parts.append(np.column_stack([np.full(200, x0 + 0.0), np.full(200, 6.5), rng.uniform(0, 6, 200)]))
    return np.vstack(parts)


@pytest.mark.parametrize("kind", ["nbld", "m2dp"])
def test_chain_invariant_to_rotation_of_the_map_about_z(rng, kind):
    points = _street(rng)
    kp_idx = rng.choice(len(points), 40, replace=False)
    keypoints = points[kp_idx]
    observers = np.column_stack([keypoints[:, 0] - 8.0, np.zeros(40), np.full(40, 1.5)])  # camera driving along +x
    desc = d3.describe(kind, points, keypoints, observers - keypoints)
    Rz = yaw_rotation(2.2)
    shift = np.array([120.0, -40.0, 3.0])
    moved = points @ Rz.T + shift
    desc_r = d3.describe(kind, moved, keypoints @ Rz.T + shift, (observers - keypoints) @ Rz.T)
    assert desc.shape == (40, 576 if kind == "nbld" else 192) and desc.dtype == np.float32
    if kind == "nbld":
        assert set(np.unique(desc)) <= {0.0, 1.0} and desc.mean() > 0.05
        assert np.mean(desc != desc_r) < 0.002  # exact in practice; a point on a cell edge may flip
    else:
        np.testing.assert_allclose(desc_r, desc, atol=1e-4)
    # a different direction of the first observer changes the descriptors
    desc_flip = d3.describe(kind, points, keypoints, keypoints - observers)
    assert np.abs(desc_flip - desc).mean() > 0.01


def test_thin_patches_keeps_about_max_points_the_same_way_everywhere():
    counts = np.array([5000, 100, 6900, 1024])
    indices = np.concatenate([np.arange(5000), np.arange(100), np.arange(3000, 9900), np.arange(7, 1031)])
    indptr = np.concatenate([[0], np.cumsum(counts)])
    ip, idx = d3.thin_patches(indptr, indices, 1024)
    kept = np.diff(ip)
    assert np.all(np.abs(kept[[0, 2]] - 1024) <= 10) and kept[1] == 100 and kept[3] == 1024
    patch = [idx[ip[k] : ip[k + 1]] for k in range(4)]
    assert np.array_equal(patch[1], np.arange(100)) and np.array_equal(patch[3], np.arange(7, 1031))
    # the more thinned patch keeps a subset of what the other keeps where they overlap (3000..4999)
    common = patch[2][patch[2] < 5000]
    assert len(common) > 100 and np.isin(common, patch[0]).all()
    # the same choice block by block: the last two patches alone give the same points
    ip2, idx2 = d3.thin_patches(indptr[2:] - indptr[2], indices[indptr[2] :], 1024)
    assert np.array_equal(idx2, idx[ip[2] :])


def test_m2dp_of_a_thinned_dense_patch_stays_close(rng):
    points = np.vstack([_street(rng) for _ in range(8)])  # eight times denser: ~15k points per patch
    keypoints = points[rng.choice(len(points), 20, replace=False)]
    dirs = np.tile([[-1.0, 0.0]], (20, 1))
    full = d3.describe("m2dp", points, keypoints, dirs)
    cfg = d3.StructureDescriptorConfig(m2dp=d3.M2DPConfig(max_points=2000))
    thin = d3.describe("m2dp", points, keypoints, dirs, cfg)
    tree = d3.xy_tree(points)
    sizes = np.diff(d3.extract_patches(points, keypoints, cfg.m2dp.domain, tree)[0])
    assert np.median(sizes) > 6000
    # [u1, v1]: two unit vectors. Thinning to 2,000 points barely moves u1 (over the planes); v1
    # (over the polar bins) stays within a few degrees for most patches, but where the first two
    # singular values of a patch are nearly equal its leading pair is unstable and thinning, like
    # any noise, can turn it (measured here: 70-90% of patches above cosine 0.9)
    P = cfg.m2dp.n_planes
    cos_u = np.einsum("ij,ij->i", full[:, :P], thin[:, :P])
    cos_v = np.einsum("ij,ij->i", full[:, P:], thin[:, P:])
    assert np.min(cos_u) > 0.9 and np.median(cos_u) > 0.99
    assert np.median(cos_v) > 0.98
    assert np.abs(full - thin).max() > 1e-4  # it did thin


def test_describe_rejects_unknown_kind():
    with pytest.raises(InputError):
        d3.describe("shot", np.zeros((3, 3)), np.zeros((1, 3)), np.ones((1, 2)))


def test_pca_round_trip_and_dims(rng, tmp_path):
    basis = np.linalg.qr(rng.normal(size=(50, 5)))[0].T  # 5 orthonormal directions in 50-D
    coeff = rng.normal(size=(400, 5)) * [5, 4, 3, 2, 1]
    X = coeff @ basis + 7.0
    pca = d3.DescriptorPCA.fit(X, dim=5)
    Y = pca.transform(X)
    assert Y.shape == (400, 5) and Y.dtype == np.float32 and pca.dim == 5
    np.testing.assert_allclose(pca.inverse_transform(Y), X, atol=1e-4)
    assert np.all(np.diff(pca.explained_variance) < 0)
    np.testing.assert_allclose(pca.components @ pca.components.T, np.eye(5), atol=1e-10)
    loaded = d3.DescriptorPCA.load(pca.save(tmp_path / "pca.npz"))
    np.testing.assert_array_equal(loaded.transform(X), Y)
    # the default: 25 dimensions
    assert d3.DescriptorPCA.fit(rng.normal(size=(100, 40))).dim == 25
    with pytest.raises(InputError):
        d3.DescriptorPCA.fit(X, dim=51)
    with pytest.raises(InputError):
        pca.transform(X[:, :10])
    np.savez(tmp_path / "bad.npz", mean=np.zeros(3))
    with pytest.raises(InputError):
        d3.DescriptorPCA.load(tmp_path / "bad.npz")
