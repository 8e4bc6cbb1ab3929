"""A newcomer's first run, timed: set-up, the main job and the tests from a fresh clone, as the README says.

    python3 bench/first_run.py [--out runs/first-run.json] [--skip-tests] [--keep]

Clones this checkout's HEAD into a temporary folder with ``../shared`` beside it (as CI does), then times
the README's commands there, one after the other, each as a whole process:

1. ``bash scripts/setup.sh`` with a new environment folder and empty pip and uv caches (nothing installed
   before; the package registry reachable);
2. ``.venv/bin/python pipelines/main.py --out runs/main`` (the main job on the demo preset);
3. ``.venv/bin/python -m pytest -q`` (the test command).

Writes the three times, the date and the machine as JSON, with the tests that failed if any
(``docs/figures.py collect first-run FILE`` turns it into the README's figures). Run it on a quiet
machine: the figure is what a newcomer waits, and a second job on 2 cores doubles it.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def timed(cmd: str, cwd: Path, env: dict, log: Path) -> tuple[float, int]:
    t0 = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.run(["bash", "-c", cmd], cwd=cwd, env=env, stdout=f, stderr=subprocess.STDOUT).returncode
    return time.perf_counter() - t0, rc


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("runs/first-run.json"))
    ap.add_argument("--skip-tests", action="store_true", help="time set-up and the main job only")
    ap.add_argument("--keep", action="store_true", help="keep the temporary clone (its logs are in it)")
    a = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="mapkit-first-run-"))
    clone = tmp / "main"
    subprocess.run(["git", "clone", "-q", "--no-local", str(ROOT), str(clone)], check=True)
    shared = ROOT.parent / "shared"
    if shared.is_dir():
        (tmp / "shared").symlink_to(shared.resolve())
    env = {
        **os.environ,
        "MAPKIT_VENV": str(tmp / "venv"),
        "PIP_CACHE_DIR": str(tmp / "pip-cache"),
        "UV_CACHE_DIR": str(tmp / "uv-cache"),
    }
    result: dict = {"measured": dt.date.today().isoformat()}
    steps = [("setup_s", "bash scripts/setup.sh"), ("main_job_s", ".venv/bin/python pipelines/main.py --out runs/main")]
    if not a.skip_tests:
        steps.append(("tests_s", ".venv/bin/python -m pytest -q"))
    try:
        for key, cmd in steps:
            print(f"[first-run] {cmd} ...", file=sys.stderr, flush=True)
            seconds, rc = timed(cmd, clone, env, tmp / f"{key}.log")
            result[key] = round(seconds, 1)
            print(f"[first-run] {cmd}: rc {rc}, {seconds:.0f} s", file=sys.stderr, flush=True)
            if rc != 0 and key == "tests_s":  # the time stands; the failures are stated beside it
                log = (tmp / f"{key}.log").read_text().splitlines()
                result["tests_failed"] = [ln.split(" - ")[0] for ln in log if ln.startswith(("FAILED", "ERROR"))]
                print("\n".join(log[-40:]), file=sys.stderr)
            elif rc != 0:
                print((tmp / f"{key}.log").read_text()[-3000:], file=sys.stderr)
                raise SystemExit(f"{cmd} failed (rc {rc}); logs in {tmp}")
        sys.path.insert(0, str(ROOT / "docs"))
        from figures import machine

        result["machine"] = machine()
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(result, indent=1) + "\n")
        print(json.dumps(result, indent=1))
    finally:
        if not a.keep:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
