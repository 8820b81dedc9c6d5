"""The blocks a report is made of, and their rendering to Markdown (PNGs beside it) or one HTML file."""

from __future__ import annotations

import base64
import html
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

# ("h", level, text) | ("p", text) | ("ul", [text]) | ("table", headers, rows) | ("fig", file, png, caption)
Block = tuple[Any, ...]


def _md_cell(s: str) -> str:
    return s.replace("|", "\\|").replace("\n", " ")


def to_markdown(blocks: Sequence[Block], out_dir: Path) -> str:
    """The Markdown of ``blocks``; writes each figure's PNG into ``out_dir``."""
    parts = []
    for b in blocks:
        if b[0] == "h":
            parts.append(f"{'#' * b[1]} {b[2]}")
        elif b[0] == "p":
            parts.append(b[1])
        elif b[0] == "ul":
            parts.append("\n".join(f"- {item}" for item in b[1]))
        elif b[0] == "table":
            head, rows = b[1], b[2]
            lines = ["| " + " | ".join(map(_md_cell, head)) + " |", "|" + "---|" * len(head)]
            lines += ["| " + " | ".join(map(_md_cell, row)) + " |" for row in rows]
            parts.append("\n".join(lines))
        elif b[0] == "fig":
            (out_dir / b[1]).write_bytes(b[2])
            parts.append(f"![{b[3]}]({b[1]})\n\n*{b[3]}*")
    return "\n\n".join(parts) + "\n"


def _inline_html(s: str) -> str:
    """Escape, then the little Markdown the report uses: `code`, **bold**, [text](#anchor)."""
    s = html.escape(s, quote=False)
    s = re.sub(r"`([^`]+)`", r"<code>\1</code>", s)
    s = re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", s)
    return re.sub(r"\[([^\]]+)\]\((#[^)]+)\)", r'<a href="\2">\1</a>', s)


def _slug(text: str) -> str:
    """A heading's anchor, as Markdown renderers make it (so [text](#anchor) links work in both formats)."""
    return re.sub(r"[^a-z0-9 -]", "", text.lower()).strip().replace(" ", "-")


_CSS = ("body{font-family:sans-serif;max-width:70em;margin:2em auto;padding:0 1em;line-height:1.4}"
        "table{border-collapse:collapse;margin:1em 0}th,td{border:1px solid #ccc;padding:.3em .6em;text-align:left}"
        "th{background:#f3f3f3}img{max-width:100%}code{background:#f3f3f3;padding:0 .2em}figcaption{font-style:italic}")


def to_html(blocks: Sequence[Block], title: str) -> str:
    """One self-contained HTML page of ``blocks``, figures embedded as data URIs."""
    parts = [f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{_CSS}</style></head><body>"]
    for b in blocks:
        if b[0] == "h":
            parts.append(f"<h{b[1]} id='{_slug(b[2])}'>{_inline_html(b[2])}</h{b[1]}>")
        elif b[0] == "p":
            parts.append(f"<p>{_inline_html(b[1])}</p>")
        elif b[0] == "ul":
            parts.append("<ul>" + "".join(f"<li>{_inline_html(i)}</li>" for i in b[1]) + "</ul>")
        elif b[0] == "table":
            head = "".join(f"<th>{_inline_html(h)}</th>" for h in b[1])
            body = "".join("<tr>" + "".join(f"<td>{_inline_html(c)}</td>" for c in row) + "</tr>" for row in b[2])
            parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
        elif b[0] == "fig":
            data = base64.b64encode(b[2]).decode("ascii")
            parts.append(f"<figure><img alt='{html.escape(b[3])}' src='data:image/png;base64,{data}'>"
                         f"<figcaption>{_inline_html(b[3])}</figcaption></figure>")
    return "\n".join(parts) + "\n</body></html>\n"
