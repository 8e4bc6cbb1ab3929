"""Semi-dense mapping against known geometry: a rendered textured room, and the real KITTI clip.

The synthetic scene is a closed box (a corridor 5 m wide, 3.5 m high, 17 m long) whose walls
carry procedural texture except for one blank panel; a camera drives down it. Every pixel's true
surface point is known, so recovered points are checked against the planes, observations against
visibility, and the blank panel against having no points at all.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from mapkit.core.errors import InputError
from mapkit.core.geometry import invert_pose, make_pose, transform_points
from mapkit.evaluation.metrics import map_accuracy
from mapkit.mapping.semidense import (
    KeyframePoints,
    SemiDenseConfig,
    SemiDenseMap,
    build_semidense_map,
    consistency,
    greedy_nms,
    map_keyframe,
    select_candidates,
)

# --- the synthetic room ------------------------------------------------------------------------------

W_IMG, H_IMG, F_PX = 320, 240, 300.0
K_SYN = np.array([[F_PX, 0.0, 159.5], [0.0, F_PX, 119.5], [0.0, 0.0, 1.0]])
# box interior: x (right), y (down), z (forward), metres
BOX_MIN = np.array([-2.5, -2.0, -3.0])
BOX_MAX = np.array([2.5, 1.5, 14.0])
TEXEL_M = 0.01
BLANK_Z = (5.0, 8.0)  # a texture-less panel on the right wall (x = +2.5), full height


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Band-limited noise at several scales (2-12 cm), contrast-stretched to 20..235."""
    img = np.zeros((h, w), np.float32)
    for sigma, weight in ((2.0, 0.6), (5.0, 1.0), (12.0, 1.0)):
        img += weight * cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma) * sigma
    img = (img - img.mean()) / img.std()
    return np.clip(128 + 45 * img, 20, 235).astype(np.float32)


def _room_textures(seed: int = 7) -> list[tuple[np.ndarray, int, int, np.ndarray]]:
    """Per face: (texture, axis of the face normal, side 0=min/1=max, axes (s, t) of the texture)."""
    rng = np.random.default_rng(seed)
    ext = (BOX_MAX - BOX_MIN) / TEXEL_M
    faces = []
    for axis in range(3):
        s_ax, t_ax = [a for a in (2, 0, 1) if a != axis][:2]
        for side in (0, 1):
            tex = _texture(rng, int(ext[t_ax]) + 2, int(ext[s_ax]) + 2)
            if axis == 0 and side == 1:  # blank panel on the right wall
                z0, z1 = ((np.array(BLANK_Z) - BOX_MIN[2]) / TEXEL_M).astype(int)
                tex[:, z0:z1] = 128.0
            faces.append((tex, axis, side, np.array([s_ax, t_ax])))
    return faces


FACES = _room_textures()


def cast(world_from_cam: np.ndarray, K: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Depth (z in the camera, m) and face index of every pixel of the box interior."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z = 1
    R, c = world_from_cam[:3, :3], world_from_cam[:3, 3]
    d = rays_cam @ R.T
    best_t = np.full(u.shape, np.inf)
    face = np.full(u.shape, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, (_, axis, side, _) in enumerate(FACES):
            plane = BOX_MAX[axis] if side else BOX_MIN[axis]
            t = (plane - c[axis]) / d[..., axis]
            better = (t > 0) & (t < best_t)
            best_t[better], face[better] = t[better], k
    return best_t, face  # t is the camera depth because rays_cam has z = 1


def render(
    world_from_cam: np.ndarray, gain: float = 1.0, bias: float = 0.0, noise: float = 1.0, seed: int = 0
) -> np.ndarray:
    """8-bit image of the room (2x2 supersampled), with an exposure change and sensor noise."""
    ss = 2
    K2 = K_SYN.copy()
    K2[:2] *= ss
    K2[:2, 2] = K_SYN[:2, 2] * ss + (ss - 1) / 2.0
    t, face = cast(world_from_cam, K2, W_IMG * ss, H_IMG * ss)
    u, v = np.meshgrid(np.arange(W_IMG * ss, dtype=np.float64), np.arange(H_IMG * ss, dtype=np.float64))
    X = transform_points(
        world_from_cam, (np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K2).T * t[..., None]).reshape(-1, 3)
    ).reshape(u.shape + (3,))
    img = np.zeros(u.shape, np.float32)
    for k, (tex, _, _, (s_ax, t_ax)) in enumerate(FACES):
        m = face == k
        if not m.any():
            continue
        mx = ((X[..., s_ax] - BOX_MIN[s_ax]) / TEXEL_M).astype(np.float32)
        my = ((X[..., t_ax] - BOX_MIN[t_ax]) / TEXEL_M).astype(np.float32)
        img[m] = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)[m]
    img = cv2.resize(img, (W_IMG, H_IMG), interpolation=cv2.INTER_AREA)
    img = gain * img + bias + np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def trajectory(n: int = 12, step_m: float = 0.3) -> np.ndarray:
    """world_from_cam of a camera driving down the box with some sway and yaw."""
    poses = []
    for i in range(n):
        yaw = np.radians(4.0 * np.sin(i / 3.0))
        R = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        poses.append(make_pose(R, [0.3 * np.sin(i / 4.0), 0.1 * np.cos(i / 5.0), i * step_m]))
    return np.array(poses)


def distance_to_box(points: np.ndarray) -> np.ndarray:
    """Distance (m) of points to the box surface (inside or outside)."""
    inside = np.all((points >= BOX_MIN) & (points <= BOX_MAX), axis=1)
    d_in = np.minimum(points - BOX_MIN, BOX_MAX - points).min(axis=1)
    d_out = np.linalg.norm(np.maximum(np.maximum(BOX_MIN - points, points - BOX_MAX), 0), axis=1)
    return np.where(inside, d_in, d_out)


@pytest.fixture(scope="module")
def room():
    poses = trajectory()
    gains = 1.0 + 0.15 * np.sin(np.arange(len(poses)) * 1.7)  # auto-exposure flicker of +-15%
    images = [
        render(T, gain=g, bias=5.0 * (g - 1.0), seed=i) for i, (T, g) in enumerate(zip(poses, gains, strict=True))
    ]
    return poses, images


ROOM_CFG = SemiDenseConfig(keyframe_spacing_m=0.55, fusion_radius_m=0.03)


@pytest.fixture(scope="module")
def room_map(room):
    poses, images = room
    per_kf: dict[int, KeyframePoints] = {}
    frames = [
        (i, 1_000_000_000 + i * 100_000_000, img, T) for i, (img, T) in enumerate(zip(images, poses, strict=True))
    ]
    sd = build_semidense_map(
        iter(frames), K_SYN, ROOM_CFG, progress=False, on_keyframe=lambda fid, T, p: per_kf.__setitem__(fid, p)
    )
    return sd, per_kf


def _visible(
    points_world: np.ndarray, world_from_cam: np.ndarray, K: np.ndarray = K_SYN, w: int = W_IMG, h: int = H_IMG
) -> np.ndarray:
    X = transform_points(invert_pose(world_from_cam), points_world)
    uvw = X @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    return (X[:, 2] > 0) & (x > -0.5) & (x < w - 0.5) & (y > -0.5) & (y < h - 0.5)


# --- synthetic room: geometry, observations, fusion, texture-less regions ---------------------------------


def test_keyframe_points_lie_on_the_known_planes(room_map, room):
    poses, _ = room
    _, per_kf = room_map
    assert sorted(per_kf) == [0, 2, 4, 6, 8, 10]  # 0.3 m steps, a keyframe every 0.55 m
    for fid, pts in per_kf.items():
        assert len(pts) > 1500, f"keyframe {fid}: only {len(pts)} points"
        rel = distance_to_box(pts.points_world(K_SYN, poses[fid])) / pts.depth
        assert np.median(rel) < 0.005, f"keyframe {fid}: median relative error {np.median(rel):.4f}"
        assert np.percentile(rel, 95) < 0.03
        # the reported sigma is honest: most points lie within 3 sigma of the plane (sigma along the ray >= distance)
        assert np.mean(distance_to_box(pts.points_world(K_SYN, poses[fid])) <= 3 * pts.sigma_depth) > 0.8
        assert np.all(pts.agreed.sum(axis=1) >= ROOM_CFG.min_agreeing_frames - 1)


