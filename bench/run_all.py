"""Run every benchmark under bench/ and write one Markdown table of them (and the raw results as JSON).

Each ``bench_*.py`` runs in its own subprocess, one after the other (the machine's cores are
shared: two benchmarks at once would each measure the other), under a timeout. A benchmark that
fails or times out is reported as such and the others go on. Benchmarks are never part of the
test suite's pass/fail; this runner always exits 0 once the report is written.

Quick mode (``--quick``): a benchmark with its own ``--quick`` flag gets it; the others get the
small-run flags of ``QUICK_ARGS`` below (their own options: fewer patches, repeats, frames); a
benchmark in neither runs in full. A benchmark with a positional ``workspace`` argument gets
``--workspace`` (an aligned workspace, default runs/main/workspace: the main job's) and is skipped when it is absent,
or when it lacks the file the benchmark names in a module-level ``WORKSPACE_NEEDS`` (a path inside the workspace: a
reference model, which only the main job with ``--sixdof`` builds).

The table, one row per benchmark:

- *what is measured*: the first sentence of the benchmark's docstring;
- *mapkit*, *baseline*, *ratio*: the headline the benchmark declares
  (``bench.common.report(..., headline=...)``), else the figures that ``HEADLINES`` below picks
  from the tables it printed (the ``BENCH_JSON`` lines of ``bench.common.report``) and its JSON
  summary, else the last line of its output that names a ratio or a speed-up, else the first
  ratio-like column (``ratio``, ``speed-up``, ``x_...``) of its first table that has one;
- *wall*: the subprocess's wall time; *status*: ok, failed (with the last line of its error
  output), timed out, or skipped (with the reason).

The raw results (command, exit code, times, every table and JSON line the benchmark printed, the
tail of its output) go to a JSON file next to the Markdown. Run from the repository root, under
``nice`` on a shared machine::

    nice -n 5 python3 bench/run_all.py --out bench-report.md --quick
    python3 bench/run_all.py --out bench-report.md --only descriptors3d mcl
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_WORKSPACE = ROOT / "runs" / "main" / "workspace"  # what the README's main job writes
JSON_PREFIX = "BENCH_JSON "
TAIL_LINES = 40  # lines of stdout / stderr kept in the JSON

#: Small runs through the benchmarks' own options, for those without a ``--quick`` flag.
QUICK_ARGS: dict[str, list[str]] = {
    "bench_align": ["--sessions", "2,3"],
    "bench_cnn": ["--steps", "2", "--naive", "10", "--patches", "256", "--repeat", "1"],
    "bench_dsift": ["--repeat", "1", "--skip-opencv-full", "--opencv-per-scale", "200", "--faiss-db", "20000"],
    "bench_executor": ["--images", "20"],
    "bench_mcl": ["--steps", "50", "--loop-steps", "1", "--repeat", "2"],
    "bench_semidense": ["--frames", "8", "--repeat", "1", "--naive", "40"],
    "bench_sixdof": ["--fast"],
    "bench_structure_index": [
        "--db-size",
        "100000",
        "--repeat",
        "1",
        "--patches-nbld",
        "300",
        "--patches-m2dp",
        "100",
        "--frames",
        "20",
        "--timed-frames",
        "5",
        "--tree-frames",
        "1",
    ],
    "bench_synth": ["--frames", "4", "--repeat", "1", "--skip-demo"],
    "bench_triplets": ["--n", "300"],
    "bench_vlad_query": [
        "--n",
        "20000",
        "--queries",
        "50",
        "--nlist",
        "128",
        "--train",
        "5000",
        "--single-flat-queries",
        "10",
        "--skip-pq",
    ],
}


# --- what a benchmark printed ---------------------------------------------------------------------------


@dataclass
class Printed:
    """The machine-readable part of a benchmark's output."""

    tables: list[dict] = field(default_factory=list)  # BENCH_JSON records of bench.common.report
    objects: list[dict] = field(default_factory=list)  # other JSON objects printed on a line of their own
    lines: list[str] = field(default_factory=list)  # every stdout line

    def table(self, prefix: str) -> list[dict]:
        """Rows of the first table whose name starts with ``prefix``."""
        return next(t["rows"] for t in self.tables if str(t.get("bench", "")).startswith(prefix))

    def note(self, prefix: str) -> str:
        return next(str(t.get("note", "")) for t in self.tables if str(t.get("bench", "")).startswith(prefix))

    def obj(self, key: str, value: str) -> dict:
        """The first JSON object (table records included) with ``obj[key] == value``."""
        return next(o for o in self.objects + self.tables if o.get(key) == value)


