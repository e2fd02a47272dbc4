"""A tiny builder for self-contained HTML5 reports.

Every text that reaches the page goes through :func:`html.escape`; images are embedded as
``data:image/png;base64,…`` URIs and the only style sheet is an inline ``<style>`` block, so a
report is one file with no external references.
"""

from __future__ import annotations

import base64
import html
import json
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ultron import atomic
from ultron.errors import argument_error

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_ATTRIBUTE_NAME = re.compile(r"^[a-z][a-z0-9-]*$")

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1400px;
       padding: 0 1em; color: #222; line-height: 1.4; }
h1 { border-bottom: 2px solid #446; padding-bottom: .2em; }
h2 { margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: .6em 0; font-size: .92em; }
th, td { border: 1px solid #bbb; padding: .25em .6em; }
th { background: #eef; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
figure { margin: 1em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: .9em; color: #444; }
p.note { color: #7a4b00; background: #fff6e0; padding: .3em .6em; border-left: 3px solid #e0a000; }
pre { background: #f6f6f6; padding: .6em; overflow-x: auto; font-size: .85em; }
nav ul { columns: 2; }
""".strip()


@dataclass(frozen=True)
class Section:
    """One ``<section>`` of a report: a heading and a body of already-built (escaped) HTML."""

    title: str
    html_body: str

    def __post_init__(self) -> None:
        if not isinstance(self.title, str) or not self.title.strip():
            raise argument_error("title", "expected a non-empty string")
        if not isinstance(self.html_body, str):
            raise argument_error("html_body", "expected a string of HTML")


def esc(value: Any) -> str:
    """``value`` as text, HTML-escaped (quotes included)."""
    return html.escape(str(value), quote=True)


def _attributes(attrs: Mapping[str, Any] | None) -> str:
    parts = []
    for name, value in (attrs or {}).items():
        if not isinstance(name, str) or not _ATTRIBUTE_NAME.match(name):
            raise argument_error("attrs", f"invalid attribute name {name!r}")
        parts.append(f' {name}="{esc(value)}"')
    return "".join(parts)


def png_data_uri(png_bytes: bytes) -> str:
    """A ``data:image/png;base64,…`` URI for PNG bytes (checked for the PNG signature)."""
    if not isinstance(png_bytes, bytes | bytearray) or not bytes(png_bytes[:8]) == PNG_SIGNATURE:
        raise argument_error("png_bytes", "expected the bytes of a PNG image")
    return "data:image/png;base64," + base64.b64encode(bytes(png_bytes)).decode("ascii")


def image_html(
    png_bytes: bytes, alt: str, caption: str = "", attrs: Mapping[str, Any] | None = None
) -> str:
    """A ``<figure>`` holding the PNG inline, with alt text, an optional caption and extra
    attributes on the figure (e.g. ``{"data-method": "UltrON"}``)."""
    if not isinstance(alt, str) or not alt.strip():
        raise argument_error("alt", "expected a non-empty description of the image")
    uri = png_data_uri(png_bytes)
    figcaption = f"<figcaption>{esc(caption)}</figcaption>" if caption else ""
    return f'<figure{_attributes(attrs)}><img src="{uri}" alt="{esc(alt)}">{figcaption}</figure>'


def paragraph_html(text: str, note: bool = False) -> str:
    """An escaped ``<p>``; ``note`` styles it as a remark (missing input, skipped section)."""
    return f'<p class="note">{esc(text)}</p>' if note else f"<p>{esc(text)}</p>"


def list_html(items: Iterable[Any]) -> str:
    """An escaped ``<ul>`` of ``items``."""
    return "<ul>" + "".join(f"<li>{esc(item)}</li>" for item in items) + "</ul>"


def pre_json_html(obj: Any) -> str:
    """``obj`` as indented JSON inside ``<pre>``."""
    return f"<pre>{esc(json.dumps(obj, indent=2, default=str))}</pre>"


def _is_number(text: str) -> bool:
    token = text.strip().split(" ")[0].replace("±", "")
    try:
        float(token)
    except ValueError:
        return False
    return True


def table_html(header: Sequence[Any], rows: Iterable[Sequence[Any]]) -> str:
    """An escaped ``<table>``; numeric-looking cells are right-aligned."""
    header = list(header)
    if not header:
        raise argument_error("header", "expected at least one column")
    lines = ["<table>", "<thead><tr>" + "".join(f"<th>{esc(h)}</th>" for h in header) + "</tr>"]
    lines.append("</thead><tbody>")
    for i, row in enumerate(rows):
        row = list(row)
        if len(row) != len(header):
            raise argument_error("rows", f"row {i} has {len(row)} cells, expected {len(header)}")
        cells = []
        for cell in row:
            text = "" if cell is None else str(cell)
            cls = ' class="num"' if text and _is_number(text) else ""
            cells.append(f"<td{cls}>{esc(text)}</td>")
        lines.append("<tr>" + "".join(cells) + "</tr>")
    lines.append("</tbody></table>")
    return "\n".join(lines)


def _split_markdown_row(line: str) -> list[str]:
    body = line.strip()
    if body.startswith("|"):
        body = body[1:]
    if body.endswith("|") and not body.endswith("\\|"):
        body = body[:-1]
    cells = re.split(r"(?<!\\)\|", body)
    return [cell.strip().replace("\\|", "|") for cell in cells]


def _is_rule(cells: list[str]) -> bool:
    return bool(cells) and all(re.fullmatch(r":?-{1,}:?", c.replace(" ", "")) for c in cells)


def markdown_table_html(markdown: str) -> str:
    """A GitHub markdown table (``| a | b |`` lines, with a ``|---|`` rule) as an HTML table.

    Lines before the table are kept as paragraphs (e.g. a caption); text is escaped, markdown
    emphasis is shown literally.
    """
    if not isinstance(markdown, str):
        raise argument_error("markdown", "expected a string")
    lines = [line for line in markdown.splitlines() if line.strip()]
    table_lines = [line for line in lines if line.strip().startswith("|")]
    other = [line for line in lines if not line.strip().startswith("|")]
    if not table_lines:
        raise argument_error("markdown", "holds no table (no lines starting with '|')")
    rows = [_split_markdown_row(line) for line in table_lines]
    header, body = rows[0], [r for r in rows[1:] if not _is_rule(r)]
    width = len(header)
    body = [(r + [""] * width)[:width] for r in body]
    return "".join(paragraph_html(text) for text in other) + table_html(header, body)


def _anchor(index: int) -> str:
    return f"section-{index + 1}"


def build_html(title: str, sections: Sequence[Section], subtitle: str = "") -> str:
    """A complete HTML5 document: title, optional subtitle, a table of contents, the sections."""
    if not isinstance(title, str) or not title.strip():
        raise argument_error("title", "expected a non-empty string")
    sections = list(sections)
    for i, section in enumerate(sections):
        if not isinstance(section, Section):
            raise argument_error("sections", f"item {i} is not a Section")
    toc = "".join(
        f'<li><a href="#{_anchor(i)}">{esc(s.title)}</a></li>' for i, s in enumerate(sections)
    )
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{esc(title)}</title>",
        f"<style>\n{_STYLE}\n</style>",
        "</head>",
        "<body>",
        f"<h1>{esc(title)}</h1>",
    ]
    if subtitle:
        parts.append(paragraph_html(subtitle))
    if sections:
        parts.append(f"<nav><ul>{toc}</ul></nav>")
    for i, section in enumerate(sections):
        parts.append(f'<section id="{_anchor(i)}">')
        parts.append(f"<h2>{esc(section.title)}</h2>")
        parts.append(section.html_body)
        parts.append("</section>")
    parts.extend(["</body>", "</html>", ""])
    return "\n".join(parts)


def write_html(path: str | Path, text: str) -> Path:
    """Write the document ``text`` atomically (UTF-8) to ``path``; returns the path."""
    if not isinstance(text, str):
        raise argument_error("text", "expected the HTML document as a string")
    path = Path(path)
    atomic.write_text(path, text)
    return path
