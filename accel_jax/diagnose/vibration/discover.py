"""Discovery of a missing term in a vibration table (`discover_table`), and what it means
for the verdict (`weigh`).

1. **Terms.** The table's linear model a_out − a_in = J θ (`table.prepare`) extended by a
   column per term of `terms.TERMS` (its exact expectation over each row's vibration):
   the library's coefficients and the terms beyond them. A term the table cannot show (its
   column a combination of the bias and scale-factor columns, or zero: cross-axis terms
   without cross-axis rows) is left out of the search (`searched`).
2. **Subsets.** Every subset of up to `MAX_TERMS` terms, fitted with the nominal bias and
   scale factor on all rows by least squares on its own columns (`_subset_fits`:
   `jnp.linalg.lstsq`, vmapped), scored by the extended BIC relative to the nominal fit,
   n ln(RSS/RSS₀) + k ln n + 2γ ln C(m, k) (γ = `EBIC_GAMMA`, m the terms searched: the
   price of looking through the library). The nominal and the `RIVALS` best subsets, and
   the `RIVALS` best with evidence, are fitted again on every cross-validation fold and on
   `N_BOOT` bootstrap resamples of the rows (a second vmapped call).
3. **The discovered subset**: the lowest criterion among the subsets with evidence
   (n ln(RSS₀/RSS) − k ln n, the ranking's 2 ln B) ≥ `base.SIGNIFICANCE` that also lower
   the cross-validated mean square; `stability` the share of resamples whose own pick
   (among the nominal and the `RIVALS` best) contains every one of its terms; `at_floor`
   the lack-of-fit F-test against the pure error of the repeated conditions
   (`verdict.lack_of_fit`; untestable without them). Rated credible
   (evidence ≥ 10, stable in ≥ `STABLE`, at the floor), tentative, or nothing found. A
   second subset within `base.INDISTINCT` of its criterion that is not the best plus a term
   is a tie: the test condition that separates the two most is named.
4. **The verdict** (`weigh`): a stable subset that is not within one library effect's
   coefficients and whose evidence beats the named effect's (0 for `none`) by at least
   `base.INDISTINCT` makes the verdict `unexplained` — the library's answer is beaten by a
   term it lacks (or by two of its effects together); the refit's `parameter_error` is
   then cleared, and the explained fraction stays the named effect's (the best partial
   effect's, as for the kind's own `unexplained`; 0 after `none`). Unlike the step kind's, this
   discovery is linear least squares and costs well under a second once compiled, so it
   runs on every table asked for (`diagnose(..., discover=True)`, the CLI's default).

Float64 (its caller's). Host side but the fits.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..._data import VibrationData
from ..._static import PPM
from .. import openworld
from ..base import INDISTINCT, SIGNIFICANCE, DiagnosisResult, held_out_gap
from ..discovery_result import VibrationCandidate, VibrationColumn, VibrationDiscovery
from .effects import COEFFICIENTS, NOMINAL_COEFFICIENTS
from .state import VibrationTable
from .table import IDENTIFIABLE, MAX_FOLDS, _unexplained, padded_rows
from .terms import TERMS, condition_columns, term_columns
from .verdict import lack_of_fit, pure_error

MAX_TERMS = 2
"""The largest subset of terms searched (exact best subset)."""

EBIC_GAMMA = 1.0
"""γ of the extended BIC's 2γ ln C(m, k) (1: the library's size fully priced)."""

STABLE = 0.8
"""A credible subset is picked (with every one of its terms) in at least this share of the
bootstrap resamples."""

N_BOOT = 200
"""Bootstrap resamples of the rows (fixed seed `_BOOT_SEED`: reproducible)."""

_BOOT_SEED = 20261203

SHOWN = 5
"""The candidates kept in the result (best first)."""

METHOD = (
    "every subset of up to two terms of the term library (the effect library's coefficients "
    "and terms beyond the static transfer function) fitted with bias and scale factor by "
    "linear least squares on the exact expectation of each row; extended BIC (γ = 1), "
    "cross-validated gap, bootstrap over rows"
)


def _subsets(columns: np.ndarray, nominal: np.ndarray) -> tuple[list[int], list[tuple]]:
    """The terms the table can show and the subsets of them whose columns it can separate
    (`table.IDENTIFIABLE`), the empty subset (the nominal) first."""
    shown = [
        j
        for j in range(columns.shape[1])
        if np.any(columns[:, j] != 0) and _unexplained(columns[:, [j]], nominal)[0] > IDENTIFIABLE
    ]
    subsets: list[tuple] = [()]
    subsets += [(j,) for j in shown]
    for i, j in itertools.combinations(shown, 2):
        basis = np.concatenate([nominal, columns[:, [i]]], axis=1)
        if MAX_TERMS >= 2 and _unexplained(columns[:, [j]], basis)[0] > IDENTIFIABLE:
            subsets.append((i, j))
    return shown, subsets


RIVALS = 11
"""The subsets (by criterion) refitted on the folds and resamples beside the nominal: the
resamples' picks are made among them (a resample's pick outside the full data's best few
would only lower the stability of every one of them)."""

_SUBSETS = 1 + len(TERMS) + math.comb(len(TERMS), 2)
_SECOND = 2 * RIVALS + 2


_WIDTH = len(NOMINAL_COEFFICIENTS) + MAX_TERMS
"""The columns of one subset's fit: the nominal's and at most `MAX_TERMS` terms."""


@jax.jit
def _subset_fits(design, target, index, valid, weights):
    """θ of every subset (its columns `index` of `design`, `valid` 0 on padding) on every
    row weighting of `weights`, by `jnp.linalg.lstsq` on the subset's own columns (each
    scaled to unit norm): (subsets, weightings, `_WIDTH`)."""

    def one(columns, ok, w):
        x = design[:, columns] * ok
        norm = jnp.sqrt(jnp.sum(x**2, axis=0))
        norm = jnp.where(norm > 0, norm, 1.0)
        theta, *_ = jnp.linalg.lstsq(x / norm * w[:, None], target * w)
        return theta / norm * ok

    per_weight = jax.vmap(one, in_axes=(None, None, 0))
    return jax.vmap(per_weight, in_axes=(0, 0, None))(index, valid, weights)


def _fit(design, target, masks, weights, n_masks, n_weights):
    """Every subset of `masks` on every row weighting of `weights` (`_subset_fits`), the
    rows, subsets and weightings padded to fixed counts (zero-weight rows, empty subsets,
    all-row weightings: tables of several sizes share one program); returns θ over
    `design`'s columns (subsets, weightings, columns)."""
    (n, width), rows = design.shape, padded_rows(design.shape[0])
    count = len(weights)
    index = np.zeros((n_masks, _WIDTH), int)
    valid = np.zeros((n_masks, _WIDTH))
    for s, mask in enumerate(masks):
        free = np.flatnonzero(mask)
        index[s, : free.size], valid[s, : free.size] = free, 1.0
    padded = np.zeros((n_weights, rows))
    padded[:count, :n] = weights
    padded[count:, :n] = 1.0
    thetas = _subset_fits(
        jnp.asarray(np.pad(design, ((0, rows - n), (0, 0)))),
        jnp.asarray(np.pad(target, (0, rows - n))),
        jnp.asarray(index),
        jnp.asarray(valid),
        jnp.asarray(padded),
    )
    thetas = np.asarray(thetas)[: len(masks), :count]
    out = np.zeros((len(masks), count, width))
    for s in range(len(masks)):
        used = valid[s] > 0
        out[s][:, index[s][used]] = thetas[s][:, used]
    return out