def parse_output(stdout: str) -> Printed:
    out = Printed(lines=stdout.splitlines())
    for line in out.lines:
        text = line.strip()
        is_table = text.startswith(JSON_PREFIX)
        if is_table:
            text = text[len(JSON_PREFIX) :]
        if not (text.startswith("{") and text.endswith("}")):
            continue
        try:
            rec = json.loads(text)
        except json.JSONDecodeError:
            continue
        if not isinstance(rec, dict):
            continue
        (out.tables if is_table and "rows" in rec else out.objects).append(rec)
    return out


_RATIO_WORDS = re.compile(r"ratio|speed-?up|\bx\d|\d\s*x\b|\d(\.\d+)?x\b", re.IGNORECASE)


def generic_ratio_line(printed: Printed) -> str | None:
    """The last plain-text output line that names a ratio or a speed-up (tables and JSON left out)."""
    for line in reversed(printed.lines):
        text = line.strip()
        if text and not text.startswith(("|", "{", JSON_PREFIX.strip())) and _RATIO_WORDS.search(text):
            return text if len(text) <= 160 else text[:157] + "..."
    return None


_RATIO_COLUMN = re.compile(r"ratio|speed.?up|speed_vs|_vs_|^x_", re.IGNORECASE)


def generic_ratio_column(printed: Printed) -> str | None:
    """``column: label value; ...`` of the first table with a ratio-like numeric column."""
    for t in printed.tables:
        rows = t.get("rows") or []
        keys = list(rows[0]) if rows and isinstance(rows[0], dict) else []
        for k in keys[1:]:
            vals = [
                (r.get(keys[0]), r.get(k))
                for r in rows
                if isinstance(r.get(k), (int, float)) and not isinstance(r.get(k), bool)
            ]
            if _RATIO_COLUMN.search(k) and vals:
                text = f"{k}: " + "; ".join(f"{label} {_f(v)}" for label, v in vals)
                return text if len(text) <= 160 else text[:157] + "..."
    return None


# --- headline figures of the benchmarks that do not declare one ------------------------------------------


def _f(v: float, digits: int = 3) -> str:
    return f"{v:.{digits}g}"


def _align(p: Printed) -> tuple[str, str, str]:
    rows = p.obj("benchmark", "align")["rows"]
    a, b = rows[0], rows[-1]
    return (
        f"{_f(b['pairs_per_s'])} submap pairs/s; {a['sessions']} -> {b['sessions']} sessions: time "
        f"x{_f(b['time_ratio'])}",
        f"overlapping pairs x{_f(b['pairs_ratio'])}, sessions^2 x{_f(b['quadratic_ratio'])}",
        f"{_f(b['time_ratio'] / b['pairs_ratio'])} (time growth / pair growth)",
    )


def _build(p: Printed) -> tuple[str, str, str]:
    rows = p.table("kiss-icp inside mapkit")
    mk = next(r for r in rows if r["what"].startswith("mapkit trajectory"))
    base = next(r for r in rows if r["what"].startswith("kiss-icp alone"))
    rtf = re.search(r"real-time factor ([\d.]+)", p.note("build real-time factor"))
    return (
        f"trajectory stage {_f(mk['seconds'])} s ({mk['scans']} scans)"
        + (f"; build real-time factor {rtf.group(1)}" if rtf else ""),
        f"kiss-icp alone {_f(base['seconds'])} s",
        f"{mk['ratio']:.3f} (time)",
    )


def _cnn(p: Printed) -> tuple[str, str, str]:
    train, desc = p.table("Training throughput"), p.table("Describe throughput")
    return (
        f"train {_f(train[0]['triplets_per_s_wall'])} triplets/s; describe {_f(desc[0]['patches_per_s_wall'])} "
        "patches/s (ONNX)",
        f"one triplet per step {_f(train[1]['triplets_per_s_wall'])}/s; torch eager "
        f"{_f(desc[1]['patches_per_s_wall'])}/s",
        f"{_f(train[0]['speedup_vs_naive_wall'])} / {_f(desc[0]['speedup_vs_torch_wall'])}",
    )


def _dsift(p: Printed) -> tuple[str, str, str]:
    s = p.obj("bench", "dsift_vlad_encode")
    return (
        f"dense SIFT {_f(s['dense_sift_s'])} s/image; encode {_f(s['encode_s'])} s",
        f"OpenCV SIFT on the same grid {_f(s['opencv_full_estimate_s'])} s/image (estimate)",
        f"{s['opencv_per_descriptor_ratio']:.0f} (per descriptor)",
    )


