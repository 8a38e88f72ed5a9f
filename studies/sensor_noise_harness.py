"""Blind harness of the real-sensor noise effects (`accel_jax.noise.select_sensor_noise`).

Records are drawn by `studies/noise_truth.py` (NumPy/SciPy only, written apart from the
diagnosing code) with the conventions a user's records come with: sample rates of 50 to
400 Hz, a level anywhere within ±1.2 g (and either polarity), white noise σ_w from 0.1 to
10 mg, and each effect at a magnitude drawn from a stated range (`RANGES`): alone, in
composites of two or three effects, and absent (white records: the false-alarm rate). The
diagnosis sees only the samples and the sample interval.

Scored: each effect named (alone or within a composite verdict) per effect, the false
alarms on white records (any verdict but `none`), the periodic lines' frequencies
(relative error of the line nearest the truth) and the quantisation steps.

Run: `python studies/sensor_noise_harness.py [--per-effect 100] [--samples 10000]
[--jobs 2] [--out DIR]` (float64; about 5 s of one core per record).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import noise_truth  # noqa: E402

EFFECTS = (
    "gauss_markov",
    "exp_cosine",
    "random_walk",
    "flicker",
    "bandlimit",
    "sinusoid",
    "startup_transient",
    "quantization",
)

RANGES = {
    "sample_rate_Hz": (50.0, 100.0, 200.0, 400.0),
    "white_g": (1e-4, 1e-2),
    "gauss_markov": {"sigma_over_white": (0.5, 2.0), "tau_samples": (3.0, 100.0)},
    "exp_cosine": {"sigma_over_white": (0.5, 2.0), "period_samples": (4.0, 50.0), "q": (2, 8)},
    "random_walk": {"walk_over_record_over_white": (1.0, 5.0)},
    "flicker": {"B_over_white": (0.05, 0.3)},
    "bandlimit": {"corner_over_nyquist": (0.2, 0.7)},
    "sinusoid": {"amplitude_over_white": (0.15, 0.5), "frequency_over_rate": (0.005, 0.45)},
    "startup_transient": {"amplitude_over_white": (3.0, 10.0), "tau_over_record": (0.005, 0.05)},
    "quantization": {"step_over_white": (0.5, 2.0)},
}
"""Truth ranges (log-uniform where a ratio)."""


def _log_uniform(rng, lo_hi):
    lo, hi = lo_hi
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def draw(rng: np.random.Generator, effects, n: int) -> dict:
    """A truth: its record's sample interval, the `noise_truth.record` spec, and the facts
    the scoring needs."""
    rate = float(rng.choice(RANGES["sample_rate_Hz"]))
    dt = 1 / rate
    white = _log_uniform(rng, RANGES["white_g"])
    spec = {"white": white, "level": float(rng.choice([-1, 1]) * rng.uniform(0.0, 1.2))}
    facts = {"effects": list(effects), "sample_rate_Hz": rate, "white_g": white}
    for e in effects:
        r = RANGES[e]
        if e == "gauss_markov":
            spec[e] = (
                white * _log_uniform(rng, r["sigma_over_white"]),
                _log_uniform(rng, r["tau_samples"]) * dt,
            )
        elif e == "exp_cosine":
            beta = 2 * math.pi / (_log_uniform(rng, r["period_samples"]) * dt)
            spec[e] = (
                white * _log_uniform(rng, r["sigma_over_white"]),
                beta / _log_uniform(rng, r["q"]),
                beta,
            )
        elif e == "random_walk":
            walk = white * _log_uniform(rng, r["walk_over_record_over_white"])
            spec[e] = walk**2 / (n * dt)
        elif e == "flicker":
            spec[e] = white * _log_uniform(rng, r["B_over_white"])
        elif e == "bandlimit":
            spec[e] = _log_uniform(rng, r["corner_over_nyquist"]) * rate / 2
        elif e == "sinusoid":
            f = _log_uniform(rng, r["frequency_over_rate"]) * rate
            spec["lines"] = [(f, white * _log_uniform(rng, r["amplitude_over_white"]))]
            facts["line_Hz"] = f
        elif e == "startup_transient":
            spec["transient"] = (
                float(rng.choice([-1, 1])) * white * _log_uniform(rng, r["amplitude_over_white"]),
                _log_uniform(rng, r["tau_over_record"]) * n * dt,
            )
        elif e == "quantization":
            spec[e] = white * _log_uniform(rng, r["step_over_white"])
            facts["step_g"] = spec[e]
    return {"dt": dt, "spec": spec, "facts": facts}


def plan(per_effect: int, seed: int) -> list:
    """(effects, seed) of every record: `per_effect` single-effect records per effect, as
    many white ones, and composites of two or three effects until every effect appears in
    `per_effect` of them too."""
    rng = np.random.default_rng(seed)
    jobs = [((), int(rng.integers(2**31)))]
    jobs = [((), int(rng.integers(2**31))) for _ in range(per_effect)]
    for e in EFFECTS:
        jobs += [((e,), int(rng.integers(2**31))) for _ in range(per_effect)]
    counts = dict.fromkeys(EFFECTS, 0)
    while min(counts.values()) < per_effect:
        k = int(rng.integers(2, 4))
        lacking = [e for e in EFFECTS if counts[e] < per_effect]
        first = str(rng.choice(lacking))
        others = [e for e in EFFECTS if e != first]
        combo = (first, *rng.choice(others, size=k - 1, replace=False).tolist())
        # one stochastic resonance per record: gauss_markov and exp_cosine together are
        # not told apart from one exp_cosine of wider band by any likelihood of this length
        if {"gauss_markov", "exp_cosine"} <= set(combo):
            continue
        for e in combo:
            counts[e] += 1
        jobs.append((tuple(sorted(combo)), int(rng.integers(2**31))))
    return jobs


# --------------------------------------------------------------------------------------
# The ideal observer: how much evidence each effect of a truth can give at all
# --------------------------------------------------------------------------------------

PENALTY_K = {
    "gauss_markov": 2,
    "exp_cosine": 3,
    "random_walk": 1,
    "flicker": 1,
    "bandlimit": 1,
    "sinusoid": 3,
    "startup_transient": 2,
}
"""Parameters of each effect: the k of the k ln J penalty an evidence rule such as BIC
charges it."""

DETECTABLE_MARGIN = 2.0
"""An effect counts as detectable in a record when the ideal observer's expected 2 ln Λ
is at least this many times the bar a BIC-type rule sets (10 + k ln J): an observer that
knew the effect's form and every parameter would then clear the bar with probability above
0.9 (2 ln Λ is noncentral χ²_k with mean k + E and variance 2k + 4E)."""


def noise_spectrum(
    spec: dict, dt: float, omega: np.ndarray, without: str | None = None, differenced=False
):
    """The truth's spectral density per sample of the stochastic part of the level record
    (`noise_truth.record`'s sum, its low-pass applied to all of it, then the ADC grid's
    q²/12), with the effect `without` left out; with `differenced`, that of the record's
    first difference (λ(ω) = 2 − 2 cos ω times it: finite at ω = 0 with a random walk)."""
    lam = 2 - 2 * np.cos(omega)
    s = np.full_like(omega, spec["white"] ** 2)
    if "gauss_markov" in spec and without != "gauss_markov":
        sigma, tau = spec["gauss_markov"]
        rho = math.exp(-dt / tau)
        s += sigma**2 * (1 - rho**2) / (1 - 2 * rho * np.cos(omega) + rho**2)
    if "exp_cosine" in spec and without != "exp_cosine":
        sigma, alpha, beta = spec["exp_cosine"]
        rho, theta = math.exp(-alpha * dt), beta * dt

        def poisson(u):
            return (1 - rho**2) / (1 - 2 * rho * np.cos(u) + rho**2)

        s += sigma**2 / 2 * (poisson(omega - theta) + poisson(omega + theta))
    if "flicker" in spec and without != "flicker":
        safe = np.where(omega > 0, omega, 1.0)
        s += np.where(omega > 0, spec["flicker"] ** 2 / safe, 0.0 if differenced else np.inf)
    if differenced:
        s = s * lam
    if "random_walk" in spec and without != "random_walk":
        walk = spec["random_walk"] * dt
        s += walk if differenced else walk / lam
    if "bandlimit" in spec and without != "bandlimit":
        from scipy import signal

        sos = signal.butter(2, spec["bandlimit"], fs=1 / dt, output="sos")
        s *= np.abs(signal.sosfreqz(sos, worN=omega)[1]) ** 2
    if "quantization" in spec:
        s += spec["quantization"] ** 2 / 12 * (lam if differenced else 1.0)
    return s


def _durbin(gamma: np.ndarray):
    """Durbin–Levinson on a stationary autocovariance: yields (k, ℓ_k, D_k), ℓ_k the
    coefficients of sample k's prediction error from all earlier ones ([1, −φ_k1, …]) and
    D_k its variance (C⁻¹ = Σ_k ℓ_k ℓ_kᵀ / D_k, ln det C = Σ_k ln D_k)."""
    phi = np.zeros(0)
    d = float(gamma[0])
    yield 0, np.ones(1), d
    for k in range(1, gamma.size):
        kappa = (gamma[k] - phi @ gamma[k - 1 : 0 : -1]) / d if k > 1 else gamma[1] / d
        phi = np.concatenate([phi - kappa * phi[::-1], [kappa]])
        d = d * (1 - kappa * kappa)
        yield k, np.concatenate([[1.0], -phi]), d


def exact_divergence(gamma_true: np.ndarray, gamma_alt: np.ndarray) -> float:
    """2 KL(N(0, C_true) ‖ N(0, C_alt)) of two stationary Gaussian series of length
    `gamma.size` exactly: tr(C_alt⁻¹ C_true) − N − ln det(C_alt⁻¹ C_true), the trace as
    N + Σ_k ℓ_kᵀ (C_true − C_alt) ℓ_k / D_k over C_alt's Durbin–Levinson rows (each
    quadratic form through the row's autocorrelation, by FFT)."""
    extra = gamma_true - gamma_alt
    trace, logdet_alt = 0.0, 0.0
    for k, row, d in _durbin(gamma_alt):
        size = 1 << (2 * row.size - 1).bit_length()
        corr = np.fft.irfft(np.abs(np.fft.rfft(row, size)) ** 2, size)[: row.size]
        trace += (extra[0] * corr[0] + 2 * extra[1 : k + 1] @ corr[1:]) / d
        logdet_alt += math.log(d)
    logdet_true = sum(math.log(d) for _, _, d in _durbin(gamma_true))
    return float(trace - logdet_true + logdet_alt)


