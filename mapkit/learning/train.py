"""``mapkit train``: triplet training of the CNN patch descriptor (semi-dense paper, Sec. 4).

A Siamese network of three instances of the CNN with shared weights (Fig. 4a) describes the
grids (X1, X2, X3) of a triplet: X1, X2 a matching pair, X3 a non-matching patch. The loss is
Eq. (1), ``max(||D(X1) - D(X2)|| + m - ||D(X1) - D(X3)||, 0)^2``. Batches of 25 triplets are
drawn from a triplet set T of 20,000 (Sec. 4.2); every K = 2 epochs, 5 % of T is replaced by hard
triplets found on the fly (Fig. 4b): for a random anchor X1 of the training split (with its
matching X2), X3 is the nearest of X1's nearest neighbours in descriptor space that is a true
non-match, i.e. lies farther than ``negative_min_distance_m`` from X1 in UTM.

Input: a triplet dataset folder (``mapkit triplets``, :class:`mapkit.places.triplets.TripletDataset`);
training uses its train split, and its test split (other UTM tiles) gives the per-epoch
triplet accuracy and distance margins. Output folder::

    checkpoints/epoch-NNNN.pt   model, optimiser, triplet set and metrics after each epoch (the last two kept)
    model.pt                    state dict and model config of the final model (torch)
    model.onnx                  the same network as ONNX (what the structure index runs, without torch)
    metrics.json                per epoch: loss, active triplets, test accuracy and margins, hard triplets; sizes of
                                the triplet sets (the same for the same data, config and thread count, run to run)
    timings.json                per epoch: training seconds (wall and CPU), triplets/s, hard-mining seconds, wall
                                time so far; the mean rate, the whole training's and this call's wall time
    training_curve.png          loss and test accuracy per epoch
    config.yaml                 the resolved TrainConfig
    manifest.json               format, config hash, model config, patch domain, dataset, checksums of every file

Everything is written atomically (temporary file, then one rename); a re-run resumes from the
last checkpoint written with the same configuration (``epochs`` may grow: training continues),
and a finished run returns at once. Seeds: the initial weights from ``seed``, the batch order and
the hard-triplet draw of epoch e from ``(seed, e)``, so a resumed run equals an uninterrupted one.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from mapkit import __version__
from mapkit.core.bundle import write_manifest
from mapkit.core.config import MapkitConfig, dump_config, load_config
from mapkit.core.errors import ConfigError, InputError
from mapkit.core.runio import (
    atomic_path,
    atomic_write_text,
    config_hash,
    is_done,
    mark_done,
    progress_bar,
    stage_hash,
    write_json,
    write_timings,
)
from mapkit.core.writers import writes_workspace
from mapkit.io.plots import training_curve
from mapkit.places.cnn import (
    MODEL_FORMAT_VERSION,
    ONNX_FILE,
    TORCH_FILE,
    CnnConfig,
    build_model,
    export_onnx,
    grids_to_input,
    require_torch,
    torch_describe,
    triplet_loss,
)
from mapkit.places.patches import pack_bits, unpack_bits
from mapkit.places.triplets import TripletDataset

log = logging.getLogger(__name__)

#: the version of this stage's algorithm, bumped whenever its output for the same inputs changes (it reruns)
STAGE_VERSION = 1
CHECKPOINTS = "checkpoints"
#: an epoch's wall-clock figures: the run record (timings.json), not metrics.json
EPOCH_TIMINGS = ("train_s", "train_cpu_s", "triplets_per_s", "wall_s", "hard_mining_s")
#: settings that change neither the weights nor the order of training: a new value resumes
_RESUME_FREE = {"epochs", "threads", "keep_checkpoints"}


class TrainConfig(MapkitConfig):
    """Triplet training of the CNN descriptor. Paper values (semi-dense paper, Sec. 4.2) are the
    defaults where it gives one."""

    model: CnnConfig = Field(
        default_factory=CnnConfig, description="The network (Sec. 3.3.2, Fig. 3c) and its input form."
    )
    batch_triplets: int = Field(25, ge=1, description="Triplets per SGD batch B (Sec. 4.2: 25).")
    triplet_set: int = Field(
        20_000,
        ge=1,
        description="Cardinality of the triplet set T, drawn from the dataset's train split "
        "(Sec. 4.2: 20,000; all train triplets when the split has fewer).",
    )
    margin: float = Field(
        0.5,
        gt=0,
        description="Margin m of the triplet loss, Eq. (1) (a tunable hyperparameter in the paper, no value "
        "given); descriptors are unit vectors, so distances lie in [0, 2].",
    )
    epochs: int = Field(
        4,
        ge=1,
        description="Passes over T (not in the paper). 4 x 20,000 triplets take about an hour on 2 CPU cores "
        "at the ~22 triplets/s of bench/bench_cnn.py; the demo budget used a 2,000-triplet set for 5 epochs. Growing "
        "it on a finished run continues training from its last checkpoint.",
    )
    hard_negatives: bool = Field(True, description="Hard-negative cycling (Sec. 4.2, Fig. 4b); off for the ablation.")
    hard_every_epochs: int = Field(
        2, ge=1, description="K: hard triplets replace part of T every K epochs (Sec. 4.2: K = 2)."
    )
    hard_fraction: float = Field(
        0.05, gt=0, le=1, description="Fraction of T replaced by hard triplets each cycle (Sec. 4.2: 5 %)."
    )
    hard_neighbours: int = Field(
        10,
        ge=1,
        description="X3 is taken among this many nearest neighbours of X1 in descriptor space "
        "(Sec. 4.2: 'one of the nearest neighbours'; the nearest true non-match among them).",
    )
    hard_pool: int | None = Field(
        None,
        ge=2,
        description="Train patches described as X3 candidates per cycle; None = every patch of "
        "the train split (the paper: 'from the same training dataset').",
    )
    negative_min_distance_m: float = Field(
        100.0,
        gt=0,
        description="A true non-match lies farther than this from the anchor in UTM "
        "(mapkit triplets' negatives use the same distance).",
    )
    optimizer: Literal["adam", "sgd"] = Field(
        "adam",
        description="The paper trains with SGD (Sec. 4.2) and gives no rate; Adam (a "
        "stochastic gradient method with per-weight steps) converges in the short CPU budget.",
    )
    lr: float = Field(1e-3, gt=0, description="Learning rate (not in the paper).")
    momentum: float = Field(0.9, ge=0, lt=1, description="Momentum of SGD (optimizer sgd only).")
    weight_decay: float = Field(0.0, ge=0, description="L2 weight decay.")
    test_triplets: int = Field(
        1000, ge=0, description="Test-split triplets scored after each epoch (accuracy, margins); 0 = none."
    )
    describe_batch: int = Field(
        256, ge=1, description="Patches per forward pass when describing (hard mining, test metrics)."
    )
    seed: int = Field(
        0, description="Seed of the initial weights, the triplet set draw, batch order and hard-triplet draws."
    )
    threads: int = Field(
        2, ge=1, description="torch.set_num_threads (the machine's cores; results are reproducible for a fixed value)."
    )
    keep_checkpoints: int = Field(2, ge=1, description="Checkpoints kept (the newest).")


# --------------------------------------------------------------------------- data


class PackedGrids:
    """The grids of a set of patch ids held in memory bits-packed (4 KiB per 32^3 occupancy
    grid, 12 KiB per density-comparison grid), unpacked per batch."""

    def __init__(self, dataset, ids: np.ndarray, form: str, chunk: int = 2048):
        self.ids = np.unique(np.asarray(ids, np.int64))
        self.form, self.grid = form, dataset.grid
        parts = [pack_bits(dataset.grids(self.ids[k : k + chunk], form)) for k in range(0, len(self.ids), chunk)]
        self.packed = np.concatenate(parts) if parts else np.zeros((0,), np.uint8)

    def rows(self, ids: np.ndarray) -> np.ndarray:
        r = np.searchsorted(self.ids, np.asarray(ids, np.int64))
        if np.any(r >= len(self.ids)) or np.any(self.ids[np.minimum(r, len(self.ids) - 1)] != ids):
            raise InputError(None, "patch id outside the loaded set", field="ids")
        return r

    def get(self, ids: np.ndarray) -> np.ndarray:
        """Unpacked uint8 grids of ``ids``."""
        return unpack_bits(self.packed[self.rows(ids)], self.grid)


def patch_xy(dataset, ids: np.ndarray) -> np.ndarray:
    """(n, 2) UTM easting/northing of patch ``ids`` (the dataset's per-patch table)."""
    t = dataset.table
    order = np.argsort(t["patch_id"], kind="stable")
    rows = order[np.searchsorted(t["patch_id"], ids, sorter=order)]
    return np.asarray(t["utm"], np.float64)[rows, :2]


# --------------------------------------------------------------------------- hard negatives (pure numpy)


def hard_negatives(
    anchor_desc: np.ndarray,
    anchor_xy: np.ndarray,
    anchor_ids: np.ndarray,
    cand_desc: np.ndarray,
    cand_xy: np.ndarray,
    cand_ids: np.ndarray,
    k: int,
    min_distance_m: float,
) -> np.ndarray:
    """For each anchor, the candidate id that is among its ``k`` nearest neighbours in descriptor
    space (L2) and a true non-match (farther than ``min_distance_m`` in UTM), the nearest such; -1
    when none of the k is. The anchor itself is never its own neighbour (Sec. 4.2's hard triplets)."""
    a = np.asarray(anchor_desc, np.float32)
    c = np.asarray(cand_desc, np.float32)
    out = np.full(len(a), -1, np.int64)
    if len(a) == 0 or len(c) == 0:
        return out
    k = min(k, len(c))
    cn = (c * c).sum(1)
    for s in range(0, len(a), 1024):  # (1024, n_cand) distances at a time
        blk = a[s : s + 1024]
        d2 = cn[None, :] - 2.0 * blk @ c.T
        d2[np.asarray(anchor_ids[s : s + 1024])[:, None] == cand_ids[None, :]] = np.inf
        nn = np.argpartition(d2, k - 1, axis=1)[:, :k] if k < len(c) else np.tile(np.arange(len(c)), (len(blk), 1))
        nn = np.take_along_axis(nn, np.argsort(np.take_along_axis(d2, nn, 1), axis=1, kind="stable"), 1)
        far = np.linalg.norm(cand_xy[nn] - anchor_xy[s : s + 1024, None, :], axis=2) > min_distance_m
        far &= np.isfinite(np.take_along_axis(d2, nn, 1))
        has = far.any(1)
        first = np.argmax(far, axis=1)
        out[s : s + 1024] = np.where(has, cand_ids[nn[np.arange(len(blk)), first]], -1)
    return out


# --------------------------------------------------------------------------- training


def _rng(seed: int, epoch: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, epoch, stream])