def _mcap_read(p: Printed) -> tuple[str, str, str]:
    rows = p.table("MCAP read")
    mk = next(r for r in rows if r["mode"] == "mapkit-nocrc" and r["log"] == "full")
    base = next(r for r in rows if r["mode"] == "mcap-decoded" and r["log"] == "full")
    return (
        f"{_f(mk['wall_s'])} s to read the log (no CRC)",
        f"bare mcap decoding {_f(base['wall_s'])} s",
        f"{mk['x_mcap_decoded']:.2f} (time)",
    )


def _mcl(p: Printed) -> tuple[str, str, str]:
    rows = p.table("mcl")
    return (
        f"{_f(rows[0]['cpu_ms_per_call'])} ms CPU per step, 1,000 particles",
        f"per-particle loop {_f(rows[1]['cpu_ms_per_call'])} ms",
        f"{rows[0]['speedup_vs_loop_cpu']:.0f} (speed-up)",
    )


def _semidense(p: Printed) -> tuple[str, str, str]:
    rows = p.table("semi-dense mapping")
    naive = next(r for r in rows if r["method"].startswith("naive"))
    return (
        f"{_f(rows[0]['keyframes_per_s'])} keyframes/s end to end",
        f"naive per-pixel loop {_f(naive['keyframes_per_s'])} keyframes/s",
        f"{naive['time_vs_map_keyframe']:.0f} (speed-up of map_keyframe)",
    )


def _structure_index(p: Printed) -> tuple[str, str, str]:
    s = p.obj("bench", "structure_index")
    d = ", ".join(f"{r['descriptor']} {_f(r['patches_per_s_cpu'])}" for r in s["describe"])
    q = s["query"]
    return (
        f"describe() {d} patches/s; query {_f(q[0]['ms_per_frame_cpu'])} ms/frame ({q[0]['db_descriptors']} "
        "descriptors)",
        f"cKDTree {_f(q[2]['ms_per_frame_cpu'])} ms/frame",
        f"{_f(s['checks']['ratio_cKDTree_over_faiss_per_frame_cpu'])} (query speed-up)",
    )


def _synth(p: Printed) -> tuple[str, str, str]:
    rows = p.table("Synthetic town: camera frames")

    def mean(k):
        return sum(r[k] for r in rows) / len(rows)

    return (
        f"{_f(mean('fps_camera_plus_lidar'))} frames/s with their LiDAR sweep",
        f"bare ray casts {_f(mean('fps_bare_ray_casts'))} frames/s",
        f"{_f(mean('shading_cost_ratio'))} (time with shading / bare)",
    )


def _triplets(p: Printed) -> tuple[str, str, str]:
    s = p.obj("benchmark", "triplets")
    return (
        f"{_f(s['mapkit']['triplets_per_s'])} triplets/s",
        f"per-place ICP {_f(s['baseline']['triplets_per_s'])} triplets/s",
        f"{s['ratio']:.2f} (speed-up)",
    )


def _vlad_query(p: Printed) -> tuple[str, str, str]:
    s = p.obj("bench", "vlad_query")
    best = s["best_meeting_goal"] or {}
    return (
        (
            f"{best['index']}: {_f(best['single_ms'])} ms/query, recall@20 {best['recall@20']:.3f}"
            if best
            else "no index under the goal"
        )
        + f" ({s['n']} x {s['dim']}-D)",
        f"exact flat {_f(s['flat_single_ms'])} ms/query",
        f"{_f(best['speedup_vs_flat'])} (speed-up)" if best else "",
    )


HEADLINES: dict[str, Callable[[Printed], tuple[str, str, str]]] = {
    "bench_align": _align,
    "bench_build": _build,
    "bench_cnn": _cnn,
    "bench_dsift": _dsift,
    "bench_mcap_read": _mcap_read,
    "bench_mcl": _mcl,
    "bench_semidense": _semidense,
    "bench_structure_index": _structure_index,
    "bench_synth": _synth,
    "bench_triplets": _triplets,
    "bench_vlad_query": _vlad_query,
}


