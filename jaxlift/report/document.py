"""A tiny report builder: headings, paragraphs, tables and figures, written as Markdown and as
a standalone HTML file.

::

    rep = Report("Calibration of lift_500kg")
    rep.heading("Where the model fails")
    rep.text("The **baseline** misses the oscillation at `stage 3`.")
    rep.table(rows, columns=["group", "rms_speed_mmps"], caption="RMS errors")
    rep.figure(out_dir / "figures" / "residuals.png", "Residuals of the fit")
    md_path, html_path = rep.write(out_dir)

Figures are linked, not copied: keep them in the output directory or below it (e.g. a
``figures/`` subdirectory); links are written relative to the output directory.  The same
content gives the same bytes (no time stamps).  Nothing here prints.
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
import re
import urllib.parse
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

_CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; line-height: 1.45;
       max-width: 1100px; margin: 2em auto; padding: 0 1em; color: #222; }
h1, h2, h3, h4 { line-height: 1.2; }
h1 { border-bottom: 2px solid #ccc; padding-bottom: .2em; }
h2 { border-bottom: 1px solid #ddd; padding-bottom: .15em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.92em; }
caption { caption-side: bottom; text-align: left; color: #555; padding-top: .4em;
          font-style: italic; }
th, td { border: 1px solid #ccc; padding: .25em .6em; }
th { background: #f2f2f2; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr:nth-child(even) td { background: #fafafa; }
code { background: #f4f4f4; padding: 0 .25em; border-radius: 3px; font-size: 0.95em; }
figure { margin: 1.2em 0; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { color: #555; font-style: italic; margin-top: .3em; }
details > summary { cursor: pointer; color: #245; margin: .6em 0; }
""".strip()


