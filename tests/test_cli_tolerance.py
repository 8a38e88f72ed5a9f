"""The `accel-jax tolerance` subcommand as a designer reads it: the README's command runs on
the shipped examples/bands.csv, the table's ok/EXCEEDS and the total δ_V agree with limits
recomputed here from the docs/models.md §3 moments, and implausible options are refused."""

import csv
import json
import math
import re
import shlex
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from accel_jax.cli import main

ROOT = Path(__file__).resolve().parent.parent
BANDS = ROOT / "examples" / "bands.csv"
CYCLONE4 = ["--budget", "5e-4", "--mean-accel", "2", "--sine", "1.2", "1.2", "0.5"]
PASSPORTS_PPM = {  # docs/models.md §3 Table 4 (m31, m32 not given: 0)
    "aks05": {"asymmetry": 15, "k2": 2, "k3": 7, "k4": 0.02, "k5": 0.3, "m31": 0, "m32": 0},
    "al1m": {"asymmetry": 25, "k2": 105, "k3": 87, "k4": 10, "k5": 0.9, "m31": 0, "m32": 0},
}
SHARES = {  # the paper's share of δ* per coefficient, eqs. (12)-(15)
    "asymmetry": 0.44,
    "k2": 0.44,
    "k3": 0.35,
    "k4": 0.24,
    "k5": 0.24,
    "m31": 0.22,
    "m32": 0.22,
}
NAMES = {"A1": "asymmetry"}


def _readme_command() -> list[str]:
    line = next(
        line
        for line in (ROOT / "README.md").read_text().splitlines()
        if "accel-jax tolerance" in line
    )
    line = re.sub(r"\[[^]]*\]", "", line)  # drop the optional [--json ...]
    words = shlex.split(line)
    return words[words.index("tolerance") :]


def _paper_sigma(path: Path) -> float:
    # σ = sqrt((1/n) Σ η S Δf), the paper's formula (docs/models.md §3).
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    power = [
        float(r["eta"]) * float(r["psd"]) * (float(r["f_high"]) - float(r["f_low"])) for r in rows
    ]
    return math.sqrt(sum(power) / len(power))


def _expected(budget, a, b, sigma):
    """Exact sensitivities ∂δ_V/∂k of the moments in docs/models.md §3 (in-phase sine b on OA, PA,
    IA plus fully correlated Gaussian σ on every axis), and the limits from them [ppm]."""
    b1, b2, b3 = b
    v2 = 0.5 * b3**2 + sigma**2  # E v3²
    v4 = 0.375 * b3**4 + 3 * b3**2 * sigma**2 + 3 * sigma**4  # E v3⁴ (sine ⟂ Gaussian)
    # A1: ½ (E|a + v3| − |a|), E over the sine phase of the Gaussian E|μ + σZ| in closed form.
    mu = a + b3 * np.sin(np.linspace(0, 2 * np.pi, 20000, endpoint=False))
    erf = np.vectorize(math.erf)
    mean_abs = sigma * np.sqrt(2 / np.pi) * np.exp(-(mu**2) / (2 * sigma**2)) + mu * erf(
        mu / (sigma * np.sqrt(2))
    )
    sens = {
        "asymmetry": 0.5 * (float(np.mean(mean_abs)) - abs(a)),
        "k2": v2,
        "k3": 3 * a * v2,
        "k4": 6 * a**2 * v2 + v4,
        "k5": 10 * a**3 * v2 + 5 * a * v4,
        "m31": 0.5 * b3 * b1 + sigma**2,
        "m32": 0.5 * b3 * b2 + sigma**2,
    }
    gradient = {k: SHARES[k] * budget / abs(s) * 1e6 for k, s in sens.items()}
    paper = {  # eqs. (13), (15) as docs/models.md §3 reconstructs them
        "asymmetry": 0.44 * budget / (0.673 * b3 + 0.125 * sigma),
        "k2": 0.44 * budget / (0.5 * b3**2 + sigma**2),
        "k3": 0.35 * budget / (a * (1.5 * b3**2 + 3 * sigma**2)),
        "k4": min(
            0.44 * budget / (0.375 * b3**4 + 3 * sigma**4),
            0.24 * budget / (3 * a**2 * (b3**2 + 2 * sigma**2)),
        ),
        "k5": min(
            0.35 * budget / (a * (1.875 * b3**4 + 15 * sigma**4)),
            0.24 * budget / (5 * a**3 * (b3**2 + 2 * sigma**2)),
        ),
        "m31": 0.22 * budget / (0.5 * b3 * b1 + sigma**2),
        "m32": 0.22 * budget / (0.5 * b3 * b2 + sigma**2),
    }
    return sens, gradient, {k: v * 1e6 for k, v in paper.items()}


