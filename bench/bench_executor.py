"""VLAD database encoding per executor (this process, 2 processes, Ray on 2 CPUs), and maps in a row on a kept pool.

The images are the synthetic ``tiny`` town's camera images (made and built into a workspace on the
first run, kept in ``--cache``, by default in the system's temporary folder) or any workspace's
(``--workspace``). The encoder has the paper's settings (128 words, 16384-D raw VLAD); its
vocabulary is learnt from the first images and its PCA from their raw VLADs, outside the timing.
Timed: ``encode_images`` of every image (dense RootSIFT, VLAD, PCA, L2) on each executor, in the
same run; reported are images per second, the ratio to this process, and whether the vectors equal
this process's bit for bit. Pool and Ray start-up are part of the time (a pool is spawned per map;
Ray's workers are warmed up once beforehand, as a long run would have them).

A second table times what a run of many stages does: ``--maps`` encodings of a few images each, one
after the other, on a pool spawned per map (the library's default for an executor nobody closes)
against one pool kept for every map (``keep_pool``: what ``mapkit`` commands and the demo use), with
the ratio and whether the vectors are the same.

Run from the repository root (Ray: ``pip install -e ".[distributed]"``; skipped without it)::

    nice -n 5 python3 bench/bench_executor.py [--images 80] [--repeat 1]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import best_of, report  # noqa: E402 (after sys.path points at this checkout)


def tiny_workspace(cache: Path) -> Path:
    """The ``tiny`` town built into ``cache/ws`` (once: a few minutes)."""
    from mapkit.core.errors import InputWarning
    from mapkit.mapping.build import build
    from mapkit.synth import session_logs, synthesize

    town = synthesize(preset="tiny", out=cache / "town", progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # tiny's drives are too short to georeference
        return build(session_logs(town), cache / "ws", progress=False)


def image_paths(ws: Path, limit: int) -> list[Path]:
    from mapkit.retrieval.index_vlad import read_session_images, workspace_sessions

    paths = [p for n in workspace_sessions(ws) for p in read_session_images(ws, n).image_paths]
    return paths[:limit]


def make_encoder(paths: list[Path]):
    from mapkit.core.executor import SERIAL
    from mapkit.retrieval.index_vlad import _map, _raw_task, _sample_task
    from mapkit.retrieval.vlad import VladConfig, VladEncoder, kmeans

    cfg = VladConfig()
    train = [str(p) for p in paths[:16]]
    tasks = [(p, cfg.kmeans_max_descriptors // len(train), cfg.seed, k) for k, p in enumerate(train)]
    sample = np.concatenate(list(_map(_sample_task, tasks, VladEncoder(cfg), SERIAL, False, "")))
    encoder = VladEncoder(cfg, kmeans(sample, cfg.num_words, 10, cfg.seed))
    with warnings.catch_warnings():
        warnings.simplefilter(
            "ignore"
        )  # the PCA is capped at 15 dimensions by 16 images: the encoding cost is the same
        encoder.fit_pca(np.stack(list(_map(_raw_task, train, encoder, SERIAL, False, ""))))
    return encoder


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--workspace", type=Path, default=None, help="a built workspace (default: the tiny town, made in --cache)"
    )
    ap.add_argument(
        "--cache",
        type=Path,
        default=Path(tempfile.gettempdir()) / "mapkit-bench-executor",
        help="where the tiny town is kept between runs",
    )
    ap.add_argument("--images", type=int, default=80, help="images encoded per executor")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs per executor; the best is reported")
    ap.add_argument("--workers", type=int, default=2, help="processes of the pool and CPUs of the Ray instance")
    ap.add_argument("--maps", type=int, default=12, help="maps in a row for the kept-pool table")
    args = ap.parse_args(argv)

    from mapkit.core.executor import SERIAL, ProcessExecutor, make_executor
    from mapkit.retrieval.index_vlad import encode_images

    ws = args.workspace or tiny_workspace(args.cache)
    paths = image_paths(ws, args.images)
    if not paths:
        print(f"no images in {ws}", file=sys.stderr)
        return 1
    encoder = make_encoder(paths)
    executors = {"this process (serial)": SERIAL, f"process pool ({args.workers})": ProcessExecutor(args.workers)}
    ray_note = ""
    try:
        t0 = time.perf_counter()
        ray_ex = make_executor("ray", args.workers)
        encode_images(encoder, paths[: 2 * args.workers], progress=False, executor=ray_ex)  # workers up, imports done
        ray_note = (
            f"Ray start-up {time.perf_counter() - t0:.1f} s (local instance and worker warm-up, not timed below)."
        )
        executors[f"Ray ({args.workers} CPUs)"] = ray_ex
    except Exception as exc:  # noqa: BLE001 - the rest of the benchmark stands without Ray
        ray_note = f"Ray skipped: {exc}"
    rows, reference, serial_s = [], None, None
    for name, ex in executors.items():
        out: dict = {}
        seconds = best_of(
            lambda out=out, ex=ex: out.__setitem__("v", encode_images(encoder, paths, progress=False, executor=ex)),
            args.repeat,
        )
        if reference is None:
            reference, serial_s = out["v"], seconds
        rows.append(
            {
                "executor": name,
                "images": len(paths),
                "seconds": seconds,
                "images_per_s": len(paths) / seconds,
                "speed_vs_serial": serial_s / seconds,
                "bit_identical": bool(np.array_equal(out["v"], reference)),
            }
        )
    for ex in executors.values():
        ex.close()
    h, w = np.asarray(__import__("cv2").imread(str(paths[0]), 0)).shape
    source = "the tiny town" if args.workspace is None else f"workspace {ws.name}"
    report(
        "VLAD database encoding per executor",
        rows,
        f"{len(paths)} images of {w}x{h} px from {source}; 128 words, {encoder.pca.dim}-D after PCA. {ray_note}",
    )
    batches = [paths[(k * 4) % len(paths) :][:4] for k in range(args.maps)]
    pools = {"a pool per map": ProcessExecutor(args.workers), "one pool kept": ProcessExecutor(args.workers, True)}
    kept_rows, per_map_s, first = [], None, None
    for name, ex in pools.items():
        got: dict = {}

        def in_a_row(ex=ex, got=got) -> None:
            got["v"] = [encode_images(encoder, b, progress=False, executor=ex) for b in batches]

        seconds = best_of(in_a_row, args.repeat)
        ex.close()
        if first is None:
            first, per_map_s = got["v"], seconds
        kept_rows.append(
            {
                "pool": name,
                "maps": len(batches),
                "seconds": seconds,
                "s_per_map": seconds / len(batches),
                "speed_vs_per_map": per_map_s / seconds,
                "bit_identical": all(np.array_equal(a, b) for a, b in zip(got["v"], first, strict=True)),
            }
        )
    report(
        "Maps in a row: a pool per map against one kept",
        kept_rows,
        f"{len(batches)} encodings of {len(batches[0])} images each, {args.workers} processes.",
        headline={
            "mapkit": f"{kept_rows[1]['s_per_map']:.2f} s/map (kept pool)",
            "baseline": f"{kept_rows[0]['s_per_map']:.2f} s/map (pool per map)",
            "ratio": f"{kept_rows[1]['speed_vs_per_map']:.2f}x",
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