def format_value(value: Any, floatfmt: str = ".3g") -> str:
    """A table cell as text: floats with ``floatfmt`` (NaN as ``–``, infinities as ``±inf``),
    integers and booleans as they are, ``None`` as empty, anything else with ``str``."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float) or _is_numpy_float(value):
        v = float(value)
        if math.isnan(v):
            return "–"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return format(v, floatfmt)
    if _is_numpy_int(value):
        return str(int(value))
    return str(value)


def _is_numpy_float(v: Any) -> bool:
    return type(v).__module__ == "numpy" and hasattr(v, "dtype") and v.dtype.kind == "f"


def _is_numpy_int(v: Any) -> bool:
    return type(v).__module__ == "numpy" and hasattr(v, "dtype") and v.dtype.kind in "iub"


def _is_number(v: Any) -> bool:
    return (
        (isinstance(v, int | float) and not isinstance(v, bool))
        or _is_numpy_float(v)
        or _is_numpy_int(v)
    )


_INLINE = re.compile(r"`([^`]+)`|\*\*(.+?)\*\*")


def markdown_inline_to_html(text: str) -> str:
    """Inline Markdown to HTML: ``**bold**`` and `` `code` `` are converted, everything else is
    escaped (``html.escape``).  Code spans are taken verbatim (no bold inside)."""
    out = []
    pos = 0
    for m in _INLINE.finditer(text):
        out.append(html.escape(text[pos : m.start()]))
        if m.group(1) is not None:
            out.append(f"<code>{html.escape(m.group(1))}</code>")
        else:
            out.append(f"<strong>{markdown_inline_to_html(m.group(2))}</strong>")
        pos = m.end()
    out.append(html.escape(text[pos:]))
    return "".join(out)


def _md_cell(s: str) -> str:
    """Text safe inside a Markdown pipe-table cell."""
    return s.replace("\\", "\\\\").replace("|", "\\|").replace("\r", " ").replace("\n", " ")


def _blocks(text: str) -> list[tuple[str, list[str]]]:
    """Split Markdown text into paragraphs and bullet lists: ``[("p"|"ul", lines)]``."""
    blocks: list[tuple[str, list[str]]] = []
    for chunk in re.split(r"\n\s*\n", text.strip()):
        lines = [ln.strip() for ln in chunk.splitlines() if ln.strip()]
        if not lines:
            continue
        if all(re.match(r"[-*] ", ln) for ln in lines):
            blocks.append(("ul", [ln[2:].strip() for ln in lines]))
        else:
            blocks.append(("p", lines))
    return blocks


class Report:
    """A report: a title and a list of blocks (headings, text, tables, figures), written as
    Markdown and HTML by :meth:`write`.  Every adding method returns the report, so calls
    can be chained."""

    def __init__(self, title: str) -> None:
        self.title = str(title)
        self._items: list[tuple[str, dict[str, Any]]] = []

    # -- content -------------------------------------------------------------------------------

    def heading(self, text: str, level: int = 2) -> Report:
        """A heading; ``level`` 1–6 (the title is level 1, so sections usually use 2)."""
        if not 1 <= int(level) <= 6:
            raise ValueError(f"heading level must be in 1..6, got {level}")
        self._items.append(("heading", {"text": str(text), "level": int(level)}))
        return self

    def text(self, markdown_paragraph: str) -> Report:
        """Text in simple Markdown: paragraphs separated by blank lines, ``- `` bullet lists,
        ``**bold**`` and `` `code` ``.  Copied as is to the Markdown file; converted (and
        escaped) for the HTML file."""
        self._items.append(("text", {"text": str(markdown_paragraph)}))
        return self

    def table(
        self,
        rows: Sequence[Mapping[str, Any]],
        columns: Sequence[str] | None = None,
        floatfmt: str = ".3g",
        caption: str | None = None,
        collapsed: str | None = None,
    ) -> Report:
        """A table of ``rows`` (dicts).  ``columns``: which keys, in order (default: every key,
        in order of first appearance); a missing key gives an empty cell.  Floats are written
        with ``floatfmt`` (NaN as ``–``); numeric columns are right-aligned.  ``collapsed``:
        for a long table that few readers need, the line a reader clicks to open it (HTML
        ``<details>``; the Markdown file shows the table)."""
        rows = [dict(r) for r in rows]
        if columns is None:
            cols: list[str] = []
            for r in rows:
                for k in r:
                    if k not in cols:
                        cols.append(k)
        else:
            cols = [str(c) for c in columns]
        format(1.0, floatfmt)  # fail early on a bad format
        cells = [[format_value(r.get(c), floatfmt) for c in cols] for r in rows]
        numeric = [
            any(c in r and r[c] is not None for r in rows)
            and all(_is_number(r[c]) for r in rows if c in r and r[c] is not None)
            for c in cols
        ]
        self._items.append(
            (
                "table",
                {
                    "columns": cols,
                    "cells": cells,
                    "numeric": numeric,
                    "caption": caption,
                    "collapsed": None if collapsed is None else str(collapsed),
                },
            )
        )
        return self

    def figure(self, png_path: str | os.PathLike, caption: str = "") -> Report:
        """A figure (an image file, usually PNG).  The link is made relative to the output
        directory when the report is written: an absolute path, or a relative path that
        exists from the current directory, is related to the output directory; a relative
        path that does not exist from the current directory is taken as relative to the
        output directory already."""
        self._items.append(("figure", {"path": os.fspath(png_path), "caption": str(caption)}))
        return self

    # -- output --------------------------------------------------------------------------------

    @staticmethod
    def _link(path: str, out_dir: Path) -> str:
        p = Path(path)
        if p.is_absolute() or p.exists():
            rel = os.path.relpath(p.resolve(), out_dir.resolve())
        else:
            rel = os.path.normpath(path)
        return Path(rel).as_posix()

    def to_markdown(self, out_dir: str | os.PathLike = ".") -> str:
        """The report as Markdown text (figure links relative to ``out_dir``)."""
        out = Path(out_dir)
        parts = [f"# {self.title}"]
        for kind, it in self._items:
            if kind == "heading":
                parts.append("#" * it["level"] + " " + it["text"])
            elif kind == "text":
                parts.append(it["text"].strip())
            elif kind == "table":
                cols, cells = it["columns"], it["cells"]
                lines = ["| " + " | ".join(_md_cell(c) for c in cols) + " |"]
                lines.append("|" + "|".join("---:" if n else "---" for n in it["numeric"]) + "|")
                for row in cells:
                    lines.append("| " + " | ".join(_md_cell(c) for c in row) + " |")
                block = "\n".join(lines)
                if it["caption"]:
                    block += f"\n\n*{it['caption']}*"
                parts.append(block)
            elif kind == "figure":
                link = urllib.parse.quote(self._link(it["path"], out))
                alt = it["caption"].replace("[", "\\[").replace("]", "\\]").replace("\n", " ")
                block = f"![{alt}]({link})"
                if it["caption"]:
                    block += f"\n\n*{it['caption']}*"
                parts.append(block)
        return "\n\n".join(parts) + "\n"

    def to_html(self, out_dir: str | os.PathLike = ".") -> str:
        """The report as a standalone HTML document: inline CSS, figures embedded as
        base64 PNG (those not written yet linked relative to ``out_dir``)."""
        out = Path(out_dir)
        e = html.escape
        body = [f"<h1>{markdown_inline_to_html(self.title)}</h1>"]
        for kind, it in self._items:
            if kind == "heading":
                lv = it["level"]
                body.append(f"<h{lv}>{markdown_inline_to_html(it['text'])}</h{lv}>")
            elif kind == "text":
                for bkind, lines in _blocks(it["text"]):
                    if bkind == "ul":
                        items = "".join(f"<li>{markdown_inline_to_html(x)}</li>" for x in lines)
                        body.append(f"<ul>{items}</ul>")
                    else:
                        body.append(f"<p>{markdown_inline_to_html(' '.join(lines))}</p>")
            elif kind == "table":
                t = ["<table>"]
                if it["caption"]:
                    t.append(f"<caption>{markdown_inline_to_html(it['caption'])}</caption>")
                t.append("<thead><tr>" + "".join(f"<th>{e(c)}</th>" for c in it["columns"]))
                t.append("</tr></thead><tbody>")
                for row in it["cells"]:
                    tds = "".join(
                        f'<td class="num">{e(c)}</td>' if n else f"<td>{e(c)}</td>"
                        for c, n in zip(row, it["numeric"], strict=True)
                    )
                    t.append(f"<tr>{tds}</tr>")
                t.append("</tbody></table>")
                if it.get("collapsed"):  # absent in reports written before it existed
                    summary = markdown_inline_to_html(it["collapsed"])
                    t = [f"<details><summary>{summary}</summary>", *t, "</details>"]
                body.append("\n".join(t))
            elif kind == "figure":
                # embedded, so that a report mailed to a colleague arrives with its
                # pictures; linked (relative) only if the file is not there yet
                png = Path(it["path"])
                if not png.is_absolute() and not png.exists():
                    png = out / png
                if png.is_file():
                    data = base64.b64encode(png.read_bytes()).decode("ascii")
                    src = f"data:image/png;base64,{data}"
                else:
                    src = e(urllib.parse.quote(self._link(it["path"], out)), quote=True)
                alt = e(it["caption"], quote=True)
                cap = (
                    f"<figcaption>{markdown_inline_to_html(it['caption'])}</figcaption>"
                    if it["caption"]
                    else ""
                )
                body.append(f'<figure><img src="{src}" alt="{alt}">{cap}</figure>')
        return (
            "<!DOCTYPE html>\n"
            '<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
            f"<title>{e(self.title)}</title>\n<style>\n{_CSS}\n</style>\n</head>\n<body>\n"
            + "\n".join(body)
            + "\n</body>\n</html>\n"
        )

    def write(self, out_dir: str | os.PathLike, stem: str = "report") -> tuple[str, str]:
        """Write ``out_dir/stem.md`` and ``out_dir/stem.html`` (UTF-8, ``\\n`` line ends),
        creating ``out_dir``, and the report's content as ``out_dir/stem.json`` (figure
        links relative to ``out_dir``; :meth:`read` loads it, so that another report can
        :meth:`include` this one).  Returns ``(md_path, html_path)``."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        md_path = out / f"{stem}.md"
        html_path = out / f"{stem}.html"
        md_path.write_text(self.to_markdown(out), encoding="utf-8", newline="\n")
        html_path.write_text(self.to_html(out), encoding="utf-8", newline="\n")
        items = [
            (kind, {**it, "path": self._link(it["path"], out)} if kind == "figure" else it)
            for kind, it in self._items
        ]
        content = {"title": self.title, "items": [[k, it] for k, it in items]}
        (out / f"{stem}.json").write_text(
            json.dumps(content, indent=0) + "\n", encoding="utf-8", newline="\n"
        )
        return os.fspath(md_path), os.fspath(html_path)

    @classmethod
    def read(cls, out_dir: str | os.PathLike, stem: str = "report") -> Report:
        """The report that :meth:`write` wrote into ``out_dir`` (from ``stem.json``),
        its figures as absolute paths.  :class:`FileNotFoundError` if there is none."""
        out = Path(out_dir).resolve()
        path = out / f"{stem}.json"
        try:
            content = json.loads(path.read_text(encoding="utf-8"))
            rep = cls(content["title"])
            for kind, it in content["items"]:
                if kind == "figure":
                    it = {**it, "path": os.fspath(out / it["path"])}
                rep._items.append((str(kind), dict(it)))
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{path}: not a jaxlift report ({err})") from None
        return rep

    def include(self, other: Report, title: str | None = None, level: int = 2) -> Report:
        """Append ``other`` as a section: its title (or ``title``) as a heading of
        ``level``, its headings moved down to fit below it (at most level 6)."""
        self.heading(other.title if title is None else title, level)
        for kind, it in other._items:
            if kind == "heading":
                it = {**it, "level": min(6, it["level"] + level - 1)}
            self._items.append((kind, dict(it)))
        return self


def json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return json_safe(x.item())
    return x
