"""The effect interface and the kind-independent logic of a sim-to-real diagnosis.

A diagnosis (docs/models.md §5) compares a measured record with the nominal model of its kind:

1. it refits the nominal parameters under their prior (a gap that this closes is a
   parameter error, not missing physics);
2. it localises the remaining residual (`where`);
3. it fits every candidate unmodelled effect of the kind's library (each an extension of
   the nominal model that is exactly the nominal model when its parameters are zero) on a
   training part of the record and ranks them by evidence (`rank_candidates`);
4. it measures the gap before and after the chosen effect on held-out data (`held_out_gap`).

What is kind-specific (the nominal model, the effects, the localisation) lives in one
module per kind (`step.py`; `vibration` and `noise` follow the same pattern); this module
holds the interface they implement and the ranking, verdict and held-out logic they share.

Adding an effect is one small class: subclass the kind's effect base (e.g. `AbstractStepEffect`),
set `name`, `parameter_names`, `units`, implement `initial_guess`, `physical` and the one
hook it changes, and decorate it with `register_effect`.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar

import equinox as eqx
import numpy as np

from .._checks import require_float64 as _require_float64
from .._noise.whiteness import ljung_box as ljung_box
from .discovery_result import Discovery, VibrationDiscovery
from .discovery_text import discovery_lines as discovery_lines

SIGNIFICANCE = 10.0
"""Evidence (2 ln Bayes factor, on the BIC scale) an effect needs over the nominal model to
be named: 10 is "very strong" on Kass & Raftery's scale (odds ≈ 150 : 1)."""

INDISTINCT = 6.0
"""Evidence difference below which the two best effects are not told apart (`cannot_tell`):
6 on the 2 ln B scale is odds of 20 : 1."""

NESTED_LEVEL = 0.01
"""Significance level of the likelihood-ratio test that resolves a tie between an effect and
an effect nested in it (see `rank_candidates`)."""

_EFFECTS: dict[str, dict[str, type]] = {}


class AbstractEffect(eqx.Module):
    """A candidate unmodelled effect: an extension of a kind's nominal model.

    The effect has `len(parameter_names)` scaled parameters z (dimensionless, O(1) for a
    typical magnitude); at z = 0 the extended model is exactly the nominal model. A kind's
    model calls the hooks of every registered effect (its own effect base class lists
    them), so an effect changes the model only through the hook it overrides.

    **Class attributes:**

    - `name`: the effect's name in reports (e.g. `"torquer_lag"`).
    - `kind`: the kind of record it applies to (`"step"`, `"vibration"`, `"noise"`).
    - `parameter_names`: names of its physical parameters, in the order of z.
    - `description`: one line for reports.
    """

    name: ClassVar[str]
    kind: ClassVar[str]
    parameter_names: ClassVar[tuple[str, ...]]
    description: ClassVar[str] = ""

    @property
    def n_params(self) -> int:
        """The number of scaled parameters z."""
        return len(self.parameter_names)

    @abc.abstractmethod
    def initial_guess(self, context) -> np.ndarray:
        """A starting point for z (shape (n_params,)) from the kind's fit context (host side,
        NumPy). It must be a point where the fit's gradient is informative."""

    @abc.abstractmethod
    def physical(self, z, context) -> dict[str, float]:
        """The physical values (unit in each key's name) of the scaled parameters z."""


def require_float64(why: str) -> None:
    """Raise the one clear `ValueError` a diagnosis gives when x64 is off (`why`: what
    float32 would lose)."""
    _require_float64("diagnose", why)


def register_effect(cls: type) -> type:
    """Class decorator: add an effect to its kind's library (by `cls.kind`, `cls.name`)."""
    library = _EFFECTS.setdefault(cls.kind, {})
    if cls.name in library and library[cls.name] is not cls:
        raise ValueError(f"an effect named {cls.name!r} is already registered for {cls.kind!r}.")
    library[cls.name] = cls
    return cls


def effect_library(kind: str) -> dict[str, type]:
    """The registered effects of a kind, name → class, in registration order."""
    return dict(_EFFECTS.get(kind, {}))


