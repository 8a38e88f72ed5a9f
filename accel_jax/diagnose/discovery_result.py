"""The typed result of the discovery of a missing term in a step record
(`step.discover`; `DiagnosisResult.discovery`) or a vibration table (`vibration.discover`:
`VibrationDiscovery`, at the end): frozen dataclasses whose attributes carry
the names of the keys of the `discovery` block of the JSON.

`to_dict()` gives that block key for key, in the same order and with the same keys present
(`frequency_Hz` only for a subset with the sinusoid, `ceiling_fraction` only where the
network reference ran, `consequence` only on the best subset and its tie: `best` and `tie`
are the same objects as their entries of `candidates`, so their `consequence` is in the
`candidates` list too). A later stage that adds to one makes a new one with
`dataclasses.replace`. The string-keyed access of the plain dict this replaced
(`result.discovery["best"]`) still works for one release, with a `DeprecationWarning`
(`accel_jax._deprecated.LegacyItems`).

What stays JSON-ready dicts, presentation and no input of a decision: each named subset's
`consequence` entries (`step.consequence`) and the `excite` entries (`step.excite`).
Shared by the kinds' modules (`base` renders it through `discovery_text`); it imports none.
"""

from __future__ import annotations

import dataclasses

from .._deprecated import LegacyItems
from .._io import field_dict


class _Fields:
    """`to_dict()`: the fields in their order, each as it is (plain values)."""

    def to_dict(self) -> dict:
        """The JSON-ready dict: one key per field, in the fields' order."""
        return field_dict(self)


@dataclasses.dataclass(frozen=True)
class DiscoveredColumn(_Fields):
    """One coefficient of a refitted subset (a sinusoid has two: its sin and cos parts).

    **Fields:** `term` the term's name (with ` (sin)`/` (cos)` for a sinusoid's part);
    `place` where in the loop it acts; `family` its family; `formula` its form;
    `coefficient` its fitted value c (in the term's units, `DiscoveryScales`); `sigma` its
    standard error: on the subsets that `excite` may name (the best, its tie, the best
    with one term added where its linearised σ leave a term below `excite.WEAK_Z`) the
    half-width of its profile-likelihood interval
    (`step.profile`), elsewhere the linearised one; both at Δχ² = max(1, the training χ²
    per degree of freedom). Where profiled (else None, not in the JSON):
    `sigma_linearised` the linearised one, `interval` (lower, upper), `profile_found`
    whether both ends were found to `profile.TOLERANCE`.
    """

    term: str
    place: str
    family: str
    formula: str
    coefficient: float
    sigma: float
    sigma_linearised: float | None = None
    interval: tuple[float, float] | None = None
    profile_found: bool | None = None

    def to_dict(self) -> dict:
        """The JSON-ready dict: the fields in their order, the profile's only when set."""
        out = {k: v for k, v in vars(self).items() if v is not None}
        if self.interval is not None:
            out["interval"] = list(self.interval)
        return out


