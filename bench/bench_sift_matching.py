"""Time of the reference model's matching step: mapkit's exact matcher against COLMAP's brute-force matcher.

On a workspace with a reference model (``mapkit model``; the main job with ``--sixdof`` makes one), its
database's SIFT features and its ``pairs.txt``, in copies of the database with the matches cleared:

* mapkit: :func:`mapkit.localization.reference_model.match_and_verify` as the model stage runs it: the
  matches by matrix products of the descriptors (``write_exact_matches``, ``num_threads`` pairs at a time),
  then ``pycolmap.match_image_pairs``, which finds them there and only verifies and guides them;
* baseline: ``pycolmap.match_image_pairs`` with COLMAP's brute-force CPU matcher (``cpu_brute_force_matcher``),
  which the model asked for before, on the same threads;
* COLMAP's default approximate index for reference (not exact: two runs can differ).

Both exact runs must write the same matches and the same verified geometries (checked, row by row).

Run from the repository root::

    python3 bench/bench_sift_matching.py runs/main/workspace
"""

from __future__ import annotations

import argparse
import shutil
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402 (after sys.path points at this checkout)

WORKSPACE_NEEDS = "reference_model/database.db"  # bench/run_all.py skips a workspace without it


def _cleared_copy(db: Path, folder: Path, name: str) -> Path:
    out = folder / name
    shutil.copy(db, out)
    con = sqlite3.connect(out)
    con.execute("DELETE FROM matches")
    con.execute("DELETE FROM two_view_geometries")
    con.commit()
    con.close()
    return out


def _rows(db: Path, table: str) -> list[tuple]:
    con = sqlite3.connect(db)
    try:
        return con.execute(f"SELECT * FROM {table} ORDER BY pair_id").fetchall()
    finally:
        con.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("--model", type=Path, default=None, help="the model's folder (default WS/reference_model)")
    args = ap.parse_args(argv)
    from mapkit.core.config import load_config
    from mapkit.localization import reference_model as rm

    folder = args.model or args.workspace / rm.DEFAULT_FOLDER
    if not (folder / "database.db").is_file():
        print(f"no reference model at {folder}: run `mapkit model {args.workspace}` first", file=sys.stderr)
        return 2
    cfg = load_config(rm.ReferenceModelConfig, folder / "config.yaml")
    pairs = [tuple(line.split()) for line in (folder / "pairs.txt").read_text().splitlines() if line.strip()]

    def colmap(db: Path, exact: bool) -> None:
        matching, verification = rm.sift_matching_options(cfg, cfg.num_threads, cfg.seed)
        matching.sift.cpu_brute_force_matcher = exact
        with rm.quiet_colmap():
            rm.colmap_match_pairs(db, folder / "pairs.txt", matching, verification)

    def mapkit(db: Path) -> None:
        matching, verification = rm.sift_matching_options(cfg, cfg.num_threads, cfg.seed)
        with rm.quiet_colmap():
            rm.match_and_verify(db, folder / "pairs.txt", matching, verification)

    runs = {
        "mapkit (exact products, then COLMAP's verification)": mapkit,
        "COLMAP brute force": lambda db: colmap(db, exact=True),
        "COLMAP approximate index (not exact)": lambda db: colmap(db, exact=False),
    }
    seconds, dbs = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for k, (label, fn) in enumerate(runs.items()):
            db = _cleared_copy(folder / "database.db", Path(tmp), f"run{k}.db")
            t = time.perf_counter()
            fn(db)
            seconds[label] = time.perf_counter() - t
            dbs[label] = {t: _rows(db, t) for t in ("matches", "two_view_geometries")}
    ours, brute, approx = list(runs)
    same = dbs[ours] == dbs[brute]
    rows = [
        {
            "matcher": label,
            "pairs": len(pairs),
            "seconds": round(s, 2),
            "matches and geometries as brute force": "yes" if dbs[label] == dbs[brute] else "no",
        }
        for label, s in seconds.items()
    ]
    ratio = seconds[brute] / seconds[ours]
    report(
        "Reference model matching: exact matrix products against COLMAP's brute-force matcher",
        rows,
        f"matching, verification and guided matching of {len(pairs)} pairs on {cfg.num_threads} threads: "
        f"{seconds[ours]:.1f} s against {seconds[brute]:.1f} s, {ratio:.2f}x; the same rows: {same}",
        headline={
            "mapkit": f"{seconds[ours]:.1f} s",
            "baseline": f"{seconds[brute]:.1f} s (COLMAP's brute-force CPU matcher)",
            "ratio": f"{ratio:.2f}x",
        },
    )
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
