"""Generic image folder + frame table reader: layouts written with known values and read back."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapkit.core.errors import InputError
from mapkit.core.types import StreamKind
from mapkit.io import guess_format, open_log
from mapkit.io.folder import FolderLog, seconds_to_ns

# seconds with nanosecond digits that a float64 cannot hold
STAMPS_TEXT = ["1700000000.123456789", "1700000000.223456791", "1700000000.323456793"]
STAMPS_NS = [1700000000123456789, 1700000000223456791, 1700000000323456793]


def _records(log, topic: str) -> list:
    return [m.record for m in log.messages(topics=[topic])]


def _image(i: int) -> np.ndarray:
    return ((np.arange(5 * 7 * 3).reshape(5, 7, 3) * 7 + 40 * i) % 256).astype(np.uint8)


def make_folder(
    root: Path, header: list[str], rows: list[list], *, images_subdir: bool = True, csv_name: str = "frames.csv"
) -> Path:
    image_dir = root / "images" if images_subdir else root
    image_dir.mkdir(parents=True, exist_ok=True)
    for i in range(3):
        cv2.imwrite(str(image_dir / f"im{i}.png"), _image(i))
    (root / csv_name).write_text(",".join(header) + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    return root


def test_premise_floats_lose_these_nanoseconds():
    assert round(float(STAMPS_TEXT[1]) * 1e9) != STAMPS_NS[1]
    assert [seconds_to_ns(s) for s in STAMPS_TEXT] == STAMPS_NS


def test_images_gps_and_poses_read_back(tmp_path):
    quats = Rotation.from_rotvec([[0.1, 0.2, 0.3], [0.0, 0.0, 1.0], [-0.5, 0.2, 0.0]]).as_quat()[:, [3, 0, 1, 2]]
    gps = [[48.1, 11.5, 520.0, 2.5], ["", "", "", ""], [48.102, 11.496, 522.0, 2.5]]  # the second row has no fix
    rows = [[STAMPS_TEXT[i], f"im{i}.png", *gps[i], 10.0 * i, -1.0, 0.5, *quats[i]] for i in range(3)]
    header = ["timestamp", "image", "lat", "lon", "alt", "gps_sigma", "x", "y", "z", "qw", "qx", "qy", "qz"]
    log = FolderLog(make_folder(tmp_path, header, rows))

    frames = _records(log, "/folder/camera/image")
    assert [f.stamp_ns for f in frames] == STAMPS_NS
    assert frames[2].encoding == "bgr8" and not frames[2].is_loaded
    for i, f in enumerate(frames):
        np.testing.assert_array_equal(f.image, _image(i))

    fixes = list(log.records(StreamKind.GPS))
    assert [f.stamp_ns for f in fixes] == [STAMPS_NS[0], STAMPS_NS[2]]
    assert (fixes[1].lat_deg, fixes[1].lon_deg, fixes[1].alt_m) == (48.102, 11.496, 522.0)
    np.testing.assert_allclose(fixes[1].covariance_enu_m2, np.eye(3) * 2.5**2)

    poses = list(log.records(StreamKind.POSE))
    assert [p.stamp_ns for p in poses] == STAMPS_NS
    assert (poses[1].parent_frame, poses[1].child_frame) == ("world", "camera")
    np.testing.assert_allclose(poses[2].parent_from_child[:3, 3], [20.0, -1.0, 0.5])
    # the rotation about z by 1 rad maps x to (cos 1, sin 1, 0)
    np.testing.assert_allclose(poses[1].parent_from_child[:3, 0], [np.cos(1.0), np.sin(1.0), 0.0], atol=1e-12)
    assert not log.topics_of(StreamKind.CAMERA_INFO)


@pytest.mark.parametrize(
    "column, values, scale",
    [
        ("timestamp_ns", STAMPS_NS, 1),
        ("timestamp_us", [1_700_000_000_123_456, 1_700_000_000_223_456, 1_700_000_000_323_456], 1000),
    ],
)
def test_integer_time_columns(tmp_path, column, values, scale):
    log = FolderLog(make_folder(tmp_path, [column, "image"], [[v, f"im{i}.png"] for i, v in enumerate(values)]))
    assert [f.stamp_ns for f in log.records(StreamKind.IMAGE)] == [v * scale for v in values]


def test_intrinsics_from_columns(tmp_path):
    rows = [[s, f"im{i}.png", 500.0, 501.0, 3.5, 2.5] for i, s in enumerate(STAMPS_TEXT)]
    log = FolderLog(make_folder(tmp_path, ["timestamp", "image", "fx", "fy", "cx", "cy"], rows))
    info = log.camera_infos()["camera"]
    assert (info.width, info.height) == (7, 5)
    np.testing.assert_allclose(info.K, [[500.0, 0, 3.5], [0, 501.0, 2.5], [0, 0, 1]])
    assert [i.stamp_ns for i in _records(log, "/folder/camera/camera_info")] == STAMPS_NS


def test_intrinsics_from_json_and_from_ros_yaml(tmp_path):
    rows = [[s, f"im{i}.png"] for i, s in enumerate(STAMPS_TEXT)]
    a = make_folder(tmp_path / "a", ["timestamp", "image"], rows)
    (a / "intrinsics.json").write_text(
        json.dumps({"fx": 400.0, "fy": 410.0, "cx": 3.0, "cy": 2.0, "D": [0.1, -0.01, 0, 0, 0]})
    )
    info = FolderLog(a).camera_infos()["camera"]
    assert (info.fx, info.fy, info.cx, info.cy) == (400.0, 410.0, 3.0, 2.0)
    np.testing.assert_allclose(info.D, [0.1, -0.01, 0, 0, 0])

    b = make_folder(tmp_path / "b", ["timestamp", "image"], rows)
    (b / "camera.yaml").write_text(
        "image_width: 7\nimage_height: 5\ncamera_name: front\n"
        "camera_matrix: {rows: 3, cols: 3, data: [300.0, 0.0, 3.1, 0.0, 301.0, 2.1, 0.0, 0.0, 1.0]}\n"
        "distortion_model: plumb_bob\ndistortion_coefficients: {rows: 1, cols: 5, data: [0.2, 0.0, 0.0, 0.0, 0.0]}\n"
    )
    info = FolderLog(b).camera_infos()["camera"]
    assert (info.fx, info.fy, info.cx, info.cy) == (300.0, 301.0, 3.1, 2.1)

    (b / "camera.yaml").write_text((b / "camera.yaml").read_text().replace("image_width: 7", "image_width: 640"))
    with pytest.raises(InputError, match="640x5"):
        FolderLog(b)


def test_images_in_the_folder_itself_and_any_single_csv(tmp_path):
    root = make_folder(
        tmp_path,
        ["timestamp", "image"],
        [[s, f"im{i}.png"] for i, s in enumerate(STAMPS_TEXT)],
        images_subdir=False,
        csv_name="log.csv",
    )
    assert guess_format(root) == "folder"
    log = open_log(root)
    assert isinstance(log, FolderLog)
    np.testing.assert_array_equal(next(log.records(StreamKind.IMAGE)).image, _image(0))


def test_malformed_row_names_file_line_and_column(tmp_path):
    rows = [[s, f"im{i}.png", 48.0, 11.0] for i, s in enumerate(STAMPS_TEXT)]
    rows[1][3] = "11,5"  # a decimal comma splits the row into five values
    root = make_folder(tmp_path, ["timestamp", "image", "lat", "lon"], rows)
    with pytest.raises(InputError) as exc:
        list(FolderLog(root).messages())
    assert exc.value.path == root / "frames.csv"
    assert "line 3" in str(exc.value) and "lon" in str(exc.value)

    rows[1][3] = "11.5E"
    root = make_folder(tmp_path / "b", ["timestamp", "image", "lat", "lon"], rows)
    with pytest.raises(InputError) as exc:
        list(FolderLog(root).messages())
    assert "line 3" in str(exc.value) and "column lon" in str(exc.value) and "11.5E" in str(exc.value)


def test_bad_time_cell_names_line_and_column(tmp_path):
    rows = [[s, f"im{i}.png"] for i, s in enumerate(STAMPS_TEXT)]
    rows[2][0] = "17000000003.2.3"
    with pytest.raises(InputError) as exc:
        list(FolderLog(make_folder(tmp_path, ["timestamp", "image"], rows)).messages())
    assert "line 4" in str(exc.value) and "timestamp" in str(exc.value)


def test_missing_image_names_table_and_image(tmp_path):
    rows = [[s, f"im{i}.png"] for i, s in enumerate(STAMPS_TEXT)]
    rows[2][1] = "gone.png"
    root = make_folder(tmp_path, ["timestamp", "image"], rows)
    log = FolderLog(root)
    with pytest.raises(InputError) as exc:
        list(log.records(StreamKind.IMAGE))
    assert exc.value.path == root / "frames.csv"
    assert "line 4" in str(exc.value) and str(root / "images" / "gone.png") in str(exc.value)


def test_incomplete_column_groups_and_bad_quaternions_are_errors(tmp_path):
    rows = [[s, f"im{i}.png", 1.0, 2.0, 3.0] for i, s in enumerate(STAMPS_TEXT)]
    with pytest.raises(InputError, match="qw"):
        FolderLog(make_folder(tmp_path / "a", ["timestamp", "image", "x", "y", "z"], rows))
    with pytest.raises(InputError, match="lon"):
        FolderLog(make_folder(tmp_path / "b", ["timestamp", "image", "lat", "x", "y"], rows))
    rows = [[s, f"im{i}.png", 0, 0, 0, 1.0, 0.5, 0, 0] for i, s in enumerate(STAMPS_TEXT)]
    log = FolderLog(make_folder(tmp_path / "c", ["timestamp", "image", "x", "y", "z", "qw", "qx", "qy", "qz"], rows))
    with pytest.raises(InputError, match="norm"):
        list(log.records(StreamKind.POSE))


def test_an_image_of_another_size_is_an_error_when_decoded(tmp_path):
    root = make_folder(tmp_path, ["timestamp", "image"], [[s, f"im{i}.png"] for i, s in enumerate(STAMPS_TEXT)])
    cv2.imwrite(str(root / "images" / "im2.png"), np.zeros((9, 9), np.uint8))
    frames = list(FolderLog(root).records(StreamKind.IMAGE))
    assert frames[1].image.shape == (5, 7, 3)
    with pytest.raises(InputError, match="9x9 mono8"):
        _ = frames[2].image  # decoding raises


def test_a_folder_without_a_frame_table_is_not_detected(tmp_path):
    root = make_folder(tmp_path, ["name", "value"], [["a", 1]], csv_name="other.csv")
    assert not FolderLog.detect(root)
    with pytest.raises(InputError, match="not recognised"):
        guess_format(root)
