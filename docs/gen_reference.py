"""MkDocs hook: the reference pages, generated at every build so that they cannot go stale.

- ``reference/cli.md``: every command of the ``mapkit`` typer app, found by walking its click command
  tree (``typer.main.get_command``): usage, help text, arguments and options with type and default.
- ``reference/api/<subpackage>.md``: one page per subpackage of ``mapkit`` with a mkdocstrings
  ``::: module`` block for each of its public modules (found by walking the package on disk, so a new
  module gets its page without anyone remembering to add it).

``mkdocs.yml`` names this file under ``hooks:``; the nav's "API reference" entry is filled here too.
"""

from __future__ import annotations

import html
import pkgutil
import re
from pathlib import Path

import mapkit

API_DIR = "reference/api"
CLI_PAGE = "reference/cli.md"


def public_modules() -> dict[str, list[str]]:
    """Subpackage (or ``mapkit`` for top-level modules) -> its public module names, in file order.

    A module is public unless a part of its dotted name starts with an underscore; packages count
    as modules too (their ``__init__`` docstring says what the subpackage holds)."""
    groups: dict[str, list[str]] = {"mapkit": ["mapkit"]}
    for info in pkgutil.walk_packages(mapkit.__path__, prefix="mapkit."):
        parts = info.name.split(".")
        if any(p.startswith("_") for p in parts):
            continue
        key = "mapkit" if len(parts) == 2 and not info.ispkg else ".".join(parts[:2])
        groups.setdefault(key, []).append(info.name)
    return {k: sorted(v, key=lambda m: (m != k, m)) for k, v in groups.items()}


def api_page_path(group: str) -> str:
    return f"{API_DIR}/{group.split('.')[-1] if group != 'mapkit' else 'mapkit'}.md"


def _api_markdown(group: str, modules: list[str]) -> str:
    title = "Top level" if group == "mapkit" else f"`{group}`"
    lines = [f"# {title}", "", "Generated from the docstrings at build time (`docs/gen_reference.py`).", ""]
    for m in modules:
        lines += [f"::: {m}", "    options:", "      show_submodules: false", ""]
    return "\n".join(lines)


def command_anchor(path: list[str]) -> str:
    """The HTML id of a command's section on the CLI page, e.g. ``mapkit-eval-build``."""
    return "-".join(path)


def walk_commands(cmd, path: list[str], ctx=None):
    """Yield (path, command, context) for the command and every command below it, depth first."""
    ctx = type(cmd).context_class(cmd, info_name=path[-1], parent=ctx)
    yield path, cmd, ctx
    for name in cmd.list_commands(ctx) if hasattr(cmd, "list_commands") else []:
        sub = cmd.get_command(ctx, name)
        if sub is not None and not sub.hidden:
            yield from walk_commands(sub, path + [name], ctx)


def _cell(text: object) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _command_markdown(path: list[str], cmd, ctx) -> list[str]:
    level = "#" * min(len(path) + 1, 4)
    out = [f"{level} `{' '.join(path)}` {{#{command_anchor(path)}}}", ""]
    if cmd.help:
        out += [cmd.help.strip(), ""]
    out += ["```text", cmd.get_usage(ctx).strip(), "```", ""]
    params = [p for p in cmd.params if not getattr(p, "hidden", False)]
    if params:
        out += ["| argument / option | type | default | meaning |", "|---|---|---|---|"]
        for p in params:
            names = ", ".join(f"`{o}`" for o in [*p.opts, *p.secondary_opts])
            if p.param_type_name == "argument":
                names = f"`{p.name.upper()}`" + (" ..." if p.nargs == -1 else "")
            default = (
                "required" if p.required else ("" if p.default is None or callable(p.default) else f"`{p.default}`")
            )
            out.append(f"| {names} | `{_cell(p.display_type(ctx))}` | {_cell(default)} | {_cell(p.help or '')} |")
        out.append("")
    return out


def cli_markdown() -> str:
    import typer

    from mapkit.cli import app

    lines = [
        "# Command reference",
        "",
        "Generated from the `mapkit` command line itself at build time (`docs/gen_reference.py`), so it",
        "says what `mapkit COMMAND --help` says. The [guides](../guide/build.md) explain when to use which.",
        "",
    ]
    for path, cmd, ctx in walk_commands(typer.main.get_command(app), ["mapkit"]):
        lines += _command_markdown(path, cmd, ctx)
    return "\n".join(lines)


def on_config(config):
    """Fill the nav's "API reference" entry with one page per subpackage."""
    pages = [{(g if g != "mapkit" else "mapkit (top level)"): api_page_path(g)} for g in public_modules()]
    for entry in config["nav"] or []:
        if isinstance(entry, dict) and "Reference" in entry:
            for sub in entry["Reference"]:
                if isinstance(sub, dict) and "API" in sub:
                    sub["API"] = pages
    return config


_AUTOREF = re.compile(r"<autoref (?P<attrs>[^>]*?)>(?P<title>.*?)</autoref>", flags=re.DOTALL)
_IDENTIFIER = re.compile(r'identifier="(?P<id>[^"]*)"')
_DOTTED_NAME = re.compile(r"^[A-Za-z_][\w.]*$")


def _literal_brackets(match: re.Match) -> str:
    """A docstring's ``[a][b]`` in prose (optional parts, e.g. ``z[, intensity][, time]``) is parsed as a
    reference-style link; an identifier that is not a dotted name can never be a cross-reference, so
    it is put back as the text it was. Real cross-references (dotted names) are left to autorefs."""
    found = _IDENTIFIER.search(match["attrs"])
    if found is None or _DOTTED_NAME.match(html.unescape(found["id"])):
        return match[0]
    return f"[{match['title']}][{found['id']}]"


def on_page_content(html_text: str, page, config, files):
    return _AUTOREF.sub(_literal_brackets, html_text)


def on_files(files, config):
    from mkdocs.structure.files import File

    files.append(File.generated(config, CLI_PAGE, content=cli_markdown()))
    for group, modules in public_modules().items():
        files.append(File.generated(config, api_page_path(group), content=_api_markdown(group, modules)))
    return files


if __name__ == "__main__":  # print the CLI page, to read it without building the site
    print(cli_markdown())
    print(Path(__file__).name, {g: len(m) for g, m in public_modules().items()})