def _optimizer(torch, model, cfg: TrainConfig):
    if cfg.optimizer == "adam":
        return torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    return torch.optim.SGD(model.parameters(), lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)


def _checkpoints(folder: Path) -> list[Path]:
    return sorted((folder / CHECKPOINTS).glob("epoch-*.pt"))


def _save_checkpoint(torch, folder: Path, epoch: int, state: dict, keep: int) -> Path:
    path = folder / CHECKPOINTS / f"epoch-{epoch:04d}.pt"
    # a killed run leaves a .partial, never a truncated epoch-*.pt
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(state, f)
        f.flush()
        os.fsync(f.fileno())
    for old in _checkpoints(folder)[:-keep]:
        old.unlink(missing_ok=True)
    return path


def _test_metrics(model, grids: PackedGrids, triplets: np.ndarray, cfg: TrainConfig) -> dict:
    """Triplet accuracy (D(X1) nearer to D(X2) than to D(X3)), distance margins and loss on test triplets."""
    if len(triplets) == 0:
        return {}
    ids = np.unique(triplets)
    desc = torch_describe(model, grids.get(ids), cfg.model.form, cfg.describe_batch)
    d = {i: desc[np.searchsorted(ids, triplets[:, i])] for i in range(3)}
    pos = np.linalg.norm(d[0] - d[1], axis=1)
    neg = np.linalg.norm(d[0] - d[2], axis=1)
    return {
        "test_accuracy": float(np.mean(pos < neg)),
        "test_margin_mean": float(np.mean(neg - pos)),
        "test_margin_median": float(np.median(neg - pos)),
        "test_pos_dist": float(np.mean(pos)),
        "test_neg_dist": float(np.mean(neg)),
        "test_loss": float(np.mean(np.maximum(pos + cfg.margin - neg, 0.0) ** 2)),
        "test_triplets": int(len(triplets)),
    }


