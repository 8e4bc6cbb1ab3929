"""The measured figures of the README and the docs: collected from what runs write, rendered into the pages.

Every table of measured figures in ``README.md`` and ``docs/`` lies between two markers::

    <!-- figures: NAME -->
    ...generated...
    <!-- /figures -->

and is made by the renderer ``NAME`` of this file from the records in ``docs/results/``. A record is what a
set of runs measured (the figures extracted from their ``metrics.json``, ``timings.json`` and evaluation
outputs), with the command that made each run, the date and the machine. So a page cannot state a figure
that no run wrote, two pages cannot disagree about one figure, and a fresh run can be held against the
docs (``compare``).

    python3 docs/figures.py collect places RUN...       # `mapkit demo --preset places --seed S --train-cnn
                                                        #  --no-lidar-maps` runs
    python3 docs/figures.py collect main-job RUN...     # runs of the README's main job (the demo preset)
    python3 docs/figures.py collect main-job-6dof RUN... # runs of the main job with --sixdof
    python3 docs/figures.py collect demo-snowy-6dof RUN... # ... and --synth-config configs/synth/demo-snowy.yaml
    python3 docs/figures.py collect tiny RUN...         # runs of `pipelines/main.py --preset tiny`
    python3 docs/figures.py collect first-run FILE      # what bench/first_run.py wrote (set-up, main job, tests)
    python3 docs/figures.py collect references FILE     # what bench/reference_checks.py wrote
    python3 docs/figures.py collect fault-campaign FILE # what bench/fault_campaign.py --out FILE wrote
    python3 docs/figures.py collect outside-localizer FILE  # what bench/outside_localizer.py --out FILE wrote
    python3 docs/figures.py collect outside-localizer-towns FILE...  # the same, one file per town (seed)
    python3 docs/figures.py render                      # fill every block of README.md and docs/**/*.md
    python3 docs/figures.py check                       # exit 1 when a block is not its rendering (a test runs it)
    python3 docs/figures.py compare places RUN          # a fresh run beside the record: within its spread?

A figure measured over several runs (seeds) is shown as its median with the range over the runs,
``0.63 (0.55-0.71)``; a comparison (A above B) holds only where it holds in every run.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import re
import statistics
import sys
from collections.abc import Callable, Iterable
from functools import partial
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from mapkit.core import blas  # noqa: E402  (standard library only: this script needs no environment)

RESULTS = ROOT / "docs" / "results"
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
BLOCK = re.compile(r"(<!-- figures: (?P<name>[a-z0-9-]+) -->\n)(?P<body>.*?)(<!-- /figures -->)", re.DOTALL)
METHODS = {"nbld": "NBLD", "m2dp": "M2DP", "cnn": "CNN", "vlad": "VLAD"}
STAGE_LABELS = {
    "synth": "synthetic town",
    "build": "build (trajectory, georeferencing, map, image database)",
    "align": "align",
    "triplets": "triplets",
    "train_cnn": "CNN training",
    "index_vlad": "VLAD index",
    "index_structure": "structure indexes",
    "localize": "MCVL localization",
    "sixdof": "reference model, 6-DoF localization, benchmark export",
    "places": "place recognition",
    "export": "bundle export",
    "view": "Rerun recording",
}


# --------------------------------------------------------------------------- reading runs


def _json(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def extract_run(run: Path) -> dict:
    """The figures of one `mapkit demo` run folder: stage times, maps, alignment, localization,
    place recognition and triplets, keyed as the renderers read them."""
    m, t = _json(run / "metrics.json"), _json(run / "timings.json")
    if not m:
        raise SystemExit(f"{run}: no metrics.json (not a finished mapkit demo run)")
    town = _json(run / "town" / "metrics.json")
    out: dict = {
        "preset": m.get("preset"),
        "seed": town.get("seed"),
        "mapkit_version": m.get("mapkit_version"),
        "status": {n: s["status"] for n, s in m["stages"].items()},
        "stages_s": {n: s.get("seconds") for n, s in (t.get("stages") or {}).items()},
        "total_s": t.get("seconds_total"),
        "driven_m": (m.get("streets") or {}).get("driven_m"),
    }
    out["maps"] = {
        n: {
            "median_m": s["map_local"]["median_distance_m"],
            "within_0.5m": s["map_local"]["fraction_within_0.5m"],
            "points_per_100m": s["map_local"]["points_per_100m"],
            "ate_m": s["trajectory_local"]["ate_rmse_m"],
        }
        for n, s in (m.get("eval_build") or {}).get("sessions", {}).items()
        if "map_local" in s
    }
    ea = m.get("eval_align") or {}
    out["align"] = {
        "pairs": {k: v["after_median_m"] for k, v in (ea.get("pairs") or {}).items()},
        "median_m": ea.get("after_median_m"),
    }
    out["localize"] = {
        cfg: {
            n: {
                "retrieval_mean_m": s["retrieval"]["mean_translation_m"],
                "retrieval_median_m": s["retrieval"]["median_translation_m"],
                "filter_mean_m": s["filter"]["mean_translation_m"],
                "filter_median_m": s["filter"]["median_translation_m"],
                "queries": s["queries"],
            }
            for n, s in sessions.items()
        }
        for cfg, sessions in (m.get("localize") or {}).items()
    }
    out["sixdof"] = m.get("sixdof") or {}
    out["places_by_source"] = m.get("places_by_source") or {}
    model = _json(run / "workspace" / "reference_model" / "metrics.json")
    if model:
        out["reference_model"] = {
            "images": model.get("images"),
            "images_with_points": model.get("images_with_points"),
            "points": model.get("points"),
            "depth_median_relative": {
                k: v.get("median_relative_difference")
                for k, v in (model.get("depth_check") or {}).items()
                if isinstance(v, dict)
            },
            "depth_fraction_compared": {
                k: v.get("fraction_compared")
                for k, v in (model.get("depth_check") or {}).items()
                if isinstance(v, dict)
            },
        }
    places = _json(run / "workspace" / "eval" / "places" / "places.json")
    out["places"] = {}
    for p in places.get("pairs", []):
        key = f"{p['query']} > {p['database']}"
        entry = {"condition": f"{_cond(p, 'query')} to {_cond(p, 'database')}"}
        for scope, block in (("held_out", p), ("all", p["all_places"])):
            entry[scope] = {
                "queries": block.get("queries"),
                **{k: r.get("auc") for k, r in block["methods"].items() if r.get("available", True)},
            }
        out["places"][key] = entry
    out["units"] = _units(run, out)
    tr = m.get("triplets") or {}
    out["triplets"] = {
        "count": sum((tr.get("export") or {}).get("triplets", {}).values()) if tr else None,
        "offset_median_m": (tr.get("truth") or {}).get("offset_median_m"),
        "offset_p90_m": (tr.get("truth") or {}).get("offset_p90_m"),
    }
    return out


def _units(run: Path, out: dict) -> dict:
    """What each stage of a run did and how long it took (from the stages' metrics.json and timings.json):
    the per-unit costs of the scaling projection."""
    ws = run / "workspace"
    sessions = sorted(p for p in (ws / "sessions").iterdir() if p.is_dir()) if (ws / "sessions").is_dir() else []

    def total(stage: str, key: str, file: str = "metrics.json") -> float:
        return float(sum((_json(p / stage / file).get(key) or 0) for p in sessions))

    u = {
        "trajectory_s": total("trajectory", "seconds", "timings.json"),
        "scans": total("trajectory", "poses"),
        "semidense_s": total("map", "seconds", "timings.json"),
        "keyframes": total("map", "keyframes"),
        "map_points": total("map", "points"),
        "imagedb_s": total("imagedb", "seconds", "timings.json"),
        "images": total("imagedb", "images"),
        "driven_m": out.get("driven_m"),
    }
    align_t, align_m = _json(ws / "align" / "timings.json"), _json(ws / "align" / "metrics.json")
    u["registering_s"], u["pairs_registered"] = (
        align_t.get("seconds_registering"),
        (align_m.get("registration") or {}).get("registered_this_run"),
    )
    u["triplets_s"] = _json(ws / "triplets" / "timings.json").get("seconds")
    u["triplets"] = sum((_json(ws / "triplets" / "metrics.json").get("triplets") or {}).values())
    vt, vm = _json(ws / "indexes" / "vlad" / "timings.json"), _json(ws / "indexes" / "vlad" / "metrics.json")
    u["vlad_encode_s"] = (vt.get("encode_training_s") or 0) + (vt.get("encode_database_s") or 0)
    u["vlad_images"] = vm.get("images_encoded")
    for kind in ("nbld", "m2dp"):
        t = (_json(ws / "indexes" / f"structure-{kind}" / "timings.json").get("sessions") or {}).values()
        fresh = [x for x in t if not x.get("cached")]
        u[f"{kind}_describe_s"] = sum(x["describe_s"] for x in fresh) if fresh else None
        u[f"{kind}_patches"] = sum(x["patches"] for x in fresh) if fresh else None
    return u


def _cond(pair: dict, role: str) -> str:
    c = (pair.get("conditions") or {}).get(role) or {}
    name = str(c.get("condition") or "")
    return "night" if name.startswith("night") else (c.get("weather") or name)


def machine() -> str:
    """This machine, as records state it: cores, memory, CPU model, OS, Python and the OpenBLAS kernel mapkit runs
    there (mapkit.core.blas: the bits of every matrix product)."""
    cpu = ""
    try:
        cpu = next(
            ln.split(":", 1)[1].strip()
            for ln in Path("/proc/cpuinfo").read_text().splitlines()
            if ln.startswith("model name")
        )
    except (OSError, StopIteration):
        cpu = platform.processor()
    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        mem = float("nan")
    kernel = blas.pin_openblas_kernel()  # the kernel in force (importing mapkit named it already)
    return (
        f"{os.cpu_count()} cores, {mem:.0f} GB, {cpu}, {platform.system()} {platform.release()}, Python "
        f"{platform.python_version()}" + (f", OpenBLAS kernel {kernel}" if kernel else "")
    )


def collect(name: str, sources: list[Path], command: str, note: str = "") -> Path:
    """Write the record ``docs/results/NAME.json`` from ``sources`` (run folders, or one JSON file)."""
    if name in (
        "first-run",
        "references",
        "mcvl-benchmark",
        "benchmarks",
        "robustness",
        "fault-campaign",
        "outside-localizer",
        "align-sources",
        "sixdof-thresholds",
        "lidar-dynamic",
    ):
        data = json.loads(sources[0].read_text())
        record = {"name": name, **data}
    elif name == "outside-localizer-towns":
        towns = [json.loads(p.read_text()) for p in sources]
        if len({t["command"] for t in towns}) != 1:
            raise SystemExit("outside-localizer records of different commands: run each town the same way")
        record = {"name": name, "command": towns[0]["command"], "towns": towns}
    else:
        runs = [extract_run(p) for p in sources]
        presets = {r["preset"] for r in runs}
        if len(presets) != 1:
            raise SystemExit(f"runs of different presets: {sorted(map(str, presets))}")
        record = {"name": name, "command": command, "preset": presets.pop(), "runs": runs}
    if note:
        record["note"] = note
    record = portable(record)
    record.setdefault("measured", dt.date.today().isoformat())
    record.setdefault("machine", machine())
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(record, indent=1, sort_keys=False) + "\n")
    return path


def portable(value, root: Path = ROOT, python: str = sys.executable):
    """``value`` (a record: dicts, lists, strings) with this machine's paths taken out of its strings: the
    interpreter becomes ``python``, paths in the checkout become relative to it and paths beside it (the shared
    data) relative to it with ``../``, so that a record says the same on every machine."""
    if isinstance(value, dict):
        return {k: portable(v, root, python) for k, v in value.items()}
    if isinstance(value, list):
        return [portable(v, root, python) for v in value]
    if not isinstance(value, str):
        return value
    out = value.replace(python, "python")
    for prefix, short in ((f"{root}/", ""), (f"{root.parent}/", "../")):
        out = out.replace(prefix, short)
    return out


def update_benchmarks(source: Path) -> Path:
    """Replace the benchmarks record's entries of the benchmarks ``source`` (a bench/run_all.py JSON report of some
    of them) ran; each replaced entry carries its own ``measured`` date (and machine, where it is not the record's),
    the others keep the record's."""
    rec = record("benchmarks")
    new = portable(json.loads(source.read_text()))
    if bool(new.get("quick")) != bool(rec.get("quick")):
        raise SystemExit("the report and the record differ in --quick: run the benchmark as the record ran them")
    today = dt.date.today().isoformat()
    here = machine()
    fresh = {
        r["name"]: {**r, "measured": today, **({"machine": here} if here != rec["machine"] else {})}
        for r in new["results"]
    }
    unknown = sorted(set(fresh) - {r["name"] for r in rec["results"]})
    rec["results"] = [fresh.get(r["name"], r) for r in rec["results"]] + [fresh[n] for n in unknown]
    path = RESULTS / "benchmarks.json"
    path.write_text(json.dumps(rec, indent=1, sort_keys=False) + "\n")
    return path


def record(name: str) -> dict:
    path = RESULTS / f"{name}.json"
    if not path.is_file():
        raise SystemExit(
            f"no record {path.relative_to(ROOT)}: collect it first (python3 docs/figures.py collect {name} ...)"
        )
    return json.loads(path.read_text())


# --------------------------------------------------------------------------- formatting


def spread(values: Iterable[float | None], fmt: str = "{:.3f}") -> str:
    """The median of ``values`` with their range over the runs (``0.63 (0.55-0.71)``); one value alone;
    ``n/a`` for none. Missing values (None) are left out and counted."""
    vals = [float(v) for v in values if v is not None]
    if not vals:
        return "n/a"
    med = statistics.median(vals)
    if len(vals) == 1 or max(vals) == min(vals):
        return fmt.format(med)
    return f"{fmt.format(med)} ({fmt.format(min(vals))}-{fmt.format(max(vals))})"


def spread_of(per_run: list[dict | None], key: str, fmt: str = "{:.3f}") -> str:
    """``spread`` of one entry over the runs; a run without the record counts as missing."""
    return spread([x[key] if x else None for x in per_run], fmt)


def verdict(differences: list[float | None]) -> str:
    """Whether "A above B" holds, from its difference in each run: in every run, in none, or in some
    (then not beyond the run-to-run spread)."""
    d = [x for x in differences if x is not None]
    if not d:
        return "not measured"
    above = sum(x > 0 for x in d)
    if above == len(d):
        return f"yes, in {len(d)} of {len(d)} runs"
    if above == 0:
        return f"no, in {len(d)} of {len(d)} runs"
    return f"not beyond the spread ({above} of {len(d)} runs)"


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def _runs(n: int) -> str:
    return "one run" if n == 1 else f"{n} runs"


def _runs_note(rec: dict) -> str:
    seeds = [r.get("seed") for r in rec["runs"]]
    if len(seeds) == 1:
        return f"One run (seed {seeds[0]}), measured {rec['measured']} on {rec['machine']}."
    return (
        f"{len(seeds)} runs (seeds {', '.join(map(str, seeds))}), measured {rec['measured']} on {rec['machine']}; "
        f"each figure is the median with its range over the runs."
    )


def _tiny(x: float) -> str:
    """A difference that may be exactly zero in float64: "below 1e-15" rather than 0.0e+00."""
    return "below 1e-15" if x < 1e-15 else f"{x:.1e}"


def _minutes(seconds: float | None) -> str:
    if seconds is None:
        return "n/a"
    m, s = divmod(int(round(seconds)), 60)
    return f"{m} min {s:02d} s" if m else f"{s} s"


# --------------------------------------------------------------------------- figures of the places runs


def _mean_auc(run: dict, method: str, scope: str = "held_out") -> float | None:
    vals = [p[scope].get(method) for p in run["places"].values()]
    vals = [v for v in vals if v is not None]
    return statistics.fmean(vals) if vals else None


def _pair_diffs(
    run: dict, a: str, b: str, scope: str = "held_out", only: Callable[[str], bool] | None = None
) -> list[float]:
    """Per pair of one run, AUC of method ``a`` minus the best of methods ``b`` (a tuple) or of ``b``."""
    out = []
    for p in run["places"].values():
        if only is not None and not only(p["condition"]):
            continue
        s = p[scope]
        bs = [s.get(x) for x in (b if isinstance(b, tuple) else (b,))]
        av = max((s.get(x) for x in (a if isinstance(a, tuple) else (a,)) if s.get(x) is not None), default=None)
        bv = max((v for v in bs if v is not None), default=None)
        if av is not None and bv is not None:
            out.append(av - bv)
    return out


def _ahead(diffs: list[float]) -> str:
    return f"{sum(d > 0 for d in diffs)} of {len(diffs)}"


def render_claims() -> str:
    """One row per claim of the papers: what was measured, what the paper says, whether it holds."""
    rows = []
    refs = _maybe("references")
    if refs:
        rows.append(
            [
                "M2DP as its authors compute it",
                f"1 - cos to `M2DP.m`'s output: {_tiny(refs['m2dp']['one_minus_cos'])}",
                "identical",
                "yes" if refs["m2dp"]["one_minus_cos"] < 1e-9 else "no",
                "`python3 bench/reference_checks.py`",
            ]
        )
        rows.append(
            [
                "dense SIFT as VLFeat computes it",
                f"median cosine to `vl_phow`: {refs['dsift']['median_cosine']:.5f}",
                "identical",
                "yes" if refs["dsift"]["median_cosine"] > 0.999 else "no",
                "`python3 bench/reference_checks.py`",
            ]
        )
    pl = _maybe("places")
    if pl:
        runs, cmd = pl["runs"], "`mapkit demo --preset places --seed S --train-cnn --no-lidar-maps`"
        d = [(_mean_auc(r, "nbld") or 0) - (_mean_auc(r, "m2dp") or 0) for r in runs]
        ahead = [_ahead(_pair_diffs(r, "nbld", "m2dp")) for r in runs]
        rows.append(
            [
                "NBLD above M2DP",
                f"mean held-out AUC {spread(_mean_auc(r, 'nbld') for r in runs)} vs "
                f"{spread(_mean_auc(r, 'm2dp') for r in runs)}; ahead on {', '.join(ahead)} pairs",
                "Table 2: on all 10 pairs",
                verdict(d),
                cmd,
            ]
        )
        for cond in ("night", "snowy"):
            per_run = [
                _pair_diffs(r, ("nbld", "m2dp"), "vlad", only=lambda c, cond=cond: c.startswith(cond)) for r in runs
            ]
            rows.append(
                [
                    f"structure above appearance ({cond} queries)",
                    f"better of NBLD, M2DP minus VLAD, per pair: {spread([x for ds in per_run for x in ds])}; "
                    f"ahead on {', '.join(_ahead(ds) for ds in per_run)} pairs",
                    "Sec. 6, Table 2: structure above appearance on 6 of 10 pairs (NetVLAD there, VLAD here)",
                    verdict([statistics.fmean(ds) if ds else None for ds in per_run]),
                    cmd,
                ]
            )
        if any(_mean_auc(r, "cnn") is not None for r in runs):
            hand = [max(_mean_auc(r, "nbld") or 0, _mean_auc(r, "m2dp") or 0) for r in runs]
            cnn = [_mean_auc(r, "cnn") for r in runs]
            rel = [(c - h) / h if c is not None and h else None for c, h in zip(cnn, hand, strict=True)]
            rows.append(
                [
                    "learned (3D CNN) above hand-crafted",
                    f"mean held-out AUC {spread(cnn)} vs the better hand-crafted "
                    f"{spread(hand)}: {spread([100 * x if x is not None else None for x in rel], '{:+.0f}')} %",
                    "Sec. 6: 5-20 % above",
                    verdict(rel),
                    cmd,
                ]
            )
        for n in sorted({s for r in runs for s in r["localize"].get("paper", {})}):
            vals = [r["localize"]["paper"].get(n) for r in runs]
            ret, fil = [v and v["retrieval_mean_m"] for v in vals], [v and v["filter_mean_m"] for v in vals]
            rows.append(
                [
                    f"MCVL filter below retrieval alone ({n})",
                    f"mean error {spread(fil, '{:.1f}')} m vs {spread(ret, '{:.1f}')} m",
                    "Table II: below",
                    verdict(
                        [r - f if r is not None and f is not None else None for r, f in zip(ret, fil, strict=True)]
                    ),
                    cmd,
                ]
            )
    bench = _maybe("mcvl-benchmark")
    if bench:
        seqs = bench["sequences"]
        below = sum(s["filter_mean_m"] < s["retrieval_mean_m"] for s in seqs.values())
        rows.append(
            [
                "MCVL filter below retrieval at the paper's scale",
                f"{below} of {len(seqs)} test sequences",
                "Table II: 5 of 5",
                "yes" if below == len(seqs) else f"on {below} of {len(seqs)}",
                "`python3 pipelines/mcvl_benchmark.py`",
            ]
        )
    note = f"\n\n{_runs_note(pl)}" if pl else ""
    return table(["claim", "figure", "paper", "holds?", "command"], rows) + note


def render_places_auc() -> str:
    """The semi-dense paper's Table 2 form: held-out AUC per pair and method, over the places runs."""
    pl = record("places")
    runs = pl["runs"]
    methods = [m for m in METHODS if any(m in p["held_out"] for r in runs for p in r["places"].values())]
    pairs = sorted({k for r in runs for k in r["places"]}, key=lambda k: (k.split(" > ")[0], k))
    rows = []
    for k in pairs:
        present = [r["places"][k] for r in runs if k in r["places"]]
        rows.append(
            [
                k.replace(" > ", " to "),
                present[0]["condition"],
                *[spread(p["held_out"].get(m) for p in present) for m in methods],
                spread([p["held_out"]["queries"] for p in present], "{:.0f}"),
                f"{len(present)} of {len(runs)}",
            ]
        )
    rows.append(["mean", "", *[spread(_mean_auc(r, m) for r in runs) for m in methods], "", ""])
    return (
        table(["query to database", "conditions", *[METHODS[m] for m in methods], "held-out queries", "runs"], rows)
        + f"\n\n{_runs_note(pl)}"
    )


def render_places_mcvl() -> str:
    """MCVL's Table II form on the places town: retrieval alone and the filter, per test drive and configuration."""
    pl = record("places")
    runs = pl["runs"]
    rows = []
    for cfg in sorted({c for r in runs for c in r["localize"]}):
        for n in sorted({s for r in runs for s in r["localize"][cfg]}):
            v = [r["localize"][cfg].get(n) for r in runs]
            f = partial(spread_of, v, fmt="{:.1f}")
            rows.append(
                [n, cfg, f("retrieval_mean_m"), f("retrieval_median_m"), f("filter_mean_m"), f("filter_median_m")]
            )
    return (
        table(
            [
                "test drive",
                "filter settings",
                "retrieval mean m",
                "retrieval median m",
                "filter mean m",
                "filter median m",
            ],
            rows,
        )
        + f"\n\n{_runs_note(pl)}"
    )


def render_maps() -> str:
    pl = record("places")
    runs = pl["runs"]
    rows = []
    for n in sorted({s for r in runs for s in r["maps"]}):
        v = [r["maps"].get(n) for r in runs]
        f = partial(spread_of, v)
        rows.append([n, f("median_m"), f("within_0.5m", "{:.2f}"), f("points_per_100m", "{:.0f}"), f("ate_m")])
    return (
        table(
            ["session", "map to true surfaces, median m", "share within 0.5 m", "points per 100 m", "trajectory ATE m"],
            rows,
        )
        + "\n\nOffset removed: each session's constant offset from the truth (its GPS bias) is taken out first. "
        + _runs_note(pl)
    )


def render_align() -> str:
    pl = record("places")
    runs = pl["runs"]
    sessions = sorted({s for r in runs for k in r["align"]["pairs"] for s in k.split(" / ")})
    rows = []
    for n in sessions:
        per_run = [[v for k, v in r["align"]["pairs"].items() if n in k.split(" / ")] for r in runs]
        rows.append(
            [
                n,
                spread([statistics.median(p) if p else None for p in per_run]),
                spread([max(p) if p else None for p in per_run]),
            ]
        )
    rows.append(["all pairs", spread(r["align"]["median_m"] for r in runs), ""])
    return (
        table(["session", "misalignment to its neighbours, median over pairs m", "worst pair m"], rows)
        + "\n\nMisalignment: the median distance between the two sessions' maps of a pair after alignment, measured "
        "against the true surfaces. " + _runs_note(pl)
    )


#: the 6-DoF table's estimates, as the demo's metrics key them
SIXDOF_ESTIMATES = (
    ("6dof", "6-DoF"),
    ("sequence", "6-DoF + odometry"),
    ("filter", "MCVL filter"),
    ("retrieval", "retrieval alone"),
)
SIXDOF_BANDS = (("0.25m_2deg", "(0.25 m, 2°)"), ("0.5m_5deg", "(0.5 m, 5°)"), ("5m_10deg", "(5 m, 10°)"))


def render_sixdof(name: str = "main-job-6dof") -> str:
    """The main job's 6-DoF stage (record ``name``): per test drive, the share of queries in each band and the median
    errors for the 6-DoF localizer, MCVL's filter and retrieval alone on the same queries; the reference model's
    size."""
    rec = record(name)
    runs = [r for r in rec["runs"] if r.get("sixdof")]
    if not runs:
        return "No run of the record holds the 6-DoF stage."
    rows = []
    for n in sorted({s for r in runs for s in r["sixdof"]}):
        for key, label in SIXDOF_ESTIMATES:
            per_run = [(r["sixdof"].get(n) or {}).get(key) for r in runs]
            if not any(per_run):
                continue  # a record made before the estimate existed
            shares = [
                spread([None if e is None else 100 * e["recall"][b] for e in per_run], "{:.1f} %")
                for b, _ in SIXDOF_BANDS
            ]
            accepted = (
                spread([(r["sixdof"].get(n) or {}).get("accepted_share") for r in runs], "{:.2f}")
                if key == "6dof"
                else ""
            )
            rows.append(
                [
                    n,
                    label,
                    *shares,
                    spread_of(per_run, "median_translation_m"),
                    spread_of(per_run, "median_rotation_deg", "{:.2f}"),
                    accepted,
                ]
            )
    models = [r.get("reference_model") or {} for r in runs]
    depth = sorted({k for m in models for k in m.get("depth_median_relative", {})})
    parts = [
        f"Reference model of the training drives: {spread([m.get('points') for m in models], '{:.0f}')} points seen "
        f"by {spread([m.get('images_with_points') for m in models], '{:.0f}')} of "
        f"{spread([m.get('images') for m in models], '{:.0f}')} images"
    ]
    for k in depth:
        median = [100 * (m["depth_median_relative"].get(k) or 0) for m in models]
        text = f"depth against the {k} map, median {spread(median, '{:.1f}')} %"
        compared = [100 * m["depth_fraction_compared"][k] for m in models if k in m.get("depth_fraction_compared", {})]
        if compared:  # a record may not hold the fraction
            text += f" of the {spread(compared, '{:.0f}')} % of observations where map and point both fix a depth"
        parts.append(text)
    note = "; ".join(parts) + ". "
    return (
        table(
            ["test drive", "estimate", *(b for _, b in SIXDOF_BANDS), "median m", "median deg", "6-DoF accepted"], rows
        )
        + f"\n\n{note}`{rec['command']}`. "
        + _runs_note({**rec, "runs": runs})
    )


def render_align_sources() -> str:
    """bench/align_map_sources.py: each pair's misalignment after align on each map source it ran."""
    rec = record("align-sources")
    src = rec["sources"]
    names = {"semidense": "semi-dense maps", "semidense+lidar": "semi-dense, LiDAR where sparse", "lidar": "LiDAR maps"}
    order = [k for k in names if k in src]
    pairs = list(src[order[0]]["pairs"])
    rows = [[pair, *(f"{src[k]['pairs'].get(pair, float('nan')):.3f}" for k in order)] for pair in pairs]
    rows.append(["**all pairs, median**", *(f"{src[k]['after_median_m']:.3f}" for k in order)])
    rows.append(["**worst pair**", *(f"{max(src[k]['pairs'].values()):.3f}" for k in order)])
    rows.append(["ICP pairs accepted", *(str(src[k]["accepted_pairs"]) for k in order)])
    rows.append(
        [
            "pairs on LiDAR maps",
            *(str((src[k].get("registered_on") or {}).get("pairs", {}).get("lidar", 0)) for k in order),
        ]
    )
    rows.append(["align, seconds", *(f"{src[k]['align_s']:.0f}" for k in order)])
    return (
        table(["session pair", *(f"{names[k]}, m" for k in order)], rows)
        + "\n\nMisalignment after align: the median distance between the two sessions' maps of the same true "
        f"surface, each source aligning the same built sessions. One run of `{rec['command']}` on the main job's "
        f"workspace, measured {rec['measured']} on {rec['machine']}." + (f" {rec['note']}" if rec.get("note") else "")
    )


def render_places_by_source() -> str:
    """The main job (its LiDAR maps): each pair's AUC per structure method from the semi-dense maps and from the
    LiDAR maps (merged to the demo's voxel), over held-out queries and over all places."""
    rec = record("main-job-6dof")
    runs = [r for r in rec["runs"] if r.get("places_by_source")]
    if not runs:
        return "No run of the record holds place recognition on LiDAR maps."
    first = runs[0]["places_by_source"]
    methods = list(next(iter(first.values()))["lidar"]["auc"])
    rows = []
    for pair in first:
        db, query = pair.split(":")
        for scope, label in (("held_out", "held out"), ("all_places", "all places")):
            e = [r["places_by_source"][pair] for r in runs]
            cells = [
                f"{spread([x['semidense']['queries'][scope] for x in e], '{:.0f}')} / "
                f"{spread([x['lidar']['queries'][scope] for x in e], '{:.0f}')}"
            ]
            for m in methods:
                semi = spread([x["semidense"]["auc"][m][scope] for x in e], "{:.3f}")
                lidar = spread([x["lidar"]["auc"][m][scope] for x in e], "{:.3f}")
                cells.append(f"{semi} / {lidar}")
            rows.append([f"{query} to {db}", label, *cells])
    return (
        table(
            [
                "pair (query to database)",
                "queries",
                "count (semi-dense / LiDAR)",
                *(f"{m.upper()} AUC (semi-dense / LiDAR)" for m in methods),
            ],
            rows,
        )
        + f"\n\nAUC from the semi-dense maps / from the LiDAR maps on the same pairs and split. `{rec['command']}`. "
        + _runs_note(rec)
    )


def render_sixdof_thresholds() -> str:
    """bench/sixdof_thresholds.py: right and off shares of held-out training drives per RANSAC threshold and
    inlier count, and the setting chosen."""
    rec = record("sixdof-thresholds")
    counts = sorted({r["min_inliers"] for r in rec["rows"]})
    chosen = rec["chosen"]
    rows = []
    for px in sorted({r["ransac_px"] for r in rec["rows"]}):
        cells = []
        for m in counts:
            r = next(r for r in rec["rows"] if r["ransac_px"] == px and r["min_inliers"] == m)
            cell = f"{100 * r['right']:.1f} / {100 * r['off']:.1f}"
            cells.append(f"**{cell}**" if (px, m) == (chosen["ransac_px"], chosen["min_inliers"]) else cell)
        rows.append([f"{px:g} px", *cells])
    drives = ", ".join(f"{k} ({v['queries']} queries)" for k, v in rec["drives"].items())
    return (
        table(["RANSAC threshold", *(f"{m} inliers" for m in counts)], rows)
        + f"\n\nPer cell: % of queries accepted within (0.25 m, 2 deg) / % accepted outside it, pooled over the "
        f"held-out drives {drives}. Chosen (bold): the most right poses with at most {100 * rec['max_off']:.0f} % "
        f"accepted off: RANSAC {chosen['ransac_px']:g} px, {chosen['min_inliers']} inliers. "
        f"One run of `{rec['command']}`, measured {rec['measured']} on {rec['machine']}."
    )


def render_lidar_dynamic() -> str:
    """bench/lidar_dynamic.py: the moving cars' points the LiDAR map keeps and the static points it removes, on
    true and own poses, the real clip's share removed, and the stage's cost."""
    rec = record("lidar-dynamic")
    label = {"truth": "true poses", "own": "the build's own poses", "truth, removal off": "true poses, removal off"}
    rows = [
        [
            label[r["poses"]],
            f"{100 * r['car_kept_fraction']:.2f} % of {r['car_points']:,}",
            f"{100 * r['static_removed_fraction']:.2f} % of {r['static_points']:,}",
            f"{r['static_points_removed_first']:,} of {r['static_points_removed']:,}",
        ]
        for r in rec["rows"]
    ]
    s, sess, e = rec["stage_s"], rec["session"], rec["own_motion_error_1s_m"]
    early = rec["rows"][0]["static_removed_first_s"]
    text = (
        table(
            [
                "Scans placed on",
                "Moving cars' points kept",
                "Static points removed",
                f"of them in the first {early:g} s",
            ],
            rows,
        )
        + f"\n\nOne {sess['length_m']:g} m drive with {sess['moving_cars']} oncoming cars in the {sess['preset']} town "
        f"of seed {sess['seed']}, every point of its {rec['rows'][0]['scans']} scans scored against the renderer's "
        f"labels. The build's own trajectory moves {e['first_second']:.2f} m off the true motion over its first "
        f"second (median {e['median_after_3s']:.3f} m per second after 3 s)."
    )
    clip = rec.get("real_clip")
    if clip:
        d, n = clip["defaults"], clip["no height tolerance"]
        text += (
            f" On the real KITTI clip ({clip['scans']} scans, no labels) the removal takes "
            f"{100 * d['removed_fraction']:.1f} % of the points and {100 * d['near_ground_removed_fraction']:.2f} % of "
            f"those near the ground; without the height tolerance {100 * n['removed_fraction']:.1f} % and "
            f"{100 * n['near_ground_removed_fraction']:.2f} %."
        )
    return text + (
        f" The LiDAR map stage took {s['lidar_map_with_removal']:.1f} s with the removal and "
        f"{s['lidar_map_without_removal']:.1f} s without it; the trajectory stage {s['trajectory']:.1f} s. "
        f"One run of `{rec['command']}`, measured {rec['measured']} on {rec['machine']}."
    )


def render_triplets() -> str:
    pl = record("places")
    runs = pl["runs"]
    rows = [
        ["triplets exported", spread([r["triplets"]["count"] for r in runs], "{:.0f}")],
        ["true offset of positives, median m", spread(r["triplets"]["offset_median_m"] for r in runs)],
        ["true offset of positives, 90th percentile m", spread(r["triplets"]["offset_p90_m"] for r in runs)],
    ]
    return table(["figure", "value"], rows) + f"\n\n{_runs_note(pl)}"


def _stages(name: str) -> str:
    rec = record(name)
    runs = rec["runs"]
    stages = [s for s in STAGE_LABELS if any(r["stages_s"].get(s) for r in runs)]
    rows = [[STAGE_LABELS[s], spread([r["stages_s"].get(s) for r in runs], "{:.0f}")] for s in stages]
    totals = [r["total_s"] for r in runs]
    whole = f"**{_minutes(statistics.median(totals))}**"
    if len(runs) > 1:
        whole += f" ({_minutes(min(totals))} - {_minutes(max(totals))})"
    rows.append(["**whole run**", whole])
    driven = runs[0].get("driven_m")
    return (
        table(["stage", "seconds"], rows)
        + f"\n\n{_runs(len(runs)).capitalize()} of `{rec['command']}`"
        + (f" ({driven / 1000:.1f} km driven)" if driven else "")
        + f", measured {rec['measured']} on {rec['machine']}."
        + (f" {rec['note']}" if rec.get("note") else "")
    )


def render_first_run() -> str:
    rec = record("first-run")
    rows = [
        ["set-up (`bash scripts/setup.sh`, empty package caches)", _minutes(rec["setup_s"])],
        ["main job (`.venv/bin/python pipelines/main.py --out runs/main`)", _minutes(rec["main_job_s"])],
        ["tests (`.venv/bin/python -m pytest -q`)", _minutes(rec["tests_s"])],
    ]
    return (
        table(["from a fresh clone", "time"], rows)
        + f"\n\nMeasured {rec['measured']} by `python3 bench/first_run.py` on {rec['machine']}, nothing else running."
        + (f" The tests that failed in that run: {', '.join(rec['tests_failed'])}." if rec.get("tests_failed") else "")
    )


def render_references() -> str:
    refs = record("references")
    rows = [
        [
            "M2DP (`m2dp_reference`) against the authors' `M2DP.m` on a real KITTI scan",
            f"1 - cos = {_tiny(refs['m2dp']['one_minus_cos'])}",
        ],
        [
            "dense SIFT (mode `phow`) against VLFeat's `vl_phow` on a KITTI frame",
            f"median cosine {refs['dsift']['median_cosine']:.5f}, 5th percentile {refs['dsift']['p05_cosine']:.5f}",
        ],
    ]
    return (
        table(["check", "agreement"], rows) + f"\n\nMeasured {refs['measured']} by `python3 bench/reference_checks.py`."
    )


def render_benchmarks() -> str:
    """The table of bench/run_all.py: each benchmark, what it measures, mapkit against its baseline in the same run."""
    rec = record("benchmarks")
    rows = [
        [
            f"`{r['name']}`",
            r["what"],
            r["mapkit"] or "",
            r["baseline"] or "",
            r["ratio"] or "",
            r["status"]
            + (f": {r['detail']}" if r["status"] != "ok" and r.get("detail") else "")
            + (
                f" (measured {r['measured']}" + (f" on {r['machine']})" if r.get("machine") else ")")
                if r.get("measured", rec["measured"]) != rec["measured"]
                else ""
            ),
        ]
        for r in rec["results"]
    ]
    mode = " --quick" if rec.get("quick") else ""
    return (
        table(["benchmark", "what is measured", "mapkit", "baseline (same run)", "ratio", "status"], rows)
        + f"\n\n`python3 bench/run_all.py{mode}`, measured {rec['measured']} on {rec['machine']}."
        + (f" {rec['note']}" if rec.get("note") else "")
    )


def render_robustness() -> str:
    """The fault campaign (bench/fuzz_readers.py): per fault class, inputs tried and their outcomes."""
    rec = record("robustness")
    outcomes = rec["outcomes"]
    rows = [[name, str(c["tried"]), *[str(c.get(o, 0)) for o in outcomes]] for name, c in rec["classes"].items()]
    total = [str(sum(c.get(o, 0) for c in rec["classes"].values())) for o in outcomes]
    rows.append(["**all**", str(sum(c["tried"] for c in rec["classes"].values())), *total])
    return (
        table(["fault class", "inputs", *outcomes], rows)
        + f"\n\n`{rec['command']}`, measured {rec['measured']} on {rec['machine']}."
    )


#: the outcome columns of the CLI fault campaign (bench/fault_campaign.py), as its table heads them
FAULT_CAMPAIGN_COLUMNS = {
    "clear error": "clear errors",
    "recovered": "recovered",
    "traceback": "tracebacks",
    "silent-wrong": "silent-wrong",
    "lost": "lost",
    "other": "other",
}


def render_fault_campaign() -> str:
    """The fault campaign through the CLI (bench/fault_campaign.py): per class, cases and their outcomes, then
    every case against the promise with its command."""
    rec = record("fault-campaign")
    classes = rec["classes"]
    rows = []
    for name, c in classes.items():
        if c.get("skipped"):  # cases not run, with the first one's reason (a tmpfs not permitted, say)
            label = f"{name} ({'skipped' if not c['cases'] else 'some not run'}: {c['skipped']})"
        else:
            label = name
        rows.append([label, str(c["cases"]), *[str(c.get(o, 0)) for o in FAULT_CAMPAIGN_COLUMNS]])
    rows.append(
        [
            "**all**",
            str(sum(c["cases"] for c in classes.values())),
            *[str(sum(c.get(o, 0) for c in classes.values())) for o in FAULT_CAMPAIGN_COLUMNS],
        ]
    )
    mode = "every case" if rec.get("mode") == "full" else "the quick selection (`--quick`: a few cases per class)"
    text = (
        table(["class", "cases", *FAULT_CAMPAIGN_COLUMNS.values()], rows)
        + f"\n\n`{rec['command']}`: {mode}, {_minutes(rec.get('seconds'))}, measured {rec['measured']} on "
        f"{rec['machine']}."
    )
    bad = [c for c in rec.get("cases", []) if c["outcome"] in ("traceback", "silent-wrong", "lost", "other")]
    if bad:
        text += "\n\nCases against the promise:\n\n" + "\n".join(
            f"- {c['klass']}, {c['name']}: **{c['outcome']}**, {c['detail']}" for c in bad
        )
    return text


def render_mcvl_benchmark() -> str:
    """MCVL at its Sec. IV-B scale (pipelines/mcvl_benchmark.py): Table II per test sequence and filter setting."""
    rec = record("mcvl-benchmark")
    rows = [
        [
            seq,
            run,
            f"{v['retrieval_mean_m']:.1f}",
            f"{v['retrieval_median_m']:.1f}",
            f"{v['filter_mean_m']:.1f}",
            f"{v['filter_median_m']:.1f}",
        ]
        for run, seqs in rec["localize"].items()
        for seq, v in seqs.items()
    ]
    return (
        table(
            [
                "test sequence",
                "filter settings",
                "retrieval mean m",
                "retrieval median m",
                "filter mean m",
                "filter median m",
            ],
            rows,
        )
        + f"\n\nOne run (seed {rec.get('seed', 7)}) of `{rec['command']}`, measured {rec['measured']} on "
        f"{rec['machine']}."
    )


#: the band the outside localizer is held to, and by how many points it may trail mapkit's localizer there, on the
#: clear drive
OUTSIDE_BAND, OUTSIDE_POINTS, OUTSIDE_CONDITION = "0.5m_5deg", 5.0, "day-clear"


def render_outside_localizer() -> str:
    """The outside localizers (COLMAP's image registrator, hloc) beside mapkit's 6-DoF localizer on one benchmark
    export, per condition."""
    rec = record("outside-localizer")
    hloc_px = rec["localizers"].get("hloc-4px", {}).get("ransac_px", 4)
    names = {
        "mapkit": "mapkit (`--localizer mapkit`)",
        "mapkit-unguided": "mapkit, no guided matching (`guided_radii_px: []`)",
        "colmap": "COLMAP image registrator (`--localizer colmap`)",
        "colmap-same-acceptance": "COLMAP image registrator, mapkit's acceptance",
        "hloc": "hloc localize_sfm (its re-triangulation, model's SIFT, NN-ratio)",
        "hloc-4px": f"hloc localize_sfm, mapkit's {hloc_px:g} px RANSAC",
    }
    rows = []
    for key, loc in rec["localizers"].items():
        for cond, s in [*loc["conditions"].items(), ("all", loc["overall"])]:
            r = s["recall"]
            rows.append(
                [
                    names[key],
                    cond,
                    str(s["queries"]),
                    *(f"{100 * r[b]:.1f} %" for b in ("0.25m_2deg", "0.5m_5deg", "5m_10deg")),
                    "-" if s["median_translation_m"] is None else f"{s['median_translation_m']:.3f}",
                    "-" if s["median_rotation_deg"] is None else f"{s['median_rotation_deg']:.2f}",
                    f"{1000 * loc['seconds_per_query']:.0f}",
                ]
            )
    gaps = []
    for other in [k for k in rec["localizers"] if k.startswith(("colmap", "hloc"))]:
        for cond in [c for c in rec["localizers"]["mapkit"]["conditions"] if c == OUTSIDE_CONDITION]:
            ours, theirs = (rec["localizers"][k]["conditions"][cond]["recall"][OUTSIDE_BAND] for k in ("mapkit", other))
            gap = 100 * (ours - theirs)
            verdict = "holds" if gap <= OUTSIDE_POINTS else "does not hold"
            gaps.append(
                f"{names[other]}, {cond}: {abs(gap):.1f} points {'below' if gap > 0 else 'above or level'} ({verdict})"
            )
    return (
        table(
            [
                "localizer",
                "condition",
                "queries",
                "(0.25 m, 2 deg)",
                "(0.5 m, 5 deg)",
                "(5 m, 10 deg)",
                "median m",
                "median deg",
                "ms/query",
            ],
            rows,
        )
        + f"\n\nAt (0.5 m, 5 deg) on the {OUTSIDE_CONDITION} drive, the outside localizers against mapkit's "
        f"localizer (goal: at most {OUTSIDE_POINTS:.0f} points below): {'; '.join(gaps)}. COLMAP's registrator "
        "with mapkit's acceptance: RANSAC "
        f"{rec.get('same_acceptance', {}).get('abs_pose_max_error_px', '-')} px, "
        f"{rec.get('same_acceptance', {}).get('abs_pose_min_num_inliers', '-')} inliers, their share of the 2D-3D "
        f"matches at least {rec.get('same_acceptance', {}).get('abs_pose_min_inlier_ratio', '-')} (COLMAP's default: "
        "0.25). Reference model "
        f"of {rec['database_images']} database images and {rec['points3D']} points; one run of `{rec['command']}` on "
        f"the main job's workspace, measured {rec['measured']} on {rec['machine']}." + _hloc_note(rec)
    )


def render_outside_localizer_towns() -> str:
    """The clear drive's share within (0.5 m, 5 deg) of mapkit's localizer and COLMAP's registrator on each town's
    export, and the gap the goal bounds."""
    rec = record("outside-localizer-towns")
    rows = []
    for town in sorted(rec["towns"], key=lambda t: t.get("town_seed") or 0):
        locs = town["localizers"]

        def cell(key: str, town_locs: dict = locs) -> str:
            s = town_locs[key]["conditions"][OUTSIDE_CONDITION]
            m = s["median_translation_m"]
            return f"{100 * s['recall'][OUTSIDE_BAND]:.1f} % ({'-' if m is None else f'{m:.3f} m'})"

        gap = 100 * (
            locs["mapkit"]["conditions"][OUTSIDE_CONDITION]["recall"][OUTSIDE_BAND]
            - locs["colmap-same-acceptance"]["conditions"][OUTSIDE_CONDITION]["recall"][OUTSIDE_BAND]
        )
        rows.append(
            [
                str(town.get("town_seed", "-")),
                str(locs["mapkit"]["conditions"][OUTSIDE_CONDITION]["queries"]),
                cell("mapkit"),
                cell("colmap-same-acceptance"),
                cell("colmap"),
                f"{gap:.1f} ({'holds' if gap <= OUTSIDE_POINTS else 'does not hold'})",
            ]
        )
    return (
        table(
            [
                "town (seed)",
                "queries",
                "mapkit",
                "COLMAP, mapkit's acceptance",
                "COLMAP, its own acceptance",
                f"points below mapkit (goal: at most {OUTSIDE_POINTS:.0f})",
            ],
            rows,
        )
        + f"\n\nThe {OUTSIDE_CONDITION} drive's share within (0.5 m, 5 deg) and, in brackets, its median error; one "
        f"run of `{rec['command']}` per town on the main job's workspace (`--sixdof --seed S`), measured "
        f"{rec['measured']} on {rec['machine']}."
    )


def _hloc_note(rec: dict) -> str:
    """What the outside-localizer record's hloc rows stand on: its model, its fallback poses, its timing."""
    if "hloc" not in rec:
        return ""
    h, locs = rec["hloc"], rec["localizers"]
    failed = "; ".join(
        f"{locs[k]['pnp_failed']['overall']} of {locs[k]['overall']['queries']} at {locs[k]['ransac_px']:g} px ("
        + ", ".join(f"{n} {c}" for c, n in locs[k]["pnp_failed"]["conditions"].items())
        + ")"
        for k in ("hloc", "hloc-4px")
        if k in locs
    )
    database = ("extract_database", "pairs_from_poses", "match_database", "triangulation")
    return (
        f" hloc {h['hloc']} (pycolmap {h['pycolmap']}) re-triangulates the model with its own SIFT features, given "
        f"the model's settings: {h['points3D']} points. Where its PnP fails, localize_sfm writes the pose of the top "
        f"retrieved database image, scored here as its estimate: {failed}. Its ms/query are the queries' features, "
        f"the matching of their retrieval pairs and localize_sfm; the database's features, their matching and the "
        f"re-triangulation took {sum(h['seconds'][k] for k in database):.0f} s."
    )


def _unit_costs(run: dict) -> dict[str, tuple[str, float | None]]:
    """Per-unit wall seconds of one places run: (unit, seconds per unit) per stage."""
    u = run.get("units") or {}

    def per(seconds: float | None, n: float | None) -> float | None:
        return seconds / n if seconds is not None and n else None

    return {
        "odometry (kiss-icp)": ("LiDAR scan", per(u.get("trajectory_s"), u.get("scans"))),
        "semi-dense mapping": ("keyframe", per(u.get("semidense_s"), u.get("keyframes"))),
        "image database": ("image", per(u.get("imagedb_s"), u.get("images"))),
        "ICP of a submap pair": ("pair", per(u.get("registering_s"), u.get("pairs_registered"))),
        "triplets": ("triplet", per(u.get("triplets_s"), u.get("triplets"))),
        "VLAD encoding (2 workers, wall)": ("image", per(u.get("vlad_encode_s"), u.get("vlad_images"))),
        "NBLD describing (2 workers, wall)": ("patch", per(u.get("nbld_describe_s"), u.get("nbld_patches"))),
        "M2DP describing (2 workers, wall)": ("patch", per(u.get("m2dp_describe_s"), u.get("m2dp_patches"))),
        "map density": ("metre driven (points)", per(u.get("map_points"), u.get("driven_m"))),
    }


def render_scaling_units() -> str:
    pl = record("places")
    runs = pl["runs"]
    costs = [_unit_costs(r) for r in runs]
    rows = [[stage, unit, spread([c[stage][1] for c in costs], "{:.3g}")] for stage, (unit, _) in costs[0].items()]
    return (
        table(["stage", "unit", "seconds (points) per unit"], rows)
        + "\n\nFrom the places runs' timings.json and metrics: "
        + _runs_note(pl)
    )


def render_scaling_projection() -> str:
    """The city job of docs/scaling.md from the places runs' per-unit costs: CPU hours per stage and the
    wall time on 512 cores (eta = 0.8) and on 2 cores."""
    pl = record("places")
    med = {
        k: statistics.median([c[k][1] for c in map(_unit_costs, pl["runs"]) if c[k][1] is not None] or [0.0])
        for k in _unit_costs(pl["runs"][0])
    }
    n = {
        "odometry (kiss-icp)": 2.19e6,
        "semi-dense mapping": 1.0e6,
        "image database": 1.0e6,
        "ICP of a submap pair": 1.0e6,
        "triplets": 2.0e4,
        "VLAD encoding (2 workers, wall)": 1.0e6,
    }
    rho = med["map density"]
    n["NBLD describing (2 workers, wall)"] = n["M2DP describing (2 workers, wall)"] = rho * 1.0e6 / 20
    workers = {k: 2.0 if "2 workers" in k else 1.0 for k in n}
    rows, total = [], 0.0
    for k, units in n.items():
        cpu_h = units * med[k] * workers[k] / 3600
        total += cpu_h
        rows.append([k, f"{units:.3g}", f"{cpu_h:,.0f}", f"{cpu_h / (0.8 * 512):.1f}", f"{cpu_h / 2 / 24:,.0f}"])
    rows.append(
        [
            "**all per-unit stages**",
            "",
            f"**{total:,.0f}**",
            f"**{total / (0.8 * 512):.1f}**",
            f"**{total / 2 / 24:,.0f}**",
        ]
    )
    return (
        table(["stage", "units n", "CPU hours", "wall hours on 512 cores", "wall days on 2 cores"], rows)
        + "\n\nPer-unit costs: the medians of the table above; rho (map points a metre) from the same runs; "
        "the global steps below come on top."
    )


def _maybe(name: str) -> dict | None:
    return json.loads((RESULTS / f"{name}.json").read_text()) if (RESULTS / f"{name}.json").is_file() else None


RENDERERS: dict[str, Callable[[], str]] = {
    "claims": render_claims,
    "places-auc": render_places_auc,
    "places-mcvl": render_places_mcvl,
    "maps": render_maps,
    "align": render_align,
    "triplets": render_triplets,
    "references": render_references,
    "first-run": render_first_run,
    "main-job-stages": lambda: _stages("main-job"),
    "main-job-sixdof": render_sixdof,
    "demo-snowy-sixdof": lambda: render_sixdof("demo-snowy-6dof"),
    "main-job-places-by-source": render_places_by_source,
    "align-sources": render_align_sources,
    "lidar-dynamic": render_lidar_dynamic,
    "sixdof-thresholds": render_sixdof_thresholds,
    "tiny-stages": lambda: _stages("tiny"),
    "places-stages": lambda: _stages("places"),
    "robustness": render_robustness,
    "fault-campaign": render_fault_campaign,
    "benchmarks": render_benchmarks,
    "mcvl-benchmark": render_mcvl_benchmark,
    "outside-localizer": render_outside_localizer,
    "outside-localizer-towns": render_outside_localizer_towns,
    "scaling-units": render_scaling_units,
    "scaling-projection": render_scaling_projection,
}


# --------------------------------------------------------------------------- pages


def blocks(text: str) -> list[tuple[str, str]]:
    """(name, body) of every figures block of a page."""
    return [(m.group("name"), m.group("body")) for m in BLOCK.finditer(text)]


def fill(text: str, render: Callable[[str], str | None]) -> str:
    """Each block's body replaced by its rendering; a block whose rendering is None keeps its body."""

    def one(m: re.Match) -> str:
        body = render(m.group("name"))
        return m.group(0) if body is None else m.group(1) + body.rstrip("\n") + "\n" + m.group(4)

    return BLOCK.sub(one, text)


def _rendered() -> Callable[[str], str]:
    cache: dict[str, str] = {}

    def render(name: str) -> str:
        if name not in RENDERERS:
            raise SystemExit(f"no renderer for figures block {name!r}; known: {', '.join(sorted(RENDERERS))}")
        if name not in cache:
            cache[name] = RENDERERS[name]()
        return cache[name]

    return render


def render_pages(pages: list[Path] = PAGES) -> list[Path]:
    """Fill every block; returns the pages that changed. A block whose record is missing keeps its text,
    with one line saying so (``check`` still fails on it)."""
    rendered, changed, missing = _rendered(), [], set()

    def render(name: str) -> str | None:
        try:
            return rendered(name)
        except SystemExit as why:
            if str(why) not in missing:
                missing.add(str(why))
                print(f"kept as it is: {why}", file=sys.stderr)
            return None

    for page in pages:
        text = page.read_text()
        new = fill(text, render)
        if new != text:
            page.write_text(new)
            changed.append(page)
    return changed


def check_pages(pages: list[Path] = PAGES) -> list[str]:
    """Blocks whose text is not their rendering from today's records ("page: block")."""
    render, stale = _rendered(), []
    for page in pages:
        text = page.read_text()
        for name, body in blocks(text):
            if body.rstrip("\n") != render(name).rstrip("\n"):
                stale.append(f"{page.relative_to(ROOT)}: {name}")
    return stale


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect", help="write docs/results/NAME.json from run folders (or a JSON file)")
    c.add_argument("name")
    c.add_argument("sources", nargs="+", type=Path)
    c.add_argument("--command", default="", help="the command that made each run, as the docs should show it")
    c.add_argument("--note", default="", help="how the runs were made, as a reader should know it")
    c.add_argument(
        "--update",
        action="store_true",
        help="benchmarks only: replace the record's entries of the benchmarks this report ran (bench/run_all.py "
        "--only ...), each dated, and keep the others",
    )
    sub.add_parser("render", help="fill every figures block of README.md and docs/")
    sub.add_parser("check", help="exit 1 when a block is not its rendering")
    cmp_ = sub.add_parser("compare", help="a fresh run's figures beside a record's spread")
    cmp_.add_argument("name")
    cmp_.add_argument("run", type=Path)
    a = ap.parse_args(argv)
    if a.cmd == "collect" and a.update:
        print(update_benchmarks(a.sources[0]))
    elif a.cmd == "collect":
        print(collect(a.name, a.sources, a.command, a.note))
    elif a.cmd == "render":
        for p in render_pages():
            print(f"rendered {p.relative_to(ROOT)}")
    elif a.cmd == "check":
        stale = check_pages()
        for s in stale:
            print(f"stale: {s} (python3 docs/figures.py render)")
        return 1 if stale else 0
    elif a.cmd == "compare":
        return compare(a.name, a.run)
    return 0


def compare(name: str, run: Path) -> int:
    """Print a fresh run's headline figures beside the record's range; exit 1 if one lies outside it."""
    rec, new = record(name), extract_run(run)
    rows, outside = [], 0

    def check(label: str, values: list[float | None], value: float | None) -> None:
        nonlocal outside
        vals = [v for v in values if v is not None]
        if not vals or value is None:
            return
        inside = min(vals) <= value <= max(vals)
        outside += not inside
        rows.append([label, spread(vals), f"{value:.3f}", "yes" if inside else "**no**"])

    for m in METHODS:
        check(f"mean held-out AUC {METHODS[m]}", [_mean_auc(r, m) for r in rec["runs"]], _mean_auc(new, m))
    for n in new["maps"]:
        check(
            f"{n} map median m", [r["maps"].get(n, {}).get("median_m") for r in rec["runs"]], new["maps"][n]["median_m"]
        )
    print(table(["figure", "record", "this run", "within the record's range"], rows))
    return 1 if outside else 0


if __name__ == "__main__":
    sys.exit(main())
