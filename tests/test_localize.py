"""The localizer chain on a real (tiny) VLAD bundle: retrieval gives z_t, the particle filter
follows it, driven by the query session's relative motion."""

from __future__ import annotations

import warnings

import numpy as np

from mapkit.geometry import invert_pose
from mapkit.index_vlad import VladIndex, build_vlad_index, read_session_images
from mapkit.localize import LocalizeConfig, run_localizer

from test_index_vlad import PLACES, make_workspace, place_pose, small_config


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
    ret_err = np.linalg.norm(r["retrieval_position"] - truth[:, :3, 3], axis=1)
    fil_err = np.linalg.norm(r["filter_position"] - truth[:, :3, 3], axis=1)
    assert np.median(ret_err) < 5.0  # the right place is retrieved
    assert np.median(fil_err) < 5.0 and np.all(np.isfinite(fil_err))
    R = r["filter_rotation"]
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-6) and np.allclose(np.linalg.det(R), 1.0)
