"""The MCVL benchmark's path: a camera-only synthetic town and a map-less image database whose
poses are the drive's own (georeferenced) pose stream, as the paper's database is (Sec. IV-B)."""

import json
from pathlib import Path

import numpy as np
import pytest

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.types import StreamKind
from mapkit.io.mcap_log import McapLog
from mapkit.io.trajectory import read_tum
from mapkit.mapping.build import build
from mapkit.mapping.imagedb import images_world_from_cam, read_images_csv
from mapkit.synth import session_log, synthesize
from mapkit.synth.config import load_config

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
ONE_DRIVE = {"sessions": [{"name": "drive", "role": "train", "weather": "clear", "length_m": 40.0, "speed_mps": 8.0}]}


@pytest.fixture(scope="module")
def town(tmp_path_factory) -> Path:
    return synthesize(
        preset="tiny",
        out=tmp_path_factory.mktemp("cam-only") / "town",
        overrides=ONE_DRIVE,
        config=CONFIGS / "synth" / "benchmark-camera.yaml",
        progress=False,
    )


def test_benchmark_camera_override_turns_off_only_the_lidar():
    base, cam = load_config("benchmark"), load_config("benchmark", CONFIGS / "synth" / "benchmark-camera.yaml")
    assert base.lidar.enabled and not cam.lidar.enabled
    assert cam.model_dump(exclude={"lidar"}) == base.model_dump(exclude={"lidar"})


def test_camera_only_log_has_no_lidar_stream_nor_extrinsic(town):
    log = McapLog(session_log(town, "drive"))
    kinds = {s.kind for s in log.streams()}
    assert StreamKind.LIDAR not in kinds and {StreamKind.IMAGE, StreamKind.GPS, StreamKind.POSE} <= kinds
    assert "lidar" not in {t.child_frame for t in log.transforms()}


def test_given_georeferencing_puts_database_images_at_their_true_poses(town, tmp_path):
    ws = build(
        [session_log(town, "drive")], tmp_path / "ws", config=CONFIGS / "build" / "mcvl-database.yaml", progress=False
    )
    session = ws / "sessions" / "drive"
    assert not (session / "map").exists(), "map: false must not build the semi-dense map"
    table = read_images_csv(session / "imagedb" / "images.csv")
    cams = images_world_from_cam(table)
    stamps_true, cams_true = read_tum(town / "sessions" / "drive.camera.tum")
    assert len(table["stamp_ns"]) > 10
    at = np.searchsorted(stamps_true, table["stamp_ns"])
    assert np.array_equal(stamps_true[at], table["stamp_ns"])
    # the town is ENU at the preset's origin, which the config names: positions agree to the CSV's 0.1 mm
    np.testing.assert_allclose(cams[:, :3, 3], cams_true[at, :3, 3], atol=2e-4)
    np.testing.assert_allclose(cams[:, :3, :3], cams_true[at, :3, :3], atol=1e-6)
    origin = LocalFrame.from_dict(json.loads((ws / "origin.json").read_text()))
    assert (origin.lat0_deg, origin.lon0_deg, origin.alt0_m) == (51.752, -1.2577, 60.0)


def test_given_georeferencing_without_origin_names_the_field(town, tmp_path):
    cfg = tmp_path / "no-origin.yaml"
    cfg.write_text(
        "topics: {poses: /ground_truth/odom}\ntrajectory: {source: poses}\ngeoref: {mode: given}\nmap: false\n"
    )
    with pytest.raises(InputError, match=r"georef\.origin"):
        build([session_log(town, "drive")], tmp_path / "ws", config=cfg, progress=False)