def test_fused_map_is_accurate_and_keeps_every_observer(room_map, room):
    poses, _ = room
    sd, _ = room_map
    d = distance_to_box(sd.points_world)
    assert len(sd) > 5000
    assert np.median(d) < 0.03 and np.mean(d < 0.5) > 0.99
    counts = sd.obs_counts
    assert counts.min() >= ROOM_CFG.min_agreeing_frames
    pt = sd.obs_point_index()
    # every listed observer sees the point, ids are sorted and unique per point, the source is among them
    vis = np.zeros(len(pt), bool)
    for fid in np.unique(sd.obs_frame_ids):
        m = sd.obs_frame_ids == fid
        vis[m] = _visible(sd.points_world[pt[m]], poses[fid])
    assert vis.all()
    assert np.all((np.diff(sd.obs_frame_ids) > 0) | (np.diff(pt) != 0))
    src_listed = np.zeros(len(sd), bool)
    src_listed[pt[sd.obs_frame_ids == sd.source_keyframe[pt]]] = True
    assert src_listed.all()
    # observers include non-keyframes (matched neighbours) and other keyframes (merged duplicates)
    assert np.isin(sd.obs_frame_ids, sd.keyframe_ids, invert=True).any()
    other_kf = np.isin(sd.obs_frame_ids, sd.keyframe_ids) & (sd.obs_frame_ids != sd.source_keyframe[pt])
    assert other_kf.sum() > 0.1 * len(sd)


def test_duplicates_of_consecutive_keyframes_are_fused(room_map, room):
    poses, _ = room
    sd, per_kf = room_map
    raw = sum(len(p) for p in per_kf.values())
    assert len(sd) < 0.8 * raw
    dist, _ = cKDTree(sd.points_world).query(sd.points_world, k=2)
    assert dist[:, 1].min() > ROOM_CFG.fusion_radius_m
    # each keyframe's own point survives, or a map point nearby now lists that keyframe (a point
    # absorbed by one that is later absorbed in turn can end up to a few radii away)
    tree = cKDTree(sd.points_world)
    pt = sd.obs_point_index()
    for fid, pts in per_kf.items():
        lists_fid = np.zeros(len(sd), bool)
        lists_fid[pt[sd.obs_frame_ids == fid]] = True
        near = tree.query_ball_point(pts.points_world(K_SYN, poses[fid]), 3 * ROOM_CFG.fusion_radius_m)
        covered = np.array([lists_fid[n].any() for n in near])
        assert covered.mean() > 0.99, f"keyframe {fid}: {covered.mean():.3f}"


def test_textureless_panel_gets_no_points(room_map, room):
    poses, images = room
    sd, _ = room_map
    # candidates: none inside the blank panel (away from its border, where the texture edge is)
    t, face = cast(poses[3], K_SYN, W_IMG, H_IMG)
    u, v = np.meshgrid(np.arange(W_IMG), np.arange(H_IMG))
    X = transform_points(
        poses[3], (np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K_SYN).T * t[..., None]).reshape(-1, 3)
    ).reshape(H_IMG, W_IMG, 3)
    right_wall = [k for k, f in enumerate(FACES) if f[1] == 0 and f[2] == 1][0]
    panel = (
        (face == right_wall)
        & (X[..., 2] > BLANK_Z[0] + 0.3)
        & (X[..., 2] < BLANK_Z[1] - 0.3)
        & (np.abs(X[..., 1]) < 1.0)
    )
    assert panel.sum() > 500  # the panel is in view
    cu, cv = select_candidates(images[3], ROOM_CFG)
    assert len(cu) > 3000
    assert not panel[cv, cu].any()
    # map: no point on the panel's interior (0.3 m from its edges and from the floor and ceiling)
    P = sd.points_world
    wall_band = (np.abs(P[:, 0] - BOX_MAX[0]) < 0.2) & (P[:, 1] > BOX_MIN[1] + 0.3) & (P[:, 1] < BOX_MAX[1] - 0.3)
    on_panel = wall_band & (P[:, 2] > BLANK_Z[0] + 0.3) & (P[:, 2] < BLANK_Z[1] - 0.3)
    assert on_panel.sum() == 0
    on_textured = wall_band & (P[:, 2] > BLANK_Z[1] + 0.3) & (P[:, 2] < BLANK_Z[1] + 3.3)
    assert on_textured.sum() > 50  # the same wall with texture has points
    # a flat image has no candidates and no points at all
    flat = np.full((H_IMG, W_IMG), 90, np.uint8)
    assert len(select_candidates(flat, ROOM_CFG)[0]) == 0
    assert len(map_keyframe(flat, poses[0], [(flat, poses[1]), (flat, poses[2])], K_SYN, ROOM_CFG)) == 0


def test_exposure_change_between_frames_is_harmless(room):
    poses, _ = room
    ref = render(poses[4], seed=40)
    dark, bright = render(poses[2], gain=0.6, bias=-10, seed=41), render(poses[6], gain=1.4, bias=10, seed=42)
    mid1, mid2 = render(poses[3], gain=0.8, seed=43), render(poses[5], gain=1.2, seed=44)
    pts = map_keyframe(
        ref,
        poses[4],
        [(mid1, poses[3]), (mid2, poses[5]), (dark, poses[2]), (bright, poses[6])],
        K_SYN,
        ROOM_CFG,
        neighbour_ids=[3, 5, 2, 6],
    )
    assert len(pts) > 1500
    rel = distance_to_box(pts.points_world(K_SYN, poses[4])) / pts.depth
    assert np.median(rel) < 0.005
    assert pts.agreed[:, 2:].any(axis=0).all()  # the strongly exposed frames took part


