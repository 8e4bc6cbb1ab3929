"""The README's main job: ``mapkit demo`` on the embedded default, the synthetic town.

The recipe is :func:`mapkit.pipelines.demo.run_demo`; this script is its stand-alone form for a checkout
(it imports this checkout's mapkit whatever is installed). In order:

1. ``mapkit synth``: the town and its sessions (multi-session ROS 2 logs with exact truth)
2. ``mapkit build`` and ``mapkit eval build``: georeferenced semi-dense maps and image databases
3. ``mapkit align`` and ``mapkit eval align``: all sessions in one frame, against the truth
4. ``mapkit triplets``: the triplet patch dataset, with the true offsets of its positives
5. ``mapkit train`` (only with ``--train-cnn``): the 3D CNN patch descriptor
6. ``mapkit index vlad`` and ``mapkit index structure``: the deployable indexes
7. ``mapkit eval localize``: the Monte Carlo localizer; with ``--sixdof``, ``mapkit model``, ``mapkit eval
   localize --refine 6dof`` and ``mapkit export benchmark``: the reference model, 6-DoF localization and the
   localization benchmark
8. ``mapkit eval places``: place recognition
9. ``mapkit index export``: the verified deployment bundle; ``report.html``: everything above

Re-running resumes: every stage skips what it already finished.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's mapkit, whatever is installed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--preset",
        default="demo",
        help=(
            "synthetic town preset: demo (default), tiny (every stage on a small town), places (the papers' claims) "
            "or benchmark"
        ),
    )
    ap.add_argument("--out", type=Path, default=Path("runs/main"), help="output folder (default runs/main)")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--workers", type=int, default=2, help="processes for image encoding (default 2)")
    ap.add_argument("--train-cnn", action="store_true", help="also train the 3D CNN (learning extra)")
    ap.add_argument(
        "--lidar-maps",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="build each session's LiDAR map beside its semi-dense map (default; --no-lidar-maps leaves them out)",
    )
    ap.add_argument(
        "--sixdof", action="store_true", help="also the reference model, 6-DoF localization and the benchmark export"
    )
    ap.add_argument(
        "--synth-config",
        type=Path,
        default=None,
        help="YAML over the town's preset, as `mapkit synth --config` takes it (configs/synth/demo-snowy.yaml adds a "
        "snowy test drive to the demo town)",
    )
    ap.add_argument(
        "--record-rate-hz",
        type=float,
        default=None,
        help="cameras record video at this rate (RobotCar's 16) and the maps use every image, as the "
        "semi-dense paper's DSO maps do; image databases and queries keep the preset's rates",
    )
    args = ap.parse_args(argv)
    # imported here, not at the top: every worker process the demo spawns re-imports this script, and needs
    # only its own task's modules
    from mapkit.pipelines.demo import run_demo

    # the demo's stage lines ("[demo] build: ok in 12 s") and its stages' progress are mapkit's INFO log records
    logging.basicConfig(level=logging.WARNING, format="%(message)s", stream=sys.stderr)
    logging.getLogger("mapkit").setLevel(logging.INFO)
    m = run_demo(
        args.out,
        args.preset,
        args.seed,
        args.workers,
        args.train_cnn,
        progress=sys.stderr.isatty(),
        record_rate_hz=args.record_rate_hz,
        lidar_maps=args.lidar_maps,
        sixdof=args.sixdof,
        synth_config=args.synth_config,
    )
    print((args.out / "timings.md").read_text(), end="")
    print(f"report: {m['report']}")
    if "bundles" in m:
        print(f"deployable bundle: {m['bundles']['path']} (indexes: {', '.join(m['bundles']['indexes'])})")
    return 1 if any(s["status"] in ("failed", "crashed") for s in m["stages"].values()) else 0


if __name__ == "__main__":
    sys.exit(main())