def _criterion(rss, rss0, k, n, m):
    """The extended BIC relative to the nominal fit (`EBIC_GAMMA`)."""
    return (
        n * np.log(rss / rss0)
        + k * math.log(n)
        + 2
        * EBIC_GAMMA
        * np.log(np.array([math.comb(m, int(kk)) for kk in np.ravel(k)]).reshape(np.shape(k)))
    )


def discover_table(
    data: VibrationData, table: VibrationTable, floor_g2: float
) -> VibrationDiscovery:
    """The discovery of a missing term in one table (module docstring): `floor_g2` the
    noise floor of the library's fits [g²] (the least residual variance among them)."""
    n = table.target.size
    columns = term_columns(data, table.design, COEFFICIENTS)
    nominal = table.design[:, list(table.nominal_columns)]
    shown, subsets = _subsets(columns, nominal)
    p0 = len(NOMINAL_COEFFICIENTS)  # a slot for each; one left empty where δ is held at 0
    design = np.concatenate([np.zeros((n, p0)), columns], axis=1)
    design[:, : nominal.shape[1]] = nominal
    masks = np.zeros((len(subsets), design.shape[1]))
    masks[:, : nominal.shape[1]] = 1
    for s, subset in enumerate(subsets):
        masks[s, [p0 + j for j in subset]] = 1
    full = _fit(design, table.target, masks, np.ones((1, n)), _SUBSETS, 1)[:, 0]
    floor_rss = n * (1e-9 * max(float(np.max(np.abs(table.target))), 1.0)) ** 2
    rss = np.maximum(np.sum((full @ design.T - table.target) ** 2, axis=1), floor_rss)
    k = np.array([len(s) for s in subsets])
    m = max(len(shown), 1)
    criterion = _criterion(rss, rss[0], k, n, m)
    evidence = n * np.log(rss[0] / rss) - k * math.log(n)
    # The folds and resamples: the nominal, the best `RIVALS` by criterion (the resamples'
    # competitors) and the best `RIVALS` of those with evidence (the candidates).
    order = sorted(range(1, len(subsets)), key=lambda s: criterion[s])
    significant = [s for s in order if evidence[s] >= SIGNIFICANCE][:RIVALS]
    rivals = [0] + order[:RIVALS]
    chosen = rivals + [s for s in significant if s not in rivals]
    counts = np.random.default_rng(_BOOT_SEED).multinomial(n, np.full(n, 1 / n), N_BOOT)
    folds = table.weights[1:]
    weights = np.concatenate(
        [folds, np.repeat(folds[:1], MAX_FOLDS - len(folds), axis=0), np.sqrt(counts)]
    )
    refits = _fit(design, table.target, masks[chosen], weights, _SECOND, MAX_FOLDS + N_BOOT)
    residuals = refits @ design.T - table.target  # (chosen, weightings, rows) [ppm]
    cv = residuals[:, table.fold_of_row, np.arange(n)] * PPM  # (chosen, rows) [g]
    cv_ms = np.mean(cv**2, axis=1)
    at = {s: i for i, s in enumerate(chosen)}
    boot = np.einsum("br,sbr->sb", counts, residuals[: len(rivals), MAX_FOLDS:] ** 2)
    boot = np.maximum(boot, floor_rss)
    k_rivals = k[rivals][:, None]
    picks = [rivals[i] for i in np.argmin(_criterion(boot, boot[:1], k_rivals, n, m), axis=0)]
    eligible = [s for s in significant if cv_ms[at[s]] < cv_ms[0]]
    replicates = pure_error(data, table.target)

    def candidate(s: int) -> VibrationCandidate:
        subset = subsets[s]
        free = np.flatnonzero(masks[s])
        dof = max(n - free.size, 1)
        sigma2 = rss[s] / dof
        covariance = sigma2 * np.linalg.pinv(design[:, free].T @ design[:, free])
        se = np.sqrt(np.clip(np.diag(covariance), 0, None))
        position = {c: i for i, c in enumerate(free)}
        cols = tuple(
            _column(j, float(full[s, p0 + j]), float(se[position[p0 + j]])) for j in subset
        )
        floor = min(floor_g2, sigma2 * PPM**2)
        gap = held_out_gap(cv[0], cv[at[s]], floor, block=1)
        lof = lack_of_fit(rss[s], free.size, replicates)
        picked = np.array([set(subset) <= set(subsets[b]) for b in picks])
        return VibrationCandidate(
            terms=tuple(TERMS[j].name for j in subset),
            columns=cols,
            evidence=float(evidence[s]),
            criterion=float(criterion[s]),
            cv_gap_before_g=float(gap["before"]),
            cv_gap_after_g=float(gap["after"]),
            explained_fraction=openworld.explained_fraction(gap["before"], gap["after"]),
            at_floor=bool(lof["explains"]) if lof["testable"] else None,
            lack_of_fit_p=float(lof["p_value"]) if lof["testable"] else None,
            stability=float(np.mean(picked)),
        )

    shown_candidates = [candidate(s) for s in eligible[:SHOWN]]
    best = shown_candidates[0] if shown_candidates else None
    tie = tie_index = None
    for s, other in zip(eligible[1:SHOWN], shown_candidates[1:], strict=False):
        if criterion[s] - criterion[eligible[0]] >= INDISTINCT:
            break
        if best is not None and not set(best.terms) <= set(other.terms):
            tie, tie_index = other, s
            break
    rating = "nothing found"
    if best is not None:
        credible = best.stability >= STABLE and best.at_floor is True
        rating = "credible" if credible else "tentative"
    separate = None
    if tie_index is not None:
        separate = _separating_row(design, full, masks, eligible[0], tie_index, table)
    return VibrationDiscovery(
        method=METHOD,
        searched=tuple(TERMS[j].name for j in shown),
        candidates=tuple(shown_candidates),
        best=best,
        tie=tie,
        rating=rating,
        separate=separate,
    )