def _table(output: str) -> dict[str, list[str]]:
    rows = {}
    for line in output.splitlines():
        words = line.split()
        if words and words[0] in ("A1", "k2", "k3", "k4", "k5", "m31", "m32"):
            rows[NAMES.get(words[0], words[0])] = words
    return rows


@pytest.fixture
def in_repo(monkeypatch):
    monkeypatch.chdir(ROOT)  # the README's command names examples/bands.csv relative to it


def test_readme_command_runs_on_the_shipped_bands(in_repo, tmp_path):
    args = _readme_command()
    assert "examples/bands.csv" in args and "--unit" in args
    out = tmp_path / "t.json"
    result = CliRunner().invoke(main, [*args, "--json", str(out)])
    assert result.exit_code == 0, result.output
    text = result.output
    # The header names the limit ok/EXCEEDS is judged against; every row is complete.
    assert "check: |aks05 passport coefficient| against the gradient limit (not the paper" in text
    assert "  gradient  the paper's share of δ* over the exact sensitivity" in text
    rows = _table(text)
    assert list(rows) == list(SHARES)
    assert all(len(words) == 8 for words in rows.values()), rows
    assert "None" not in text and not re.search(r"[\[(][-\d.]+,", text)  # no raw lists
    # Fixed widths: each number ends where its column's name ends, the mark starts under
    # "check".
    header = next(line for line in text.splitlines() if line.startswith("coef"))
    ends = [header.index(c) + len(c) for c in ("paper", "gradient", "full δ*", "|k|", "[g]")]
    for words in rows.values():
        line = next(line for line in text.splitlines() if line.split() == words)
        fields = list(re.finditer(r"\S+", line))
        assert [f.end() for f in fields[2:7]] == ends, (header, line)
        assert fields[7].start() == header.index("check"), (header, line)
    total = re.search(
        r"^total vibration error δ_V = (\S+) g against the budget δ\* = (\S+) g: (within|EXCEEDS)$",
        text,
        flags=re.M,
    )
    assert total, text
    assert text.rstrip().splitlines()[-2] == total.group(0)  # then only "json written"
    doc = json.loads(out.read_text())
    check = doc["unit_check"]
    assert check["judged_against"] == "gradient_paper_shares"
    assert float(total.group(1)) == pytest.approx(check["total_vibration_error_g"], rel=5e-3)
    assert float(total.group(2)) == 5e-4
    assert (total.group(3) == "within") == check["within_budget"]


