"""The documentation site: it builds offline with ``mkdocs build --strict``, every command and every public
module has a reference page, and the worked examples of "your own data" run on the real data as written."""

from __future__ import annotations

import json
import os
import pkgutil
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO, SHARED_DATA

import mapkit
from mapkit.core.errors import InputWarning
from mapkit.core.workspace import Workspace

DOCS = REPO / "docs"


def _commands() -> list[list[str]]:
    """Every command path of the typer app, e.g. ["mapkit", "eval", "build"], walked independently of the site's
    hook."""
    import typer

    from mapkit.cli import app

    out = []

    def walk(cmd, path, parent):
        ctx = type(cmd).context_class(cmd, info_name=path[-1], parent=parent)
        out.append(path)
        for name in getattr(cmd, "list_commands", lambda _: [])(ctx):
            sub = cmd.get_command(ctx, name)
            if not sub.hidden:
                walk(sub, path + [name], ctx)

    walk(typer.main.get_command(app), ["mapkit"], None)
    return out


def _public_modules() -> list[str]:
    return ["mapkit"] + [
        m.name
        for m in pkgutil.walk_packages(mapkit.__path__, prefix="mapkit.")
        if not any(p.startswith("_") for p in m.name.split("."))
    ]


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    for module in ("mkdocs", "material", "mkdocstrings_handlers.python"):
        pytest.importorskip(module, reason="the docs extra is not installed (pip install -e '.[docs]')")
    out = tmp_path_factory.mktemp("site")
    run = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return out


def test_every_command_has_a_reference_section(site):
    page = (site / "reference" / "cli" / "index.html").read_text()
    commands = _commands()
    assert ["mapkit", "eval", "build"] in commands and ["mapkit", "index", "vlad"] in commands and len(commands) >= 20
    missing = [" ".join(c) for c in commands if f'id="{"-".join(c)}"' not in page]
    assert not missing, f"commands without a section on the CLI reference page: {missing}"
    # the page carries each command's own help, not just its name
    assert "LOG::/topic" in page and "--truth-time-offset" in page


def test_every_public_module_has_an_api_page(site):
    html = "\n".join(p.read_text() for p in (site / "reference" / "api").rglob("index.html"))
    modules = _public_modules()
    assert "mapkit.core.workspace" in modules and "mapkit.io.kitti" in modules
    missing = [m for m in modules if f'id="{m}"' not in html]
    assert not missing, f"public modules without an API reference entry: {missing}"
    # the docstrings are rendered, not just the names
    assert "every path of a mapkit project folder" in html


def test_pages_and_picture(site):
    """The hand-written pages are in the site, the picture is small, the README is a front door."""
    assert (site / "img" / "tiny-town-top-view.png").is_file()
    assert (DOCS / "img" / "tiny-town-top-view.png").stat().st_size < 300_000
    assert not list(site.rglob("*.py")), "the docs' Python helpers must not be published"
    assert 'class="mermaid"' in (site / "architecture" / "index.html").read_text()
    readme = (REPO / "README.md").read_text()
    assert 40 <= len(readme.splitlines()) <= 120
    for link in re.findall(r"\]\((docs/[^)#]+)", readme):
        assert (REPO / link).is_file(), f"README links to a missing page {link}"


def test_the_site_loads_nothing_from_a_network(site):
    """Every script, style sheet, font and picture of every page comes from the site itself: Mermaid is
    served as js/mermaid.min.js (docs/offline.py), before the theme's bundle would fetch it from a CDN."""
    pages = list(site.rglob("*.html"))
    assert len(pages) > 20
    external = re.compile(r"<(?:script|link|img|iframe|source)\b[^>]*\b(?:src|href)=[\"'](?:https?:)?//", re.IGNORECASE)
    found = [f"{p.relative_to(site)}: {m.group(0)}" for p in pages for m in external.finditer(p.read_text())]
    assert not found, found[:10]
    css = [
        f"{p.relative_to(site)}: {m.group(0)}"
        for p in site.rglob("*.css")
        for m in re.finditer(r"(?:@import\s+|url\()\s*[\"']?(?:https?:)?//", p.read_text())
    ]
    assert not css, css[:10]
    arch = (site / "architecture" / "index.html").read_text()
    assert '<script src="../js/mermaid.min.js"' in arch
    script = (site / "js" / "mermaid.min.js").read_bytes()
    assert len(script) > 1_000_000 and b"flowchart" in script