def test_short_lines_and_periodic_texture_give_no_wrong_points(room):
    poses, images = room
    # neighbours 1 cm away and at the same place: no parallax, no points
    near = poses[4].copy()
    near[:3, 3] += [0.0, 0.0, 0.01]
    cfg = ROOM_CFG.model_copy(update={"min_baseline_m": 0.0})
    assert (
        len(map_keyframe(images[4], poses[4], [(render(near, seed=9), near), (images[4], poses[4])], K_SYN, cfg)) == 0
    )
    # a fronto-parallel wall 5 m away seen by a camera moving sideways: pure horizontal shifts
    depth, baselines = 5.0, (0.0, 0.15, 0.25, 0.4)
    poses_side = [make_pose(np.eye(3), [b, 0, 0]) for b in baselines]
    rng = np.random.default_rng(3)
    noise = cv2.GaussianBlur(rng.standard_normal((H_IMG, W_IMG + 40)).astype(np.float32), (0, 0), 1.5)
    textured = np.clip(128 + 60 * noise / noise.std(), 0, 255).astype(np.uint8)
    stripes = np.tile(((np.arange(W_IMG + 40) // 4) % 2 * 120 + 60).astype(np.uint8), (H_IMG, 1))  # period 8 px
    for wall, periodic in ((textured, False), (stripes, True)):
        views = [wall[:, int(round(F_PX * b / depth)) :][:, :W_IMG].copy() for b in baselines]
        pts = map_keyframe(views[0], poses_side[0], list(zip(views[1:], poses_side[1:], strict=True)), K_SYN, ROOM_CFG)
        if periodic:  # lines span several periods: the full-range search must find no unambiguous match
            assert pts.stats["with_estimate"] < 0.1 * pts.stats["candidates"]
        else:
            assert len(pts) > 0.5 * pts.stats["candidates"]
        assert np.all(np.abs(pts.depth - depth) < 0.02 * depth)


# --- building blocks ---------------------------------------------------------------------------------------


def test_greedy_nms_matches_sequential_suppression(rng):
    pts = rng.uniform(0, 1, size=(600, 3))
    prio = rng.uniform(size=600)
    keep, target = greedy_nms(pts, prio, 0.08)
    ref_keep = np.zeros(600, bool)
    for i in np.argsort(prio):
        if not any(np.linalg.norm(pts[j] - pts[i]) <= 0.08 for j in np.nonzero(ref_keep)[0]):
            ref_keep[i] = True
    assert np.array_equal(keep, ref_keep)
    assert np.all(target[keep] == np.nonzero(keep)[0])
    sup = ~keep
    assert keep[target[sup]].all()
    assert np.all(np.linalg.norm(pts[sup] - pts[target[sup]], axis=1) <= 0.08)


def test_map_records_every_frame_stamp_for_pose_interpolation(room_map, room):
    """Every input frame's id and stamp are kept (not only keyframes'), so that a non-key frame's
    pose between keyframes is interpolated at its own time: the structure index's frame table
    then puts each observing frame where the camera was."""
    from mapkit.places.index_structure import session_frames

    sd, _ = room_map
    poses, _ = room
    assert np.array_equal(sd.frame_ids, np.arange(len(poses)))
    assert np.array_equal(sd.frame_stamps_ns, 1_000_000_000 + np.arange(len(poses)) * 100_000_000)
    table = session_frames(sd)
    others = ~np.isin(table["frame_id"], sd.keyframe_ids) & (table["stamp_ns"] >= 0)
    assert others.any()
    assert np.array_equal(table["stamp_ns"][others], 1_000_000_000 + table["frame_id"][others] * 100_000_000)


def test_save_load_round_trip(room_map, tmp_path):
    sd, _ = room_map
    out = sd.save(tmp_path / "map")
    assert sorted(p.name for p in out.iterdir()) == ["config.yaml", "observations.npz", "points.ply"]
    header = (out / "points.ply").read_bytes()[:400]
    assert b"binary_little_endian" in header and b"property double x" in header
    back = SemiDenseMap.load(out)
    assert np.array_equal(back.points_world, sd.points_world)  # float64, bit for bit
    for name in (
        "intensity",
        "sigma_depth",
        "source_keyframe",
        "obs_indptr",
        "obs_frame_ids",
        "keyframe_ids",
        "keyframe_stamps_ns",
        "keyframe_world_from_cam",
        "K",
        "frame_ids",
        "frame_stamps_ns",
    ):
        assert np.array_equal(getattr(back, name), getattr(sd, name)), name
    assert back.image_size_wh == (W_IMG, H_IMG)
    assert back.config == ROOM_CFG
    assert np.array_equal(back.observations(7), sd.observations(7))
    with pytest.raises(InputError):
        SemiDenseMap.load(tmp_path / "nothing")


def test_consistency_separates_right_from_wrong_depths(room_map, room):
    poses, _ = room
    sd, per_kf = room_map
    kfs = [(fid, poses[fid], p) for fid, p in per_kf.items()]
    good = consistency(sd, kfs)
    assert good["pairs"] > 5000 and good["median_rel"] < 0.02
    # the same map with every point pushed 10% farther from its source keyframe must fail
    centres = {fid: poses[fid][:3, 3] for fid in per_kf}
    c = np.array([centres[s] for s in sd.source_keyframe])
    bad = SemiDenseMap(**{**sd.__dict__, "points_world": c + 1.1 * (sd.points_world - c)})
    assert consistency(bad, kfs)["median_rel"] > 0.05


class _LiveImages:
    """Streams ``(i, stamp, copy of image i, pose i)`` and records the most images alive at once (``peak``)."""

    def __init__(self, images, poses, stamps=None):
        self.images, self.poses, self.peak = images, poses, 0
        self.stamps = list(range(len(poses))) if stamps is None else stamps

    def stream(self):
        import gc
        import weakref

        refs: list[weakref.ref] = []
        for i, T in enumerate(self.poses):
            gc.collect()
            self.peak = max(self.peak, sum(r() is not None for r in refs))
            img = self.images[i].copy()
            refs.append(weakref.ref(img))
            yield i, self.stamps[i], img, T
            del img


def test_streams_with_a_bounded_window(room):
    """No more than 2 * neighbour_window_frames + 1 images are alive while the map is built."""
    poses, images = room
    frames = _LiveImages(images, poses)
    cfg = ROOM_CFG.model_copy(update={"neighbour_window_frames": 2})
    sd = build_semidense_map(frames.stream(), K_SYN, cfg, progress=False)
    assert len(sd) > 1000
    assert frames.peak <= 2 * 2 + 1


def test_bad_input_is_reported():
    with pytest.raises(InputError, match="grey image"):
        build_semidense_map(iter([(0, 0, np.zeros((4, 4, 3), np.uint8), np.eye(4))]), K_SYN, progress=False)
    with pytest.raises(InputError, match="differs"):
        build_semidense_map(
            iter([(0, 0, np.zeros((8, 8), np.uint8), np.eye(4)), (1, 1, np.zeros((9, 8), np.uint8), np.eye(4))]),
            K_SYN,
            progress=False,
        )
    with pytest.raises(ValueError):
        SemiDenseConfig(min_depth_m=10.0, max_depth_m=5.0)
    empty = build_semidense_map(iter([]), K_SYN, progress=False)
    assert len(empty) == 0 and len(empty.obs_indptr) == 1


# --- the real KITTI clip -------------------------------------------------------------------------------------


def _read_kitti(clip: Path, n: int):
    first = (clip / "calib.txt").read_text().splitlines()[0].split()
    K = np.array([float(x) for x in first if not x.endswith(":")]).reshape(3, 4)[:, :3]
    rows = np.loadtxt(clip / "poses.txt").reshape(-1, 3, 4)[:n]
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows  # camera -> frame-0 camera (world)
    images = [cv2.imread(str(clip / "image_l" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) for i in range(n)]
    return K, poses, images


@pytest.mark.realdata
def test_kitti_clip_map_is_consistent_across_frames(kitti_clip):
    K, poses, images = _read_kitti(kitti_clip, 12)
    own = {}
    sd = build_semidense_map(
        ((i, i * 100_000_000, img, T) for i, (img, T) in enumerate(zip(images, poses, strict=True))),
        K,
        progress=False,
        on_keyframe=lambda fid, T, p: own.__setitem__(fid, (T, p)),
    )
    assert len(own) == 12  # 1.2 m per frame: every frame is a keyframe
    assert min(len(p) for _, p in own.values()) > 1500
    assert len(sd) > 20000
    c = consistency(sd, [(fid, T, p) for fid, (T, p) in own.items()])
    assert c["pairs"] > 20000
    assert c["median_rel"] < 0.05  # the goal: keyframes agree within 5 % (median)
    assert c["by_keyframe_distance_m"][0]["median_rel"] < 0.03  # neighbouring keyframes agree closely


def test_accuracy_against_a_mesh_matches_the_known_box(room_map):
    sd, _ = room_map
    corners = np.array(
        [
            [x, y, z]
            for x in (BOX_MIN[0], BOX_MAX[0])
            for y in (BOX_MIN[1], BOX_MAX[1])
            for z in (BOX_MIN[2], BOX_MAX[2])
        ]
    )
    # 12 triangles of the box (corner index = 4x + 2y + z)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    acc = map_accuracy(sd.points_world, (corners, tris), road_length_m=3.0)
    d = distance_to_box(sd.points_world)
    assert acc["median_distance_m"] == pytest.approx(np.median(d), abs=1e-4)
    assert acc["fraction_within_0.5m"] == pytest.approx(np.mean(d <= 0.5), abs=1e-3)
    assert acc["points_per_100m"] == pytest.approx(len(sd) / 3.0 * 100)
    assert acc["median_distance_m"] < 0.15 and acc["fraction_within_0.5m"] > 0.8  # the town goals, on the room


def test_blank_frames_give_an_empty_map_not_a_crash():
    """Sky, fog or a lens cap: keyframes without a single candidate must pass through fusion."""
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    blank = np.full((240, 320), 128, np.uint8)
    frames = [(i, i * 10**8, blank, make_pose(np.eye(3), [0.0, 0.0, 1.2 * i])) for i in range(8)]
    sd = build_semidense_map(frames, K, SemiDenseConfig(), progress=False)
    assert len(sd) == 0 and len(sd.keyframe_ids) >= 5
    assert sd.obs_indptr.tolist() == [0]


# --- outlier rejection: one known answer per filter -------------------------------------------------------


def _plane_depth(world_from_cam: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Camera depth of the slanted wall z = 8 + 0.2 x (world) along the rays of pixels ``uv`` (N, 2)."""
    rays = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K_SYN).T @ world_from_cam[:3, :3].T  # camera z = 1
    c = world_from_cam[:3, 3]
    return (8.0 + 0.2 * c[0] - c[2]) / (rays[:, 2] - 0.2 * rays[:, 0])


def test_multi_view_filter_removes_depths_injected_along_rays(rng):
    """Six views of a known wall hold sparse depths (40 % of pixels, 5 % of them wrong); the keyframe's
    true wall points survive the multi-view test and points moved along their rays do not."""
    from mapkit.mapping.semidense import multi_view_filter

    uv_all = np.stack(np.meshgrid(np.arange(W_IMG), np.arange(H_IMG)), -1).reshape(-1, 2).astype(np.float64)
    views = []
    for i in (-3, -2, -1, 1, 2, 3):  # a sideways drive past the wall, the keyframe in the middle
        T = make_pose(np.eye(3), [0.25 * i, 0.05 * i, 0.1 * i])
        depth = np.full((H_IMG, W_IMG), np.nan, np.float32)
        pick = rng.random(len(uv_all)) < 0.4
        z = _plane_depth(T, uv_all[pick])
        wrong = rng.random(len(z)) < 0.05
        z[wrong] *= rng.choice([0.6, 1.5], size=wrong.sum())
        depth[uv_all[pick, 1].astype(int), uv_all[pick, 0].astype(int)] = z
        views.append((T, depth))
    kf = np.eye(4)
    uv = uv_all[rng.choice(len(uv_all), 3000, replace=False)]
    z = _plane_depth(kf, uv)
    injected = rng.random(len(z)) < 0.2
    z[injected] *= np.where(
        rng.random(injected.sum()) < 0.5, rng.uniform(0.6, 0.85, injected.sum()), rng.uniform(1.2, 1.6, injected.sum())
    )
    X = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K_SYN).T * z[:, None]
    cfg = SemiDenseConfig(min_consistent_views=1)
    keep = multi_view_filter(
        transform_points(kf, X),
        views,
        K_SYN,
        min_views=cfg.min_consistent_views,
        min_agree_over_conflict=cfg.min_agree_over_conflict,
        rel_tol=cfg.consistency_rel_tol,
        pixel_radius=cfg.consistency_pixel_radius,
    )
    assert np.mean(~keep[injected]) >= 0.9  # recall of the injected outliers
    assert np.mean(keep[~injected]) >= 0.9  # the true points stay


def test_multi_view_filter_in_the_mapper_keeps_the_room_accurate(room, room_map):
    """Switched on in ``build_semidense_map``: what enters fusion is a subset of each keyframe's
    depths, the map keeps most of the room but none of its stray points, and says what went."""
    poses, images = room
    sd_off, _ = room_map
    raw, fused = {}, {}
    frames = [
        (i, 1_000_000_000 + i * 100_000_000, img, T) for i, (img, T) in enumerate(zip(images, poses, strict=True))
    ]
    cfg = ROOM_CFG.model_copy(update={"min_consistent_views": 1})
    sd = build_semidense_map(
        iter(frames),
        K_SYN,
        cfg,
        progress=False,
        on_keyframe=lambda f, T, p: raw.__setitem__(f, p),
        on_fused=lambda f, T, p: fused.__setitem__(f, p),
    )
    assert sorted(fused) == sorted(raw)
    for f in raw:
        assert set(map(tuple, fused[f].pixels_uv)) <= set(map(tuple, raw[f].pixels_uv))
    assert sd.rejected["multi_view"] == sum(len(raw[f]) - len(fused[f]) for f in raw) > 0
    assert 0.6 * len(sd_off) < len(sd) < len(sd_off)
    d, d_off = distance_to_box(sd.points_world), distance_to_box(sd_off.points_world)
    assert (d_off > 0.3).sum() > 20 and (d > 0.3).sum() == 0  # the unfiltered map's stray points are gone
    assert (d > 0.1).sum() < 0.3 * (d_off > 0.1).sum()


def test_four_agreeing_frames_keep_a_subset_with_fewer_stray_points(room, room_map):
    """min_agreeing_frames = 4 (configs/build/clean-maps.yaml): every accepted depth has at least 3
    agreeing neighbours, each keyframe's depths are a subset of those at 3 (the same estimates, fewer
    accepted), and the room's stray points (> 0.3 m off the walls) drop by more than half."""
    poses, images = room
    sd3, raw3 = room_map
    raw4 = {}
    frames = [
        (i, 1_000_000_000 + i * 100_000_000, img, T) for i, (img, T) in enumerate(zip(images, poses, strict=True))
    ]
    sd4 = build_semidense_map(
        iter(frames),
        K_SYN,
        ROOM_CFG.model_copy(update={"min_agreeing_frames": 4}),
        progress=False,
        on_keyframe=lambda f, T, p: raw4.__setitem__(f, p),
    )
    assert sorted(raw4) == sorted(raw3)
    for f, p4 in raw4.items():
        assert (p4.agreed.sum(axis=1) >= 3).all()
        at3 = {tuple(uv): rho for uv, rho in zip(raw3[f].pixels_uv.tolist(), raw3[f].inv_depth, strict=True)}
        assert all(at3.get(tuple(uv)) == rho for uv, rho in zip(p4.pixels_uv.tolist(), p4.inv_depth, strict=True))
    assert sum(len(p) for p in raw4.values()) < sum(len(p) for p in raw3.values())
    stray3, stray4 = ((distance_to_box(sd.points_world) > 0.3).sum() for sd in (sd3, sd4))
    assert stray3 > 20 and stray4 < 0.5 * stray3


def test_ratio_test_rejects_matches_on_repeated_texture(room):
    """Stripes with a period of 8 px: with the margin test off, the full-range search matches them at
    random periods; the second-best ratio rejects nearly all of them, and keeps unique texture."""
    depth, baselines = 5.0, (0.0, 0.15, 0.25, 0.4)
    poses_side = [make_pose(np.eye(3), [b, 0, 0]) for b in baselines]
    rng = np.random.default_rng(3)
    noise = cv2.GaussianBlur(rng.standard_normal((H_IMG, W_IMG + 40)).astype(np.float32), (0, 0), 1.5)
    textured = np.clip(128 + 60 * noise / noise.std(), 0, 255).astype(np.uint8)
    stripes = np.tile(((np.arange(W_IMG + 40) // 4) % 2 * 120 + 60).astype(np.uint8), (H_IMG, 1))
    no_margin = ROOM_CFG.model_copy(update={"ambiguity_margin": 0.0})
    ratio = no_margin.model_copy(update={"ambiguity_ratio": 0.9})

    def run(wall, cfg):
        views = [wall[:, int(round(F_PX * b / depth)) :][:, :W_IMG].copy() for b in baselines]
        return map_keyframe(views[0], poses_side[0], list(zip(views[1:], poses_side[1:], strict=True)), K_SYN, cfg)

    loose, strict = run(stripes, no_margin), run(stripes, ratio)
    assert loose.stats["with_estimate"] > 0.3 * loose.stats["candidates"]  # ambiguity gets through without a test
    assert strict.stats["with_estimate"] < 0.05 * strict.stats["candidates"]
    unique = run(textured, ratio)
    assert len(unique) > 0.5 * unique.stats["candidates"]
    assert np.all(np.abs(unique.depth - depth) < 0.02 * depth)


def test_convergence_threshold_keeps_exactly_the_sharp_depths(room):
    """max_sigma_inv_depth admits exactly the depths whose fused inverse-depth sigma is below it,
    and those lie closer to the walls than the ones it holds back."""
    poses, images = room
    nbs = [(images[i], poses[i]) for i in (2, 3, 5, 6)]
    every = map_keyframe(images[4], poses[4], nbs, K_SYN, ROOM_CFG)
    thr = float(np.median(every.sigma_inv_depth))
    sharp = map_keyframe(images[4], poses[4], nbs, K_SYN, ROOM_CFG.model_copy(update={"max_sigma_inv_depth": thr}))
    below = every.sigma_inv_depth <= thr
    assert set(map(tuple, sharp.pixels_uv)) == set(map(tuple, every.pixels_uv[below]))
    err = distance_to_box(every.points_world(K_SYN, poses[4]))
    assert np.median(err[below]) < np.median(err[~below])


def test_statistical_pass_removes_isolated_points_and_keeps_observations(room_map, rng):
    """open3d's statistical pass drops points scattered in the air off a dense wall; the map's
    ``select`` keeps each surviving point's observers."""
    from mapkit.mapping.semidense import statistical_inliers

    wall = np.column_stack(
        [rng.uniform(0, 5, 4000), rng.uniform(0, 3, 4000), np.full(4000, 8.0) + rng.normal(0, 0.01, 4000)]
    )
    air = rng.uniform([0, 0, 1], [5, 3, 7], size=(100, 3))
    keep = statistical_inliers(np.vstack([wall, air]), 20, 2.0)
    assert keep[:4000].mean() >= 0.95 and (~keep[4000:]).mean() >= 0.9
    sd, _ = room_map
    mask = np.arange(len(sd)) % 3 == 0
    sub = sd.select(mask)
    assert len(sub) == mask.sum() and sub.obs_indptr[-1] == len(sub.obs_frame_ids)
    for j, i in enumerate(np.nonzero(mask)[0][:50]):
        assert np.array_equal(sub.observations(j), sd.observations(i))


def test_consistency_breaks_down_by_depth(room_map, room):
    """Every pair falls in exactly one depth range and one keyframe-distance range."""
    poses, _ = room
    sd, per_kf = room_map
    c = consistency(sd, [(fid, poses[fid], p) for fid, p in per_kf.items()])
    assert (
        sum(b["pairs"] for b in c["by_depth_m"]) == c["pairs"] == sum(b["pairs"] for b in c["by_keyframe_distance_m"])
    )
    assert all(b["p90_rel"] < 0.05 for b in c["by_depth_m"] if b["pairs"] > 100)  # the room: every depth range agrees


def _room_true_depths(world_from_cam: np.ndarray) -> np.ndarray:
    """(H, W) true depth of the room in a camera, as the sparse depth images the filters read (float32)."""
    return cast(world_from_cam, K_SYN, W_IMG, H_IMG)[0].astype(np.float32)


def test_photometric_filter_removes_depths_moved_along_rays(room, rng):
    """A keyframe's true depths of the room keep their patch in the other keyframes' images (NCC near 1
    despite the exposure flicker); depths moved along their rays by 25-40 % land on other texture and
    are rejected, except near the focus of expansion of the forward motion, where a wrong depth
    hardly moves in the other images."""
    from mapkit.mapping.semidense import photometric_filter, photometric_ncc

    poses, images = room
    k = 5
    u, v = select_candidates(images[k], ROOM_CFG)
    pick = rng.choice(len(u), 2000, replace=False)
    uv = np.column_stack([u[pick], v[pick]]).astype(np.int32)
    z = _room_true_depths(poses[k])[uv[:, 1], uv[:, 0]].astype(np.float64)
    moved = rng.random(len(z)) < 0.2
    z[moved] *= np.where(
        rng.random(moved.sum()) < 0.5, rng.uniform(0.6, 0.75, moved.sum()), rng.uniform(1.25, 1.4, moved.sum())
    )
    views = [(poses[i], images[i], _room_true_depths(poses[i])) for i in (2, 3, 4, 6, 7, 8)]
    cfg = SemiDenseConfig(photometric_min_views=1)
    keep = photometric_filter(
        poses[k],
        images[k],
        uv,
        z,
        views,
        K_SYN,
        min_views=cfg.photometric_min_views,
        ncc_min=cfg.photometric_ncc_min,
        min_agree_over_conflict=cfg.photometric_min_agree_over_conflict,
        patch_radius=cfg.photometric_patch_radius,
        rel_tol=cfg.consistency_rel_tol,
        pixel_radius=cfg.consistency_pixel_radius,
    )
    # where the views' parallax moves a wrong depth's image by more than a few pixels in most views (not near
    # the focus of expansion of the forward motion), the patch lands on other texture there: rejected
    z_true = _room_true_depths(poses[k])[uv[:, 1], uv[:, 0]].astype(np.float64)
    rays = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K_SYN).T
    shifts = []
    for T, _, _ in views:
        a, b = (transform_points(invert_pose(T) @ poses[k], rays * d[:, None]) @ K_SYN.T for d in (z, z_true))
        shifts.append(np.hypot(*(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:]).T))
    shifted = moved & (np.median(shifts, axis=0) > 2)
    assert shifted.sum() > 150
    assert np.mean(~keep[shifted]) >= 0.9  # (5x5 patches of smooth texture are ramps: a few wrong ones still correlate)
    assert (
        np.mean(~keep[moved]) >= 0.85
    )  # those pushed behind the wall are hidden in every view, so no view speaks for them
    assert np.mean(keep[~moved]) >= 0.95
    ncc = photometric_ncc(poses[k], images[k], uv, z, views, K_SYN, patch_radius=2, rel_tol=0.06, pixel_radius=1.5)
    assert np.nanmedian(ncc[~moved]) > 0.9
    # a view whose depths show a surface in front of every point is not asked (the points are hidden there)
    near_wall = np.full((H_IMG, W_IMG), 0.5, np.float32)
    hidden = photometric_ncc(
        poses[k],
        images[k],
        uv,
        z,
        [(poses[4], images[4], near_wall)],
        K_SYN,
        patch_radius=2,
        rel_tol=0.06,
        pixel_radius=1.5,
    )
    assert np.isnan(hidden).all()


def test_visibility_tells_free_space_violations_from_occlusions(rng):
    """A slanted wall seen by six views: keyframe points on it agree everywhere; points pulled towards
    the camera float in front of it (free-space violations), points pushed behind it are hidden
    (occluded), and neither kind agrees. ``free_space_filter`` rejects the first kind only."""
    from mapkit.mapping.semidense import free_space_filter, visibility_views

    uv_all = np.stack(np.meshgrid(np.arange(W_IMG), np.arange(H_IMG)), -1).reshape(-1, 2).astype(np.float64)
    views = []
    for i in (-3, -2, -1, 1, 2, 3):
        T = make_pose(np.eye(3), [0.25 * i, 0.05 * i, 0.1 * i])
        depth = _plane_depth(T, uv_all).reshape(H_IMG, W_IMG).astype(np.float32)
        views.append((T, depth))
    kf = np.eye(4)
    inner = uv_all[
        (uv_all[:, 0] >= 60) & (uv_all[:, 0] < W_IMG - 60) & (uv_all[:, 1] >= 60) & (uv_all[:, 1] < H_IMG - 60)
    ]
    uv = inner[rng.choice(len(inner), 3000, replace=False)].astype(np.int32)  # inside every view (shifts < 60 px)
    z = _plane_depth(kf, uv.astype(np.float64))
    kind = rng.integers(0, 3, len(z))  # 0 on the wall, 1 in front of it, 2 behind it
    z = z * np.where(kind == 1, 0.7, np.where(kind == 2, 1.4, 1.0))
    X = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K_SYN).T * z[:, None]
    agree, occluded, free = visibility_views(X, views, K_SYN, 0.06, 1.5)
    in_view = np.sum([_visible(X, T) for T, _ in views], axis=0)
    assert np.all(in_view == 6)
    assert np.all(agree[kind == 0] == 6) and np.all(occluded[kind == 0] + free[kind == 0] == 0)
    assert np.all(free[kind == 1] == 6) and np.all(occluded[kind == 1] == 0) and np.all(agree[kind == 1] == 0)
    assert np.all(occluded[kind == 2] == 6) and np.all(free[kind == 2] == 0) and np.all(agree[kind == 2] == 0)
    # world points of each view's depths (the wall), for the hidden-in-source half of the test
    walls = [
        transform_points(
            T,
            np.column_stack([uv_all, np.ones(len(uv_all))])
            @ np.linalg.inv(K_SYN).T
            * d.reshape(-1)[:, None].astype(np.float64),
        )
        for T, d in views
    ]
    keep = free_space_filter(
        kf,
        uv,
        z,
        X,
        [(T, d, P) for (T, d), P in zip(views, walls, strict=True)],
        K_SYN,
        (H_IMG, W_IMG),
        rel_tol=0.06,
        pixel_radius=1.5,
        max_violations=0,
    )
    assert np.all(keep[kind == 0]) and not np.any(keep[kind == 1])
    # the points behind the wall are hidden in the keyframe itself by the wall the views saw: rejected as well
    assert np.mean(~keep[kind == 2]) > 0.9


def test_hidden_in_source_counts_the_views_whose_surface_hides_a_depth():
    """A keyframe's depths at 10 m; three views saw a pole 5 m in front of a block of its pixels and a
    board at 9.7 m (within tolerance) in front of another: only the first block is hidden, three times."""
    from mapkit.mapping.semidense import hidden_in_source

    kf = np.eye(4)
    uv = np.stack(np.meshgrid(np.arange(100, 140), np.arange(80, 120)), -1).reshape(-1, 2).astype(np.int32)
    depth = np.full(len(uv), 10.0)
    rays = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K_SYN).T
    pole = uv[:, 0] < 110
    board = uv[:, 0] >= 130
    surface = np.vstack([rays[pole] * 5.0, rays[board] * 9.7])
    count = hidden_in_source(kf, uv, depth, [surface] * 3, K_SYN, (H_IMG, W_IMG), 0.06)
    assert np.all(count[pole] == 3) and np.all(count[~pole] == 0)


def test_view_window_votes_within_the_window_also_at_the_end():
    """Each item is released with exactly the items within +-window of it, including the last ones
    (flushed once the stream ends)."""
    from mapkit.mapping.semidense_fusion import _ViewWindow

    window, n = 3, 11
    vw: _ViewWindow[int] = _ViewWindow(window)
    seen = []
    for i in range(n):
        seen.extend(vw.push(i))
    seen.extend(vw.flush())
    assert [item for item, _ in seen] == list(range(n))
    for item, others in seen:
        assert sorted(others) == [j for j in range(max(0, item - window), min(n, item + window + 1)) if j != item]


def test_photometric_and_free_space_filters_in_the_mapper(room, room_map):
    """Switched on in ``build_semidense_map``, each alone: what enters fusion is a subset of each
    keyframe's depths, the map says how many each test removed, and it keeps the room accurate."""
    poses, images = room
    sd_off, _ = room_map
    frames = [
        (i, 1_000_000_000 + i * 100_000_000, img, T) for i, (img, T) in enumerate(zip(images, poses, strict=True))
    ]
    d_off = distance_to_box(sd_off.points_world)
    for name, update in (
        ("photometric", {"photometric_min_views": 1}),
        ("free_space", {"free_space_window_keyframes": 4}),
    ):
        raw, fused = {}, {}
        sd = build_semidense_map(
            iter(frames),
            K_SYN,
            ROOM_CFG.model_copy(update=update),
            progress=False,
            on_keyframe=lambda f, T, p, raw=raw: raw.__setitem__(f, p),
            on_fused=lambda f, T, p, fused=fused: fused.__setitem__(f, p),
        )
        assert sorted(fused) == sorted(raw)
        for f in raw:
            assert set(map(tuple, fused[f].pixels_uv)) <= set(map(tuple, raw[f].pixels_uv))
        assert sd.rejected[name] == sum(len(raw[f]) - len(fused[f]) for f in raw)
        d = distance_to_box(sd.points_world)
        assert len(sd) > 0.6 * len(sd_off), name
        assert (d > 0.3).sum() <= (d_off > 0.3).sum() and np.median(d) < 0.03, name


def _occlusion_scene():
    """Map points on a wall 10 m ahead, from keyframe 0; keyframes 1 and 2 see it (their own depths agree);
    keyframe 3's depth there is 5 m: verified (a pole hides the wall) for half the points, a stray depth its
    multi-view test rejected for the other half. Returns (map, poses, own depths, verified depths, half)."""
    rng = np.random.default_rng(4)
    uv = np.unique(rng.integers([20, 20], [W_IMG - 20, H_IMG - 20], size=(400, 2)), axis=0)
    Kinv = np.linalg.inv(K_SYN)
    P = np.column_stack([uv, np.ones(len(uv))]) @ Kinv.T * 10.0  # keyframe A at the origin: the map's source
    poses = {
        0: np.eye(4),
        1: make_pose(np.eye(3), [0.3, 0, 0]),
        2: make_pose(np.eye(3), [-0.3, 0, 0]),
        3: make_pose(np.eye(3), [0, 0.2, 0]),
    }

    def own(fid: int, scale: np.ndarray) -> KeyframePoints:
        X = transform_points(invert_pose(poses[fid]), P)
        pix = np.rint(X[:, :2] / X[:, 2:3] @ K_SYN[:2, :2].T + K_SYN[:2, 2]).astype(np.int32)
        n = len(P)
        return KeyframePoints(
            pix,
            1.0 / (X[:, 2] * scale),
            np.full(n, 1e-3),
            np.zeros(n, np.uint8),
            np.zeros(0, np.int64),
            np.zeros((n, 0), bool),
            fid,
        )

    half = np.arange(len(P)) % 2 == 0
    kf = {1: own(1, np.ones(len(P))), 2: own(2, np.ones(len(P))), 3: own(3, np.full(len(P), 0.5))}
    verified = {1: kf[1], 2: kf[2], 3: kf[3].select(half)}
    ids = np.array(sorted(poses))
    sd = SemiDenseMap(
        P,
        np.zeros(len(P), np.uint8),
        np.full(len(P), 0.01, np.float32),
        np.zeros(len(P), np.int64),
        np.arange(len(P) + 1, dtype=np.int64),
        np.zeros(len(P), np.int64),
        ids,
        ids,
        np.array([poses[i] for i in ids]),
        K_SYN,
        (W_IMG, H_IMG),
    )
    return sd, poses, kf, verified, half


def test_consistency_tells_occluded_pairs_from_unverified_references():
    """The scene of ``_occlusion_scene``: every pair with keyframe 3 lies 100 % farther; half are occluded,
    half have an unverified reference, none is unexplained; against the verified depths with the occluded
    pairs left out, the map agrees exactly."""
    sd, poses, kf, verified, half = _occlusion_scene()
    P = sd.points_world
    c = consistency(
        sd, [(f, poses[f], p) for f, p in kf.items()], verified=[(f, poses[f], p) for f, p in verified.items()]
    )
    assert c["pairs"] == 3 * len(P)
    assert c["frac_map_farther_5pct"] == pytest.approx(1 / 3)
    fc = c["farther_causes"]
    assert fc["occluded"] == pytest.approx(half.sum() / c["pairs"])
    assert fc["reference_unverified"] == pytest.approx((~half).sum() / c["pairs"])
    assert fc["unexplained"] == 0.0
    assert c["verified_visible"]["pairs"] == 2 * len(P) and c["verified_visible"]["p90_rel"] < 1e-9


def test_consistency_breaks_down_along_the_drive():
    """The same scene by keyframe range: every point comes from keyframe 0 (source range [0, 3) holds all
    pairs); by reference, keyframes 1-2 agree exactly and keyframe 3 holds every farther pair, half of its
    pairs occluded and half unverified."""
    sd, poses, kf, verified, half = _occlusion_scene()
    n = len(sd)
    c = consistency(
        sd,
        [(f, poses[f], p) for f, p in kf.items()],
        verified=[(f, poses[f], p) for f, p in verified.items()],
        keyframe_bins=[0, 3, np.inf],
    )
    src, ref = c["by_source_keyframe"], c["by_reference_keyframe"]
    assert [b["pairs"] for b in src] == [3 * n, 0]
    assert [b["pairs"] for b in ref] == [2 * n, n] and ref[1]["from_frame"] == 3 and ref[1]["to_frame"] is None
    assert ref[0]["frac_map_farther_5pct"] == 0.0 and ref[0]["p90_rel"] < 1e-9
    assert ref[1]["frac_map_farther_5pct"] == 1.0
    fc = ref[1]["farther_causes"]
    assert fc["occluded"] == pytest.approx(half.mean()) and fc["reference_unverified"] == pytest.approx(1 - half.mean())
    assert fc["unexplained"] == 0.0 and ref[0]["farther_causes"]["occluded"] == 0.0


def test_rotation_refinement_recovers_perturbed_rotations(rng):
    """All frames at once (bench/semidense_kitti_clip.py --refine-rotations): a straight drive of 8
    frames 1.2 m apart past random points; frames 1-6 get rotations off by 0.3-0.8 deg (as KITTI's first
    frames are), the matches are the true projections. The epipolar distances go from pixels to nearly
    zero, and every frame's rotation relative to frame 0 comes back within 0.02 deg."""
    from scipy.spatial.transform import Rotation

    from mapkit.core.geometry import rotation_angle_rad
    from mapkit.mapping.pose_refine import epipolar_distances_px, refine_rotations

    true = np.array([make_pose(np.eye(3), [0.0, 0.0, 1.2 * i]) for i in range(8)])
    X = rng.uniform([-8, -3, 12], [8, 2, 40], size=(300, 3))
    matches = []
    for i in range(8):
        for j in range(i + 1, min(i + 3, 7) + 1):
            xi, xj = (transform_points(invert_pose(true[f]), X) @ K_SYN.T for f in (i, j))
            matches.append((i, j, xi[:, :2] / xi[:, 2:], xj[:, :2] / xj[:, 2:]))
    given = true.copy()
    for f in range(1, 7):
        axis = rng.normal(size=3)
        given[f, :3, :3] = (
            true[f, :3, :3]
            @ Rotation.from_rotvec(np.radians(rng.uniform(0.3, 0.8)) * axis / np.linalg.norm(axis)).as_matrix()
        )
    before = np.median(np.concatenate([epipolar_distances_px(K_SYN, given, i, j, a, b) for i, j, a, b in matches]))
    refined = refine_rotations(K_SYN, given, matches)
    after = np.median(np.concatenate([epipolar_distances_px(K_SYN, refined, i, j, a, b) for i, j, a, b in matches]))
    assert before > 0.5 and after < 0.02
    assert np.allclose(refined[:, :3, 3], given[:, :3, 3])  # positions held
    for f in range(1, 8):
        err = rotation_angle_rad((refined[0, :3, :3].T @ refined[f, :3, :3]).T @ (true[0, :3, :3].T @ true[f, :3, :3]))
        assert np.degrees(err) < 0.02, f


@pytest.mark.parametrize("f_px", [F_PX, (F_PX, 2.5 * F_PX)], ids=["square", "fx!=fy"])
def test_epipolar_derivatives_match_finite_differences(rng, f_px):
    """The refiner's epipolar distances are the pixel distances the fundamental matrix gives (also where fx != fy,
    as in an image resized to another aspect), and its analytic derivatives with respect to each camera's rotation
    are the finite differences of the distance itself (random cameras, random matches)."""
    from scipy.spatial.transform import Rotation

    from mapkit.mapping.pose_refine import _pair_terms, epipolar_distances_px

    Ri, Rj = Rotation.random(2, random_state=4).as_matrix()
    Ci, Cj = rng.normal(size=3), rng.normal(size=3)
    a = np.column_stack([rng.normal(size=(20, 2)) * 0.4, np.ones(20)])
    b = np.column_stack([rng.normal(size=(20, 2)) * 0.4, np.ones(20)])

    def terms(Ri, Rj, derivatives=True):
        return _pair_terms(
            f_px, np.broadcast_to(Rj.T @ Ri, (20, 3, 3)), np.broadcast_to(Rj.T @ (Ci - Cj), (20, 3)), a, b, derivatives
        )

    r, d_i, d_j = terms(Ri, Rj)
    fx, fy = np.broadcast_to(f_px, (2,))
    K = np.array([[fx, 0, 320.0], [0, fy, 240.0], [0, 0, 1]])
    poses = [make_pose(Ri, Ci), make_pose(Rj, Cj)]
    assert np.allclose(np.abs(r), epipolar_distances_px(K, poses, 0, 1, (a @ K.T)[:, :2], (b @ K.T)[:, :2]), rtol=1e-9)
    h = 1e-6
    for k in range(3):
        turn = Rotation.from_rotvec(h * np.eye(3)[k]).as_matrix()
        fd_i = (terms(Ri @ turn, Rj, False)[0] - r) / h
        fd_j = (terms(Ri, Rj @ turn, False)[0] - r) / h
        assert np.allclose(fd_i, d_i[:, k], rtol=1e-4, atol=1e-3 * np.abs(d_i).max())
        assert np.allclose(fd_j, d_j[:, k], rtol=1e-4, atol=1e-3 * np.abs(d_j).max())


def test_right_jacobians_are_the_first_order_turn(rng):
    """``R0 exp(x + dx)`` is ``R0 exp(x) exp(Jr(x) dx)`` to first order, for rotations of several sizes and at zero."""
    from scipy.spatial.transform import Rotation

    from mapkit.mapping.pose_refine import _right_jacobians

    x = np.vstack([np.zeros(3), rng.normal(size=(5, 3)) * [[1e-3], [0.01], [0.3], [1.0], [2.5]]])
    Jr = _right_jacobians(x)
    h = 1e-7
    for xk, J in zip(x, Jr, strict=True):
        for k in range(3):
            dx = h * np.eye(3)[k]
            turn = Rotation.from_rotvec(xk).inv() * Rotation.from_rotvec(xk + dx)  # exp(x)^-1 exp(x + dx)
            assert np.allclose(turn.as_rotvec() / h, J @ np.eye(3)[k], atol=1e-6)


def test_rotation_solver_agrees_with_scipy_least_squares(rng):
    """The refiner's own solver (Levenberg-Marquardt on reweighted 3x3-block normal equations) reaches the minimum
    that scipy's general robust least squares finds for the same Huber cost: pixel epipolar distances computed the
    textbook way (fundamental matrix of the poses, ``epipolar_distances_px``) and the prior, on noisy matches with
    10% wrong ones; every frame's correction agrees within 1e-4 deg."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from mapkit.mapping.pose_refine import _normalised, _solve, epipolar_distances_px

    n_frames = 6
    true = np.array([make_pose(np.eye(3), [0.1 * i, 0.0, 1.0 * i]) for i in range(n_frames)])
    given = _perturbed_rotations(true, rng, range(1, n_frames), (0.2, 0.6))
    X = rng.uniform([-8, -3, 10], [8, 2, 40], size=(200, 3))
    matches = []
    for i in range(n_frames):
        for j in range(i + 1, min(i + 3, n_frames - 1) + 1):
            xi, xj = (transform_points(invert_pose(true[f]), X) @ K_SYN.T for f in (i, j))
            ui, uj = (
                xi[:, :2] / xi[:, 2:] + rng.normal(0, 0.3, (200, 2)),
                xj[:, :2] / xj[:, 2:] + rng.normal(0, 0.3, (200, 2)),
            )
            uj[:20] += rng.uniform(-6, 6, (20, 2))  # wrong matches
            matches.append((i, j, ui, uj))
    free = list(range(n_frames))
    prior_px, huber_px = 1.0, 1.0

    def poses_at(x):
        out = given.copy()
        out[:, :3, :3] = given[:, :3, :3] @ Rotation.from_rotvec(x.reshape(-1, 3)).as_matrix()
        return out

    def residuals(x):  # signs do not matter under a Huber loss of squares
        P = poses_at(x)
        return np.concatenate(
            [epipolar_distances_px(K_SYN, P, i, j, a, b) for i, j, a, b in matches] + [F_PX * x / prior_px]
        )

    ref = least_squares(
        residuals, np.zeros(3 * n_frames), loss="huber", f_scale=huber_px, xtol=1e-12, ftol=1e-12, gtol=1e-12
    ).x
    pairs = [(i, j, _normalised(K_SYN, a), _normalised(K_SYN, b)) for i, j, a, b in matches]
    ours = _solve(
        F_PX,
        {f: given[f, :3, :3] for f in free},
        {f: given[f, :3, 3] for f in free},
        free,
        pairs,
        huber_px,
        prior_px,
        step_tol_rad=1e-9,
    )
    assert np.degrees(np.abs(ref - ours.ravel())).max() < 1e-4, np.degrees(np.abs(ref - ours.ravel())).max()
    assert np.degrees(np.abs(ref)).max() > 0.1  # the comparison is not vacuous: both moved the rotations


def test_sparse_depth_answers_as_the_dense_image(rng):
    """A keyframe's depths kept as pixels (``SparseDepth``) give the visibility counts of its dense depth image."""
    from mapkit.mapping.semidense import visibility_views
    from mapkit.mapping.semidense_fusion import SparseDepth

    uv = np.unique(np.column_stack([rng.integers(0, W_IMG, 4000), rng.integers(0, H_IMG, 4000)]), axis=0).astype(
        np.int32
    )
    depth = rng.uniform(4.0, 12.0, len(uv))
    dense = np.full((H_IMG, W_IMG), np.nan, np.float32)
    dense[uv[:, 1], uv[:, 0]] = depth
    sparse = SparseDepth(uv, depth, (H_IMG, W_IMG))
    lin = rng.integers(0, H_IMG * W_IMG, 1000)
    assert np.array_equal(sparse.take(lin), dense.ravel()[lin], equal_nan=True)
    T = make_pose(np.eye(3), [0.2, 0.0, 0.1])
    X = rng.uniform([-3, -2, 3], [3, 2, 14], size=(3000, 3))
    for a, b in zip(
        visibility_views(X, [(T, dense)], K_SYN, 0.06, 1.5),
        visibility_views(X, [(T, sparse)], K_SYN, 0.06, 1.5),
        strict=True,
    ):
        assert np.array_equal(a, b)
    assert visibility_views(X, [(T, dense)], K_SYN, 0.06, 1.5)[0].sum() > 0  # some agree: the comparison is not vacuous


def _perturbed_rotations(
    poses: np.ndarray, rng: np.random.Generator, frames: range, deg: tuple[float, float]
) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    out = poses.copy()
    for f in frames:
        axis = rng.normal(size=3)
        out[f, :3, :3] = (
            poses[f, :3, :3]
            @ Rotation.from_rotvec(np.radians(rng.uniform(*deg)) * axis / np.linalg.norm(axis)).as_matrix()
        )
    return out


@pytest.mark.parametrize("matcher", ["tracks", "sift"])
def test_mapper_refines_rotations_that_disagree_with_the_images(room, room_map, matcher):
    """The room's images with poses whose rotations are off by 0.3-0.8 deg (frames 1-10, as KITTI's first frames
    are): the mapper's own refinement (refine_rotations, with either matcher) brings every keyframe's rotation back
    within 0.1 deg of the truth relative to frame 0 (0.25 deg absolute: a common roll about the drive is invisible
    to the epipolar lines and the prior averages it), keeps the given positions, and the map is as accurate as on
    the true poses; without it the map is worse."""
    from mapkit.core.geometry import rotation_angle_rad

    poses, images = room
    given = _perturbed_rotations(poses, np.random.default_rng(3), range(1, 11), (0.3, 0.8))
    frames = [
        (i, 1_000_000_000 + i * 100_000_000, img, T) for i, (img, T) in enumerate(zip(images, given, strict=True))
    ]
    plain = build_semidense_map(iter(frames), K_SYN, ROOM_CFG, progress=False)
    cfg = ROOM_CFG.model_copy(update={"refine_rotations": True, "refine_matcher": matcher, "refine_features": 1500})
    refined = build_semidense_map(iter(frames), K_SYN, cfg, progress=False)

    ids = refined.keyframe_ids
    assert np.array_equal(ids, plain.keyframe_ids)
    assert np.allclose(refined.keyframe_world_from_cam[:, :3, 3], given[ids, :3, 3])
    err_given = [np.degrees(rotation_angle_rad(given[f, :3, :3].T @ poses[f, :3, :3])) for f in ids]
    R = refined.keyframe_world_from_cam[:, :3, :3]
    err_refined = [np.degrees(rotation_angle_rad(Rf.T @ poses[f, :3, :3])) for f, Rf in zip(ids, R, strict=True)]
    err_relative = [
        np.degrees(rotation_angle_rad((R[0].T @ Rf).T @ (poses[ids[0], :3, :3].T @ poses[f, :3, :3])))
        for f, Rf in zip(ids, R, strict=True)
    ]
    assert max(err_given) > 0.7 and max(err_relative) < 0.1 and max(err_refined) < 0.25, (
        err_given,
        err_relative,
        err_refined,
    )
    pr = refined.pose_refinement
    assert pr["frames"] == len(poses) and pr["epipolar_px_median_refined"] < 0.5 * pr["epipolar_px_median_given"]

    true_sd = room_map[0]
    d_true, d_plain, d_ref = (np.median(distance_to_box(m.points_world)) for m in (true_sd, plain, refined))
    assert d_ref < 1.2 * d_true + 0.002 and d_plain > 1.5 * d_ref, (d_true, d_plain, d_ref)


def test_rotation_refiner_streams_in_order_with_a_bounded_window(room):
    """The refiner hands frames on in order, ``lag`` frames late, holding no more than lag + 1 images; a frame that
    matches nothing (a blank image) keeps its given rotation (the prior), and a lag below the match gap is refused."""
    from mapkit.mapping.pose_refine import RotationRefiner

    poses, images = room
    off5 = _perturbed_rotations(poses, np.random.default_rng(5), range(5, 6), (0.5, 0.5))[5]
    frames = _LiveImages(
        [np.full_like(im, 128) if i == 5 else im for i, im in enumerate(images)],
        [off5 if i == 5 else T for i, T in enumerate(poses)],
        stamps=[10 * i for i in range(len(poses))],
    )
    refiner = RotationRefiner(K_SYN, max_gap=2, lag=3, features=800)
    out = []
    for fid, stamp, img, T in refiner.stream(frames.stream()):
        out.append((fid, stamp, T))
        del img
    assert [o[0] for o in out] == list(range(len(poses))) and [o[1] for o in out] == [10 * i for i in range(len(poses))]
    assert frames.peak <= 3 + 1
    assert np.allclose(
        out[5][2], off5, atol=1e-6
    )  # the blank frame matches nothing: the prior holds its given rotation
    assert max(c for f, c in refiner.corrections_deg.items() if f != 5) < 0.05  # true poses: nothing to correct
    with pytest.raises(ValueError, match="lag"):
        RotationRefiner(K_SYN, max_gap=3, lag=2)


def test_clean_map_presets_load_with_their_filters():
    """The two clean-map build presets are valid build configs with the fields their comments promise."""
    from mapkit.core.config import load_config
    from mapkit.mapping.build import BuildConfig

    root = Path(__file__).resolve().parents[1] / "configs" / "build"
    clean = load_config(BuildConfig, root / "clean-maps.yaml").semidense
    ins = load_config(BuildConfig, root / "clean-maps-ins-poses.yaml").semidense
    for c in (clean, ins):
        assert c.min_consistent_views == 1 and c.free_space_window_keyframes == 25
    assert not clean.refine_rotations and ins.refine_rotations
    assert ins.refine_lag_frames >= ins.refine_max_gap_frames