def _cycle_hard(
    model,
    grids: PackedGrids,
    train_all: np.ndarray,
    tset: np.ndarray,
    cand_ids: np.ndarray,
    cand_xy: np.ndarray,
    cfg: TrainConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, dict]:
    """Replace ``hard_fraction`` of the triplet set by hard triplets (Sec. 4.2). The anchors and
    their matching patches are random positive pairs of the train split; the candidates X3 are
    described with the current weights."""
    t0 = time.perf_counter()
    n_rep = max(1, int(round(cfg.hard_fraction * len(tset))))
    pool = (
        cand_ids
        if cfg.hard_pool is None or cfg.hard_pool >= len(cand_ids)
        else np.sort(rng.choice(cand_ids, cfg.hard_pool, replace=False))
    )
    pairs = train_all[rng.choice(len(train_all), n_rep, replace=len(train_all) < n_rep), :2]
    need = np.union1d(pool, pairs[:, 0])
    desc = torch_describe(model, grids.get(need), cfg.model.form, cfg.describe_batch)
    pool_rows = np.searchsorted(need, pool)
    anchor_rows = np.searchsorted(need, pairs[:, 0])
    xy_of = dict(zip(cand_ids.tolist(), range(len(cand_ids)), strict=True))
    pool_xy = cand_xy[[xy_of[i] for i in pool]]
    anchor_xy = cand_xy[[xy_of[i] for i in pairs[:, 0]]]
    neg = hard_negatives(
        desc[anchor_rows],
        anchor_xy,
        pairs[:, 0],
        desc[pool_rows],
        pool_xy,
        pool,
        cfg.hard_neighbours,
        cfg.negative_min_distance_m,
    )
    ok = neg >= 0
    hard = np.c_[pairs[ok], neg[ok]]
    rows = rng.choice(len(tset), len(hard), replace=False)
    new = tset.copy()
    new[rows] = hard
    return new, {
        "hard_triplets": int(len(hard)),
        "hard_wanted": int(n_rep),
        "hard_candidates": int(len(pool)),
        "hard_mining_s": time.perf_counter() - t0,
    }


