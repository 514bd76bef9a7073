"""The HTML page of ``viper replay``, ``viper demo`` and ``viper estimate --report``: one look for all.

The page names files relative to its own folder (a file elsewhere by its name alone), so it shows no
absolute path and still opens when the folder is moved; every link is URL-quoted, then HTML-escaped.
The builders return HTML fragments; text goes in escaped, nothing else is escaped twice.
"""

from __future__ import annotations

import html
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from urllib.parse import quote

STYLE = (
    "body{font-family:sans-serif;margin:2em;max-width:1400px}"
    "table{border-collapse:collapse;margin:0.5em 0 1em;font-size:90%}div.wide{overflow-x:auto}"
    "td,th{border:1px solid #aaa;padding:3px 8px;text-align:right}"
    "th{background:#eee}table.facts td:first-child{text-align:left;font-weight:bold}"
    "img{max-width:100%;border:1px solid #ccc}h2{margin-top:2em;border-bottom:1px solid #ccc}"
    "div.banner{color:#fff;padding:0.5em 1em;margin:0.4em 0;border-radius:4px;font-size:120%}"
    "div.banner.ok{background:#1b7f2a}div.banner.ambiguous{background:#b3261e}"
    "div.banner b{font-size:160%;margin-right:0.6em}div.banner ul{margin:0.3em 0 0;font-size:85%}"
)


def shown_path(path: str | Path, folder: str | Path) -> str:
    """``path`` relative to ``folder`` (forward slashes) when it lies inside it, else its file name."""
    p, f = Path(os.path.abspath(path)), Path(os.path.abspath(folder))
    try:
        return p.relative_to(f).as_posix()
    except ValueError:
        return p.name


def without_folders(text: str, paths: Iterable[str | Path], folder: str | Path) -> str:
    """``text`` (a message naming files) with each of ``paths`` as :func:`shown_path` shows it."""
    for p in paths:
        for spelling in sorted({str(p), os.path.abspath(p)}, key=len, reverse=True):
            text = text.replace(spelling, shown_path(p, folder))
    return text


def href(path: str | Path, folder: str | Path) -> str:
    """The link to ``path`` from a page in ``folder``: URL-quoted, then escaped for an attribute."""
    return html.escape(quote(shown_path(path, folder)), quote=True)


def link(path: str | Path, folder: str | Path, text: str | None = None) -> str:
    shown = shown_path(path, folder)
    return f"<a href=\"{href(path, folder)}\">{html.escape(shown if text is None else text)}</a>"


def image(path: str | Path, folder: str | Path, alt: str) -> str:
    return (f"<p><a href=\"{href(path, folder)}\"><img src=\"{href(path, folder)}\" "
            f"alt=\"{html.escape(alt, quote=True)}\"></a></p>")


def paragraph(text: str, label: str | None = None) -> str:
    head = "" if label is None else f"<b>{html.escape(label)}</b> "
    return f"<p>{head}{html.escape(text)}</p>"


def heading(text: str, level: int = 2, anchor: str | None = None) -> str:
    ident = "" if anchor is None else f" id=\"{html.escape(anchor, quote=True)}\""
    return f"<h{level}{ident}>{html.escape(text)}</h{level}>"


def table(rows: Sequence[Mapping[str, str]], links: Mapping[int, str] | None = None) -> str:
    """A table with a header row from the first row's keys; ``links`` gives a row's first cell a link
    target (already an ``href``) by row index."""
    if not rows:
        return ""
    out = ["<table><tr>" + "".join(f"<th>{html.escape(k)}</th>" for k in rows[0]) + "</tr>"]
    for i, row in enumerate(rows):
        cells = []
        for j, v in enumerate(row.values()):
            text = html.escape(v)
            if j == 0 and links is not None and i in links:
                text = f"<a href=\"{links[i]}\">{text}</a>"
            cells.append(f"<td>{text}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "<div class=\"wide\">" + "\n".join(out) + "</div>"


def banner(headline: str, ok: bool, where: str = "", reasons: Sequence[str] = ()) -> str:
    """The status banner: ``headline`` large on green (``ok``) or red, then ``where`` (the answer's name
    and place), then the ``reasons`` as a list."""
    items = "".join(f"<li>{html.escape(r)}</li>" for r in reasons)
    return (f"<div class=\"banner {'ok' if ok else 'ambiguous'}\"><b>{html.escape(headline)}</b>"
            f"{html.escape(where)}{f'<ul>{items}</ul>' if items else ''}</div>")


def facts_table(facts: Iterable[tuple[str, str]]) -> str:
    """Two columns, a name and its value, one fact a row."""
    rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>" for k, v in facts)
    return f"<table class=\"facts\">{rows}</table>" if rows else ""


def page(title: str, parts: Iterable[str]) -> str:
    """The whole page: ``title`` in the head and as the first heading, then the fragments."""
    t = html.escape(title)
    head = (f"<!doctype html><html><head><meta charset=\"utf-8\"><title>{t}</title>"
            f"<style>{STYLE}</style></head><body>")
    return "\n".join([head, f"<h1>{t}</h1>", *parts, "</body></html>"])