def _differenced_autocovariance(spec, dt, size, without=None) -> np.ndarray:
    grid = 8 * size
    w = 2 * np.pi * np.arange(grid) / grid
    folded = np.minimum(w, 2 * np.pi - w)
    f = noise_spectrum(spec, dt, folded, without=without, differenced=True)
    return np.real(np.fft.ifft(f))[:size]


def oracle_evidence(spec: dict, dt: float, n: int) -> dict:
    """The ideal observer's expected 2 ln Λ for each effect of the truth on the training
    part (the first 2/3 of the record, m samples, as the diagnosis uses), the effect's form
    and parameters known and the level unknown, all on the record's first difference (the
    level drops out; C its Toeplitz covariance): for a stochastic effect 2 KL of the truth
    against the truth without it, exactly (`exact_divergence`; the Whittle sum
    Σ_j 2(ρ − 1 − ln ρ) is 2.2× too low for a random walk and 1.2× for flicker); for a
    periodic line A² m / (2 S(ω)); for the start-up transient s, Δsᵀ C⁻¹ Δs
    (`scipy.linalg.solve_toeplitz`; at the record's start nothing before pins the level the
    transient departs from, which a frequency-domain form would assume, 3× too high under
    a random walk). NumPy/SciPy only."""
    from scipy.linalg import solve_toeplitz

    m = int(round(2 / 3 * n))
    gamma = _differenced_autocovariance(spec, dt, m - 1)
    out = {}
    for name in ("gauss_markov", "exp_cosine", "random_walk", "flicker", "bandlimit"):
        if name in spec:
            without = _differenced_autocovariance(spec, dt, m - 1, without=name)
            out[name] = exact_divergence(gamma, without)
    for f, amp in spec.get("lines", ()):
        w = 2 * np.pi * f * dt
        out["sinusoid"] = float(amp**2 * m / (2 * noise_spectrum(spec, dt, np.array([w]))[0]))
    if "transient" in spec:
        a, tau = spec["transient"]
        ds = np.diff(a * np.exp(-np.arange(m) * dt / tau))
        out["startup_transient"] = float(ds @ solve_toeplitz(gamma, ds))
    return out