def _paragraphs(text: str) -> list[str]:
    """The prose paragraphs of a Markdown page: blocks between blank lines, outside code fences, tables
    and generated figure blocks; a list item is a paragraph of its own."""
    text = re.sub(r"```.*?```", "", text, flags=re.DOTALL)
    text = re.sub(r"<!-- figures: .*?<!-- /figures -->", "", text, flags=re.DOTALL)
    out = []
    for block in re.split(r"\n\s*\n", text):
        lines = [ln for ln in block.splitlines() if not ln.lstrip().startswith("|")]
        item: list[str] = []
        for ln in lines:
            if re.match(r"\s*(?:[-*]|\d+\.)\s", ln) and item:
                out.append(" ".join(item))
                item = []
            item.append(ln)
        if item:
            out.append(" ".join(item))
    return out


def test_no_paragraph_of_the_docs_runs_over_150_words():
    assert [len(p.split()) for p in _paragraphs("a b c\n\nd e\n- f g h\n- i")] == [3, 2, 4, 2]
    assert [len(p.split()) for p in _paragraphs("x\n```\n" + "w " * 400 + "\n```\ny")] == [1, 1]  # code is no paragraph
    pages = [REPO / "README.md", *sorted(DOCS.rglob("*.md"))]
    long = [
        f"{p.relative_to(REPO)}: {len(par.split())} words: {par[:80]}"
        for p in pages
        for par in _paragraphs(p.read_text())
        if len(par.split()) > 150
    ]
    assert not long, long


def test_every_figures_block_is_its_rendering_from_the_records():
    """The measured figures of the README and the docs are generated (docs/figures.py) from the records
    in docs/results/: a block edited by hand, or a record changed without rendering, fails here."""
    sys.path.insert(0, str(DOCS))
    try:
        import figures
    finally:
        sys.path.remove(str(DOCS))
    named = {name for p in figures.PAGES for name, _ in figures.blocks(p.read_text())}
    assert {"claims", "main-job-stages", "first-run"} <= named, named
    assert not named - set(figures.RENDERERS), f"blocks without a renderer: {sorted(named - set(figures.RENDERERS))}"
    assert figures.check_pages() == []
    # and the check sees a hand-edited figure
    page = next(p for p in figures.PAGES if "<!-- figures: claims -->" in p.read_text())
    edited = page.read_text().replace(
        "<!-- figures: claims -->\n", "<!-- figures: claims -->\n| edited | by hand |\n", 1
    )
    assert figures.fill(edited, lambda name: figures.RENDERERS[name]()) != edited


def _worked_example(name: str) -> tuple[list[str], dict[str, str]]:
    """The commands of the ``<!-- docs-test: NAME -->`` block of your-data.md, and every titled YAML block."""
    text = (DOCS / "your-data.md").read_text()
    block = re.search(rf"<!-- docs-test: {name} -->\n```bash\n(.*?)```", text, flags=re.DOTALL)
    assert block, f"your-data.md has no docs-test block {name}"
    files = dict(re.findall(r'```yaml title="([^"]+)"\n(.*?)```', text, flags=re.DOTALL))
    return [line for line in block.group(1).splitlines() if line.strip()], files


def _run(lines: list[str], files: dict[str, str], cwd: Path, monkeypatch) -> None:
    from mapkit.cli import main

    for name, content in files.items():
        (cwd / name).write_text(content)
    monkeypatch.chdir(cwd)
    for line in lines:
        argv = shlex.split(line.replace("../shared/data", str(SHARED_DATA)))
        assert argv[0] == "mapkit"
        assert main(argv[1:]) == 0, line


