"""A self-contained HTML report: one file, pictures embedded, readable without a network.

Stages write their findings as Markdown tables (``eval_build.md``, ``qa.md``, ``places.md``, ...)
and PNG pictures; :func:`write_report` puts them on one page. The Markdown subset understood is
what mapkit writes: headings, pipe tables, bullet lists, paragraphs, ``**bold**`` and
```code```.
"""

from __future__ import annotations

import base64
import html
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from mapkit.core.runio import atomic_write_text


@dataclass
class Picture:
    path: Path
    caption: str = ""
    width: int | None = None  # CSS pixels; None = up to the page width


@dataclass
class Section:
    """One stage of the report: a title, Markdown text and pictures, in order."""

    title: str
    blocks: list[str | Picture] = field(default_factory=list)
    seconds: float | None = None

    def md(self, text: str) -> Section:
        self.blocks.append(text)
        return self

    def md_file(self, path: Path, drop_title: bool = True) -> Section:
        if Path(path).is_file():
            text = Path(path).read_text()
            if drop_title:
                text = re.sub(r"\A#[^\n]*\n", "", text.lstrip())
            self.blocks.append(text)
        else:
            self.blocks.append(f"(`{Path(path).name}` was not written)")
        return self

    def picture(self, path: Path, caption: str = "", width: int | None = None) -> Section:
        if Path(path).is_file():
            self.blocks.append(Picture(Path(path), caption, width))
        return self


_INLINE = [(re.compile(r"\*\*(.+?)\*\*"), r"<b>\1</b>"), (re.compile(r"`([^`]+)`"), r"<code>\1</code>")]


def _inline(text: str) -> str:
    s = html.escape(text, quote=False)
    for rx, rep in _INLINE:
        s = rx.sub(rep, s)
    return s


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def markdown_to_html(text: str) -> str:
    """The Markdown subset mapkit writes, as HTML (everything escaped)."""
    out: list[str] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        m = re.match(r"^(#{1,6})\s+(.*)$", line)
        if m:
            level = min(len(m.group(1)) + 2, 6)  # the page owns h1/h2
            out.append(f"<h{level}>{_inline(m.group(2))}</h{level}>")
            i += 1
            continue
        if line.lstrip().startswith("|"):
            rows = []
            while i < len(lines) and lines[i].lstrip().startswith("|"):
                rows.append(lines[i])
                i += 1
            head, body = _cells(rows[0]), rows[1:]
            if body and re.fullmatch(r"[\s|:\-]+", body[0]):
                body = body[1:]
            t = ["<table><thead><tr>" + "".join(f"<th>{_inline(c)}</th>" for c in head) + "</tr></thead><tbody>"]
            t += ["<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in _cells(r)) + "</tr>" for r in body]
            out.append("\n".join(t) + "</tbody></table>")
            continue
        if re.match(r"^\s*[-*]\s+", line):
            items = []
            while i < len(lines) and re.match(r"^\s*[-*]\s+", lines[i]):
                items.append(re.sub(r"^\s*[-*]\s+", "", lines[i]))
                i += 1
            out.append("<ul>" + "".join(f"<li>{_inline(t)}</li>" for t in items) + "</ul>")
            continue
        para = []
        while (
            i < len(lines)
            and lines[i].strip()
            and not lines[i].lstrip().startswith(("|", "#"))
            and not re.match(r"^\s*[-*]\s+", lines[i])
        ):
            para.append(lines[i].strip())
            i += 1
        out.append(f"<p>{_inline(' '.join(para))}</p>")
    return "\n".join(out)


def _img(p: Picture) -> str:
    data = base64.b64encode(p.path.read_bytes()).decode("ascii")
    style = f' style="max-width:{p.width}px"' if p.width else ""
    cap = f"<figcaption>{_inline(p.caption)}</figcaption>" if p.caption else ""
    return (
        f'<figure><img alt="{html.escape(p.caption or p.path.name)}" '
        f'src="data:image/png;base64,{data}"{style}>{cap}</figure>'
    )


# one rule set per line, as the page carries it
_CSS = (
    "\n"
    "body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;"
    "max-width:1180px;margin:2em auto;padding:0 1em;color:#222}\n"
    "h1{margin-bottom:.2em} h2{border-bottom:2px solid #ddd;padding-bottom:.2em;margin-top:2em}\n"
    "table{border-collapse:collapse;margin:.6em 0;font-size:.9em} "
    "th,td{border:1px solid #ccc;padding:.25em .5em;text-align:left}\n"
    "th{background:#f3f3f3} tbody tr:nth-child(even){background:#fafafa}\n"
    "figure{display:inline-block;margin:.5em 1em .5em 0;vertical-align:top} img{max-width:100%;border:1px solid #ddd}\n"
    "figcaption{font-size:.85em;color:#555} code{background:#f3f3f3;padding:0 .2em} "
    ".time{color:#777;font-weight:normal;font-size:.7em}\n"
    "nav a{margin-right:1em}\n"
)


def render(title: str, intro: str, sections: Sequence[Section]) -> str:
    """The whole page as a string."""
    anchors = [re.sub(r"[^a-z0-9]+", "-", s.title.lower()).strip("-") for s in sections]
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        markdown_to_html(intro),
        "<nav>"
        + "".join(f'<a href="#{a}">{html.escape(s.title)}</a>' for a, s in zip(anchors, sections, strict=True))
        + "</nav>",
    ]
    for a, s in zip(anchors, sections, strict=True):
        t = f' <span class="time">{s.seconds:.0f} s</span>' if s.seconds is not None else ""
        parts.append(f'<h2 id="{a}">{html.escape(s.title)}{t}</h2>')
        for b in s.blocks:
            parts.append(_img(b) if isinstance(b, Picture) else markdown_to_html(b))
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(path: str | Path, title: str, intro: str, sections: Sequence[Section]) -> Path:
    """Write the page atomically; returns its path."""
    return atomic_write_text(path, render(title, intro, sections))


__all__ = ["Picture", "Section", "markdown_to_html", "render", "write_report"]