STOCHASTIC = ("gauss_markov", "exp_cosine", "random_walk", "flicker", "bandlimit")


def realized_evidence(spec: dict, dt: float, x: np.ndarray) -> dict:
    """The ideal observer's 2 ln Λ on *this* record, for each stochastic effect of the
    truth: the exact Gaussian log-likelihood ratio of the whole record's first difference
    y (the detector's evidence is on the whole record too) under the truth against the truth without the effect, both with their true
    parameters, yᵀ(C₀⁻¹ − C₁⁻¹)y + ln det C₀ − ln det C₁ (`solve_toeplitz`, `_durbin`).
    The expected value (`oracle_evidence`) says what a record of this truth holds on
    average; this says what the one drawn holds (an effect whose evidence lies in a few of
    the lowest bins, flicker above all, scatters widely about its mean). Only for records
    whose other effects are stochastic too (no line or transient: their phase and start
    are not the observer's); the output grid is taken as white q²/12. NumPy/SciPy only.
    None where a covariance of the whole record's length is not positive definite in
    float64 (a Durbin–Levinson variance D_k ≤ 0: a low-pass far below Nyquist leaves the
    differenced spectrum near zero over most of the band): the observer is then not
    computed, and the record is left out of the realized count (not counted undetectable)."""
    from scipy.linalg import solve_toeplitz

    if "lines" in spec or "transient" in spec:
        return {}
    m = x.size
    y = np.diff(x)

    def log_det(gamma):
        variances = [d for _, _, d in _durbin(gamma)]
        if not min(variances) > 0:
            return None
        return sum(math.log(d) for d in variances)

    gamma = _differenced_autocovariance(spec, dt, m - 1)
    full_det = log_det(gamma)
    if full_det is None:
        return None
    full = float(y @ solve_toeplitz(gamma, y)) + full_det
    out = {}
    for name in STOCHASTIC:
        if name in spec:
            without = _differenced_autocovariance(spec, dt, m - 1, without=name)
            det = log_det(without)
            if det is None:
                return None
            out[name] = float(y @ solve_toeplitz(without, y)) + det - full
    return out