@writes_workspace("out", within=True)
def train_cnn(
    dataset,
    out: str | Path,
    config: TrainConfig | str | Path | None = None,
    overrides: dict | None = None,
    progress: bool = False,
) -> Path:
    """Train the CNN descriptor on a triplet dataset (folder or ``TripletDataset``); returns ``out``.

    Resumes from the last checkpoint in ``out`` written with the same configuration (all fields
    but ``epochs``, ``threads`` and ``keep_checkpoints``); a checkpoint of another configuration is
    a ConfigError (choose another folder). Returns at once when ``out`` holds a finished run of
    exactly this configuration.
    """
    torch = require_torch()

    ds = dataset if isinstance(dataset, TripletDataset) else TripletDataset(dataset)
    cfg = load_config(TrainConfig, config, overrides)
    if cfg.model.grid != ds.grid:
        raise ConfigError(f"model.grid is {cfg.model.grid} but the triplet dataset's grids are {ds.grid}^3")
    out = Path(out)
    resume_config = {
        "config": cfg.model_dump(mode="json", exclude=_RESUME_FREE),
        "dataset": ds.manifest.get("config_hash"),
        "dataset_files": ds.manifest.get("files"),
    }
    # the version is in the checkpoints' hash too: a checkpoint of another version of the training is not resumed
    resume_hash = stage_hash("train", STAGE_VERSION, resume_config)
    full_hash = stage_hash("train", STAGE_VERSION, {"resume": resume_hash, "epochs": cfg.epochs})
    legacy_hash = config_hash({"resume": config_hash(resume_config), "epochs": cfg.epochs})
    if is_done(out, full_hash, legacy_hash=legacy_hash, version=STAGE_VERSION) and (out / ONNX_FILE).is_file():
        return out
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(cfg.threads)
    t_start = time.perf_counter()

    train_all, tset, test_t = _triplet_sets(ds, cfg)
    train_ids = np.unique(train_all)
    train_xy = patch_xy(ds, train_ids)
    grids = PackedGrids(ds, np.union1d(train_ids, np.unique(test_t)), cfg.model.form)

    model = build_model(cfg.model, seed=cfg.seed)
    opt = _optimizer(torch, model, cfg)
    history: list[dict] = []
    start_epoch = 1
    state = _resume_state(torch, out, cfg.epochs, resume_hash)
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        tset = np.asarray(state["triplet_set"], np.int64)
        history = list(state["history"])
        start_epoch = int(state["epoch"]) + 1
    (out / ".done").unlink(missing_ok=True)  # from here on, out is not a finished run until the end

    for epoch in range(start_epoch, cfg.epochs + 1):
        row: dict = {"epoch": epoch}
        if cfg.hard_negatives and epoch > 1 and (epoch - 1) % cfg.hard_every_epochs == 0:
            # every K epochs (Sec. 4.2): before epoch K+1, 2K+1, ... so that the set of a
            # checkpoint does not depend on how many epochs follow
            tset, info = _cycle_hard(model, grids, train_all, tset, train_ids, train_xy, cfg, _rng(cfg.seed, epoch, 2))
            row.update(info)
        t0 = time.perf_counter()
        row.update(_train_epoch(torch, model, opt, grids, tset, cfg, epoch, progress))
        row.update(_test_metrics(model, grids, test_t, cfg))
        row["wall_s"] = (
            (history[-1]["wall_s"] if history else 0.0) + time.perf_counter() - t0 + row.get("hard_mining_s", 0.0)
        )
        history.append(row)
        if progress:
            _log_epoch(row)
        _save_checkpoint(
            torch,
            out,
            epoch,
            {
                "epoch": epoch,
                "resume_hash": resume_hash,
                "model": model.state_dict(),
                "optimizer": opt.state_dict(),
                "triplet_set": tset,
                "history": history,
            },
            cfg.keep_checkpoints,
        )

    # the deployable model: torch state dict, ONNX, metrics, curve, manifest last
    _write_model(torch, out, model, cfg)
    _write_records(out, history, cfg, torch.__version__, len(train_all), len(tset), len(test_t), t_start)
    training_curve(
        out / "training_curve.png",
        history,
        title=f"CNN descriptor, {cfg.model.form}, hard negatives {'on' if cfg.hard_negatives else 'off'}",
    )
    write_manifest(out, _model_manifest(cfg, ds, full_hash, resume_hash, len(history)))
    mark_done(out, full_hash, version=STAGE_VERSION)
    return out


