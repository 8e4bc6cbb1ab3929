"""Maps made the way the semi-dense paper's are: every image of video, against the preset's rates.

The paper's point clouds come from DSO run on the full-rate image stream (Sec. 3); the demo maps
its drives from images at MCVL's rates (4 Hz). This bench runs the main job (``mapkit demo``)
twice on the same town and the same drives, once at the preset's camera rates and once with every
camera recording video (``--rate``, RobotCar's Bumblebee XB3: 16 Hz) and the maps made from every
image; image databases and queries keep the preset's rates in both runs
(:func:`mapkit.pipelines.demo.demo_build_config`). It prints, side by side: each session's map
density (keyframes, points, points per 100 m of the keyframes' path), the place-recognition AUC of
every pair and method (held-out places first, then all places) and the stage times. The baseline is
the preset-rate run; ratios are video over it.

A subset of the demo's drives keeps it to about an hour on 2 cores (``--sessions``; a session that
follows another needs it listed too)::

    python3 bench/places_video_rate.py --out /tmp/video-rate
    python3 bench/places_video_rate.py --preset tiny --sessions tiny-sunny tiny-night --rate 8 --out /tmp/vr-tiny

Writes ``OUT/video_rate.md`` and ``OUT/video_rate.json``; each run keeps its whole demo folder
(``OUT/preset-rate``, ``OUT/video-<rate>hz``), so a second call resumes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEFAULT_SESSIONS = ("train-sunny", "train-cloudy", "test-night", "test-snowy")


def _subset(preset: str, names: list[str]) -> dict:
    """Synth overrides keeping only ``names`` of the preset's listed sessions, in its order."""
    from mapkit.synth.config import load_config

    listed = load_config(preset).model_dump(mode="json")["sessions"]
    by_name = {s["name"]: s for s in listed}
    missing = [n for n in names if n not in by_name]
    if missing:
        raise SystemExit(f"preset {preset!r} has no session(s) {missing}; it has {sorted(by_name)}")
    keep = [s for s in listed if s["name"] in names]
    orphans = [s["name"] for s in keep if s.get("follow") and s["follow"] not in names]
    if orphans:
        raise SystemExit(f"session(s) {orphans} follow a session not listed; add it to --sessions")
    return {"sessions": keep}


def _run_summary(out: Path, metrics: dict) -> dict:
    """Densities, AUCs and stage times of one demo run."""
    places = json.loads((out / "workspace" / "eval" / "places" / "places.json").read_text())
    pairs = {}
    for p in places["pairs"]:
        key = f"{p['query']} to {p['database']}"
        scopes = {
            "held_out": (p.get("methods"), p.get("queries")) if places.get("headline") == "held_out" else (None, None),
            "all_places": ((p.get("all_places") or p).get("methods"), (p.get("all_places") or p).get("queries")),
        }
        pairs[key] = {
            scope: {"queries": q, **{m: (r or {}).get("auc") for m, r in (ms or {}).items()}}
            for scope, (ms, q) in scopes.items()
            if ms is not None
        }
    return {
        "maps": places.get("maps", {}),
        "pairs": pairs,
        "stages_s": {n: s.get("seconds") for n, s in metrics["stages"].items()},
        "status": {n: s.get("status") for n, s in metrics["stages"].items()},
    }


def _fmt(v, d: int = 3) -> str:
    return "n/a" if v is None else f"{v:,.{d}f}"


def _ratio(a, b) -> str:
    return "n/a" if a is None or b in (None, 0) else f"{a / b:.2f}"


