"""The report as one self-contained HTML file: inline CSS, figures embedded as base64 PNG data
URIs, no scripts, fonts or other external assets, so it opens anywhere (a mail attachment, an
offline machine, a CI artefact viewer)."""

from __future__ import annotations

import base64
import re
from html import escape
from pathlib import Path

from reports.document import Code, Document, Image, Para, Table

CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 2em auto;
       max-width: 1200px; padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { font-size: 1.25em; border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 2em; }
.headline { font-size: 1.1em; font-weight: 600; background: #eef6ee; padding: 0.6em 0.8em;
            border-left: 4px solid #2ca02c; }
.warning { background: #fff4e5; border-left: 4px solid #e67e22; padding: 0.5em 0.8em; }
.note { color: #555; font-style: italic; }
table { border-collapse: collapse; margin: 0.6em 0 1.2em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.55em; text-align: left; vertical-align: top; }
td.n { text-align: right; font-variant-numeric: tabular-nums; }
th { background: #f3f3f3; }
caption { caption-side: top; text-align: left; font-style: italic; padding-bottom: 0.3em; }
pre { background: #f6f6f6; padding: 0.6em; overflow-x: auto; font-size: 0.85em; }
figure { margin: 1em 0 1.6em; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #444; }
nav ul { columns: 2; }
"""


def _data_uri(png: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(png.read_bytes()).decode("ascii")


#: Figures (with a unit-less suffix such as % or a "/" pair) are right-aligned, text is not.
_NUMERIC = re.compile(r"^[-+]?[\d.,]+(e[-+]?\d+)?%?(/[-+]?[\d.,]+%?)?$|^-$")


def _cell(text: str) -> str:
    cls = ' class="n"' if _NUMERIC.match(text.strip()) else ""
    return f"<td{cls}>{escape(text)}</td>"


def to_html(doc: Document, plots_dir: Path) -> str:
    """One HTML page; figures are read from `plots_dir` and embedded."""
    out = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{escape(doc.title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{escape(doc.title)}</h1>",
        f'<p class="headline">{escape(doc.headline)}</p>',
        "<nav><ul>",
    ]
    for i, s in enumerate(doc.sections):
        out.append(f'<li><a href="#s{i}">{escape(s.title)}</a></li>')
    out.append("</ul></nav>")
    for i, s in enumerate(doc.sections):
        out.append(f'<section id="s{i}"><h2>{escape(s.title)}</h2>')
        for b in s.blocks:
            if isinstance(b, Para):
                cls = f' class="{b.kind}"' if b.kind != "text" else ""
                out.append(f"<p{cls}>{escape(b.text)}</p>")
            elif isinstance(b, Table):
                out.append("<table>")
                if b.caption:
                    out.append(f"<caption>{escape(b.caption)}</caption>")
                out.append("<tr>" + "".join(f"<th>{escape(h)}</th>" for h in b.headers) + "</tr>")
                for row in b.rows:
                    cells = (
                        f'<td><a href="{escape(c)}">{escape(c)}</a></td>'
                        if i in b.link_columns
                        else _cell(c)
                        for i, c in enumerate(row)
                    )
                    out.append("<tr>" + "".join(cells) + "</tr>")
                out.append("</table>")
            elif isinstance(b, Code):
                if b.caption:
                    out.append(f'<p class="note">{escape(b.caption)}</p>')
                out.append(f"<pre>{escape(b.text)}</pre>")
            elif isinstance(b, Image):
                p = b.plot
                out.append(
                    f'<figure><img src="{_data_uri(plots_dir / p.file)}" '
                    f'alt="{escape(p.title)}" data-plot="{escape(p.file)}">'
                    f"<figcaption><b>{escape(p.title)}.</b> {escape(p.caption)}</figcaption>"
                    "</figure>"
                )
        out.append("</section>")
    out.append("</body></html>")
    return "\n".join(out) + "\n"


__all__ = ["to_html"]
