"""A report as a list of sections, written as Markdown (figures beside it) and as one self-contained HTML page.

The pipeline's report and the studies' reports are built of `Section`s and written by `write_sections`.
"""

import base64
import html
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from carp.outputs import write_text


@dataclass
class Section:
    """One report section: a title, paragraphs, tables and figures in that order."""

    title: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[pd.DataFrame] = field(default_factory=list)
    figures: list[Path] = field(default_factory=list)
    code: str = ""


IMAGE_MEDIA_TYPES = {".png": "image/png", ".gif": "image/gif"}
"""Media type of each kind of figure the HTML embeds (plots are PNG, rollout videos animated GIF)."""


def render_markdown(sections: Sequence[Section], title: str, base_dir: Path) -> str:
    """Markdown with figures referenced by paths relative to ``base_dir``."""
    lines = [f"# {title}", ""]
    for section in sections:
        lines += [f"## {section.title}", ""]
        for paragraph in section.paragraphs:
            lines += [paragraph, ""]
        for table in section.tables:
            lines += [table.to_markdown(index=False, disable_numparse=True), ""]
        for figure in section.figures:
            lines += [f"![{figure.stem}]({os.path.relpath(figure, base_dir)})", ""]
        if section.code:
            lines += ["```yaml", section.code.rstrip(), "```", ""]
    return "\n".join(lines)


def render_html(sections: Sequence[Section], title: str) -> str:
    """Self-contained HTML: inline CSS, figures as data URIs, no external resources."""
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:60em;margin:2em auto;padding:0 1em}"
        "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}"
        "img{max-width:100%}pre{background:#f6f6f6;padding:1em;overflow:auto}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
    ]
    for section in sections:
        parts.append(f"<h2>{html.escape(section.title)}</h2>")
        parts += [f"<p>{html.escape(paragraph).replace('`', '')}</p>" for paragraph in section.paragraphs]
        parts += [table.to_html(index=False, border=0) for table in section.tables]
        for figure in section.figures:
            encoded = base64.b64encode(Path(figure).read_bytes()).decode()
            media_type = IMAGE_MEDIA_TYPES[Path(figure).suffix.lower()]
            parts.append(f"<img alt='{html.escape(figure.stem)}' src='data:{media_type};base64,{encoded}'>")
        if section.code:
            parts.append(f"<pre>{html.escape(section.code)}</pre>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_sections(sections: Sequence[Section], output_dir: Path, title: str) -> tuple[Path, Path]:
    """Write `sections` as ``report.md`` and ``report.html`` into ``output_dir``, atomically; returns the two paths."""
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    markdown_path, html_path = output_dir / "report.md", output_dir / "report.html"
    for path, text in (
        (markdown_path, render_markdown(sections, title, output_dir)),
        (html_path, render_html(sections, title)),
    ):
        write_text(path, text)
    return markdown_path, html_path