def _triplet_sets(ds: TripletDataset, cfg: TrainConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(every train triplet, the initial triplet set T, the test triplets scored per epoch), each
    (n, 3) patch ids; T and the test triplets are drawn at random, without repeats, in dataset order."""
    train_all = ds.triplets("train").astype(np.int64)
    test_all = ds.triplets("test").astype(np.int64)
    if len(train_all) == 0:
        raise InputError(ds.folder, "the triplet dataset has no train triplets", field="triplets")
    init_rng = _rng(cfg.seed, 0, 0)
    tset = train_all[np.sort(init_rng.choice(len(train_all), min(cfg.triplet_set, len(train_all)), replace=False))]
    test_t = (
        test_all[np.sort(init_rng.choice(len(test_all), min(cfg.test_triplets, len(test_all)), replace=False))]
        if len(test_all)
        else test_all
    )
    return train_all, tset, test_t


def _resume_state(torch, out: Path, epochs: int, resume_hash: str) -> dict | None:
    """The last checkpoint in ``out`` up to epoch ``epochs`` (None when there is none); a
    ConfigError when ``out`` holds checkpoints of later epochs only, or of another configuration."""
    all_ckpts = _checkpoints(out)
    ckpts = [c for c in all_ckpts if int(c.stem.split("-")[1]) <= epochs]
    if all_ckpts and not ckpts:
        raise ConfigError(
            f"{out} holds checkpoints beyond epoch {epochs} only; train into another folder or raise epochs"
        )
    if not ckpts:
        return None
    state = torch.load(ckpts[-1], map_location="cpu", weights_only=False)
    if state.get("resume_hash") != resume_hash:
        raise ConfigError(
            f"{out} holds checkpoints of another training configuration, dataset or version of the training; "
            "train into another folder "
            f"or remove {out / CHECKPOINTS}"
        )
    return state


def _train_epoch(
    torch, model, opt, grids: PackedGrids, tset: np.ndarray, cfg: TrainConfig, epoch: int, progress: bool
) -> dict:
    """Epoch ``epoch``: one pass over the triplet set ``tset`` (n, 3) in an order drawn from
    ``(seed, epoch)`` (torch's seed too), in batches of ``cfg.batch_triplets``, each an SGD step
    on the loss of Eq. (1). Returns the epoch's mean loss, fraction of active triplets (positive
    loss) and its wall and CPU seconds."""
    torch.manual_seed(int(_rng(cfg.seed, epoch, 3).integers(2**31)))
    triplets = tset[_rng(cfg.seed, epoch, 1).permutation(len(tset))]
    B = cfg.batch_triplets
    model.train()
    losses, active = [], 0
    t0, c0 = time.perf_counter(), time.process_time()
    bar = progress_bar(len(triplets), progress, f"epoch {epoch}/{cfg.epochs}", "triplet", leave=False)
    for b in range(0, len(triplets), B):
        rows = triplets[b : b + B]
        n = len(rows)
        # X1 of the batch, then X2, then X3: one pass, shared weights
        x = torch.from_numpy(grids_to_input(grids.get(rows.T.reshape(-1)), cfg.model.form))
        d = model(x)
        loss = triplet_loss(d[:n], d[n : 2 * n], d[2 * n :], cfg.margin)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()) * n)
        with torch.no_grad():
            active += int(
                ((d[:n] - d[n : 2 * n]).norm(dim=1) + cfg.margin - (d[:n] - d[2 * n :]).norm(dim=1) > 0).sum()
            )
        bar.update(n)
    bar.close()
    train_s, train_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    return {
        "loss": float(np.sum(losses) / len(triplets)),
        "active_fraction": active / len(triplets),
        "train_s": train_s,
        # CPU time of this process (all threads): steadier than wall on a shared machine
        "train_cpu_s": train_cpu_s,
        "triplets_per_s": len(triplets) / train_s if train_s > 0 else None,
    }


def _log_epoch(row: dict) -> None:
    log.info(
        "epoch %d: loss %.4f, test accuracy %.3f, %.1f triplets/s",
        row["epoch"],
        row["loss"],
        row.get("test_accuracy", float("nan")),
        row["triplets_per_s"],
    )


def _write_model(torch, out: Path, model, cfg: TrainConfig) -> None:
    """The trained model as a torch state dict (with its configs) and as ONNX, and the resolved config."""
    with atomic_path(out / TORCH_FILE) as tmp, open(tmp, "wb") as f:
        torch.save(
            {
                "state_dict": model.state_dict(),
                "model_config": cfg.model.model_dump(mode="json"),
                "train_config": cfg.model_dump(mode="json"),
            },
            f,
        )
    export_onnx(model, cfg.model, out / ONNX_FILE)
    atomic_write_text(out / "config.yaml", dump_config(cfg))


def _write_records(
    out: Path,
    history: list[dict],
    cfg: TrainConfig,
    torch_version: str,
    n_train: int,
    n_set: int,
    n_test: int,
    t_start: float,
) -> None:
    """``metrics.json`` (per epoch without its wall-clock figures, the final epoch, set sizes) and
    ``timings.json`` (the epochs' wall-clock figures, the mean rate, the wall time so far and of this call)."""
    epochs = [{k: v for k, v in r.items() if k not in EPOCH_TIMINGS} for r in history]
    metrics = {
        "epochs": epochs,
        "final": epochs[-1] if epochs else {},
        "train_triplets_available": int(n_train),
        "triplet_set": int(n_set),
        "test_triplets": int(n_test),
        "threads": cfg.threads,
        "torch_version": torch_version,
    }
    write_json(out / "metrics.json", metrics)
    write_timings(
        out,
        epochs=[{k: r[k] for k in EPOCH_TIMINGS if k in r} for r in history],
        triplets_per_s_mean=float(np.mean([r["triplets_per_s"] for r in history])) if history else None,
        wall_s_training=history[-1]["wall_s"] if history else 0.0,
        wall_s_this_call=time.perf_counter() - t_start,
    )


def _model_manifest(cfg: TrainConfig, ds: TripletDataset, full_hash: str, resume_hash: str, epochs: int) -> dict:
    """The trained model's manifest: format, hashes, configs, patch domain, ONNX signature, dataset."""
    return {
        "format_version": MODEL_FORMAT_VERSION,
        "kind": "mapkit cnn descriptor",
        "mapkit_version": __version__,
        "config_hash": full_hash,
        "resume_hash": resume_hash,
        "config": cfg.model_dump(mode="json"),
        "model_config": cfg.model.model_dump(mode="json"),
        "domain": ds.manifest["domain"],
        "epochs": epochs,
        "hard_negatives": cfg.hard_negatives,
        "onnx": {
            "file": ONNX_FILE,
            "input": "grids (n, C, g, g, g) float32 0/1",
            "output": "descriptors (n, dim) float32, unit L2 norm",
        },
        "dataset": {
            "path": str(ds.folder.resolve()),
            "config_hash": ds.manifest.get("config_hash"),
            "sessions": ds.manifest.get("sessions"),
            "tiles": ds.manifest.get("tiles"),
            "triplets": ds.manifest.get("triplets"),
        },
    }


__all__ = ["TrainConfig", "train_cnn", "hard_negatives", "PackedGrids", "patch_xy"]
