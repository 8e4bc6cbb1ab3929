"""Camera-only builds on real images: the KITTI clip as a walk of geotagged photos (JPEGs with EXIF
GPS, time and 35 mm focal length, as a phone writes them) and as a generic folder log (images, a
frame table with GPS, intrinsics), its trajectory from pycolmap, georeferenced by GPS alone.

GPS is the clip's true camera positions placed in ENU (heading 30 deg east of north, camera y down
= ENU down, the camera 1.65 m above the road as on KITTI's car) plus 2 m of noise per axis, so the
truth of every pose is known in the workspace frame."""

from __future__ import annotations

import json
import re
import warnings

import cv2
import numpy as np
import pytest
from test_readers_photos import write_geotagged_folder  # JPEGs with EXIF tags, as a phone writes them

from mapkit.core.errors import InputWarning, MapkitError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import rotation_angle_rad, sim3_scale, transform_points, umeyama
from mapkit.core.runio import is_done
from mapkit.core.workspace import Workspace
from mapkit.mapping.build import build, format_build_summary
from mapkit.mapping.imagedb import read_images_csv
from mapkit.mapping.semidense import SemiDenseMap
from mapkit.mapping.trajectory import Trajectory

HEADING = np.radians(30.0)
# enu_from_cam0: camera z (forward) to the heading, x (right) to its right, y (down) to ENU down
ENU_FROM_CAM0 = np.array([[np.cos(HEADING), 0, np.sin(HEADING)], [-np.sin(HEADING), 0, np.cos(HEADING)], [0, -1, 0]])
CAMERA_HEIGHT_M = 1.65  # KITTI's cameras above the road
ORIGIN = LocalFrame(49.0110, 8.4170, 115.0)  # Karlsruhe, where the clip was recorded
T0_S = 1317384000  # 2011-09-30
CONFIG = """\
trajectory:
  source: camera
  camera: {max_threads: 2, max_image_size: 640, sequential_overlap: 5}
semidense: {keyframe_spacing_m: 4.0}
imagedb: {min_spacing_m: 2.0}
"""


def _truth(kitti_clip):
    """(true camera positions (N, 3) in ORIGIN's ENU, true enu_from_camera rotations (N, 3, 3))."""
    poses = np.loadtxt(kitti_clip / "poses.txt").reshape(-1, 3, 4)
    return poses[:, :, 3] @ ENU_FROM_CAM0.T + [0, 0, CAMERA_HEIGHT_M], ENU_FROM_CAM0 @ poses[:, :, :3]


def _folder_log(kitti_clip, folder, n: int):
    """The first ``n`` frames as a generic folder log: images/ (links to the clip's PNGs), frames.csv
    (image, timestamp, lat, lon, alt, gps_sigma) and intrinsics.json."""
    true_enu, _ = _truth(kitti_clip)
    gps = true_enu[:n] + np.random.default_rng(0).normal(scale=2.0, size=(n, 3))
    lat, lon, alt = ORIGIN.enu_to_geodetic(gps)
    (folder / "images").mkdir(parents=True)
    rows = ["image,timestamp,lat,lon,alt,gps_sigma"]
    for i in range(n):
        (folder / "images" / f"{i:06d}.png").symlink_to(kitti_clip / "image_l" / f"{i:06d}.png")
        rows.append(f"{i:06d}.png,{T0_S + 0.1 * i:.1f},{lat[i]:.9f},{lon[i]:.9f},{alt[i]:.3f},2.0")
    (folder / "frames.csv").write_text("\n".join(rows) + "\n")
    (folder / "intrinsics.json").write_text(
        json.dumps({"fx": 707.0912, "fy": 707.0912, "cx": 601.8873, "cy": 183.1104})
    )
    return folder


