"""Speed of the CNN descriptor (semi-dense paper, Sec. 3.3.2 and 4): training and describing.

Figures, each the best of ``--repeat`` runs, as wall and CPU time of this process (the machine's
2 cores are shared: CPU time leaves out the time spent waiting for a core; with 2 threads it can
exceed the wall time):

1. Training throughput, triplets per second (forward of X1, X2, X3, Eq. (1), backward, optimiser
   step) with batches of 25 triplets run as one forward pass of 75 grids (``mapkit.learning.train``),
   against a naive loop of one triplet at a time (three forward passes of one grid, one step per
   triplet) timed in the same run; the ratio is printed.
2. Describe throughput, patches per second, of the exported model in onnxruntime (the
   deployment path of ``mapkit index structure``) against torch eager (no gradients), same
   weights, same grids, same batch; the ratio is printed, and the largest difference between
   the two descriptors.
3. The whole index describer (``mapkit.places.cnn.describe_cnn``: extract, yaw-normalise, voxelise,
   ONNX) on a synthetic street, patches per second, and the share of it spent in voxel grids.

Grids are the real demo triplet dataset's when ``--dataset`` exists (default
``runs/main/workspace/triplets``, what the README's main job writes), else random 32^3 grids of the
same fill (~5 %). Run from the repository root (keep other load low)::

    python3 bench/bench_cnn.py
    python3 bench/bench_cnn.py --form density_comparison --threads 2
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import best_wall_and_cpu, report  # noqa: E402 (after sys.path points at this checkout)


def _grids(dataset: Path, n: int, form: str, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if (dataset / "manifest.json").is_file():
        from mapkit.places.triplets import TripletDataset

        ds = TripletDataset(dataset)
        ids = np.sort(rng.choice(int(ds.manifest["patches"]), n, replace=False))
        return ds.grids(ids, form)
    shape = (n, 3, 32, 32, 32) if form == "density_comparison" else (n, 32, 32, 32)
    return (rng.random(shape) < 0.05).astype(np.uint8)


def bench_training(
    torch, grids: np.ndarray, form: str, batch: int, steps: int, naive_triplets: int, repeat: int
) -> list[dict]:
    from mapkit.places.cnn import CnnConfig, build_model, grids_to_input, triplet_loss

    cfg = CnnConfig(form=form)
    model = build_model(cfg, seed=0)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    x_all = torch.from_numpy(grids_to_input(grids, form))
    rng = np.random.default_rng(0)
    trip = rng.integers(0, len(grids), (max(steps * batch, naive_triplets), 3))

    def batched():
        for s in range(steps):
            t = trip[s * batch : (s + 1) * batch]
            d = model(x_all[t.T.reshape(-1)])
            loss = triplet_loss(d[:batch], d[batch : 2 * batch], d[2 * batch :], 0.5)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

    def naive():
        for t in trip[:naive_triplets]:
            d1, d2, d3 = (model(x_all[i : i + 1]) for i in t)
            loss = triplet_loss(d1, d2, d3, 0.5)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

    batched()  # warm-up (allocator, oneDNN kernels)
    wb, cb = best_wall_and_cpu(batched, repeat)
    wn, cn = best_wall_and_cpu(naive, repeat)
    nb = steps * batch
    return [
        {
            "method": f"batch of {batch} triplets (mapkit.learning.train)",
            "triplets": nb,
            "wall_s": wb,
            "cpu_s": cb,
            "triplets_per_s_wall": nb / wb,
            "triplets_per_s_cpu": nb / cb,
            "speedup_vs_naive_wall": (nb / wb) / (naive_triplets / wn),
        },
        {
            "method": "naive: one triplet per step, 3 forwards",
            "triplets": naive_triplets,
            "wall_s": wn,
            "cpu_s": cn,
            "triplets_per_s_wall": naive_triplets / wn,
            "triplets_per_s_cpu": naive_triplets / cn,
            "speedup_vs_naive_wall": 1.0,
        },
    ]


def bench_describe(torch, grids: np.ndarray, form: str, batch: int, repeat: int) -> tuple[list[dict], float]:
    import onnxruntime as ort

    from mapkit.places.cnn import CnnConfig, build_model, export_onnx, grids_to_input, torch_describe

    cfg = CnnConfig(form=form)
    model = build_model(cfg, seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        export_onnx(model, cfg, Path(tmp) / "m.onnx")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = torch.get_num_threads()
        sess = ort.InferenceSession(str(Path(tmp) / "m.onnx"), opts, providers=["CPUExecutionProvider"])

    def run_onnx():
        return np.concatenate(
            [
                sess.run(["descriptors"], {"grids": grids_to_input(grids[k : k + batch], form)})[0]
                for k in range(0, len(grids), batch)
            ]
        )

    def run_torch():
        return torch_describe(model, grids, form, batch)

    diff = float(np.abs(run_onnx() - run_torch()).max())
    wt, ct = best_wall_and_cpu(run_torch, repeat)
    wo, co = best_wall_and_cpu(run_onnx, repeat)
    n = len(grids)
    rows = [
        {
            "method": "onnxruntime (deployment)",
            "patches": n,
            "wall_s": wo,
            "cpu_s": co,
            "patches_per_s_wall": n / wo,
            "patches_per_s_cpu": n / co,
            "speedup_vs_torch_wall": wt / wo,
        },
        {
            "method": "torch eager, no_grad",
            "patches": n,
            "wall_s": wt,
            "cpu_s": ct,
            "patches_per_s_wall": n / wt,
            "patches_per_s_cpu": n / ct,
            "speedup_vs_torch_wall": 1.0,
        },
    ]
    return rows, diff


def bench_index_describer(torch, form: str, n_kp: int, repeat: int) -> list[dict]:
    """describe_cnn (the structure index's describer) on a synthetic street."""
    from mapkit.core.bundle import write_manifest
    from mapkit.places.cnn import CnnConfig, build_model, describe_cnn, export_onnx
    from mapkit.places.index_structure import StructureIndexConfig
    from mapkit.places.patches import CNN_DOMAIN, voxel_grids, xy_tree

    rng = np.random.default_rng(0)
    # a street: two facades (y = +-8 m), ground, poles; ~300k points over 300 m
    x = rng.uniform(0, 300, 300_000)
    kind = rng.integers(0, 3, len(x))
    y = np.where(kind == 0, 8.0, np.where(kind == 1, -8.0, rng.uniform(-8, 8, len(x))))
    z = np.where(kind < 2, rng.uniform(0, 12, len(x)), 0.0) + rng.normal(0, 0.03, len(x))
    pts = np.c_[x, y + rng.normal(0, 0.03, len(x)), z]
    kp = pts[rng.choice(len(pts), n_kp, replace=False)]
    obs = np.c_[kp[:, 0] - 8.0, np.zeros(len(kp)), np.full(len(kp), 1.5)] - kp
    tree = xy_tree(pts)
    cfg_m = CnnConfig(form=form)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        export_onnx(build_model(cfg_m, seed=0), cfg_m, folder / "model.onnx")
        write_manifest(
            folder,
            {
                "format_version": 1,
                "kind": "mapkit cnn descriptor",
                "model_config": cfg_m.model_dump(mode="json"),
                "domain": CNN_DOMAIN.model_dump(),
            },
        )
        cfg = StructureIndexConfig(kind="cnn", cnn_model=str(folder))
        describe_cnn(pts, kp[:8], obs[:8], cfg, tree)  # warm-up, loads the session
        w, c = best_wall_and_cpu(lambda: describe_cnn(pts, kp, obs, cfg, tree), repeat)
        wg, cg = best_wall_and_cpu(lambda: voxel_grids(pts, kp, obs, CNN_DOMAIN, 32, tree, packed=True), repeat)
    return [
        {
            "stage": "describe_cnn (extract + yaw + voxelise + ONNX)",
            "patches": n_kp,
            "wall_s": w,
            "cpu_s": c,
            "patches_per_s_wall": n_kp / w,
            "share_in_voxel_grids": wg / w,
        },
        {
            "stage": "voxel_grids alone",
            "patches": n_kp,
            "wall_s": wg,
            "cpu_s": cg,
            "patches_per_s_wall": n_kp / wg,
            "share_in_voxel_grids": 1.0,
        },
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--dataset", type=Path, default=Path("runs/main/workspace/triplets"), help="triplet dataset for real grids"
    )
    ap.add_argument("--form", choices=("occupancy", "density_comparison"), default="occupancy")
    ap.add_argument("--threads", type=int, default=2, help="torch and onnxruntime threads")
    ap.add_argument("--steps", type=int, default=8, help="batches of 25 triplets timed")
    ap.add_argument("--naive", type=int, default=50, help="triplets timed one at a time")
    ap.add_argument("--patches", type=int, default=1024, help="patches described")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    from mapkit.places.cnn import require_torch

    torch = require_torch()
    torch.set_num_threads(args.threads)
    grids = _grids(args.dataset, max(args.patches, 256), args.form, 0)
    src = f"real grids of {args.dataset}" if (args.dataset / "manifest.json").is_file() else "random grids (~5 % fill)"
    print(f"# CNN descriptor speed: {args.form}, {args.threads} threads, torch {torch.__version__}, {src}")
    t0 = time.perf_counter()
    report(
        "Training throughput (forward + backward + step)",
        bench_training(torch, grids[:256], args.form, 25, args.steps, args.naive, args.repeat),
        "speedup_vs_naive_wall: batched triplets/s over the per-triplet loop's, same run.",
    )
    rows, diff = bench_describe(torch, grids[: args.patches], args.form, 256, args.repeat)
    report(
        "Describe throughput (inference on 32^3 grids)",
        rows,
        "speedup_vs_torch_wall: onnxruntime over torch eager, same weights and grids; max |ONNX - torch| = "
        f"{diff:.2e}.",
    )
    report("Index describer on a synthetic street", bench_index_describer(torch, args.form, args.patches, args.repeat))
    print(f"\nbench seconds: {time.perf_counter() - t0:.1f}")


if __name__ == "__main__":
    main()
