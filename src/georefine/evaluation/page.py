"""Building blocks of the self-contained HTML reports: style, embedded images, tables.

The run report (:mod:`georefine.evaluation.report`) and the block demo's report use the same
style and helpers, so every page looks alike and opens from the file system (images are
embedded as base64 PNG).
"""

from __future__ import annotations

import base64
import html
from pathlib import Path

__all__ = ["CSS", "image", "table"]

CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:2em auto;max-width:1200px;color:#222;padding:0 1em}
h1{font-size:1.6em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0}th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}
.maps{display:flex;gap:1em;flex-wrap:wrap}.maps figure{flex:1;min-width:420px;margin:0}
img{max-width:100%}figcaption{font-size:.9em;color:#555}pre{background:#f7f7f7;padding:1em;overflow:auto;font-size:.85em}
.note{color:#555;font-size:.9em}
"""


def image(path: Path, alt: str) -> str:
    """An ``<img>`` with the PNG at ``path`` embedded, or a note when there is no such file."""
    if not path.is_file():
        return f'<p class="note">({html.escape(alt)}: not available)</p>'
    data = base64.b64encode(path.read_bytes()).decode()
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def table(header: list[str], rows: list[list]) -> str:
    """An HTML table of ``rows`` under ``header``, every cell escaped."""
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"