# --------------------------------------------------------------------------------------
# Evidence and verdict
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class CandidateFit:
    """One fitted model of a kind (the nominal model or nominal + one effect).

    **Fields:**

    - `effect`: the effect's name, or `"nominal"`.
    - `n_effect_params`: k, its number of effect parameters (0 for the nominal model).
    - `log_likelihood`: ln L on the training data at the fit, with the noise variance
        profiled out and the log-prior of the nominal parameters added.
    - `n_train`: the number of training samples (rows).
    - `held_out_ms`: mean square of the held-out prediction errors [unit²].
    - `held_out_errors`: the held-out prediction errors [unit], shape (n_test,).
    - `train_ms`: mean square of the training prediction errors [unit²] (the noise floor
        this model leaves).
    - `params`: the effect's fitted physical values.
    - `converged`: whether the fit converged.
    """

    effect: str
    n_effect_params: int
    log_likelihood: float
    n_train: int
    held_out_ms: float
    held_out_errors: np.ndarray
    train_ms: float
    params: dict
    converged: bool = True

    @property
    def log_evidence(self) -> float:
        """ln L − (k/2) ln n: the Schwarz (BIC) approximation of the log marginal likelihood
        (the nominal parameters are common to every model and carry their prior in ln L)."""
        return self.log_likelihood - 0.5 * self.n_effect_params * np.log(self.n_train)


def rank_candidates(
    nominal: CandidateFit,
    candidates: list[CandidateFit],
    *,
    significance: float = SIGNIFICANCE,
    indistinct: float = INDISTINCT,
    nested: dict[str, str] | None = None,
    nested_level: float = NESTED_LEVEL,
) -> tuple[str, list[dict], list[str]]:
    """Rank the effects by evidence and give the verdict.

    The evidence of an effect is 2 (ln E_effect − ln E_nominal) (`CandidateFit.log_evidence`;
    positive favours the effect). An effect is significant when its evidence is at least
    `significance` and it also predicts the held-out data better than the nominal model (a
    training-only gain is over-fitting, not physics). The verdict is:

    - `"none"` when no effect is significant;
    - `"cannot_tell"` when the runner-up is also significant and within `indistinct` of the
      best (both named in the returned `tied` list);
    - otherwise the best effect's name.

    Nested effects: `nested` maps an effect to a simpler one that it contains as a special
    case or limit of its extra parameters (e.g. an exponential-cosine noise at β = 0 is a
    Gauss–Markov noise). Two such effects always fit about equally well when the simpler
    one is true, so a `cannot_tell` between them is resolved for the simpler one unless the
    likelihood ratio of the larger, 2 (ln L_large − ln L_simple), is significant at
    `nested_level` for χ² with the difference of their parameter counts (Occam: the data do
    not need the extra parameters). The relation is followed transitively.

    **Returns:** `(verdict, ranking, tied)`: the ranking is a list of dicts (effect,
    evidence, significant, held_out_mean_square, params, converged), best first.
    """
    ranking = []
    for fit in candidates:
        evidence = 2.0 * (fit.log_evidence - nominal.log_evidence)
        if not np.isfinite(evidence) or not fit.converged:
            evidence = -np.inf if not np.isfinite(evidence) else evidence
        improves = fit.held_out_ms < nominal.held_out_ms
        ranking.append(
            {
                "effect": fit.effect,
                "evidence": float(evidence),
                "significant": bool(evidence >= significance and improves and fit.converged),
                "held_out_mean_square": float(fit.held_out_ms),
                "params": dict(fit.params),
                "converged": bool(fit.converged),
            }
        )
    ranking.sort(key=lambda r: (r["significant"], r["evidence"]), reverse=True)
    significant = [r for r in ranking if r["significant"]]
    if not significant:
        return "none", ranking, []
    if (
        len(significant) > 1
        and significant[0]["evidence"] - significant[1]["evidence"] < indistinct
    ):
        first, second = significant[0]["effect"], significant[1]["effect"]
        simpler = _resolve_nested(first, second, candidates, nested or {}, nested_level)
        if simpler is not None:
            return simpler, ranking, []
        return "cannot_tell", ranking, [first, second]
    return significant[0]["effect"], ranking, []