def headline(name: str, printed: Printed) -> dict:
    """``{"mapkit", "baseline", "ratio", "source"}`` of a benchmark's output (empty strings if none)."""
    declared = [t["headline"] for t in printed.tables if isinstance(t.get("headline"), dict)]
    if declared:
        h = declared[0]
        return {
            "mapkit": h.get("mapkit", ""),
            "baseline": h.get("baseline", ""),
            "ratio": h.get("ratio", ""),
            "source": "declared",
        }
    pick = HEADLINES.get(name)
    if pick is not None:
        try:
            mk, base, ratio = pick(printed)
            return {"mapkit": mk, "baseline": base, "ratio": ratio, "source": "run_all"}
        except (StopIteration, KeyError, IndexError, TypeError, ValueError, ZeroDivisionError, AttributeError):
            pass  # the output changed shape: fall back to the text
    line = generic_ratio_line(printed)
    if line:
        return {"mapkit": "", "baseline": "", "ratio": line, "source": "text"}
    column = generic_ratio_column(printed)
    return {"mapkit": "", "baseline": "", "ratio": column or "", "source": "table" if column else "none"}


# --- running ---------------------------------------------------------------------------------------------


@dataclass
class BenchSpec:
    name: str
    path: Path
    what: str
    has_quick: bool
    positionals: list[str]
    workspace_needs: str | None = None  # a file inside the workspace, without which the benchmark has nothing to time


@dataclass
class BenchResult:
    name: str
    what: str
    command: list[str]
    status: str  # ok | failed | timed out | skipped
    detail: str = ""
    returncode: int | None = None
    wall_s: float = 0.0
    mapkit: str = ""
    baseline: str = ""
    ratio: str = ""
    headline_source: str = ""
    tables: list[dict] = field(default_factory=list)
    objects: list[dict] = field(default_factory=list)
    stdout_tail: list[str] = field(default_factory=list)
    stderr_tail: list[str] = field(default_factory=list)


def inspect_bench(path: Path) -> BenchSpec:
    """Docstring's first line, whether it takes ``--quick``, its positional arguments; read, not imported."""
    tree = ast.parse(path.read_text(), filename=str(path))
    doc = (ast.get_docstring(tree) or "").strip()
    options, positionals = set(), []
    needs = None
    for node in tree.body:
        if (
            isinstance(node, ast.Assign)
            and any(isinstance(t, ast.Name) and t.id == "WORKSPACE_NEEDS" for t in node.targets)
            and isinstance(node.value, ast.Constant)
            and isinstance(node.value.value, str)
        ):
            needs = node.value.value
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "add_argument"
            and node.args
        ):
            first = node.args[0]
            if isinstance(first, ast.Constant) and isinstance(first.value, str):
                (options.add(first.value) if first.value.startswith("-") else positionals.append(first.value))
    return BenchSpec(path.stem, path, _first_sentence(doc), "--quick" in options, positionals, needs)


def _first_sentence(doc: str, limit: int = 160) -> str:
    """The docstring's first paragraph (its first sentence if that is long), RST literals as Markdown ones."""
    text = " ".join(doc.split("\n\n")[0].split()).replace("``", "`")
    if len(text) > limit:
        end = re.search(r"(?<!Sec)(?<!Fig)(?<!e\.g)(?<!i\.e)\. [A-Z]", text)
        text = text[: end.start() + 1] if end else text
    return text if len(text) <= limit else text[: limit - 3] + "..."


def discover(bench_dir: Path, only: list[str] | None = None) -> list[BenchSpec]:
    paths = sorted(bench_dir.glob("bench_*.py"))
    if only:
        wanted = {n.removesuffix(".py").removeprefix("bench_") for n in only}
        unknown = wanted - {p.stem.removeprefix("bench_") for p in paths}
        if unknown:
            raise SystemExit(f"error: no benchmark named {', '.join(sorted(unknown))} in {bench_dir}")
        paths = [p for p in paths if p.stem.removeprefix("bench_") in wanted]
    return [inspect_bench(p) for p in paths]


def command_for(spec: BenchSpec, quick: bool, workspace: Path) -> tuple[list[str], str | None]:
    """The command line of a benchmark, or the reason it cannot run."""
    cmd = [sys.executable, str(spec.path)]
    for pos in spec.positionals:
        if pos != "workspace":
            return cmd, f"needs the positional argument {pos!r}"
        if not workspace.is_dir():
            return cmd, f"no workspace at {workspace}"
        if spec.workspace_needs and not (workspace / spec.workspace_needs).is_file():
            return cmd, f"no {spec.workspace_needs} in {workspace}"
        cmd.append(str(workspace))
    if quick:
        cmd += ["--quick"] if spec.has_quick else QUICK_ARGS.get(spec.name, [])
    return cmd, None


