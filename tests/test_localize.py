"""The localizer chain on a real (tiny) VLAD bundle: retrieval gives z_t, the particle filter
follows it, driven by the query session's relative motion."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_index_vlad import PLACES, make_workspace, place_pose, small_config

from mapkit.core.config import load_config
from mapkit.core.errors import ConfigError
from mapkit.core.geometry import invert_pose, make_pose, rotation_angle_rad
from mapkit.localization.localize import LocalizeConfig, run_localizer
from mapkit.localization.mcl import FORWARD_CAMERA_ROTATION
from mapkit.retrieval.index_vlad import VladIndex, build_vlad_index, read_session_images


def test_filter_follows_retrieval_on_a_bundle(tmp_path):
    ws = make_workspace(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bundle = build_vlad_index(ws, config=small_config(), progress=False)
    index = VladIndex.load(bundle)
    imgs = read_session_images(ws, "test-c")
    truth = np.stack([place_pose(p) for p in range(PLACES)])
    # the query session's own motion between queries, as its odometry would give it
    odo = [None] + [invert_pose(imgs.world_from_cam[k - 1]) @ imgs.world_from_cam[k] for k in range(1, PLACES)]
    cfg = LocalizeConfig(top_k=4, odometry=True)
    r = run_localizer(index, list(imgs.image_paths), cfg, odo)
    ret_err = np.linalg.norm(r.retrieval_position - truth[:, :3, 3], axis=1)
    fil_err = np.linalg.norm(r.filter_position - truth[:, :3, 3], axis=1)
    assert np.median(ret_err) < 5.0  # the right place is retrieved
    assert np.median(fil_err) < 5.0 and np.all(np.isfinite(fil_err))
    R = r.filter_rotation
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-6) and np.allclose(np.linalg.det(R), 1.0)
    # the filter runs on base poses; what comes back is the camera's pose (optical z along the road)
    assert np.median(rotation_angle_deg(R, truth[:, :3, :3])) < 5.0
    # another mount (pitched 10 deg, 1.5 m ahead, 1.2 m up) changes the tracked base, not the camera poses returned
    pitched = make_pose(
        Rotation.from_euler("y", 10.0, degrees=True).as_matrix() @ FORWARD_CAMERA_ROTATION, [1.5, 0.0, 1.2]
    )
    r_p = run_localizer(
        index, list(imgs.image_paths), cfg.model_copy(update={"base_from_camera": tuple(map(tuple, pitched))}), odo
    )
    np.testing.assert_allclose(r_p.retrieval_position, r.retrieval_position)
    assert np.median(np.linalg.norm(r_p.filter_position - truth[:, :3, 3], axis=1)) < 5.0
    assert np.median(rotation_angle_deg(r_p.filter_rotation, truth[:, :3, :3])) < 5.0

    # beyond the paper: the multi-hypothesis preset on hits retrieved once and cached
    from mapkit.localization.localize import cached_query_all

    paths = list(imgs.image_paths)
    ids, dist, cached = cached_query_all(index, paths, 4, tmp_path / "cache", "test-c")
    assert not cached and ids.shape == (PLACES, 4)
    ids2, dist2, cached = cached_query_all(VladIndex.load(bundle), paths, 4, tmp_path / "cache", "test-c")
    assert cached
    np.testing.assert_array_equal(ids2, ids)
    mh = load_config(LocalizeConfig, PRESETS / "odometry-multihypothesis.yaml", {"top_k": 4})
    r_mh = run_localizer(index, paths, mh, odo, hits=(ids, dist))
    np.testing.assert_allclose(r_mh.retrieval_position, r.retrieval_position)  # same hits, same retrieval figure
    np.testing.assert_array_equal(r_mh.ids, ids)
    mh_err = np.linalg.norm(r_mh.filter_position - truth[:, :3, 3], axis=1)
    assert np.median(mh_err) < 5.0 and np.all(np.isfinite(mh_err))
    assert np.median(rotation_angle_deg(r_mh.filter_rotation, truth[:, :3, :3])) < 5.0


def rotation_angle_deg(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    return np.degrees(rotation_angle_rad(np.swapaxes(R_gt, -1, -2) @ R_est))


PRESETS = Path(__file__).resolve().parents[1] / "configs" / "localize"


def test_presets_load_and_paper_is_the_default():
    assert load_config(LocalizeConfig, PRESETS / "paper.yaml") == LocalizeConfig()
    odo = load_config(LocalizeConfig, PRESETS / "odometry.yaml")
    assert (
        odo.odometry
        and not odo.mcl.multi_hypothesis.enabled
        and odo.mcl == LocalizeConfig().mcl.model_copy(update={"odometry": odo.mcl.odometry})
    )
    mh = load_config(LocalizeConfig, PRESETS / "odometry-multihypothesis.yaml")
    assert mh.odometry and mh.mcl.multi_hypothesis.enabled and mh.mcl.estimate == "mode"
    assert mh.mcl.multi_hypothesis.reinject_below > 0 and mh.top_k == 20
    for name in ("paper", "odometry", "odometry-multihypothesis"):  # every value names its source
        lines = [
            ln
            for ln in (PRESETS / f"{name}.yaml").read_text().splitlines()
            if ":" in ln and not ln.lstrip().startswith("#")
        ]
        leaves = [ln for ln in lines if not ln.rstrip().endswith(":") and "#" not in ln.split(":", 1)[0]]
        assert all("#" in ln for ln in leaves), [ln for ln in leaves if "#" not in ln]
        # no preset pins the camera mount: the bundle's recorded mount, else a forward camera
        cfg = load_config(LocalizeConfig, PRESETS / f"{name}.yaml")
        assert cfg.base_from_camera is None
        np.testing.assert_array_equal(
            cfg.camera_mount().base_from_camera, make_pose(FORWARD_CAMERA_ROTATION, np.zeros(3))
        )


def test_camera_mount_must_be_rigid():
    with pytest.raises(ConfigError, match="base_from_camera"):
        load_config(
            LocalizeConfig, overrides={"base_from_camera": [[0, 0, 2, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]]}
        )
    with pytest.raises(ConfigError):
        load_config(LocalizeConfig, overrides={"base_from_camera": [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]})  # 3x3


class _CountingIndex:
    """Stands in for a VladIndex in the cache tests: a bundle folder with a manifest, a search
    that counts its calls, and camera positions for the recall diagnostics."""

    def __init__(self, folder, build_hash="abc"):
        self.path = folder
        self.manifest = {"build_hash": build_hash}
        (folder / "manifest.json").write_text(json.dumps({"build_hash": build_hash, "files": {}}))
        self.calls = 0
        self.world_from_cam = np.tile(np.eye(4), (30, 1, 1))
        self.world_from_cam[:, 0, 3] = 10.0 * np.arange(30)

    def _as_vector(self, image):
        self.calls += 1
        return np.full(4, float(Path(image).stat().st_size), np.float32)

    def encode_files(self, paths, progress=False, desc="", cache_dir=None):
        return np.stack([self._as_vector(p) for p in paths])

    def search(self, q, k):
        v = q[:, :1].astype(int)
        return np.arange(k, dtype=np.float32)[None] + v, (np.arange(k)[None] + v) % 30


def test_hits_cache_serves_only_the_same_bundle_session_top_k_and_images(tmp_path):
    from mapkit.localization.localize import cached_query_all

    (tmp_path / "bundle").mkdir()
    index = _CountingIndex(tmp_path / "bundle")
    images = []
    for i in range(5):
        p = tmp_path / f"im{i}.png"
        p.write_bytes(b"x" * (i + 1))
        images.append(p)
    cache = tmp_path / "cache"
    ids, dist, cached = cached_query_all(index, images, 3, cache, "s1")
    assert not cached and index.calls == 5 and ids.shape == (5, 3)
    np.testing.assert_array_equal(ids[:, 0], [1, 2, 3, 4, 5])
    ids2, dist2, cached = cached_query_all(index, images, 3, cache, "s1")
    assert cached and index.calls == 5  # nothing encoded again
    np.testing.assert_array_equal(ids2, ids)
    np.testing.assert_array_equal(dist2, dist)
    assert cached_query_all(index, images, 4, cache, "s1")[2] is False  # another top_k
    assert cached_query_all(index, images, 3, cache, "s2")[2] is False  # another session
    assert cached_query_all(index, images[:4], 3, cache, "s1")[2] is False  # other images
    images[0].write_bytes(b"yy")  # the same path, another image
    assert cached_query_all(index, images, 3, cache, "s1")[2] is False
    calls = index.calls
    # a bundle grown in place keeps its build hash; its manifest changes, and so does the key
    (tmp_path / "bundle" / "manifest.json").write_text('{"build_hash": "abc", "files": {"more": 1}}')
    assert cached_query_all(index, images, 3, cache, "s1")[2] is False and index.calls == calls + 5
    # another bundle at the same place with the same build hash but other files
    other = _CountingIndex(tmp_path / "bundle", build_hash="def")
    assert cached_query_all(other, images, 3, cache, "s1")[2] is False
    # without a cache folder, nothing is written
    assert cached_query_all(index, images, 3, None, "s1")[2] is False


def test_cache_file_from_another_bundle_is_never_read(tmp_path):
    # a cache file copied (or renamed) under the key of another bundle: its content names its bundle
    from mapkit.localization.localize import bundle_fingerprint, cached_query_all

    for name in ("a", "b"):
        (tmp_path / name).mkdir()
    a, b = _CountingIndex(tmp_path / "a", "h1"), _CountingIndex(tmp_path / "b", "h2")
    img = tmp_path / "im.png"
    img.write_bytes(b"abc")
    cache = tmp_path / "cache"
    cached_query_all(a, [img], 2, cache, "s")
    src = cache / f"hits-s-k2-{bundle_fingerprint(a)}.npz"
    src.rename(cache / f"hits-s-k2-{bundle_fingerprint(b)}.npz")
    assert cached_query_all(b, [img], 2, cache, "s")[2] is False and b.calls == 1


def test_hit_recall_known_answer(tmp_path):
    from mapkit.evaluation.localization import hit_recall

    index = _CountingIndex(tmp_path)  # database image i at x = 10 i
    ids = np.array([[0, 5, 9], [20, 21, 3], [7, -1, -1]])
    gt = np.array([[0.0, 0, 0], [30.0, 0, 0], [500.0, 0, 0]])
    r = hit_recall(index, ids, gt, radius_m=5.0)
    assert r["recall_at_1"] == pytest.approx(1 / 3) and r["recall_at_3"] == pytest.approx(2 / 3)
    # MCVL's recall@1/5/20: the right place fifth (x = 30 m) counts from @5 on
    ids20 = np.array([[9, 8, 7, 6, 3] + [9] * 15, [0] * 20])
    r = hit_recall(index, ids20, np.array([[30.0, 0, 0], [0.0, 0, 0]]), radius_m=5.0)
    assert (r["recall_at_1"], r["recall_at_5"], r["recall_at_20"]) == (
        pytest.approx(0.5),
        pytest.approx(1.0),
        pytest.approx(1.0),
    )
    ids20[0, 4] = 9
    assert hit_recall(index, ids20, np.array([[30.0, 0, 0], [0.0, 0, 0]]), radius_m=5.0)[
        "recall_at_5"
    ] == pytest.approx(0.5)


def test_localize_log_writes_tum_poses_a_reader_takes_back(tmp_path):
    """``mapkit localize``: the query images in a drive log (MCAP) against a bundle give TUM
    trajectories, one row per localized image: retrieval near the truth at every place; the filter
    (the paper's random walk, no odometry in a bare log) starts there, then lags places 40 m apart."""
    import cv2

    from mapkit.core.types import CameraFrame
    from mapkit.io.mcap_log import McapWriter
    from mapkit.io.trajectory import read_tum
    from mapkit.localization.localize import localize_log

    ws = make_workspace(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bundle = build_vlad_index(ws, config=small_config(), progress=False)
    imgs = read_session_images(ws, "test-c")
    stamps = 1_000_000_000 + np.arange(PLACES, dtype=np.int64) * 250_000_000
    log = tmp_path / "query.mcap"
    with McapWriter(log) as w:
        for stamp, path in zip(stamps, imgs.image_paths, strict=True):
            gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            w.write("/camera/image", CameraFrame(int(stamp), "camera", gray, encoding="mono8"), compress="png")
    config = tmp_path / "localize.yaml"
    config.write_text("top_k: 4\n")
    out = localize_log(bundle, log, tmp_path / "loc", config, progress=False)
    truth = np.stack([place_pose(p) for p in range(PLACES)])
    errors = {}
    for name in ("poses_tum.txt", "retrieval_tum.txt"):
        got_stamps, got = read_tum(out / name)
        assert len(got_stamps) >= PLACES - 1 and set(got_stamps.tolist()) <= set(stamps.tolist())
        k = np.searchsorted(stamps, got_stamps)
        errors[name] = np.linalg.norm(got[:, :3, 3] - truth[k, :3, 3], axis=1)
    assert np.median(errors["retrieval_tum.txt"]) < 5.0
    assert errors["poses_tum.txt"][0] < 5.0
    assert (out / "metrics.json").is_file() and (out / "config.yaml").is_file()
