"""The CNN descriptor (semi-dense paper, Sec. 3.3.2 and 4) against known answers: Eq. (1) on a
hand-built batch, the shapes of Fig. 3(c) for both input forms, ONNX equal to torch, a fixed
seed giving identical weights, a resumed training equal to an uninterrupted one, hard negatives
that are true non-matches among near neighbours, and the cnn kind of the structure index.

Training runs on a tiny synthetic triplet dataset (8^3 grids, a few dozen patches) with a tiny
network, so that the whole file takes seconds."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mapkit.cli import config_model  # noqa: E402 (after importorskip: without torch the file is skipped)
from mapkit.core.config import load_config  # noqa: E402 (after importorskip: without torch the file is skipped)
from mapkit.core.errors import ConfigError, InputError  # noqa: E402 (after importorskip: without torch the file is skipped)
from mapkit.core.runio import read_timings, write_json  # noqa: E402 (after importorskip: without torch the file is skipped)
from mapkit.learning.train import TrainConfig, hard_negatives, train_cnn  # noqa: E402 (after importorskip: without torch the file is skipped)
from mapkit.places.cnn import (  # noqa: E402 (after importorskip: without torch the file is skipped)
    CnnConfig,
    OnnxDescriber,
    build_model,
    describe_cnn,
    export_onnx,
    grids_to_input,
    load_torch_model,
    require_torch,
    torch_describe,
    triplet_loss,
)
from mapkit.places.patches import CNN_DOMAIN, density_comparison, pack_bits  # noqa: E402 (after importorskip: without torch the file is skipped)
from mapkit.places.triplets import TripletDataset  # noqa: E402 (after importorskip: without torch the file is skipped)

TINY = CnnConfig(grid=8, conv1_channels=3, conv1_kernel=3, conv2_channels=4, hidden=16, dim=8)
TINY_TRAIN = {
    "model": TINY.model_dump(),
    "triplet_set": 40,
    "batch_triplets": 5,
    "epochs": 3,
    "hard_every_epochs": 1,
    "hard_fraction": 0.1,
    "hard_neighbours": 5,
    "negative_min_distance_m": 100.0,
    "threads": 1,
    "seed": 7,
}


def make_tiny_dataset(folder: Path, grid: int = 8, places: int = 12, members: int = 3, seed: int = 0) -> Path:
    """A triplet dataset in the format of ``mapkit triplets``: each place has a random occupancy
    pattern, its members are copies with 5 % of the voxels flipped; places lie 200 m apart;
    places 0..8 are train, the rest test; each positive pair gets a member of another place."""
    rng = np.random.default_rng(seed)
    occ, utm, split, pid = [], [], [], 0
    triplets = {"train": [], "test": []}
    ids_of = []
    for p in range(places):
        base = rng.random((grid,) * 3) < 0.2
        ids = []
        for _ in range(members):
            g = base ^ (rng.random(base.shape) < 0.05)
            occ.append(g.astype(np.uint8))
            utm.append([600_000.0 + 200.0 * p + rng.normal(0, 1), 5_700_000.0, 50.0])
            split.append("train" if p < 9 else "test")
            ids.append(pid)
            pid += 1
        ids_of.append(ids)
    for p, ids in enumerate(ids_of):
        s = "train" if p < 9 else "test"
        same = [q for q in range(places) if (q < 9) == (p < 9) and q != p]
        for i in range(members):
            for j in range(i + 1, members):
                q = same[rng.integers(len(same))]
                triplets[s].append([ids[i], ids[j], ids_of[q][rng.integers(members)]])
    occ = np.stack(occ)
    dcg = density_comparison(occ.astype(np.int32))
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(
        folder / "patches-00000.npz", occupancy=pack_bits(occ), density_comparison=pack_bits(dcg), first_id=np.int64(0)
    )
    n = len(occ)
    np.savez(folder / "patches.npz", patch_id=np.arange(n), split=np.array(split), utm=np.array(utm))
    for s in ("train", "test"):
        np.save(folder / f"triplets_{s}.npy", np.array(triplets[s], np.int64))
    write_json(
        folder / "manifest.json",
        {
            "format_version": 1,
            "grid": grid,
            "domain": CNN_DOMAIN.model_dump(),
            "config_hash": f"tiny-{seed}",
            "sessions": ["a", "b"],
            "tiles": [],
            "shards": [{"file": "patches-00000.npz", "first_id": 0, "patches": n, "sha256": ""}],
            "patches": n,
            "triplets": {s: len(v) for s, v in triplets.items()},
            "files": {},
        },
    )
    return folder


@pytest.fixture(scope="module")
def tiny_ds(tmp_path_factory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("triplets"))


@pytest.fixture(scope="module")
def tiny_model(tiny_ds, tmp_path_factory) -> Path:
    return train_cnn(tiny_ds, tmp_path_factory.mktemp("model") / "cnn", overrides=TINY_TRAIN)


def _weights(folder: Path) -> dict:
    return torch.load(folder / "model.pt", weights_only=True)["state_dict"]


# --------------------------------------------------------------------------- loss and shapes


def test_triplet_loss_equals_hand_computed_value():
    d1 = torch.tensor([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]])
    d2 = torch.tensor([[3.0, 4.0], [0.0, 1.0], [1.0, 0.0]])
    d3 = torch.tensor([[0.0, 1.0], [6.0, 8.0], [1.0, 0.5]])
    # rows: max(5 + 1 - 1, 0)^2 = 25; max(1 + 1 - 10, 0)^2 = 0; max(0 + 1 - 0.5, 0)^2 = 0.25; mean over the batch
    assert float(triplet_loss(d1, d2, d3, margin=1.0)) == pytest.approx((25.0 + 0.0 + 0.25) / 3, abs=1e-6)
    assert float(triplet_loss(d1, d2, d3, margin=0.0)) == pytest.approx(16.0 / 3, abs=1e-6)


@pytest.mark.parametrize("form,channels", [("occupancy", 1), ("density_comparison", 3)])
def test_shapes_of_the_paper_network_for_both_input_forms(form, channels):
    cfg = CnnConfig(form=form)
    assert cfg.grid == 32 and cfg.dim == 512 and cfg.channels == channels  # Sec. 3.3.2, Fig. 3(c)
    model = build_model(cfg, seed=0)
    grids = (
        np.random.default_rng(0).random((3, 3, 32, 32, 32) if form == "density_comparison" else (3, 32, 32, 32)) < 0.1
    )
    x = grids_to_input(grids.astype(np.uint8), form)
    assert x.shape == (3, channels, 32, 32, 32) and x.dtype == np.float32
    d = torch_describe(model, grids.astype(np.uint8), form)
    assert d.shape == (3, 512) and d.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    convs = [m for m in model.modules() if isinstance(m, torch.nn.Conv3d)]
    fcs = [m for m in model.modules() if isinstance(m, torch.nn.Linear)]
    assert len(convs) == 2 and len(fcs) == 2 and convs[0].in_channels == channels
    with pytest.raises(InputError):
        grids_to_input(grids.astype(np.uint8), "occupancy" if form == "density_comparison" else "density_comparison")


def test_missing_torch_says_how_to_install_the_cpu_build(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)  # import torch now raises ImportError
    with pytest.raises(ConfigError) as e:
        require_torch()
    assert (
        "pip install torch==2.13.0" in str(e.value) and ".[learning]" in str(e.value) and "cpu" in str(e.value).lower()
    )


def test_train_config_defaults_are_the_papers_and_registered():
    cfg = TrainConfig()
    assert (cfg.batch_triplets, cfg.triplet_set, cfg.hard_every_epochs, cfg.hard_fraction) == (25, 20_000, 2, 0.05)
    assert config_model("train") is TrainConfig
    with pytest.raises(ConfigError):
        load_config(TrainConfig, None, {"model": {"grid": 30}})  # not a multiple of stride * pool


# --------------------------------------------------------------------------- ONNX


def test_onnx_export_gives_the_torch_descriptors(tmp_path):
    cfg = CnnConfig()  # the full-size network of Fig. 3(c)
    model = build_model(cfg, seed=3)
    grids = (np.random.default_rng(1).random((5, 32, 32, 32)) < 0.08).astype(np.uint8)
    export_onnx(model, cfg, tmp_path / "m.onnx")
    import onnxruntime as ort

    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    onnx_d = sess.run(["descriptors"], {"grids": grids_to_input(grids, "occupancy")})[0]
    np.testing.assert_allclose(onnx_d, torch_describe(model, grids, "occupancy"), atol=1e-5)


def test_trained_model_folder_onnx_equals_torch(tiny_model, tiny_ds):
    grids = TripletDataset(tiny_ds).grids(np.arange(20))
    model, cfg = load_torch_model(tiny_model)
    d_onnx = OnnxDescriber(tiny_model).describe_grids(grids, batch=7)
    np.testing.assert_allclose(d_onnx, torch_describe(model, grids, cfg.form), atol=1e-5)
    assert d_onnx.shape == (20, 8) and d_onnx.dtype == np.float32


# --------------------------------------------------------------------------- training


def test_training_writes_every_output_and_learns(tiny_model, tiny_ds):
    for name in (
        "model.pt",
        "model.onnx",
        "metrics.json",
        "config.yaml",
        "training_curve.png",
        "manifest.json",
        ".done",
    ):
        assert (tiny_model / name).is_file(), name
    m = json.loads((tiny_model / "metrics.json").read_text())
    assert [r["epoch"] for r in m["epochs"]] == [1, 2, 3]
    assert m["epochs"][-1]["loss"] < m["epochs"][0]["loss"]
    assert all(r["hard_triplets"] > 0 for r in m["epochs"][1:]) and "hard_triplets" not in m["epochs"][0]
    # learns: on its 9 test triplets (3 held-out places) the trained network puts positives nearer than
    # negatives well above chance (0.5; measured 8 of 9), and separates them more than the network it
    # started from (the same seed untrained: mean margin 0.030 against 0.056 trained), more each epoch
    final = m["final"]
    assert final["test_triplets"] == 9 and final["test_accuracy"] >= 6 / 9, final
    test = np.load(tiny_ds / "triplets_test.npy")
    d = torch_describe(
        build_model(TINY, seed=TINY_TRAIN["seed"]), TripletDataset(tiny_ds).grids(np.unique(test)), TINY.form
    )
    d = d[np.searchsorted(np.unique(test), test)]
    untrained_margin = np.mean(np.linalg.norm(d[:, 0] - d[:, 2], axis=1) - np.linalg.norm(d[:, 0] - d[:, 1], axis=1))
    assert final["test_margin_mean"] > 1.5 * untrained_margin > 0, (final["test_margin_mean"], untrained_margin)
    margins = [r["test_margin_mean"] for r in m["epochs"]]
    assert margins == sorted(margins) and margins[0] < margins[-1], margins
    # how long it took is the run record, apart from the results
    assert "triplets_per_s" not in m["final"] and read_timings(tiny_model)["epochs"][-1]["triplets_per_s"] > 0
    man = json.loads((tiny_model / "manifest.json").read_text())
    assert man["kind"] == "mapkit cnn descriptor" and "model.onnx" in man["files"] and man["model_config"]["grid"] == 8
    assert load_config(TrainConfig, tiny_model / "config.yaml").model.conv2_channels == 4
    assert not list(tiny_model.rglob("*.partial"))


def test_fixed_seed_gives_identical_weights(tiny_ds, tiny_model, tmp_path):
    again = train_cnn(tiny_ds, tmp_path / "again", overrides=TINY_TRAIN)
    a, b = _weights(tiny_model), _weights(again)
    assert all(torch.equal(a[k], b[k]) for k in a)
    other = train_cnn(tiny_ds, tmp_path / "other", overrides={**TINY_TRAIN, "seed": 8})
    assert not torch.equal(a["conv1.weight"], _weights(other)["conv1.weight"])


def test_resumed_training_equals_an_uninterrupted_one(tiny_ds, tiny_model, tmp_path):
    out = tmp_path / "resumed"
    train_cnn(tiny_ds, out, overrides={**TINY_TRAIN, "epochs": 1})  # "interrupted" after epoch 1
    # a half-written checkpoint of a killed run is a .partial file: never read as a finished epoch
    (out / "checkpoints" / ".epoch-0002.pt.x.partial").write_bytes(b"truncated")
    train_cnn(tiny_ds, out, overrides=TINY_TRAIN)  # epochs 2 and 3, with hard cycles before each
    a, b = _weights(tiny_model), _weights(out)
    assert all(torch.equal(a[k], b[k]) for k in a)
    la = [r["loss"] for r in json.loads((tiny_model / "metrics.json").read_text())["epochs"]]
    lb = [r["loss"] for r in json.loads((out / "metrics.json").read_text())["epochs"]]
    assert la == lb
    with pytest.raises(ConfigError):  # checkpoints of another configuration are not resumed
        train_cnn(tiny_ds, out, overrides={**TINY_TRAIN, "epochs": 4, "margin": 0.3})


def test_hard_negative_is_a_true_non_match_among_near_neighbours():
    # anchor 100 at the origin of descriptor space and of the map; candidates, nearest first in
    # descriptor space: itself (excluded), 1 (10 m away: a true match), 2 (500 m: the hard
    # negative), 3 (500 m but farther in descriptor space), 4 (far in both)
    anchor_desc = np.array([[0.0, 0.0]])
    cand_desc = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0], [0.3, 0.0], [5.0, 0.0]])
    cand_ids = np.array([100, 1, 2, 3, 4])
    cand_xy = np.array([[0.0, 0.0], [10.0, 0.0], [500.0, 0.0], [0.0, 500.0], [900.0, 0.0]])
    got = hard_negatives(
        anchor_desc, np.zeros((1, 2)), np.array([100]), cand_desc, cand_xy, cand_ids, k=3, min_distance_m=100.0
    )
    assert got.tolist() == [2]
    # with 2 moved to 50 m, neither of the anchor's 2 nearest neighbours (1 and 2; itself excluded) is a non-match
    cand_xy[2] = [50.0, 0.0]
    got = hard_negatives(
        anchor_desc, np.zeros((1, 2)), np.array([100]), cand_desc, cand_xy, cand_ids, k=2, min_distance_m=100.0
    )
    assert got.tolist() == [-1]


# --------------------------------------------------------------------------- the structure index, kind cnn


def test_cnn_kind_through_the_structure_index(tiny_model, tmp_path):
    from test_index_structure import FAST, make_street_workspace

    from mapkit.places.index_structure import StructureIndex, StructureIndexConfig, build_structure_index

    ws = tmp_path / "ws"
    maps = make_street_workspace(ws)
    bundle = build_structure_index(
        ws, "cnn", out=tmp_path / "cnn", sessions=["a"], overrides={**FAST, "cnn_model": str(tiny_model)}
    )
    idx = StructureIndex.load(bundle)
    man = idx.manifest
    assert idx.kind == "cnn" and man["counts"]["raw_dim"] == 8
    assert (
        man["cnn_model"]["onnx_sha256"]
        == json.loads((tiny_model / "manifest.json").read_text())["files"]["model.onnx"]["sha256"]
    )
    # the index's query descriptors are the ONNX model's (PCA'd), equal to torch's on the same grids
    b = maps["b"]
    kp = b.points_world[:50]
    obs = kp + np.array([-10.0, 0.0, 0.0])
    cfg = StructureIndexConfig(kind="cnn", cnn_model=str(tiny_model))
    raw = describe_cnn(b.points_world, kp, obs - kp, cfg)
    np.testing.assert_allclose(idx.describe(b.points_world, kp, obs), idx.pca.transform(raw), atol=1e-5)
    from mapkit.places.patches import voxel_grids

    occ, _, _ = voxel_grids(b.points_world, kp, obs - kp, CNN_DOMAIN, 8, packed=False)
    model, _ = load_torch_model(tiny_model)
    np.testing.assert_allclose(raw, torch_describe(model, occ, "occupancy"), atol=1e-5)
    m = idx.query_session_frames(b, b.keyframe_ids[::4], name="b")
    assert len(m) == len(b.keyframe_ids[::4]) and np.all(m.best_frame >= 0)
    # a cnn index without a model (and no registered describer) is a config error
    with pytest.raises(ConfigError):
        build_structure_index(ws, "cnn", out=tmp_path / "none", sessions=["a"], overrides=FAST)


def test_cnn_as_a_method_of_the_places_evaluation(tiny_model, tmp_path):
    from test_index_structure import make_street_workspace

    from mapkit.evaluation.places import evaluate_places

    ws = tmp_path / "ws"
    maps = make_street_workspace(ws)
    with pytest.raises(InputError) as e:  # the method needs its model
        evaluate_places(ws, [("a", "b")], methods=["cnn"], out=tmp_path / "none")
    assert e.value.field == "structure.cnn_model"
    overrides = {
        "structure": {"keypoint_fraction": 0.02, "cnn_model": str(tiny_model)},
        "query_stride": 3,
        "bootstrap": 0,
    }
    res = evaluate_places(ws, [("a", "b")], methods=["nbld", "cnn"], out=tmp_path / "eval", overrides=overrides)
    cnn = res["pairs"][0]["methods"]["cnn"]
    assert (
        cnn["available"]
        and 0.0 <= cnn["auc"] <= 1.0
        and cnn["reachable"] == res["pairs"][0]["queries"] == len(maps["b"].keyframe_ids[::3])
    )
    assert (
        res["cnn_model"]["onnx_sha256"]
        == json.loads((tiny_model / "manifest.json").read_text())["files"]["model.onnx"]["sha256"]
    )
    assert "| NBLD | CNN |" in (tmp_path / "eval" / "places.md").read_text()


def test_cli_train_then_cnn_index_from_the_command_line(tiny_ds, tiny_model, tmp_path, capsys):
    """`mapkit train DATASET -o MODEL -c YAML` gives the same model as the API; `mapkit index
    structure --kind cnn --model` refuses a folder that is not a trained model, in one line."""
    import yaml

    from mapkit.cli import main

    cfg = tmp_path / "train.yaml"
    cfg.write_text(yaml.safe_dump(TINY_TRAIN))
    assert main(["train", str(tiny_ds), "--out", str(tmp_path / "m"), "-c", str(cfg)]) == 0
    assert "model.onnx loads without torch" in capsys.readouterr().out
    a, b = _weights(tiny_model), _weights(tmp_path / "m")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert main(["index", "structure", str(tmp_path), "--kind", "cnn", "--model", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "error:" in err