@dataclasses.dataclass(frozen=True)
class DiscoveryCandidate:
    """One refitted subset of terms.

    **Fields:**

    - `terms`: the terms' names; `columns`: their coefficients (`DiscoveredColumn`).
    - `evidence`: 2 ln B ≈ Δχ² − k ln n against the nominal fit (BIC); `criterion`: the
        extended BIC relative to the nominal fit (lower is better; the candidates' order);
        `delta_chi2_train`: Δχ² on the training part; `ebic_linearised`: the criterion of
        the linearised screen that chose it.
    - `held_out_gap_before_V`, `held_out_gap_after_V` [V]: the held-out gap above the
        noise floor without and with the terms; `explained_fraction`: the fraction of its
        square removed; `held_out_at_floor`: whether the gap after is at the floor.
    - `stability`: the fraction of block-bootstrap resamples whose pick contains every
        term of the subset; `converged`: whether the full refit converged;
        `chi2_per_dof_train`: the training χ² per degree of freedom.
    - `frequency_Hz` [Hz]: a sinusoid's fitted frequency (None, and not in the JSON,
        without the sinusoid).
    - `ceiling_fraction`: the fraction of the network reference's shrink the subset reaches
        (None where the reference removed nothing); in the JSON only where the reference ran,
        `ceiling_compared` (never in the JSON).
    - `consequence`: what the subset means for a designer (`step.consequence`'s JSON-ready
        entries, one per column), for the best subset and its tie; else None, not in the
        JSON.
    """

    terms: tuple[str, ...]
    columns: tuple[DiscoveredColumn, ...]
    evidence: float
    criterion: float
    delta_chi2_train: float
    ebic_linearised: float
    held_out_gap_before_V: float
    held_out_gap_after_V: float
    explained_fraction: float
    held_out_at_floor: bool
    stability: float
    converged: bool
    chi2_per_dof_train: float
    frequency_Hz: float | None = None
    ceiling_fraction: float | None = None
    ceiling_compared: bool = False
    consequence: tuple[dict, ...] | None = None

    def to_dict(self) -> dict:
        """The JSON-ready dict: the fields in their order, `terms` and `columns` as lists;
        `frequency_Hz` and `consequence` only when set, `ceiling_fraction` only where the
        reference ran (`ceiling_compared` never)."""
        out = {
            "terms": list(self.terms),
            "columns": [column.to_dict() for column in self.columns],
            "evidence": self.evidence,
            "criterion": self.criterion,
            "delta_chi2_train": self.delta_chi2_train,
            "ebic_linearised": self.ebic_linearised,
            "held_out_gap_before_V": self.held_out_gap_before_V,
            "held_out_gap_after_V": self.held_out_gap_after_V,
            "explained_fraction": self.explained_fraction,
            "held_out_at_floor": self.held_out_at_floor,
            "stability": self.stability,
            "converged": self.converged,
            "chi2_per_dof_train": self.chi2_per_dof_train,
        }
        if self.frequency_Hz is not None:
            out["frequency_Hz"] = self.frequency_Hz
        if self.ceiling_compared:
            out["ceiling_fraction"] = self.ceiling_fraction
        if self.consequence is not None:
            out["consequence"] = list(self.consequence)
        return out


@dataclasses.dataclass(frozen=True)
class NetworkReference(_Fields):
    """The network reference of what a term of the loop's states could remove
    (`step.ceiling.fit_reference`): an estimate, not a bound, never a verdict.

    **Fields:** `method` in words; `parameters` the network's weights; `delta_chi2_train`
    Δχ² on the training part; `held_out_gap_before_V`, `held_out_gap_after_V` [V] the
    held-out gap above the floor without and with it; `explained_fraction` the fraction of
    its square removed; `converged` whether its fit converged; `extrapolates` whether the
    held-out part holds test levels outside the training part's
    (`step.ceiling.outside_training`).
    """

    method: str
    parameters: int
    delta_chi2_train: float
    held_out_gap_before_V: float
    held_out_gap_after_V: float
    explained_fraction: float
    converged: bool
    extrapolates: bool


@dataclasses.dataclass(frozen=True)
class DiscoveryScales(_Fields):
    """The units of the terms' coefficients: `half_V` the training output's half range h
    [V], `period_s` the nominal device's period T [s]."""

    half_V: float
    period_s: float


@dataclasses.dataclass(frozen=True)
class Discovery(LegacyItems):
    """The discovery of a missing term in one step record (`step.discover`): a hypothesis,
    never a verdict.

    **Fields:**

    - `method`: the method in words; `sinusoid_start_Hz` [Hz]: the sinusoid's starting
        frequency (the nominal residual's periodogram peak); `scales`: the terms' units
        (`DiscoveryScales`).
    - `candidates`: the refitted subsets, best (lowest criterion) first
        (`DiscoveryCandidate`).
    - `best`, `tie`: the discovered subset and one that cannot be told from it, each the
        same object as its entry of `candidates` (None where nothing was found / no tie).
    - `rating`: `"credible"`, `"tentative"` or `"nothing found"`.
    - `ceiling`: the network reference (`NetworkReference`), with `reference=True`; else
        None, not in the JSON.
    - `excite`: the records that would excite a barely measured term (`step.excite`'s
        JSON-ready entries); None, not in the JSON, where no term is barely measured.

    `to_dict()` is the JSON's `discovery` block; `result.discovery["best"]` and the other
    keys of the dict this replaced still work for one release, with a
    `DeprecationWarning`.
    """

    method: str
    sinusoid_start_Hz: float
    scales: DiscoveryScales
    candidates: tuple[DiscoveryCandidate, ...]
    best: DiscoveryCandidate | None = None
    tie: DiscoveryCandidate | None = None
    rating: str = "nothing found"
    ceiling: NetworkReference | None = None
    excite: tuple[dict, ...] | None = None

    def to_dict(self) -> dict:
        """The JSON-ready dict: the fields in their order (`best` and `tie` as their
        candidates' dicts); `ceiling` and `excite` only when set."""
        return field_dict(self, unless_none=("ceiling", "excite"))

    def _legacy(self) -> dict:
        return self.to_dict()


