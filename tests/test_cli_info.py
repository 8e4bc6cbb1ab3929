"""The command line: version, info on written logs and the real clip, one-line errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from mapkit import __version__
from mapkit.cli import main
from mapkit.core.geodesy import LocalFrame
from mapkit.core.types import CameraFrame, GpsFix, LidarScan
from mapkit.io.info import summarize
from mapkit.io.mcap_log import McapWriter

T0 = 1_700_000_000_000_000_000


def _drive(path, n=21, gps_every=2):
    """A 10 Hz drive with GPS at 5 Hz moving 1 m per fix due east."""
    frame = LocalFrame(49.0, 8.4, 100.0)
    with McapWriter(path) as w:
        for i in range(n):
            t = T0 + i * 100_000_000
            w.write("/cam/image", CameraFrame(t, "cam", np.full((4, 4), i, np.uint8)))
            w.write("/lidar/points", LidarScan(t, "lidar", np.ones((10, 3), np.float32)))
            if i % gps_every == 0:
                lat, lon, alt = frame.enu_to_geodetic(np.array([i / gps_every * 1.0, 0.0, 0.0]))
                w.write("/gps/fix", GpsFix(t, float(lat), float(lon), float(alt), covariance_enu_m2=np.eye(3) * 9))
    return path


def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"mapkit {__version__}"


def test_info_summary_of_a_written_log(tmp_path, capsys):
    path = _drive(tmp_path / "d.mcap")
    s = summarize(path)
    streams = {r["topic"]: r for r in s["streams"]}
    assert s["messages_read"] == 21 + 21 + 11
    assert streams["/cam/image"]["count"] == 21 and streams["/cam/image"]["rate_hz"] == pytest.approx(10.0)
    assert streams["/gps/fix"]["rate_hz"] == pytest.approx(5.0)
    assert streams["/lidar/points"]["duration_s"] == pytest.approx(2.0)
    gps = s["gps"]["/gps/fix"]
    assert gps["distance_m"] == pytest.approx(10.0, abs=0.01)
    assert gps["median_horizontal_sigma_m"] == pytest.approx(3.0)
    assert gps["fix_fraction"] == 1.0
    assert main(["info", str(path), "--json", str(tmp_path / "i.json")]) == 0
    out = capsys.readouterr().out
    assert "/gps/fix" in out and "10.0 m covered" in out
    assert json.loads((tmp_path / "i.json").read_text())["messages_read"] == 53


def test_info_on_truncated_log_reports_damage_and_succeeds_if_something_remains(tmp_path, capsys):
    path = _drive(tmp_path / "d.mcap", n=200)
    data = path.read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    assert main(["info", str(tmp_path / "cut.mcap")]) == 0
    captured = capsys.readouterr()
    assert "log damaged" in captured.out


def test_info_with_nothing_usable_exits_non_zero(tmp_path, capsys):
    path = _drive(tmp_path / "d.mcap")
    (tmp_path / "stub.mcap").write_bytes(path.read_bytes()[:40])
    assert main(["info", str(tmp_path / "stub.mcap")]) == 2
    assert "no usable message" in capsys.readouterr().err


def test_user_errors_are_one_line_without_traceback(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "mapkit.cli", "info", str(tmp_path / "missing.mcap")], capture_output=True, text=True
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "missing.mcap" in proc.stderr and "Traceback" not in proc.stderr


def test_index_export_without_indexes_is_one_line(tmp_path, capsys):
    assert main(["index", "export", str(tmp_path), "--out", str(tmp_path / "bundle")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no finished index" in err
    assert not (tmp_path / "bundle").exists()


def test_align_on_a_workspace_without_sessions_is_one_line(tmp_path, capsys):
    assert main(["align", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "origin.json" in err


@pytest.mark.realdata
def test_info_on_the_real_kitti_clip(kitti_clip):
    s = summarize(kitti_clip)
    images = [r for r in s["streams"] if r["kind"] == "image"]
    assert images and images[0]["count"] == 51
    assert images[0]["rate_hz"] == pytest.approx(10.0, rel=0.05)


def test_unknown_executor_is_one_line_and_exit_2(tmp_path, capsys):
    assert main(["--executor", "bogus", "info", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--executor" in err[0] and "bogus" in err[0]


def test_executor_config_prints_its_defaults(capsys):
    assert main(["config", "defaults", "executor"]) == 0
    out = capsys.readouterr().out
    assert "kind: local" in out and "workers: null" in out
