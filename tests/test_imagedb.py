"""The image database round-trips through COLMAP's format and carries exact georeferencing."""

import numpy as np
import pycolmap
import pytest

from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import invert_pose, make_pose, yaw_rotation
from mapkit.core.types import CameraInfo
from mapkit.mapping.imagedb import ImageDbConfig, ImageDbWriter, read_images_csv, scaled_info, select_by_spacing

K = np.array([[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]])
# camera optical frame (x right, y down, z forward) looking along the map's +x
WORLD_FROM_OPTICAL = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)


def _poses(n=5):
    return [make_pose(yaw_rotation(0.1 * i) @ WORLD_FROM_OPTICAL, [2.0 * i, 0.5 * i, 1.5]) for i in range(n)]


def test_colmap_and_csv_round_trip(tmp_path, rng):
    info = CameraInfo("cam", 640, 480, K)
    w = ImageDbWriter(tmp_path / "db", ImageDbConfig(image_format="png"), {"cam": info})
    poses = _poses()
    imgs = [rng.integers(0, 255, (480, 640), dtype=np.uint8) for _ in poses]
    for i, (T, img) in enumerate(zip(poses, imgs, strict=True)):
        w.add(1_000 + i, "cam", img, T)
    # a point 10 m ahead of the first camera, seen by images 1 and 2
    p = np.array([[10.0, 0.0, 1.5]])
    frame = LocalFrame(49.0, 8.4, 100.0)
    w.close(frame, p, (np.array([0, 2]), np.array([1, 2])))
    rec = pycolmap.Reconstruction(str(tmp_path / "db" / "colmap"))
    assert rec.num_images() == 5 and rec.num_points3D() == 1
    for im in rec.images.values():
        cam_from_world = im.cam_from_world().matrix()
        np.testing.assert_allclose(cam_from_world, invert_pose(poses[im.image_id - 1])[:3, :], atol=1e-9)
    (pt,) = rec.points3D.values()
    assert sorted(e.image_id for e in pt.track.elements) == [1, 2]
    # the keypoint of image 1 is the projection of the point: the principal point (it is dead ahead), in COLMAP's
    # pixel convention (the image's corner at 0, 0): the centre of a 640 x 480 image is (320, 240) there, as the
    # camera says
    kp = rec.image(1).points2D[0].xy
    np.testing.assert_allclose(kp, [320.0, 240.0], atol=1e-6)
    np.testing.assert_allclose(rec.cameras[1].params, [400.0, 400.0, 320.0, 240.0])
    table = read_images_csv(tmp_path / "db" / "images.csv")
    np.testing.assert_array_equal(table["stamp_ns"], 1_000 + np.arange(5))
    lat, lon, alt = frame.enu_to_geodetic(np.array([T[:3, 3] for T in poses]))
    np.testing.assert_allclose(table["lat_deg"], lat, atol=1e-9)
    np.testing.assert_allclose(table["lon_deg"], lon, atol=1e-9)
    assert set(table["utm_epsg"].tolist()) == {32632}
    import cv2

    back = cv2.imread(str(tmp_path / "db" / table["image"][3]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back, imgs[3])  # png: stored exactly


def test_keypoints_of_a_distorted_camera_are_where_opencv_projects_them(tmp_path, rng):
    """With lens distortion the COLMAP model's camera carries it (OPENCV) and each track's keypoint is the point's
    projection as cv2.projectPoints gives it, moved into COLMAP's pixel convention (half a pixel)."""
    import cv2

    D = np.array([-0.28, 0.09, 0.001, -0.0005])
    info = CameraInfo("cam", 640, 480, K, "plumb_bob", D)
    w = ImageDbWriter(tmp_path / "db", ImageDbConfig(image_format="png"), {"cam": info})
    poses = _poses(2)
    for i, T in enumerate(poses):
        w.add(1_000 + i, "cam", rng.integers(0, 255, (480, 640), dtype=np.uint8), T)
    # points off the optical axis of the first camera (its optical z is the map's +x), where distortion moves them
    p = np.array([[10.0, 3.0, 0.0], [8.0, -2.5, 3.5], [12.0, 1.0, 4.0]])
    w.close(None, p, (np.array([0, 1, 2, 3]), np.array([1, 1, 1])))
    rec = pycolmap.Reconstruction(str(tmp_path / "db" / "colmap"))
    assert rec.cameras[1].model.name == "OPENCV"
    cam_from_world = invert_pose(poses[0])
    expected, _ = cv2.projectPoints(p, cv2.Rodrigues(cam_from_world[:3, :3])[0], cam_from_world[:3, 3], K, D)
    image = rec.image(1)
    kp = np.array([image.points2D[i].xy for i in range(3)])
    np.testing.assert_allclose(kp, expected.reshape(-1, 2) + 0.5, atol=1e-6)
    pinhole, _ = cv2.projectPoints(p, cv2.Rodrigues(cam_from_world[:3, :3])[0], cam_from_world[:3, 3], K, None)
    assert np.abs(kp - (pinhole.reshape(-1, 2) + 0.5)).max() > 5.0  # the distortion matters here


def test_downscaled_intrinsics_keep_pixel_centres():
    info = scaled_info(CameraInfo("cam", 640, 480, K), 2)
    assert (info.width, info.height) == (320, 240)
    # the image centre stays the image centre
    assert info.cx == pytest.approx(159.5) and info.cy == pytest.approx(119.5) and info.fx == pytest.approx(200.0)


def test_select_by_spacing():
    x = np.array([[0.0, 0, 0], [0.2, 0, 0], [0.6, 0, 0], [0.7, 0, 0], [1.3, 0, 0]])
    assert select_by_spacing(x, 0.5).tolist() == [0, 2, 4]
