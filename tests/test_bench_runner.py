"""bench/run_all.py on a folder of fake benchmarks: one reports a ratio, one fails, one hangs."""

import importlib.util
import json
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench"

OK_BENCH = '''"""Fake speed of something, against a loop."""
import argparse, json
ap = argparse.ArgumentParser()
ap.add_argument("--quick", action="store_true")
args = ap.parse_args()
rows = [{"method": "mapkit", "per_s": 500.0}, {"method": "loop", "per_s": 200.0}]
print("| method | per_s |")
print("BENCH_JSON " + json.dumps({"bench": "fake", "rows": rows, "note": "",
      "headline": {"mapkit": "500 /s" + (" quick" if args.quick else ""), "baseline": "200 /s", "ratio": "2.50"}}))
'''

TEXT_BENCH = '''"""Fake figure printed as text only."""
print("mapkit 3 ms, loop 12 ms")
print("speed-up over the loop: 4.0x")
print("done")
'''

FAILING_BENCH = '''"""Fake benchmark that breaks."""
print("starting")
raise RuntimeError("boom: no data")
'''

HANGING_BENCH = '''"""Fake benchmark that never ends."""
import time
time.sleep(60)
'''


def _run_all():
    spec = importlib.util.spec_from_file_location("bench_run_all_under_test", BENCH / "run_all.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def test_run_all_reports_ratios_failures_and_timeouts(tmp_path):
    run_all = _run_all()
    benches = tmp_path / "benches"
    benches.mkdir()
    for name, text in (
        ("bench_fast", OK_BENCH),
        ("bench_text", TEXT_BENCH),
        ("bench_broken", FAILING_BENCH),
        ("bench_slow", HANGING_BENCH),
    ):
        (benches / f"{name}.py").write_text(text)
    (benches / "helper.py").write_text("raise SystemExit('not a benchmark')\n")
    out = tmp_path / "report" / "bench.md"
    assert run_all.main(["--bench-dir", str(benches), "--out", str(out), "--quick", "--timeout", "3"]) == 0

    raw = json.loads(out.with_suffix(".json").read_text())
    by_name = {r["name"]: r for r in raw["results"]}
    assert sorted(by_name) == ["bench_broken", "bench_fast", "bench_slow", "bench_text"]  # helper.py is not a benchmark
    fast, text, broken, slow = (by_name[n] for n in ("bench_fast", "bench_text", "bench_broken", "bench_slow"))
    assert fast["status"] == "ok" and fast["command"][-1] == "--quick"  # it declares --quick, so it gets it
    assert (fast["mapkit"], fast["baseline"], fast["ratio"]) == ("500 /s quick", "200 /s", "2.50")
    assert fast["tables"][0]["rows"][1]["per_s"] == 200.0
    assert (
        text["status"] == "ok"
        and text["ratio"] == "speed-up over the loop: 4.0x"
        and text["command"][-1].endswith("bench_text.py")
    )
    assert broken["status"] == "failed" and broken["returncode"] != 0
    assert broken["detail"] == "RuntimeError: boom: no data"
    assert slow["status"] == "timed out" and slow["wall_s"] < 30

    rows = [ln for ln in out.read_text().splitlines() if ln.startswith("| ") and not ln.startswith("| benchmark")]
    assert len(rows) == 4
    cells = {r.split(" | ")[0].lstrip("| "): [c.strip() for c in r.strip("|").split(" | ")] for r in rows}
    assert cells["fast"][1:5] == ["Fake speed of something, against a loop.", "500 /s quick", "200 /s", "2.50"]
    assert cells["fast"][-1] == "ok"
    assert cells["broken"][-1] == "failed: RuntimeError: boom: no data"
    assert cells["slow"][-1] == "timed out: after 3 s"

    # --only runs just the named ones, under either spelling
    run_all.main(["--bench-dir", str(benches), "--out", str(out), "--only", "fast", "bench_text.py"])
    assert [r["name"] for r in json.loads(out.with_suffix(".json").read_text())["results"]] == [
        "bench_fast",
        "bench_text",
    ]


def test_headline_falls_back_to_a_ratio_column():
    run_all = _run_all()
    rows = [{"method": "mapkit", "ms": 2.0, "speedup": 3.5}, {"method": "loop", "ms": 7.0, "speedup": 1.0}]
    printed = run_all.parse_output("some text\nBENCH_JSON " + json.dumps({"bench": "t", "rows": rows}) + "\ndone\n")
    h = run_all.headline("bench_unknown", printed)
    assert h["source"] == "table" and h["ratio"] == "speedup: mapkit 3.5; loop 1"


NEEDS_MODEL_BENCH = '''"""Fake benchmark of a workspace's reference model."""
import argparse, pathlib
WORKSPACE_NEEDS = "reference_model/sfm/images.bin"
ap = argparse.ArgumentParser()
ap.add_argument("workspace")
args = ap.parse_args()
print("measured", pathlib.Path(args.workspace).name)
print("ratio 1.5")
'''


def test_a_workspace_without_what_a_benchmark_needs_is_a_skip_not_a_failure(tmp_path):
    """A benchmark that names the file it needs (``WORKSPACE_NEEDS``) is skipped, with that file as its reason, on a
    workspace without it, and runs on one that has it."""
    run_all = _run_all()
    benches = tmp_path / "benches"
    benches.mkdir()
    (benches / "bench_model.py").write_text(NEEDS_MODEL_BENCH)
    ws = tmp_path / "ws"
    ws.mkdir()
    out = tmp_path / "bench.md"
    run_all.main(["--bench-dir", str(benches), "--out", str(out), "--workspace", str(ws)])
    (r,) = json.loads(out.with_suffix(".json").read_text())["results"]
    assert r["status"] == "skipped" and r["detail"] == f"no reference_model/sfm/images.bin in {ws}", r
    (ws / "reference_model" / "sfm").mkdir(parents=True)
    (ws / "reference_model" / "sfm" / "images.bin").write_bytes(b"")
    run_all.main(["--bench-dir", str(benches), "--out", str(out), "--workspace", str(ws)])
    (r,) = json.loads(out.with_suffix(".json").read_text())["results"]
    assert r["status"] == "ok" and r["ratio"] == "ratio 1.5", r