def _reference(term) -> tuple[str, tuple]:
    """The reference condition of a term's vibration error (`VibrationColumn`)."""
    if not term.cross:
        return "1 g with a 2 g sinusoid on the input axis", (1.0, 2.0, 0.0, 0.0, 0.0)
    on_oa = term.name in ("m31", "oa_square", "oa_pa", "ia_oa_square")
    on_pa = term.name in ("m32", "pa_square", "oa_pa")
    axes = " and ".join(a for a, on in (("OA", on_oa), ("PA", on_pa)) if on)
    return (
        f"1 g with 4 g in phase on the input axis and on {axes}",
        (1.0, 4.0, 0.0, 4.0 * on_oa, 4.0 * on_pa),
    )


def _column(j: int, coefficient: float, sigma: float) -> VibrationColumn:
    term = TERMS[j]
    text, condition = _reference(term)
    vibrating, static = condition_columns(*np.array([condition, (condition[0], 0, 0, 0, 0)]).T)[
        :, j
    ]
    return VibrationColumn(
        term=term.name,
        formula=term.formula,
        unit=term.unit,
        library=term.library,
        coefficient=coefficient,
        sigma=sigma,
        rectified_ug=coefficient * (vibrating - static),  # ppm of 1 g = µg
        condition=text,
    )


