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


_LIMITS = ("A1", "k2", "k3", "k4", "k5", "m")
_LIMIT_UNITS = ("ppm", "ppm/g", "ppm/g²", "ppm/g³", "ppm/g⁴", "ppm/g")


def _tolerance_table(result: dict) -> str:
    """Table 2 of SPEC.md §3: the paper's limits, ours by its method, ours by gradients."""
    cases = [("Cyclone-4", result.get("cyclone4"))]
    tactical = result.get("tactical")
    if tactical:
        cases.append(("tactical, short range", tactical))
        if tactical.get("long_range"):
            cases.append(("tactical, long range", tactical["long_range"]))
    head = "<tr><th>example</th><th>method</th>" + "".join(
        f"<th>{k} [{u}]</th>" for k, u in zip(_LIMITS, _LIMIT_UNITS, strict=True)
    )
    rows = []
    for label, case in cases:
        if not case:
            continue
        for method, key in (
            ("paper, Table 2", "table2"),
            ("paper's method (ours)", "paper"),
            ("gradient (ours)", "gradient"),
        ):
            values = case.get(key, {})
            rows.append(
                f"<tr><td>{html.escape(label)}</td><td>{html.escape(method)}</td>"
                + "".join(f"<td>{_fmt(values.get(k, ''))}</td>" for k in _LIMITS)
                + "</tr>"
            )
    if not rows:
        return ""
    return (
        "<h3>Tolerance limits on the transfer-function coefficients (admissible |k|)</h3>"
        '<p>See <a href="#tolerance_limits">tolerance_limits</a> for which Table 2 entries '
        "reproduce and why the others do not.</p>"
        f"<table>{head}</tr>{''.join(rows)}</table>"
    )


def _sim_to_real_table(result: dict) -> str:
    """The blind validation of the gap diagnosis, one row per kind of record."""
    rows = []
    labels = {"step_independent": "step (independent simulator, other conventions)"}
    for kind in ("step", "step_independent", "vibration", "noise"):
        section = result.get(kind)
        if not isinstance(section, dict) or "n_datasets" not in section:
            continue
        assurance = section.get("false_assurance")
        cells = [
            labels.get(kind, kind),
            section.get("n_datasets"),
            section.get("accuracy"),
            section.get("accuracy_incl_cannot_tell_naming_truth"),
            section.get("false_alarm_rate"),
            section.get("median_gap_shrink"),
            section.get("out_of_library_unexplained_rate", "–"),
            "–" if assurance is None else f"{assurance} of {section.get('none_verdicts')}",
        ]
        rows.append("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in cells) + "</tr>")
    if not rows:
        return ""
    head = (
        "<tr><th>kind</th><th>blind datasets</th><th>named correctly</th>"
        "<th>… or cannot_tell naming the truth</th><th>false alarms</th>"
        "<th>median held-out gap shrink</th><th>outside the library: unexplained</th>"
        "<th>false assurance (none with a true gap ≥ 3 floors)</th></tr>"
    )
    return (
        "<h3>Sim-to-real diagnosis, checked blind</h3>"
        "<p>Targets (issue 6): ≥ 0.90 named, ≤ 0.05 false alarms, median shrink ≥ 0.5. "
        'Details in <a href="#sim_to_real_validation">sim_to_real_validation</a>.</p>'
        f"<table>{head}{''.join(rows)}</table>"
    )


def _overview(study_dirs: list[Path]) -> str:
    results = {}
    for d in study_dirs:
        try:
            results[d.name] = json.loads((d / "result.json").read_text())
        except (OSError, ValueError):
            continue
    parts = [_published_table(results)]
    if "tolerance_limits" in results:
        parts.append(_tolerance_table(results["tolerance_limits"]))
    if "sim_to_real_validation" in results:
        parts.append(_sim_to_real_table(results["sim_to_real_validation"]))
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