@pytest.mark.parametrize("unit, exceeds", [("aks05", set()), ("al1m", {"k3", "k4", "k5"})])
def test_table_agrees_with_independently_recomputed_limits(in_repo, unit, exceeds):
    result = CliRunner().invoke(
        main, ["tolerance", *CYCLONE4, "--psd", "examples/bands.csv", "--unit", unit]
    )
    assert result.exit_code == 0, result.output
    sigma = _paper_sigma(BANDS)
    assert sigma == pytest.approx(1.161, abs=1e-3)  # the paper's Table 1
    assert f"random σ = {sigma:.4g} g" in result.output
    sens, gradient, paper = _expected(5e-4, 2.0, (1.2, 1.2, 0.5), sigma)
    rows = _table(result.output)
    passport = PASSPORTS_PPM[unit]
    marks = {}
    for name, words in rows.items():
        _, _, paper_col, gradient_col, full_col, k_col, part_col, mark = words
        rel = 1e-3  # printed to 4 significant figures
        assert float(paper_col) == pytest.approx(paper[name], rel=1e-3), name
        assert float(gradient_col) == pytest.approx(gradient[name], rel=rel), name
        assert float(full_col) == pytest.approx(gradient[name] / SHARES[name], rel=rel), name
        assert float(k_col) == pytest.approx(abs(passport[name]))
        assert float(part_col) == pytest.approx(sens[name] * passport[name] * 1e-6, rel=rel)
        # ok/EXCEEDS is |k| against the recomputed gradient limit (not the paper column).
        assert mark == ("ok" if abs(passport[name]) <= gradient[name] else "EXCEEDS"), name
        marks[name] = mark
    assert {n for n, m in marks.items() if m == "EXCEEDS"} == exceeds
    if unit == "al1m":  # k5 = 0.9 ppm/g⁴ passes the paper column but not the gradient one
        assert paper["k5"] > 0.9 > gradient["k5"]
    total = sum(sens[n] * passport[n] * 1e-6 for n in SHARES)
    line = re.search(r"^total vibration error δ_V = (\S+) g .*: (\w+)$", result.output, re.M)
    assert float(line.group(1)) == pytest.approx(total, rel=5e-3)
    assert line.group(2) == ("within" if abs(total) <= 5e-4 else "EXCEEDS")
    assert line.group(2) == ("within" if unit == "aks05" else "EXCEEDS")


def test_without_a_unit_the_total_line_says_why_there_is_none():
    result = CliRunner().invoke(main, ["tolerance", *CYCLONE4, "--rms", "1.4"])
    assert result.exit_code == 0, result.output
    assert "EXCEEDS" not in result.output and "check:" not in result.output
    assert "total vibration error δ_V: no device coefficients given" in result.output


@pytest.mark.parametrize(
    "args, message",
    [
        (["--budget", "500"], "in g (e.g. 5e-4"),
        (["--budget", "0"], "budget must be positive"),
        (["--budget", "-1"], "budget must be positive"),
        (["--budget", "nan"], "--budget: nan; the budget"),  # quoted as given, not "—"
        (["--budget", "inf"], "at most 1 g"),
        (["--budget", "5e-4", "--sine", "-1", "1", "1"], "non-negative"),
        (["--budget", "5e-4", "--rms", "1", "--sine-freq", "-30"], "positive"),
        (["--budget", "5e-4", "--rms", "-1"], "non-negative"),
        (["--budget", "5e-4", "--rms", "nan"], "nan g; the RMS must be finite"),
        # finite but beyond any accelerometer (the a⁵ terms of 1e300 g overflow)
        (["--budget", "5e-4", "--rms", "1e300"], "at most 100000 g"),
        (["--budget", "5e-4", "--rms", "1", "--sine", "1e300", "0", "0"], "at most 100000 g"),
        (["--budget", "5e-4", "--rms", "1", "--sine-freq", "1e300"], "at most 1e+09 Hz"),
        (["--budget", "5e-4"], "no vibration given"),
    ],
)
def test_implausible_options_get_one_error_line(args, message):
    result = CliRunner().invoke(main, ["tolerance", "--mean-accel", "2", *args])
    _one_error_line(result, message)


def test_a_mean_acceleration_beyond_any_accelerometer_is_refused():
    args = ["tolerance", "--budget", "5e-4", "--rms", "1", "--mean-accel", "1e300"]
    _one_error_line(CliRunner().invoke(main, args), "at most 100000 g in size")


def _one_error_line(result, message):
    assert result.exit_code != 0
    assert isinstance(result.exception, SystemExit)  # a click error, not a crash
    assert "Traceback" not in result.output
    errors = [line for line in result.stderr.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, result.stderr
    assert message in errors[0], errors[0]
    assert result.stdout == ""
