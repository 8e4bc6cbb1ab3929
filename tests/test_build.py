"""`mapkit build` on a cut of the real KITTI clip: outputs, formats, and resuming after a crash."""

import json
import shutil

import numpy as np
import open3d as o3d
import pycolmap
import pytest

from mapkit.mapping.build import build
from mapkit.cli import main
from mapkit.core.errors import InputError
from mapkit.mapping.imagedb import read_images_csv
from mapkit.core.runio import is_done

N = 12


@pytest.fixture(scope="module")
def clip12(kitti_clip, tmp_path_factory):
    """The first 12 frames of the clip, with its calibration and poses."""
    d = tmp_path_factory.mktemp("kitti12") / "clip12"
    (d / "image_l").mkdir(parents=True)
    for i in range(N):
        shutil.copy(kitti_clip / "image_l" / f"{i:06d}.png", d / "image_l")
    shutil.copy(kitti_clip / "calib.txt", d)
    lines = (kitti_clip / "poses.txt").read_text().splitlines()[:N]
    (d / "poses.txt").write_text("\n".join(lines) + "\n")
    (d / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(N)))
    return d


def test_build_writes_every_stage_in_the_fields_formats(clip12, tmp_path):
    ws = build([clip12], tmp_path / "ws", progress=False)
    s = ws / "sessions" / "clip12"
    for stage in ("trajectory", "georef", "map", "imagedb"):
        assert is_done(s / stage), stage
    pcd = o3d.io.read_point_cloud(str(s / "map" / "points.ply"))
    assert len(pcd.points) > 5000
    rec = pycolmap.Reconstruction(str(s / "imagedb" / "colmap"))
    assert rec.num_images() >= 8  # frames at least 0.5 m apart
    assert rec.num_points3D() > 1000
    # every COLMAP point reprojects onto its track's keypoints
    pid, pt = next(iter(rec.points3D.items()))
    for el in pt.track.elements:
        im = rec.image(el.image_id)
        uv = im.project_point(pt.xyz)
        np.testing.assert_allclose(uv, im.points2D[el.point2D_idx].xy, atol=1e-6)
    table = read_images_csv(s / "imagedb" / "images.csv")
    assert len(table["stamp_ns"]) == rec.num_images() and np.all(np.isnan(table["lat_deg"]))  # no GPS: not georeferenced
    ga = json.loads((s / "georef" / "gps_alignment.json").read_text())
    assert ga["georeferenced"] is False
    m = json.loads((ws / "metrics.json").read_text())["sessions"]["clip12"]["stages"]
    assert m["trajectory"]["source"] == "poses:/kitti/ground_truth" and m["semidense"]["points"] == len(pcd.points)
    assert (s / "map" / "top_view.png").stat().st_size > 10_000
    assert (s / "trajectory" / "poses_tum.txt").is_file() and (s / "trajectory" / "poses_kitti.txt").is_file()


def test_interrupted_build_resumes_without_redoing_finished_stages(clip12, tmp_path, monkeypatch):
    ws = tmp_path / "ws"

    def crash(self, *a, **k):
        raise RuntimeError("power cut while writing the image database")

    monkeypatch.setattr("mapkit.mapping.imagedb.ImageDbWriter.close", crash)
    with pytest.raises(RuntimeError):
        build([clip12], ws, progress=False)
    s = ws / "sessions" / "clip12"
    assert is_done(s / "map") and not is_done(s / "imagedb")  # the half-written stage is not finished
    ply_mtime = (s / "map" / "points.ply").stat().st_mtime_ns
    monkeypatch.undo()
    build([clip12], ws, progress=False)
    assert is_done(s / "imagedb")
    assert (s / "map" / "points.ply").stat().st_mtime_ns == ply_mtime  # the finished map was not redone


def test_changed_config_redoes_only_what_depends_on_it(clip12, tmp_path):
    ws = tmp_path / "ws"
    build([clip12], ws, progress=False)
    s = ws / "sessions" / "clip12"
    traj_mtime = (s / "trajectory" / "trajectory.npz").stat().st_mtime_ns
    n_before = len(read_images_csv(s / "imagedb" / "images.csv")["stamp_ns"])
    cfg = tmp_path / "c.yaml"
    cfg.write_text("imagedb:\n  min_spacing_m: 2.0\n")
    build([clip12], ws, config=cfg, progress=False)
    assert (s / "trajectory" / "trajectory.npz").stat().st_mtime_ns == traj_mtime
    assert len(read_images_csv(s / "imagedb" / "images.csv")["stamp_ns"]) < n_before


def test_build_cli_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "c.yaml"
    bad.write_text("imagedb:\n  min_spacing: 2\n")
    assert main(["build", str(tmp_path), "--out", str(tmp_path / "ws"), "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "imagedb.min_spacing" in err and "Traceback" not in err


def test_missing_intrinsics_is_one_clear_error_and_keeps_finished_stages(tmp_path, rng, capsys):
    """A generic folder with poses but no intrinsics: the trajectory is built, the map refuses."""
    import cv2

    d = tmp_path / "drive"
    (d / "images").mkdir(parents=True)
    rows = ["timestamp_ns,image,x,y,z,qw,qx,qy,qz"]
    for i in range(6):
        cv2.imwrite(str(d / "images" / f"{i}.png"), rng.integers(0, 255, (48, 64), dtype=np.uint8))
        rows.append(f"{1000 + i * 100_000_000},{i}.png,0,0,{i * 0.5},1,0,0,0")
    (d / "frames.csv").write_text("\n".join(rows) + "\n")
    assert main(["build", str(d), "--out", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err
    assert "no camera intrinsics" in err and str(d) in err and "Traceback" not in err
    s = tmp_path / "ws" / "sessions" / "drive"
    assert is_done(s / "trajectory") and not is_done(s / "map")


def test_two_logs_with_one_session_name_are_refused_before_anything_is_written(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    logs = [tmp_path / "a" / "drive.mcap", tmp_path / "b" / "drive.mcap"]
    with pytest.raises(InputError, match="same session name 'drive'"):
        build(logs, tmp_path / "ws", progress=False)
    assert not (tmp_path / "ws").exists()
