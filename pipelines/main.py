"""The README's main job on the embedded default: the synthetic town, generated and inspected.

Each stage returns its output path and is skipped when its output is already complete, so running
this again resumes. Later stages (map construction, alignment, indexes, localization) join this
chain as they land; ``mapkit demo`` will be its one-command form.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mapkit.info import format_summary, summarize
from mapkit.runio import write_json
from mapkit.synth import synthesize


def run(preset: str, out: Path, seed: int | None = None) -> Path:
    town = synthesize(preset=preset, out=out / "town", seed=seed)
    summaries = {}
    for log in sorted((town / "sessions").glob("*.mcap")):
        s = summarize(log)
        summaries[log.stem] = s
        print(format_summary(s), flush=True)
    write_json(out / "sessions_info.json", summaries)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="demo", help="synthetic town preset: tiny, demo or benchmark (default demo)")
    ap.add_argument("--out", type=Path, default=Path("runs/main"), help="output folder (default runs/main)")
    ap.add_argument("--seed", type=int, default=None)
    args = ap.parse_args(argv)
    out = run(args.preset, args.out, args.seed)
    print(f"outputs in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