@pytest.mark.realdata
def test_worked_example_kitti_raw(tmp_path, monkeypatch, capsys):
    drive = SHARED_DATA / "kitti-raw-0001-oxts" / "2011_09_26" / "2011_09_26_drive_0001_sync"
    if not drive.is_dir():
        pytest.skip(f"real data not found at {drive} (expected ../shared/data/kitti-raw-0001-oxts beside the project)")
    lines, files = _worked_example("kitti-raw")
    assert [shlex.split(x)[1] for x in lines] == ["info", "build", "eval"]
    with pytest.warns(InputWarning, match="imagedb skipped: the log has no image stream"):  # as the page says
        _run(lines, files, tmp_path, monkeypatch)
    out = capsys.readouterr().out
    assert "/kitti/oxts/pose" in out and "107.1 m covered, 108/108 fixes" in out
    # the figures the page quotes: 1.9 mm GPS residual with yaw_scale, ATE 0.046 m against the INS stream
    ws = Workspace(tmp_path / "ws-kitti-raw")
    alignment = json.loads(ws.session(drive.name).gps_alignment.read_text())["alignment"]
    assert alignment["mode"] == "yaw_scale" and alignment["residual_rmse_m"] < 0.005
    ate = json.loads(ws.eval_build_json.read_text())["sessions"][drive.name]["ate"]
    assert 0.03 < ate["rmse_m"] < 0.06


@pytest.mark.realdata
def test_worked_example_kitti_odometry(tmp_path, monkeypatch, capsys, kitti_clip):
    lines, files = _worked_example("kitti-odometry")
    with pytest.warns(InputWarning, match="no times.txt"):  # as the page says
        _run(lines, files, tmp_path, monkeypatch)
    out = capsys.readouterr().out
    assert "kitti-odometry" in out and "/kitti/camera_0/image" in out and "/kitti/ground_truth" in out


def test_the_demo_expects_the_stage_times_its_records_measured():
    """`mapkit demo` tells a user what to expect of each stage (EXPECTED_SECONDS): within a third of the
    median the docs' records measured on 2 cores, for every stage that takes more than a few seconds."""
    from mapkit.pipelines.demo import EXPECTED_SECONDS

    sys.path.insert(0, str(DOCS))
    try:
        import figures
    finally:
        sys.path.remove(str(DOCS))
    checked = 0
    for preset, name in (("demo", "main-job"), ("tiny", "tiny"), ("places", "places")):
        runs = figures.record(name)["runs"]
        for stage in runs[0]["stages_s"]:
            median = sorted(r["stages_s"][stage] for r in runs)[len(runs) // 2]
            if median < 5:
                continue
            expected = EXPECTED_SECONDS[preset].get(stage)
            assert expected is not None and abs(expected - median) <= median / 3, (preset, stage, expected, median)
            checked += 1
    assert checked >= 15


# an absolute path: a slash not inside a word, URL or relative path, then two or more components
_ABSOLUTE = re.compile(r"(?<![\w.:/~-])/(?:[\w.+-]+/)+[\w.+-]+")


def test_the_records_name_no_folder_of_the_machine_they_were_measured_on():
    """A record of docs/results says the same on every machine: an absolute path whose first folder exists here
    (/tmp, /home, /usr, ...) is a machine's folder; a ROS topic (/kitti/oxts/pose) is not."""
    roots = {p.name for p in Path("/").iterdir()}
    found = [
        f"{record.name}: {m.group(0)}"
        for record in sorted((DOCS / "results").glob("*.json"))
        for m in _ABSOLUTE.finditer(record.read_text())
        if m.group(0).split("/")[1] in roots
    ]
    assert not found, found[:5]


def test_a_collected_record_says_paths_relative_to_the_checkout():
    sys.path.insert(0, str(DOCS))
    try:
        import figures
    finally:
        sys.path.remove(str(DOCS))
    root = Path("/srv/checkout")
    raw = {
        "command": ["/srv/checkout/.venv/bin/python", "/srv/checkout/bench/bench_x.py", "/srv/shared/data/clip"],
        "tail": ["/srv/checkout/mapkit/a.py:3: InputWarning: topic /kitti/oxts/pose", 3.5],
    }
    assert figures.portable(raw, root, "/srv/checkout/.venv/bin/python") == {
        "command": ["python", "bench/bench_x.py", "../shared/data/clip"],
        "tail": ["mapkit/a.py:3: InputWarning: topic /kitti/oxts/pose", 3.5],
    }