def report(base: dict, video: dict, rate: float, base_label: str) -> str:
    lines = [
        f"# Maps from every image ({rate:g} Hz video) against the preset's rates ({base_label})",
        "",
        "## Map densities",
        "",
        "| session | keyframes (preset / video) | points (preset / video) | per 100 m (preset / video) | ratio |",
        "|---|---|---|---|---|",
    ]
    for name in sorted(set(base["maps"]) | set(video["maps"])):
        a, b = base["maps"].get(name, {}), video["maps"].get(name, {})
        lines.append(
            f"| {name} | {_fmt(a.get('keyframes'), 0)} / {_fmt(b.get('keyframes'), 0)} | {_fmt(a.get('points'), 0)} / "
            f"{_fmt(b.get('points'), 0)} | {_fmt(a.get('points_per_100m'), 0)} / {_fmt(b.get('points_per_100m'), 0)} | "
            f"{_ratio(b.get('points_per_100m'), a.get('points_per_100m'))} |"
        )
    for scope, title in (("held_out", "Held-out places"), ("all_places", "All places")):
        keys = [k for k in base["pairs"] if scope in base["pairs"][k] or scope in video["pairs"].get(k, {})]
        if not keys:
            continue
        methods = [
            m for m in ("nbld", "m2dp", "cnn", "vlad") if any(m in base["pairs"][k].get(scope, {}) for k in keys)
        ]
        lines += [
            "",
            f"## {title}: AUC, preset rate / video",
            "",
            "| pair | queries | " + " | ".join(m.upper() for m in methods) + " |",
            "|---|---|" + "---|" * len(methods),
        ]
        for k in keys:
            a, b = base["pairs"][k].get(scope, {}), video["pairs"].get(k, {}).get(scope, {})
            lines.append(
                f"| {k} | {_fmt(a.get('queries'), 0)} / {_fmt(b.get('queries'), 0)} | "
                + " | ".join(f"{_fmt(a.get(m))} / {_fmt(b.get(m))}" for m in methods)
                + " |"
            )
        for m in methods:
            va = [base["pairs"][k][scope].get(m) for k in keys if base["pairs"][k].get(scope, {}).get(m) is not None]
            vb = [
                video["pairs"][k][scope].get(m)
                for k in keys
                if video["pairs"].get(k, {}).get(scope, {}).get(m) is not None
            ]
            if va and vb:
                lines.append(
                    f"\n{m.upper()} mean AUC: {sum(va) / len(va):.3f} (preset) / {sum(vb) / len(vb):.3f} (video), "
                    f"ratio {sum(vb) / len(vb) / (sum(va) / len(va)):.2f}"
                )
    lines += ["", "## Stage times (s), preset / video", "", "| stage | preset | video | ratio |", "|---|---|---|---|"]
    for n in base["stages_s"]:
        lines.append(
            f"| {n} | {_fmt(base['stages_s'][n], 1)} | {_fmt(video['stages_s'].get(n), 1)} | "
            f"{_ratio(video['stages_s'].get(n), base['stages_s'][n])} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    import logging

    from mapkit.core.runio import atomic_write_text, write_json
    from mapkit.pipelines.demo import run_demo

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="demo")
    ap.add_argument(
        "--sessions",
        nargs="+",
        default=list(DEFAULT_SESSIONS),
        help=f"drives of the preset to keep (default {' '.join(DEFAULT_SESSIONS)}); 'all' keeps every one",
    )
    ap.add_argument("--rate", type=float, default=16.0, help="video rate (Hz; default 16, RobotCar's stereo camera)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s", stream=sys.stderr)
    logging.getLogger("mapkit").setLevel(logging.INFO)
    overrides = None if args.sessions == ["all"] else _subset(args.preset, args.sessions)
    runs = {}
    for label, rate in (("preset-rate", None), (f"video-{args.rate:g}hz", args.rate)):
        out = args.out / label
        print(f"[{label}] mapkit demo --preset {args.preset} into {out}", file=sys.stderr)
        m = run_demo(
            out,
            args.preset,
            None,
            args.workers,
            False,
            progress=sys.stderr.isatty(),
            record_rate_hz=rate,
            synth_overrides=overrides,
        )
        bad = {n: s["status"] for n, s in m["stages"].items() if s["status"] in ("failed", "crashed")}
        if bad:
            print(f"[{label}] stages did not finish: {bad}; see {out / 'report.html'}", file=sys.stderr)
            return 1
        runs[label] = _run_summary(out, m)
    base, video = runs["preset-rate"], runs[f"video-{args.rate:g}hz"]
    text = report(base, video, args.rate, f"preset {args.preset!r}, sessions {', '.join(args.sessions)}")
    atomic_write_text(args.out / "video_rate.md", text)
    write_json(
        args.out / "video_rate.json", {"preset": args.preset, "sessions": args.sessions, "rate_hz": args.rate, **runs}
    )
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