_GRID = [
    (a, b, s, b1, b2)
    for a in (-1.0, -0.5, 0.0, 0.5, 1.0)
    for b in (0.0, 1.0, 2.0, 4.0, 8.0)
    for s in (0.0, 3.0)
    for b1 in (0.0, 4.0)
    for b2 in (0.0, 4.0)
    if b > 0 or (b1 == 0 and b2 == 0)
]
"""The test conditions a separating row is chosen from (a_in, b3, σ, b1, b2) [g]."""


def _separating_row(design, thetas, masks, best, tie, table) -> str:
    """The condition of `_GRID` where the best subset's and its tie's fitted models differ
    most, in words, against the table's row noise."""
    grid = np.array(_GRID)
    rows = np.concatenate([np.ones((len(grid), 1)), grid[:, :1], condition_columns(*grid.T)], 1)
    if COEFFICIENTS.index("scale_factor_error") not in table.nominal_columns:
        rows[:, 1] = 0.0  # δ held at 0: its slot is empty
    difference = rows @ (thetas[best] - thetas[tie])
    i = int(np.argmax(np.abs(difference)))
    a, b, s, b1, b2 = _GRID[i]
    noise = math.sqrt(
        float(np.sum((design @ thetas[best] - table.target) ** 2))
        / max(table.target.size - int(masks[best].sum()), 1)
    )
    parts = [f"a_in = {a:g} g"]
    parts += [f"{b:g} g sinusoid on IA"] if b else []
    parts += [f"{s:g} g RMS random on IA"] if s else []
    parts += [f"{b1:g} g on OA"] if b1 else []
    parts += [f"{b2:g} g on PA"] if b2 else []
    return (
        f"a row at {', '.join(parts)} separates them by {abs(difference[i]):.3g} µg "
        f"({abs(difference[i]) / noise:.1f}× the row noise the fit leaves, {noise:.2g} µg)"
    )


