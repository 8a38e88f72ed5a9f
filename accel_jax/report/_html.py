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
import math
import re
from pathlib import Path

from .._format import number
from .._io import _atomic_write_bytes
from ._glossary import GLOSSARY

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
.banner { background: #fff4d6; border: 1px solid #e0b84c; padding: .6em 1em; }
.st-reproduced, .st-met { color: #1b6e2d; font-weight: 600; }
.st-explained { color: #7a5b00; font-weight: 600; }
.st-differs, .st-missed { color: #a4161a; font-weight: 600; }
dl.glossary dt { font-weight: 600; margin-top: .4em; }
dl.glossary dd { margin-left: 1.5em; }
"""

STATUSES = ("reproduced", "explained", "differs", "met", "missed")
"""The status of a number beside a published one or a target (see `row_status`)."""

TOLERANCE = 0.05
"""Relative difference within which a number reproduces a published one, unless the row
states its own `tolerance` (or a spread: `ours` written as "mean ± std")."""

_PLUS_MINUS = re.compile(r"^\s*([-+0-9.eE]+)\s*±\s*([0-9.eE+-]+)")


def _as_number(value):
    """A float, or (mean, spread) from "mean ± std", or None when not a number."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int | float):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, str):
        match = _PLUS_MINUS.match(value)
        if match:
            try:
                return float(match.group(1)), float(match.group(2))
            except ValueError:
                return None
        try:
            return float(value)
        except ValueError:
            return None
    return None


def row_status(row: dict) -> str | None:
    """The status of a summary row: its own `status` when the study states one; else, for
    a row with a published value or target: a target (`target` "≥" or "≤") met or missed;
    a number reproduced when within `tolerance` (relative, default `TOLERANCE`) or within
    two spreads of a "mean ± std"; explained when it differs and the row carries an
    `explanation`; differs otherwise. None for a row with nothing to compare with."""
    if row.get("status"):
        return str(row["status"])
    paper = row.get("paper")
    if not _has_paper_value(paper):
        return None
    ours, theirs = _as_number(row.get("ours")), _as_number(paper)
    if ours is None or theirs is None or isinstance(theirs, tuple):
        return None
    spread = 0.0
    if isinstance(ours, tuple):
        ours, spread = ours
    target = row.get("target")
    if target == "≥":
        return "met" if ours >= theirs else "missed"
    if target == "≤":
        return "met" if ours <= theirs else "missed"
    tolerance = float(row.get("tolerance", TOLERANCE))
    close = abs(ours - theirs) <= max(tolerance * abs(theirs), 2 * spread)
    if close:
        return "reproduced"
    return "explained" if row.get("explanation") else "differs"


def _status_cell(status: str | None) -> str:
    if status is None:
        return "<td></td>"
    return f'<td class="st-{html.escape(status)}">{html.escape(status)}</td>'


def _fmt(value) -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        return html.escape(number(value))
    if isinstance(value, list) and all(isinstance(v, int | float) for v in value):
        return html.escape(", ".join(number(v) for v in value))
    if isinstance(value, dict | list):
        return html.escape(json.dumps(value))
    return html.escape(str(value))


def _kv_table(mapping: dict) -> str:
    rows = "".join(
        f"<tr><th>{html.escape(str(k))}</th><td>{_fmt(v)}</td></tr>" for k, v in mapping.items()
    )
    return f"<table>{rows}</table>"


def study_failure(study_dir: Path) -> str | None:
    """Why a study of this report did not finish (its marker's reason), or None. A folder
    without a readable result.json and no reason recorded reads as not run."""
    try:
        marker = json.loads((study_dir / ".accel_jax_run.json").read_text())
    except (OSError, ValueError):
        marker = {}
    if marker.get("failed"):
        return str(marker["failed"])
    try:
        json.loads((study_dir / "result.json").read_text())
    except (OSError, ValueError):
        return "no result.json: the study did not finish"
    return None


def _failed_section(study_dir: Path, reason: str) -> str:
    name = html.escape(study_dir.name)
    log = study_dir / "error.log"
    where = (
        f" Its log: <code>{html.escape(str(log))}</code>." if log.exists() else ""
    )
    return (
        f'<section id="{name}"><h2>{name}: <span class="st-differs">failed</span></h2>'
        f"<p>This study raised before it finished: {html.escape(reason)}.{where} Run the "
        "same command again after the cause is fixed: the studies that finished are "
        "reused.</p></section>"
    )


def _study_section(study_dir: Path, *, quick: bool = False) -> str:
    reason = study_failure(study_dir)
    if reason is not None:
        return _failed_section(study_dir, reason)
    result = json.loads((study_dir / "result.json").read_text())
    title = result.get("title", study_dir.name)
    parts = [f'<h2 id="{html.escape(study_dir.name)}">{html.escape(title)}</h2>']
    if result.get("description"):
        parts.append(f"<p>{html.escape(result['description'])}</p>")
    summary = result.get("summary", [])
    if summary:
        head = (
            "<tr><th>quantity</th><th>accel_jax</th><th>paper / target</th><th>status</th>"
            "<th>note</th></tr>"
        )
        rows = "".join(
            "<tr>"
            + "".join(f"<td>{_fmt(row.get(k, ''))}</td>" for k in ("quantity", "ours", "paper"))
            + _status_cell(row_status(row))
            + f"<td>{html.escape(_note(row))}</td></tr>"
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
            f"<figcaption>{'<b>[quick run: reduced statistics]</b> ' if quick else ''}"
            f"{html.escape(figure.get('caption', ''))}</figcaption></figure>"
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


def _note(row: dict) -> str:
    note = str(row.get("note", "") or "")
    if row.get("explanation"):
        note = f"{row['explanation']}. {note}" if note else str(row["explanation"])
    return note


def _published_rows(results: dict[str, dict]) -> list[tuple[str, dict, str | None]]:
    return [
        (name, row, row_status(row))
        for name, result in results.items()
        for row in result.get("summary", [])
        if _has_paper_value(row.get("paper")) or row.get("status")
    ]


def _status_summary(results: dict[str, dict]) -> str:
    """The first screen: how many published numbers and targets are reproduced, explained
    or differ, and the rows that differ or miss, each with its study's reason."""
    rows = _published_rows(results)
    counts = {s: sum(1 for _, _, st in rows if st == s) for s in STATUSES}
    compared = sum(counts.values())
    if not compared:
        return ""
    items = ", ".join(f'<span class="st-{s}">{counts[s]} {s}</span>' for s in STATUSES if counts[s])
    flagged = [
        f'<li><a href="#{html.escape(name)}">{html.escape(name)}</a>: '
        f"{html.escape(str(row.get('quantity', '')))} — ours {_fmt(row.get('ours'))}, "
        f"paper / target {_fmt(row.get('paper'))} "
        f'(<span class="st-{st}">{st}</span>)</li>'
        for name, row, st in rows
        if st in ("differs", "missed")
    ]
    parts = [f"<p><b>Status of {compared} published numbers and targets:</b> {items}.</p>"]
    per_study = []
    for name in dict.fromkeys(n for n, _, _ in rows):
        own = [(row, st) for n, row, st in rows if n == name and st]
        if not own:
            continue
        tally = ", ".join(
            f'<span class="st-{s}">{sum(1 for _, st in own if st == s)} {s}</span>'
            for s in STATUSES
            if any(st == s for _, st in own)
        )
        # The study's headline: its first row, ours against the paper's, with its status.
        row, st = own[0]
        head = (
            f"{html.escape(str(row.get('quantity', '')))}: {_fmt(row.get('ours'))} vs "
            f"{_fmt(row.get('paper'))}, {st}"
        )
        if row.get("explanation"):
            head += f" — {html.escape(str(row['explanation']))}"
        per_study.append(
            f'<li><a href="#{html.escape(name)}">{html.escape(name)}</a> ({tally}): {head}</li>'
        )
    if per_study:
        parts.append(f"<p>By study:</p><ul>{''.join(per_study)}</ul>")
    if flagged:
        parts.append(
            "<p>Where we differ from the paper or miss a target (each study's section "
            f"says why):</p><ul>{''.join(flagged)}</ul>"
        )
    return "".join(parts)


def _published_table(results: dict[str, dict]) -> str:
    """Every summary row that has a published value, beside ours, study by study."""
    rows = [
        f'<tr><td><a href="#{html.escape(name)}">{html.escape(name)}</a></td>'
        + "".join(f"<td>{_fmt(row.get(k, ''))}</td>" for k in ("quantity", "ours"))
        + f"<td>{_fmt(row.get('paper'))}</td>"
        + _status_cell(status)
        + f"<td>{html.escape(_note(row))}</td></tr>"
        for name, row, status in _published_rows(results)
    ]
    if not rows:
        return ""
    head = "<tr><th>study</th><th>quantity</th><th>accel_jax</th><th>paper / target</th>"
    head += "<th>status</th><th>note</th></tr>"
    return (
        "<h3>Published numbers and targets beside ours</h3>"
        "<p>Each study's own section gives the assumptions behind its numbers. Status: "
        f"reproduced within {TOLERANCE:.0%} (or the row's own tolerance or spread), explained "
        "(differs, for a cause the study shows), differs, or a target met / missed.</p>"
        f"<table>{head}{''.join(rows)}</table>"
    )


def _glossary() -> str:
    items = "".join(
        f"<dt>{html.escape(term)}</dt><dd>{html.escape(meaning)}</dd>" for term, meaning in GLOSSARY
    )
    return f'<h2 id="glossary">Glossary</h2><dl class="glossary">{items}</dl>'


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
    failed = [d.name for d in study_dirs if study_failure(d) is not None]
    parts = [_failures(failed), _status_summary(results), _published_table(results)]
    parts += [_overview_tables(name, result.get("overview")) for name, result in results.items()]
    body = "".join(p for p in parts if p)
    return f'<h2 id="overview">At a glance</h2>{body}' if body else ""


def _failures(names: list[str]) -> str:
    if not names:
        return ""
    links = ", ".join(f'<a href="#{html.escape(n)}">{html.escape(n)}</a>' for n in names)
    return (
        f'<p class="banner"><b>{len(names)} of the studies failed</b> and are missing from '
        f"the tables below: {links} (each section says why and where its log is).</p>"
    )


QUICK_BANNER = (
    "Quick run: every number and figure below comes from reduced statistics (fewer "
    "seeds, records and grid points) and is not the published comparison; run "
    "`make report` (or `accel-jax report` without --quick) for the full one."
)


def build_report(
    study_dirs: list[Path], out_file: Path, *, title: str, quick: bool = False
) -> Path:
    """Write `out_file` (HTML) from the given study output folders, atomically. A quick
    run (`quick`) carries a banner, and every figure's caption says it is from reduced
    statistics."""
    toc = (
        '<li><a href="#overview">At a glance</a></li>'
        + "".join(
            f'<li><a href="#{html.escape(d.name)}">{html.escape(d.name)}</a></li>'
            for d in study_dirs
        )
        + '<li><a href="#glossary">Glossary</a></li>'
    )
    body = (
        _overview(study_dirs)
        + "\n".join(_study_section(d, quick=quick) for d in study_dirs)
        + _glossary()
    )
    banner = f'<p class="banner">{html.escape(QUICK_BANNER)}</p>' if quick else ""
    page = (
        f"<!doctype html>{REPORT_MARKER}<html><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)}</title>"
        f"<style>{_STYLE}</style></head><body><h1>{html.escape(title)}</h1>{banner}"
        f"<ul>{toc}</ul>{body}</body></html>"
    )
    _atomic_write_bytes(out_file, page.encode())
    return out_file
