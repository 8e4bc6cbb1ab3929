"""The README's main job on the embedded default: the synthetic town, mapped and measured.

1. ``mapkit synth``: the town and its sessions (multi-session ROS 2 logs with exact truth)
2. ``mapkit build``: every session to a georeferenced semi-dense map and image database
3. ``mapkit eval build``: trajectories and maps against the town's ground truth
4. ``mapkit align``: all sessions in one frame (ICP between sessions' submaps, pose graph)
5. ``mapkit eval align``: inter-session misalignment before and after, against the truth

Each stage returns its output path and skips what is already complete, so running this again
resumes. Later stages (multi-session alignment, triplets, indexes, localization) join this chain
as they land; ``mapkit demo`` will be its one-command form.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's mapkit, whatever is installed

from mapkit.align import align_workspace, format_align_truth  # noqa: E402
from mapkit.build import build, format_build_summary  # noqa: E402
from mapkit.evaluate import evaluate_align, evaluate_build, format_eval  # noqa: E402
from mapkit.runio import write_json  # noqa: E402
from mapkit.synth import synthesize  # noqa: E402


def run(preset: str, out: Path, seed: int | None = None, build_config: Path | None = None) -> Path:
    t0 = time.perf_counter()
    timings = {}
    town = synthesize(preset=preset, out=out / "town", seed=seed)
    timings["synth_s"] = time.perf_counter() - t0
    logs = sorted((town / "sessions").glob("*.mcap"))
    t1 = time.perf_counter()
    workspace = build(logs, out / "workspace", config=build_config, progress=sys.stderr.isatty())
    timings["build_s"] = time.perf_counter() - t1
    print(format_build_summary(workspace), flush=True)
    t2 = time.perf_counter()
    results = evaluate_build(workspace, town)
    timings["eval_s"] = time.perf_counter() - t2
    print(format_eval(results), flush=True)
    metrics = {"preset": preset, "timings": timings, "eval_build": results}
    georeferenced = [n for n, r in results["sessions"].items() if r.get("georeferenced")]
    if len(georeferenced) >= 2:  # the tiny preset's drives are too short to georeference
        t3 = time.perf_counter()
        aligned = align_workspace(workspace, progress=sys.stderr.isatty())
        timings["align_s"] = time.perf_counter() - t3
        print((aligned / "qa.md").read_text(), flush=True)
        metrics["eval_align"] = evaluate_align(workspace, town)
        print(format_align_truth(metrics["eval_align"]), flush=True)
    else:
        print(f"multi-session alignment skipped: {len(georeferenced)} georeferenced session(s)", flush=True)
    timings["total_s"] = time.perf_counter() - t0
    write_json(out / "metrics.json", metrics)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="demo", help="synthetic town preset: tiny, demo or benchmark (default demo)")
    ap.add_argument("--out", type=Path, default=Path("runs/main"), help="output folder (default runs/main)")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--build-config", type=Path, default=None, help="YAML for mapkit build")
    args = ap.parse_args(argv)
    out = run(args.preset, args.out, args.seed, args.build_config)
    print(f"outputs in {out}: town/ (logs, truth, pictures), workspace/ (maps, image databases, eval_build.md, "
          "align/ with the merged map, qa.md and eval_align.md)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