def weigh(result: DiagnosisResult, discovery: VibrationDiscovery, effects) -> None:
    """The verdict in the light of the discovery (module docstring, 4), in place. A subset
    within one library effect's coefficients (m31 alone is within `cross_coupling`) never
    overturns: the ranking has weighed that effect. Where the verdict is kept but a subset
    with a term outside the library fits about as well as the named effect (within
    `base.INDISTINCT`), a note says that the table cannot tell them apart, with the row
    that separates them where the discovery's best is the named effect's own and the rival
    its tie."""
    result.discovery = discovery
    best = discovery.best
    if best is None or result.verdict == "unexplained":
        return
    own = {e.name: set(e.coefficients) for e in effects}
    ranked = {entry["effect"]: entry["evidence"] for entry in result.ranking}
    named = [result.verdict] if result.verdict in own else list(result.tied)
    against = max((ranked.get(e, 0.0) for e in named), default=0.0)
    before = " / ".join(named) if named else result.verdict
    library = {t.name for t in TERMS if t.library is not None}
    if (
        best.stability >= STABLE
        and not any(set(best.terms) <= c for c in own.values())
        and best.evidence - against >= INDISTINCT
    ):
        what = (
            "library effects together, which the library names one at a time"
            if set(best.terms) <= library
            else "terms beyond the effect library"
        )
        result.reason = (
            f"{what} fit the table: {' + '.join(best.terms)} "
            f"(evidence {best.evidence:.1f} against {against:.1f} for {before}; the "
            f"cross-validated gap {best.cv_gap_before_g:.3g} → {best.cv_gap_after_g:.3g} g "
            f"above the floor; stable in {best.stability:.0%} of resamples). Before the "
            f"discovery the verdict was {before}: {result.reason}"
        )
        result.verdict = "unexplained"
        result.tied = []
        if not named:
            result.explained_fraction = 0.0
        # (the refit closing the gap no longer means a parameter error: a term is missing)
        result.refit["parameter_error"] = False
        result.discovery = dataclasses.replace(discovery, overturned=before)
        return
    if not named:
        return
    rival = next(
        (
            c
            for c in discovery.candidates
            if not set(c.terms) <= library and c.evidence > against - INDISTINCT
        ),
        None,
    )
    if rival is not None:
        mine = any(set(best.terms) <= own[e] for e in named)
        separate = discovery.separate if rival is discovery.tie and mine else None
        result.notes.append(
            f"the table cannot tell {before} from {' + '.join(rival.terms)}, outside the "
            f"effect library (evidence {rival.evidence:.1f} against {against:.1f})"
            + (f"; to separate them: {separate}" if separate else "")
        )