def realized_evidence_unavailable(spec: dict, realized: dict) -> bool:
    """Whether the record's stochastic effects went without the realized observer (its
    covariance not positive definite in float64: `realized_evidence` returned None)."""
    if "lines" in spec or "transient" in spec:
        return False
    return any(name in spec for name in STOCHASTIC) and not realized


def detectable(effect: str, oracle: dict, n: int) -> bool:
    """Whether the ideal observer clears `DETECTABLE_MARGIN` × the bar for `effect`
    (quantisation, found from the values, always counts)."""
    if effect == "quantization":
        return True
    return oracle.get(effect, 0.0) >= DETECTABLE_MARGIN * _bar(effect, n)


def _bar(effect: str, n: int) -> float:
    """10 + k ln J, J the record's Fourier bins (n/2): the detector's evidence uses them
    all."""
    return 10 + PENALTY_K[effect] * math.log(n // 2)


def run_one(job, n: int) -> dict:
    import accel_jax as aj

    effects, seed = job
    rng = np.random.default_rng(seed)
    truth = draw(rng, effects, n)
    x = noise_truth.record(rng, n, truth["dt"], truth["spec"])
    started = time.perf_counter()
    try:
        found = aj.noise.select_sensor_noise(x, truth["dt"])
    except Exception as error:  # a failure is a result: recorded, not hidden
        return {
            "truth": truth["facts"],
            "oracle": oracle_evidence(truth["spec"], truth["dt"], n),
            "error": f"{type(error).__name__}: {error}",
        }
    out = {
        "truth": truth["facts"],
        "oracle": oracle_evidence(truth["spec"], truth["dt"], n),
        "realized": realized_evidence(truth["spec"], truth["dt"], x) or {},
        "verdict": found.verdict,
        "effects": list(found.effects),
        "unexplained": found.unexplained,
        "ties": [[t["effect"], t["alternative"]] for t in found.held_out.ties],
        # no record here has a step in its level: every one found is a false alarm
        "level_shifts": len(found.held_out.level_shifts),
        # every truth here is stationary: a spectral change found is a false alarm
        "spectral_change": bool(found.held_out.spectral_change.get("significant")),
        "seconds": time.perf_counter() - started,
    }
    if realized_evidence_unavailable(truth["spec"], out["realized"]):
        out["realized_unavailable"] = True
    if "line_Hz" in truth["facts"] and "sinusoid" in found.parameters:
        lines = [line["frequency_Hz"] for line in found.parameters["sinusoid"]]
        nearest = min(lines, key=lambda f: abs(f - truth["facts"]["line_Hz"]))
        out["line_relative_error"] = abs(nearest / truth["facts"]["line_Hz"] - 1)
    if "step_g" in truth["facts"] and found.quantization is not None:
        out["step_relative_error"] = abs(found.quantization["step"] / truth["facts"]["step_g"] - 1)
    return out


def _worker(args):
    job, n = args
    os.environ.setdefault("XLA_FLAGS", "")
    import jax

    jax.config.update("jax_enable_x64", True)
    return run_one(job, n)


def score(rows: list, n: int) -> dict:
    per = {}
    for e in EFFECTS:
        with_e = [r for r in rows if e in r["truth"]["effects"] and "error" not in r]
        named = [r for r in with_e if e in r["effects"]]
        seen = [r for r in with_e if detectable(e, r["oracle"], n)]
        seen_named = [r for r in seen if e in r["effects"]]
        alone = [r for r in seen if len(r["truth"]["effects"]) == 1]
        # not named, but offered as the equal of a named effect (a tie the record leaves)
        tied = [
            r
            for r in seen
            if e not in r["effects"] and any(alt == e for _, alt in r.get("ties", []))
        ]
        # where the ideal observer, the truth's parameters known, clears the bar on the
        # record drawn (records without a line or transient: `realized_evidence`)
        held = [
            r
            for r in with_e
            if e in STOCHASTIC and r.get("realized", {}).get(e, -math.inf) >= _bar(e, n)
        ]
        per[e] = {
            "records": len(with_e),
            "named": len(named),
            "rate": len(named) / max(len(with_e), 1),
            "detectable": len(seen),
            "named_when_detectable": len(seen_named),
            "rate_when_detectable": len(seen_named) / max(len(seen), 1),
            "tied_when_detectable_not_named": len(tied),
            "realized_detectable": len(held),
            "named_when_realized_detectable": sum(e in r["effects"] for r in held),
            "detectable_alone": len(alone),
            "detectable_in_composites": len(seen) - len(alone),
        }
    white = [r for r in rows if not r["truth"]["effects"] and "error" not in r]
    alarms = [r for r in white if r["verdict"] != "none"]
    lines = [r["line_relative_error"] for r in rows if "line_relative_error" in r]
    steps = [r["step_relative_error"] for r in rows if "step_relative_error" in r]
    extras = {}
    for r in rows:
        if "error" in r:
            continue
        for e in r["effects"]:
            if e not in r["truth"]["effects"]:
                extras[e] = extras.get(e, 0) + 1
    return {
        "per_effect": per,
        "white_records": len(white),
        "false_alarms": len(alarms),
        "false_alarm_rate": len(alarms) / max(len(white), 1),
        "false_alarm_verdicts": sorted({r["verdict"] for r in alarms}),
        "lines_within_1pct": sum(e <= 0.01 for e in lines),
        "lines_scored": len(lines),
        "steps_within_5pct": sum(e <= 0.05 for e in steps),
        "steps_scored": len(steps),
        "spurious_effects_named": extras,
        "unexplained_records": sum(bool(r.get("unexplained")) for r in rows),
        "records_with_a_false_level_shift": sum(r.get("level_shifts", 0) > 0 for r in rows),
        "records_with_a_false_spectral_change": sum(bool(r.get("spectral_change")) for r in rows),
        "errors": [r["error"] for r in rows if "error" in r],
        "realized_unavailable_records": sum(bool(r.get("realized_unavailable")) for r in rows),
        "median_seconds": float(np.median([r["seconds"] for r in rows if "seconds" in r])),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-effect", type=int, default=100)
    parser.add_argument("--samples", type=int, default=10000)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument(
        "--resume",
        action="store_true",
        help="keep the rows already in OUT/rows.jsonl (a run cut short, same arguments) and "
        "run the plan's records after them",
    )
    parser.add_argument(
        "--shuffle",
        action="store_true",
        help="run the records in a random order (the same records): a run stopped early "
        "leaves a fair sample in OUT/rows.jsonl",
    )
    args = parser.parse_args(argv)
    jobs = plan(args.per_effect, args.seed)
    if args.shuffle:
        jobs = [jobs[i] for i in np.random.default_rng(args.seed + 1).permutation(len(jobs))]
    started = time.perf_counter()
    stream = None
    rows = []
    if args.resume:
        if args.out is None or not (args.out / "rows.jsonl").is_file():
            parser.error("--resume needs --out DIR holding the rows.jsonl of the run cut short")
        with open(args.out / "rows.jsonl") as done:
            rows = [json.loads(line) for line in done if line.strip()]
        if len(rows) > len(jobs):
            parser.error(f"{len(rows)} rows in OUT/rows.jsonl, more than the plan's {len(jobs)}")
        print(f"resuming after {len(rows)} records", flush=True)
    resumed = len(rows)
    todo = jobs[resumed:]  # the pool keeps the plan's order, so the rows are its head
    if args.out is not None:  # each row as it comes (a run cut short keeps what it did)
        args.out.mkdir(parents=True, exist_ok=True)
        stream = open(args.out / "rows.jsonl", "a" if args.resume else "w")  # noqa: SIM115

    def keep(row):
        rows.append(row)
        if stream is not None:
            stream.write(json.dumps(row, default=float) + "\n")
            stream.flush()
        if len(rows) % 100 == 0:
            print(
                f"{len(rows)}/{len(jobs)} records, {time.perf_counter() - started:.0f} s",
                flush=True,
            )

    if args.jobs > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(args.jobs) as pool:
            for row in pool.imap(_worker, [(j, args.samples) for j in todo], chunksize=2):
                keep(row)
    else:
        for j in todo:
            keep(_worker((j, args.samples)))
    if stream is not None:
        stream.close()
    result = {
        "assumptions": {
            "samples_per_record": args.samples,
            "held_out": "the last third of each record",
            "ranges": RANGES,
            "truth_generator": "studies/noise_truth.py (NumPy/SciPy, not accel_jax)",
            "precision": "float64",
            "detectable": (
                f"the ideal observer's expected 2 ln Λ (oracle_evidence: the effect's form and "
                f"parameters known) ≥ {DETECTABLE_MARGIN} × (10 + k ln J), J the record's "
                f"Fourier bins (n/2)"
            ),
            "realized_detectable": (
                "the ideal observer's 2 ln Λ on the record drawn, the truth's parameters known "
                "(realized_evidence; records without a line or transient) ≥ 10 + k ln J"
            ),
            "seed": args.seed,
        },
        "resumed_after": resumed,
        "records": len(rows),
        "score": score(rows, args.samples),
        "wall_s": time.perf_counter() - started,
        "rows": rows,
    }
    text = json.dumps(result, indent=1, default=float)
    if args.out is not None:
        tmp = args.out / "result.json.tmp"
        tmp.write_text(text)
        tmp.replace(args.out / "result.json")
    print(json.dumps(result["score"], indent=1, default=float))
    print(f"{len(rows)} records in {result['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