def _photo_walk(kitti_clip, folder, n: int):
    """The first ``n`` frames as a folder of geotagged JPEGs: GPS (as in ``_folder_log``, no accuracy
    tag), UTC time, and the 35 mm equivalent focal length in whole millimetres (24 mm: fx 710.3 px
    where the calibration says 707.1, the rounding a phone's EXIF carries)."""
    true_enu, _ = _truth(kitti_clip)
    gps = true_enu[:n] + np.random.default_rng(0).normal(scale=2.0, size=(n, 3))
    images = [cv2.imread(str(kitti_clip / "image_l" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) for i in range(n)]
    h, w = images[0].shape
    f35 = round(707.0912 * np.hypot(36, 24) / np.hypot(w, h))
    stamps = [(T0_S * 10 + i) * 100_000_000 for i in range(n)]
    folder.mkdir(parents=True)
    return write_geotagged_folder(folder, images, np.c_[ORIGIN.enu_to_geodetic(gps)], stamps, f35)


def _frame_index(stamps_ns: np.ndarray) -> np.ndarray:
    return np.round((stamps_ns * 1e-9 - T0_S) / 0.1).astype(int)


@pytest.fixture(scope="module")
def walk(kitti_clip, tmp_path_factory):
    """The whole clip (51 frames, about 60 m straight) as a geotagged photo walk, built camera-only."""
    tmp = tmp_path_factory.mktemp("camera_only")
    log = _photo_walk(kitti_clip, tmp / "kitti_walk", 51)
    (tmp / "build.yaml").write_text(CONFIG)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ws = build([log], tmp / "ws", config=tmp / "build.yaml", progress=False)
    assert not [w for w in caught if "georeferenced" in str(w.message) or "skipped" in str(w.message)]
    return Workspace(ws), kitti_clip


def test_geotagged_photo_walk_is_georeferenced_within_gps_noise(walk):
    ws, clip = walk
    s = ws.session("kitti_walk")
    ga = json.loads(s.gps_alignment.read_text())
    al = ga["alignment"]
    assert json.loads(ws.metrics.read_text())["sessions"]["kitti_walk"]["log"].endswith("kitti_walk")
    assert ga["georeferenced"] and al["mode"] == "sim3" and al["fixes_used"] >= 48
    # 3D residuals of 2 m-per-axis noise: RMSE sqrt(3)*2 = 3.5 m (measured 3.24 m)
    assert 2.5 < al["residual_rmse_m"] < 4.5
    assert al["extent_m"] == pytest.approx(60, abs=5)  # GPS metres, while the reconstruction spans ~12 units
    # a 60 m straight drive: GPS cannot fix the roll about it, the cameras' mean up does
    assert al["gravity"] == "up hint" and al["up_tilt_deg"] < 2.0
    true_enu, true_R = _truth(clip)
    truth = ws.frame().geodetic_to_enu(*ORIGIN.enu_to_geodetic(true_enu))  # into the workspace frame
    enu = Trajectory.load(s.georef_trajectory)
    idx = _frame_index(enu.stamps_ns)
    assert len(idx) >= 48  # pycolmap registered (almost) every frame
    p = enu.world_from_base[:, :3, 3]
    abs_rmse = np.sqrt(np.mean(np.sum((p - truth[idx]) ** 2, axis=1)))
    assert abs_rmse < 1.5  # measured 0.77 m: 51 fixes of 2 m noise, averaged
    fit = umeyama(p, truth[idx], with_scale=True)
    assert sim3_scale(fit) == pytest.approx(1.0, abs=0.03)  # measured 0.993
    ate = np.sqrt(np.mean(np.sum((transform_points(fit, p) - truth[idx]) ** 2, axis=1)))
    assert ate < 0.2  # measured 0.02 m: the reconstruction's own shape
    rot_err = np.degrees(rotation_angle_rad(enu.world_from_base[:, :3, :3] @ np.transpose(true_R[idx], (0, 2, 1))))
    assert np.max(rot_err) < 2.0  # measured 0.67 deg median, 0.89 max
    stages = json.loads(ws.metrics.read_text())["sessions"]["kitti_walk"]["stages"]
    assert stages["trajectory"]["units"].startswith("arbitrary") and "length_m" not in stages["trajectory"]
    assert stages["georef"]["units"] == "m" and stages["georef"]["length_m"] == pytest.approx(60, abs=3)


def test_camera_only_map_is_in_metres(walk):
    """The semi-dense map is made from the GPS-scaled poses: the road 4-10 m ahead of the cameras
    lies about KITTI's camera height below them (a little less, the cameras pitch down slightly)."""
    ws, _ = walk
    s = ws.session("kitti_walk")
    assert is_done(s.map) and is_done(s.imagedb)
    smap = SemiDenseMap.load(s.map)
    assert len(smap.points_world) > 10_000
    below = []
    for T in Trajectory.load(s.georef_trajectory).world_from_base:
        q = (smap.points_world - T[:3, 3]) @ T[:3, :3]  # map points in that camera's frame
        below.append(q[(np.abs(q[:, 0]) < 1.5) & (q[:, 2] > 4) & (q[:, 2] < 10) & (q[:, 1] > 0.5), 1])
    below = np.concatenate(below)
    assert len(below) > 1000 and np.median(below) == pytest.approx(CAMERA_HEIGHT_M, abs=0.25)  # measured 1.54 m
    assert json.loads((s.map / "metrics.json").read_text())["crs"] is not None
    assert json.loads((s.imagedb / "metrics.json").read_text())["pose_units"] == "m"
    assert np.isfinite(read_images_csv(s.images_csv)["lat_deg"]).all()


def test_unreferenced_camera_only_session_says_arbitrary_units_and_skips_the_map(kitti_clip, tmp_path):
    """12 frames, 13 m (14 m by the noisy GPS): too short for GPS to fix the scale. The session is
    built, not georeferenced, with every length in the reconstruction's units and saying so; the
    metre-based mapper does not run; the image database keeps every registered frame (a spacing in
    metres means nothing here)."""
    log = _folder_log(kitti_clip, tmp_path / "short", 12)
    (tmp_path / "build.yaml").write_text(CONFIG)
    with pytest.warns(InputWarning) as caught:
        ws = build([log], tmp_path / "ws", config=tmp_path / "build.yaml", progress=False)
    messages = [str(w.message) for w in caught]
    assert any(re.search(r"spans 1\d\.\d m \(GPS metres\)", m) and "NOT georeferenced" in m for m in messages), messages
    assert any("semidense skipped: the camera-only trajectory is not georeferenced" in m for m in messages), messages
    w = Workspace(ws)
    s = w.session("short")
    st = json.loads(w.metrics.read_text())["sessions"]["short"]["stages"]
    assert st["georef"]["georeferenced"] is False and "GPS metres" in st["georef"]["reason"]
    for stage in ("trajectory", "georef"):
        assert (
            st[stage]["units"].startswith("arbitrary units")
            and "length_m" not in st[stage]
            and st[stage]["length_sfm_units"] > 0
        )
    assert "not georeferenced" in st["semidense"]["skipped"] and not s.map.exists()
    assert (
        s.georef / "trajectory_top_view.png"
    ).stat().st_size > 10_000  # drawn in arbitrary units, levelled by the cameras' up
    db = json.loads((s.imagedb / "metrics.json").read_text())
    assert db["pose_units"].startswith("arbitrary units") and db["images"] == st["trajectory"]["poses"]
    assert np.isnan(read_images_csv(s.images_csv)["lat_deg"]).all()
    summary = format_build_summary(w)
    assert " au " in summary and "semidense skipped: the camera-only trajectory is not georeferenced" in summary
    assert "imagedb poses in arbitrary units" in summary
    # later stages: the index refuses poses in arbitrary units instead of mixing them with metre radii
    from mapkit.retrieval.index_vlad import build_vlad_index

    with (
        pytest.warns(
            InputWarning, match=r"\['short'\] left out of the index: their image poses are in arbitrary units"
        ),
        pytest.raises(MapkitError, match="no session with a metric image database"),
    ):
        build_vlad_index(w, progress=False)