def _contains(large: str, small: str, nested: dict[str, str]) -> bool:
    seen = set()
    while large in nested and large not in seen:
        seen.add(large)
        large = nested[large]
        if large == small:
            return True
    return False


def _resolve_nested(first, second, candidates, nested, level) -> str | None:
    """The simpler of two tied effects when one nests the other and the larger's
    likelihood ratio is not significant at `level`; None otherwise."""
    from scipy.special import gammaincc  # on the host: no program to compile for one number

    fits = {fit.effect: fit for fit in candidates}
    for large, small in ((first, second), (second, first)):
        if not _contains(large, small, nested):
            continue
        dof = fits[large].n_effect_params - fits[small].n_effect_params
        ratio = 2.0 * (fits[large].log_likelihood - fits[small].log_likelihood)
        if dof <= 0:
            return None
        p_value = float(gammaincc(dof / 2.0, max(ratio, 0.0) / 2.0))
        return small if p_value > level else None
    return None


# --------------------------------------------------------------------------------------
# Held-out gap
# --------------------------------------------------------------------------------------


def _excess_rms(mean_square, floor):
    return np.sqrt(np.maximum(mean_square - floor, 0.0))


def held_out_gap(
    before: np.ndarray,
    after: np.ndarray,
    noise_floor: float,
    *,
    floor_after: float | None = None,
    n_boot: int = 200,
    block: int | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """The sim-to-real gap on held-out data before and after adding an effect.

    The gap is the RMS prediction error in excess of the noise floor,
    gap = sqrt(max(mean(e²) − σ², 0)) (σ² = `noise_floor`, the white-noise variance the
    best model leaves on the training data), so that an effect that explains everything
    systematic shrinks it to ≈ 0; the shrink is 1 − after/before. Its uncertainty is a
    moving-block bootstrap over the held-out samples (the same blocks for both models;
    blocks keep the residual's correlation), with σ² held fixed.

    **Arguments:**

    - `before`, `after`: held-out prediction errors of the nominal refit and of the model
        with the effect [unit], same shape (n_test,).
    - `noise_floor`: σ² [unit²].
    - `floor_after`: the variance the model with the effect expects of its own errors, when
        the effect is a noise (default `noise_floor`).
    - `n_boot`: bootstrap resamples; `block`: block length in samples (default
        max(10, n_test // 20)); `seed`: NumPy seed of the resampling (reproducible).

    **Returns:** a dict with `metric`, `before`, `after` [unit], `shrink`, `shrink_std`,
    `shrink_p16`, `shrink_p84`, `rms_before`, `rms_after` (the raw held-out RMS errors),
    `noise_floor_rms`, `n_held_out`.
    """
    before = np.asarray(before, dtype=np.float64)
    after = np.asarray(after, dtype=np.float64)
    n = before.shape[0]
    floor_after = noise_floor if floor_after is None else floor_after
    gap_before = float(_excess_rms(np.mean(before**2), noise_floor))
    gap_after = float(_excess_rms(np.mean(after**2), floor_after))
    shrink = 1.0 - gap_after / gap_before if gap_before > 0 else 0.0
    block = max(10, n // 20) if block is None else block
    block = min(block, n)
    rng = np.random.default_rng(seed)
    n_blocks = -(-n // block)
    starts = rng.integers(0, n - block + 1, size=(n_boot, n_blocks))
    index = (starts[:, :, None] + np.arange(block)[None, None, :]).reshape(n_boot, -1)[:, :n]
    boot_before = _excess_rms(np.mean(before[index] ** 2, axis=1), noise_floor)
    boot_after = _excess_rms(np.mean(after[index] ** 2, axis=1), floor_after)
    with np.errstate(divide="ignore", invalid="ignore"):
        boot_shrink = np.where(boot_before > 0, 1.0 - boot_after / boot_before, 0.0)
    return {
        "metric": "held-out RMS prediction error in excess of the noise floor",
        "before": gap_before,
        "after": gap_after,
        "shrink": float(shrink),
        "shrink_std": float(np.std(boot_shrink)),
        "shrink_p16": float(np.percentile(boot_shrink, 16)),
        "shrink_p84": float(np.percentile(boot_shrink, 84)),
        "rms_before": float(np.sqrt(np.mean(before**2))),
        "rms_after": float(np.sqrt(np.mean(after**2))),
        "noise_floor_rms": float(np.sqrt(noise_floor)),
        "n_held_out": int(n),
    }


# --------------------------------------------------------------------------------------
# The result
# --------------------------------------------------------------------------------------


@dataclasses.dataclass
class DiagnosisResult:
    """The outcome of a diagnosis.

    **Fields:**

    - `kind`: the kind of record.
    - `verdict`: the named effect, `"none"`, `"cannot_tell"` or `"unexplained"`
        (`accel_jax.diagnose.openworld`); for the noise kind also a composite of several
        effects joined by "+" (e.g. `"bandlimit+sinusoid+quantization"`, ending in
        `"+unexplained"` when what they leave is significant; `noise.sensor`).
    - `tied`: with `cannot_tell`, the two effects that fit equally well; else empty.
    - `ranking`: one dict per effect, best first (effect, evidence, gap_shrink, params…).
    - `gap`: the held-out gap before/after the chosen effect (`held_out_gap`).
    - `where`: the localisation of the nominal residual.
    - `refit`: the refitted nominal parameters and their shifts.
    - `traces`: arrays for plots (time or row axis, measured, nominal and best predictions,
        residuals, held-out mask), NumPy float64; not part of `to_dict`.
    - `notes`: plain-language caveats of this diagnosis (e.g. an effect left out of the
        candidates because the data cannot show it).
    - `explained_fraction`: the fraction of the held-out excess (gap²) that the chosen
        effect, or for `unexplained` the best partial effect, removes (0 when none).
    - `remaining_gap`: what remains after it: `V` (or the kind's unit), `noise_floor_…`,
        `over_floor`, `model`, `where` (in words).
    - `reason`: one or two sentences: why this verdict.
    - `next_experiment`: with a `cannot_tell` that another experiment can break (the step
        kind's two lags), the experiments a user can run, best first, each with its
        expected 2 ln B (`step.design.next_experiments`); else empty.
    - `discovery`: for a step record searched for a missing term, the `Discovery`
        (`step.discover`: a hypothesis, never a verdict — though it can show that a noise
        verdict in question explains nothing, `step.question.weigh_discovery`; `to_dict()`
        its JSON block); for a vibration table, the `VibrationDiscovery`
        (`vibration.discover`, which makes a verdict `unexplained` where terms beyond the
        library beat it); else None.
    """

    kind: str
    verdict: str
    tied: list
    ranking: list
    gap: dict
    where: dict
    refit: dict
    traces: dict = dataclasses.field(default_factory=dict, repr=False)
    notes: list = dataclasses.field(default_factory=list)
    explained_fraction: float = 0.0
    remaining_gap: dict = dataclasses.field(default_factory=dict)
    reason: str = ""
    next_experiment: list = dataclasses.field(default_factory=list)
    discovery: Discovery | VibrationDiscovery | None = None

    def to_dict(self) -> dict:
        """The JSON document of docs/models.md §5's CLI contract (plain numbers and strings)."""
        return {
            "kind": self.kind,
            "verdict": self.verdict,
            "tied": list(self.tied),
            "reason": self.reason,
            "explained_fraction": self.explained_fraction,
            "remaining_gap": self.remaining_gap,
            "ranking": self.ranking,
            "gap": self.gap,
            "where": self.where,
            "refit": self.refit,
            "notes": list(self.notes),
            **({"next_experiment": self.next_experiment} if self.next_experiment else {}),
            **({"discovery": self.discovery.to_dict()} if self.discovery is not None else {}),
        }

    def summary(self) -> str:
        """A few lines for a terminal: the verdict and why first."""
        lines = [f"kind: {self.kind}"]
        if self.verdict == "cannot_tell":
            lines.append(verdict_line(self.verdict, self.tied))
        elif self.verdict == "unexplained":
            lines.append("verdict: unexplained — the gap is real and no library effect closes it")
        elif self.verdict == "none":
            lines.append("verdict: none — nothing is missing from the nominal model")
        else:
            lines.append(f"verdict: {self.verdict}")
        if self.reason:
            lines.append(f"why: {self.reason}")
        lines.extend(_fitted_lines(self))
        unit = self.gap.get("unit", "")
        remaining = self.remaining_gap
        if remaining:
            floor_key = next((k for k in remaining if k.startswith("noise_floor")), None)
            floor = f" against a {remaining[floor_key]:.3g} {unit} noise floor" if floor_key else ""
            lines.append(
                f"explained: {self.explained_fraction:.0%} of the held-out excess; remaining gap "
                f"{remaining.get(unit, remaining.get('value', float('nan'))):.3g} {unit}{floor}"
            )
        shifts = self.refit.get("parameters", {})
        moved = [
            f"{k} {v['shift_relative']:+.2%} ({v['shift_sigma']:+.1f}σ)" for k, v in shifts.items()
        ]
        model = self.refit.get("model")
        if moved:
            label = f"refit (with {model})" if model and model != "nominal" else "refit"
            lines.append(f"{label}: " + ", ".join(moved))
        alone = self.refit.get("nominal_model_parameters")
        if model and model != "nominal" and alone:
            wide = [
                f"{k} {v['shift_relative']:+.2%} ({v['shift_sigma']:+.1f}σ)"
                for k, v in alone.items()
                if abs(v["shift_sigma"]) >= 2
            ]
            if wide:
                verdict = (
                    "not credible" if self.refit.get("nominal_model_out_of_prior") else "strained"
                )
                lines.append(
                    "without the effect the nominal model would need "
                    + ", ".join(wide)
                    + f" ({verdict}: a compensation, not the device's state)"
                )
        if self.refit.get("description"):
            lines.append("refit: " + self.refit["description"])
        model = self.refit.get("model_parameters")
        if model:
            lines.append(_model_line(model))
        lines.extend(_nuisance_lines(self.refit))
        if self.refit.get("parameter_error"):
            lines.append("the refit closes the gap: a parameter error, not missing physics")
        gap = self.gap
        lines.append(
            f"held-out gap ({unit} above the noise floor): {gap['before']:.3g} → "
            f"{gap['after']:.3g} ({gap.get('model_after', '')}), shrink {gap['shrink']:.2f} ± "
            f"{gap['shrink_std']:.2f}"
        )
        if self.ranking and all("held_out_gain" in r for r in self.ranking):
            order = (
                "in the order the forward selection added them, each 2 ln B over the model before"
            )
        else:
            order = "significant effects first, then by evidence"
        if self.ranking:
            lines.append(
                "ranking (evidence = 2 ln B against the nominal model; * = significant: "
                f"evidence ≥ {SIGNIFICANCE:g} and a better held-out prediction; {order}):"
            )
        else:
            lines.append("ranking: none (see the notes)")
        for r in self.ranking:
            mark = "*" if r.get("significant") else " "
            if r.get("fit_failed"):  # a nested fit that lost to the nominal: no evidence
                # (One whose reported ln L alone ended below is reported at its no-effect
                # value instead: `at_no_effect`, below.)
                below = r["objective_below_nominal"]
                reported = r.get("log_likelihood_below_nominal", 0.0)
                lines.append(
                    f"   {r['effect']:<18} fit failed (ended {below:.3g} below the nominal "
                    f"model's penalised ln L, {reported:.3g} below its reported ln L; the "
                    "nominal is the effect switched off: no evidence either way)"
                )
                continue
            line = (
                f" {mark} {r['effect']:<18} evidence {r['evidence']:>10.1f}  "
                f"shrink {r['gap_shrink']:+.2f}"
            )
            if r.get("at_no_effect"):  # the nested model at z = 0: the nominal exactly
                line += (
                    "  (at its no-effect value: the solver's optimum ended "
                    f"{r['optimum_log_likelihood_below_nominal']:.3g} below the nominal's ln L)"
                )
            lines.append(line)
        for e in self.next_experiment[:3]:
            lines.append(
                f"next experiment: {e['description']} (expected 2 ln B ≈ {e['expected_2lnB']:.3g})"
            )
        lines.extend(discovery_lines(self.discovery))
        lines.extend(f"note: {note}" for note in self.notes)
        return "\n".join(lines)


def _fitted_lines(result) -> list[str]:
    """The named effect's fitted physical values (the tied pair's, for `cannot_tell`), as
    its ranking entry holds them (`params`; the unit in each key's name)."""
    named = list(result.tied) if result.verdict == "cannot_tell" else [result.verdict]
    lines = []
    for entry in result.ranking:
        if entry.get("effect") in named and entry.get("params"):
            values = ", ".join(
                f"{key} = {value:.4g}" if isinstance(value, (int, float)) else f"{key} = {value}"
                for key, value in entry["params"].items()
            )
            lines.append(f"fitted {entry['effect']}: {values}")
    return lines


def _nuisance_lines(refit: dict) -> list[str]:
    """The step refit's nuisances, each with its shift in σ of its prior where it has one,
    and their joint test (`step.nuisance.nuisance_test`)."""
    test, values = refit.get("nuisance_test"), refit.get("nuisances") or {}
    if not test:
        return []
    gain = values.get("test_winding_gain")
    parts = []
    if gain is not None:
        polarity = values.get("test_winding_polarity", "")
        parts.append(
            f"test winding gain {gain:.4g} ({test['standardised']['test_winding_gain']:+.1f}σ"
            f", polarity {polarity})"
        )
    known = test.get("known_input_delay_samples")
    parts.append(
        f"input delay {test['input_delay_samples']:+.2f} samples"
        + ("" if known is None else f" (given: {known:+.2f})")
        + (
            f", a loop lag up to {test['hidden_lag_s'] * 1e6:.3g} µs would hide in it"
            if "hidden_lag_s" in test
            else ""
        )
    )
    if "external_moment_V" in values:
        parts.append(f"output offset (external moment) {values['external_moment_V']:+.3g} V")
    if "initial_displacement_V" in values:
        parts.append(
            f"initial state {values['initial_displacement_V']:+.3g} V, "
            f"{values['initial_velocity_V']:+.3g} V (no prior)"
        )
    verdict = "STRAINED" if test["strained"] else "within their priors"
    return [
        "nuisances: " + "; ".join(parts),
        f"nuisances judged together: largest {test['largest']} {test['largest_sigma']:+.1f}σ, "
        f"family-wise p = {test['family_p_value']:.2g} over {test['count']} ({verdict} at "
        f"α = {test['alpha']:g})",
    ]


def verdict_line(verdict: str, tied) -> str:
    """`verdict: …` of a summary, naming both effects of a `cannot_tell`."""
    if verdict == "cannot_tell":
        return f"verdict: cannot_tell — {tied[0]} or {tied[1]}"
    return f"verdict: {verdict}"


def _model_line(model: dict) -> str:
    """One line of a fitted model's parameters with their intervals (noise kind)."""
    from .._format import interval, seconds

    parts = []
    for entry in model["parameters"].values():
        unit = entry["unit"]
        if unit == "s":
            text = seconds(entry["value"])
            if "low" in entry:
                text += f" [{seconds(entry['low'])}, {seconds(entry['high'])}]"
        else:
            text = interval(entry["value"], entry.get("low"), entry.get("high"), unit)
        parts.append(f"{entry['symbol']} = {text}")
    level = f"{model['level']:.0%} intervals" if "note" not in model else model["note"]
    return f"model ({model['model']}; {level}): " + ", ".join(parts)
