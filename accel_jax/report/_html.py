"""Assemble a self-contained HTML report from studies' `result.json` files and figures.

A study's result file may carry, beside its numbers:
- `title`: a heading; `summary`: a list of rows `{"quantity", "ours", "paper", "note"}`;
- `figures`: a list of `{"file": "name.png", "caption": "..."}` (PNG beside result.json);
- `assumptions` and `provenance`: shown as tables.
Figures are embedded as base64 so the single `index.html` can be mailed or archived.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

from .._io import _atomic_write_bytes

# Written into every index.html, so a later run knows the file is ours to replace.
REPORT_MARKER = "<!-- written by accel-jax report -->"

_STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; color: #222;
       line-height: 1.45; padding: 0 1em; }
h1 { border-bottom: 2px solid #345; padding-bottom: .3em; }
h2 { margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.92em; }
th, td { border: 1px solid #bbb; padding: 4px 8px; text-align: left; vertical-align: top; }
th { background: #eef2f6; }
figure { margin: 1.5em 0; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #444; margin-top: .4em; }
details { margin: 1em 0; }
pre { background: #f6f6f6; padding: .8em; overflow-x: auto; font-size: 0.8em; }
"""


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, dict | list):
        return html.escape(json.dumps(value))
    return html.escape(str(value))


def _kv_table(mapping: dict) -> str:
    rows = "".join(
        f"<tr><th>{html.escape(str(k))}</th><td>{_fmt(v)}</td></tr>" for k, v in mapping.items()
    )
    return f"<table>{rows}</table>"


def _study_section(study_dir: Path) -> str:
    result = json.loads((study_dir / "result.json").read_text())
    title = result.get("title", study_dir.name)
    parts = [f'<h2 id="{html.escape(study_dir.name)}">{html.escape(title)}</h2>']
    if result.get("description"):
        parts.append(f"<p>{html.escape(result['description'])}</p>")
    summary = result.get("summary", [])
    if summary:
        head = "<tr><th>quantity</th><th>accel_jax</th><th>paper</th><th>note</th></tr>"
        rows = "".join(
            "<tr>"
            + "".join(f"<td>{_fmt(row.get(k, ''))}</td>" for k in ("quantity", "ours", "paper"))
            + f"<td>{html.escape(str(row.get('note', '')))}</td></tr>"
            for row in summary
        )
        parts.append(f"<table>{head}{rows}</table>")
    for figure in result.get("figures", []):
        png = study_dir / figure["file"]
        if not png.exists():
            parts.append(f"<p><em>missing figure {html.escape(figure['file'])}</em></p>")
            continue
        data = base64.b64encode(png.read_bytes()).decode()
        parts.append(
            f'<figure><img alt="{html.escape(figure["file"])}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(figure.get('caption', ''))}</figcaption></figure>"
        )
    if result.get("assumptions"):
        parts.append("<h3>Assumptions</h3>" + _kv_table(result["assumptions"]))
    if result.get("provenance"):
        parts.append("<h3>Provenance</h3>" + _kv_table(result["provenance"]))
    parts.append(
        "<details><summary>Full result.json</summary><pre>"
        + html.escape(json.dumps(result, indent=2))
        + "</pre></details>"
    )
    return "\n".join(parts)


def _has_paper_value(value) -> bool:
    return value is not None and str(value).strip() not in ("", "—", "-")


def _published_table(results: dict[str, dict]) -> str:
    """Every summary row that has a published value, beside ours, study by study."""
    rows = []
    for name, result in results.items():
        for row in result.get("summary", []):
            if _has_paper_value(row.get("paper")):
                rows.append(
                    f'<tr><td><a href="#{html.escape(name)}">{html.escape(name)}</a></td>'
                    + "".join(f"<td>{_fmt(row.get(k, ''))}</td>" for k in ("quantity", "ours"))
                    + f"<td>{_fmt(row.get('paper'))}</td>"
                    + f"<td>{html.escape(str(row.get('note', '')))}</td></tr>"
                )
    if not rows:
        return ""
    head = "<tr><th>study</th><th>quantity</th><th>accel_jax</th><th>paper / target</th>"
    head += "<th>note</th></tr>"
    return (
        "<h3>Published numbers and targets beside ours</h3>"
        "<p>Each study's own section gives the assumptions behind its numbers.</p>"
        f"<table>{head}{''.join(rows)}</table>"
    )


def _overview_tables(name: str, tables) -> str:
    """A study's own "At a glance" tables (`result["overview"]`: a list of {"title",
    "note", "columns", "rows"}), rendered the same way for every study: the report knows
    no study's result schema."""
    parts = []
    for table in tables if isinstance(tables, list) else []:
        rows = table.get("rows") or []
        if not rows:
            continue
        head = "".join(f"<th>{html.escape(str(c))}</th>" for c in table.get("columns", []))
        body = "".join(
            "<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in row) + "</tr>" for row in rows
        )
        link = f'<a href="#{html.escape(name)}">{html.escape(name)}</a>'
        parts.append(
            f"<h3>{html.escape(str(table.get('title', name)))}</h3>"
            f"<p>{html.escape(str(table.get('note', '')))} Details in {link}.</p>"
            f"<table><tr>{head}</tr>{body}</table>"
        )
    return "".join(parts)


def _overview(study_dirs: list[Path]) -> str:
    results = {}
    for d in study_dirs:
        try:
            results[d.name] = json.loads((d / "result.json").read_text())
        except (OSError, ValueError):
            continue
    parts = [_published_table(results)]
    parts += [_overview_tables(name, result.get("overview")) for name, result in results.items()]
    body = "".join(p for p in parts if p)
    return f'<h2 id="overview">At a glance</h2>{body}' if body else ""


def build_report(study_dirs: list[Path], out_file: Path, *, title: str) -> Path:
    """Write `out_file` (HTML) from the given study output folders, atomically."""
    toc = '<li><a href="#overview">At a glance</a></li>' + "".join(
        f'<li><a href="#{html.escape(d.name)}">{html.escape(d.name)}</a></li>' for d in study_dirs
    )
    body = _overview(study_dirs) + "\n".join(_study_section(d) for d in study_dirs)
    page = (
        f"<!doctype html>{REPORT_MARKER}<html><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)}</title>"
        f"<style>{_STYLE}</style></head><body><h1>{html.escape(title)}</h1>"
        f"<ul>{toc}</ul>{body}</body></html>"
    )
    _atomic_write_bytes(out_file, page.encode())
    return out_file