# --- the vibration kind's discovery (`vibration.discover`) -------------------------------


@dataclasses.dataclass(frozen=True)
class VibrationColumn(_Fields):
    """One coefficient of a discovered subset of a vibration table's terms.

    **Fields:** `term` the term's name (`vibration.terms.TERMS`); `formula` its form;
    `unit` its coefficient's unit; `library` the effect library's coefficient it is (None:
    outside the library's static transfer function); `coefficient` its least-squares value
    and `sigma` its standard error (σ² the fit's residual variance per degree of freedom);
    `rectified_ug` its vibration error at a reference condition [µg] and `condition` that
    condition in words (the papers' Table 5 condition, 1 g with a 2 g sinusoid on the input
    axis, for an input-axis term; 1 g with 4 g in phase on the input axis and on the term's
    cross axis for the others)."""

    term: str
    formula: str
    unit: str
    library: str | None
    coefficient: float
    sigma: float
    rectified_ug: float
    condition: str


@dataclasses.dataclass(frozen=True)
class VibrationCandidate(_Fields):
    """One subset of a vibration table's terms fitted with the nominal bias and scale
    factor (a linear least-squares fit: exact).

    **Fields:** `terms` their names; `columns` their coefficients (`VibrationColumn`);
    `evidence` 2 ln B = n ln(RSS₀/RSS) − k ln n against the nominal fit (the kind's
    ranking's scale); `criterion` the extended BIC relative to the nominal fit, n ln(RSS/RSS₀)
    + k ln n + 2 ln C(m, k) over the m terms the table can show (lower is better);
    `cv_gap_before_g`, `cv_gap_after_g` the cross-validated gap above the noise floor
    without and with the terms [g]; `explained_fraction` the fraction of its square
    removed; `at_floor` whether the fit leaves no lack of fit against the pure error of the
    table's repeated conditions (None where the table has none: untestable);
    `lack_of_fit_p` that test's p-value (None where untestable); `stability` the fraction of
    bootstrap resamples of the rows whose pick contains every term of the subset."""

    terms: tuple[str, ...]
    columns: tuple[VibrationColumn, ...]
    evidence: float
    criterion: float
    cv_gap_before_g: float
    cv_gap_after_g: float
    explained_fraction: float
    at_floor: bool | None
    lack_of_fit_p: float | None
    stability: float


@dataclasses.dataclass(frozen=True)
class VibrationDiscovery(_Fields):
    """The discovery of a missing term in one vibration table (`vibration.discover`).

    **Fields:**

    - `method`: the method in words; `searched`: the terms the table can show (the others
        need conditions it lacks); `candidates`: the fitted subsets with evidence, best
        (lowest criterion) first, at most `vibration.discover.SHOWN`.
    - `best`, `tie`: the discovered subset and one that cannot be told from it (the same
        objects as their entries of `candidates`; None where nothing was found / no tie).
    - `rating`: `"credible"` (evidence ≥ 10, stable in ≥ 80 % of resamples, at the floor of
        the repeated conditions), `"tentative"` or `"nothing found"`.
    - `separate`: with a tie, the test condition that separates the two most, in words
        (None otherwise).
    - `overturned`: the verdict the discovery replaced by `unexplained` (None: kept).
    """

    method: str
    searched: tuple[str, ...]
    candidates: tuple[VibrationCandidate, ...]
    best: VibrationCandidate | None = None
    tie: VibrationCandidate | None = None
    rating: str = "nothing found"
    separate: str | None = None
    overturned: str | None = None