def shown(cmd: list[str]) -> list[str]:
    """A command as the report records it: the interpreter as ``python`` and paths relative to the checkout (or
    beside it), so that the report names no folder of the machine it ran on."""
    out = ["python"]
    for arg in cmd[1:]:
        p = Path(arg)
        if p.is_absolute():
            for base, prefix in ((ROOT, ""), (ROOT.parent, "../")):
                if p.is_relative_to(base):
                    arg = prefix + str(p.relative_to(base))
                    break
        out.append(arg)
    return out


def run_one(spec: BenchSpec, quick: bool, workspace: Path, timeout_s: float) -> BenchResult:
    cmd, why_not = command_for(spec, quick, workspace)
    res = BenchResult(spec.name, spec.what, shown(cmd), "skipped", why_not or "")
    if why_not:
        return res
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    t0 = time.perf_counter()
    # its own session, so that a timeout ends the benchmark's children (workers, fresh processes) too
    proc = subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        stdout, stderr = proc.communicate(timeout=timeout_s)
        timed_out = False
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        stdout, stderr = proc.communicate()
        timed_out = True
    res.wall_s = time.perf_counter() - t0
    res.returncode = proc.returncode
    printed = parse_output(stdout)
    h = headline(spec.name, printed)
    res.mapkit, res.baseline, res.ratio, res.headline_source = h["mapkit"], h["baseline"], h["ratio"], h["source"]
    res.tables, res.objects = printed.tables, printed.objects
    res.stdout_tail, res.stderr_tail = stdout.splitlines()[-TAIL_LINES:], stderr.splitlines()[-TAIL_LINES:]
    if timed_out:
        res.status, res.detail = "timed out", f"after {timeout_s:.0f} s"
    elif proc.returncode != 0:
        last = [ln.strip() for ln in (stderr.splitlines() or stdout.splitlines()) if ln.strip()]
        res.status, res.detail = "failed", last[-1] if last else f"exit code {proc.returncode}"
    else:
        res.status = "ok"
    return res


# --- the report --------------------------------------------------------------------------------------------


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def markdown(results: list[BenchResult], quick: bool, started: str) -> str:
    lines = [
        "# Benchmarks",
        "",
        f"`python3 bench/run_all.py{' --quick' if quick else ''}`, started {started}, {os.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.1f} at the end. Each benchmark measures its baseline in the same run; "
        "the ratio is its own (what it divides is said in brackets). Raw results: the JSON file beside this one.",
        "",
        "| benchmark | what is measured | mapkit | baseline | ratio | wall (s) | status |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        status = r.status + (f": {r.detail}" if r.detail else "")
        wall = f"{r.wall_s:.0f}" if r.status != "skipped" else ""
        lines.append(
            "| "
            + " | ".join(
                _cell(c) for c in (r.name.removeprefix("bench_"), r.what, r.mapkit, r.baseline, r.ratio, wall, status)
            )
            + " |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=Path("bench-report.md"), help="Markdown report; the JSON goes beside it (.json)"
    )
    ap.add_argument("--quick", action="store_true", help="small runs: each benchmark's --quick, else its QUICK_ARGS")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="run only these (descriptors3d or bench_descriptors3d)")
    ap.add_argument(
        "--timeout", type=float, default=None, help="seconds per benchmark (default 900 with --quick, else 3600)"
    )
    ap.add_argument(
        "--workspace", type=Path, default=DEFAULT_WORKSPACE, help="aligned workspace for the benchmarks that take one"
    )
    ap.add_argument("--bench-dir", type=Path, default=BENCH_DIR, help="folder of the bench_*.py scripts")
    args = ap.parse_args(argv)
    timeout_s = args.timeout or (900.0 if args.quick else 3600.0)
    specs = discover(args.bench_dir, args.only)
    started = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    results = []
    for spec in specs:
        print(f"[run_all] {spec.name} ...", file=sys.stderr, flush=True)
        r = run_one(spec, args.quick, args.workspace, timeout_s)
        print(
            f"[run_all] {spec.name}: {r.status}{': ' + r.detail if r.detail else ''} ({r.wall_s:.0f} s)",
            file=sys.stderr,
            flush=True,
        )
        results.append(r)
        # written after every benchmark, so that an interrupted run keeps what it measured
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(markdown(results, args.quick, started))
        args.out.with_suffix(".json").write_text(
            json.dumps(
                {
                    "started": started,
                    "quick": args.quick,
                    "timeout_s": timeout_s,
                    "results": [asdict(x) for x in results],
                },
                indent=1,
                default=str,
            )
        )
    print(markdown(results, args.quick, started))
    return 0


if __name__ == "__main__":
    sys.exit(main())
