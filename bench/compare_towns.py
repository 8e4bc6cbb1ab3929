"""Are two synthetic towns made with the same preset and seed identical? (determinism check)

Compares the config hash, the bytes of the mesh, road graph and every session's ground truth, and
the decoded images of every session (every 10th frame unless --all-frames).

    mapkit synth --preset demo --out /tmp/a && mapkit synth --preset demo --out /tmp/b
    python bench/compare_towns.py /tmp/a /tmp/b
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def compare(a: Path, b: Path, step: int) -> list[str]:
    from mapkit.io.mcap_log import McapLog
    from mapkit.synth import session_log, session_logs

    diffs = []
    ha, hb = (json.loads((t / "world" / "manifest.json").read_text())["config_hash"] for t in (a, b))
    if ha != hb:
        diffs.append(f"config hash {ha} != {hb}")
    files = ["world/mesh.ply", "world/roads.json"] + [
        f"sessions/{p.name}" for p in sorted((a / "sessions").glob("*.gt.tum"))
    ]
    for rel in files:
        if not (b / rel).is_file() or _digest(a / rel) != _digest(b / rel):
            diffs.append(f"{rel} differs")
    for log_a in session_logs(a):
        with McapLog(log_a) as la, McapLog(session_log(b, log_a.name.split(".")[0])) as lb:
            fa = list(la.records("image"))[::step]
            fb = list(lb.records("image"))[::step]
            same = len(fa) == len(fb) and all(
                x.stamp_ns == y.stamp_ns and np.array_equal(x.image, y.image) for x, y in zip(fa, fb, strict=True)
            )
            print(f"{log_a.stem}: {len(fa)} images compared, {'identical' if same else 'DIFFERENT'}")
            if not same:
                diffs.append(f"{log_a.name}: images differ")
    return diffs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    ap.add_argument("--all-frames", action="store_true")
    args = ap.parse_args(argv)
    diffs = compare(args.a, args.b, 1 if args.all_frames else 10)
    print("identical" if not diffs else "\n".join(diffs))
    return 0 if not diffs else 1


if __name__ == "__main__":
    sys.exit(main())
