"""The sensor-noise selection's refinements of a selected model.

`_backward`: each effect of the final model judged again against the model without it,
the weakest below the evidence bar removed until every one stands (an effect added early
can lose its evidence once a later one is in). `_exchanges`: each named low-frequency or
exponential-cosine process tried against the other `LOW_FREQUENCY` ones in its place, and
a low-pass with the white noise after it against the best of a Gauss–Markov process, a
random walk or flicker in its place (a Gauss–Markov process against the low-pass too; the
low-pass stays only where it is better by the bar); a better one by the bar replaces it,
one within the bar either way is a tie. Both judge by `sensor_model`'s evidence and held-out check.
`_low_pass_order`: the low-pass of another order in its place, with and without each
process beside it, once the selection is done.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from .._runtime import beside
from . import chain_filters, spectral
from .sensor_model import (
    HELD_OUT_Z,
    PARAMETER_COUNT,
    _evaluate,
    _evaluate_many,
    _evidence,
    _held_out_z,
    _Model,
    _transient_test,
)


def _backward(rec, floor, model: _Model, log_j: float, evidence: float):
    """The backward check of the forward selection: each effect of the final model is
    judged again against the final model without it (a stochastic effect by its Whittle
    2 ln B on the whole record, `_evidence`, the start-up transient by its time-domain test against
    the reduced noise model); the weakest that falls below `evidence` is removed and the
    check repeats. An effect added early can lose its evidence once a later one is in: a
    random walk taken for the low-frequency power of a start-up transient, or a transient
    seen in the start of a record whose wandering level was not yet modelled.

    Returns (model, removed: [{"effect", "evidence"}])."""
    removed = []
    while True:
        weakest = None
        specs = []
        counts = []
        for name in model.names:
            # the low-pass goes with the white noise after it (alone that is white noise)
            gone = {name, "filter_floor"} if name in spectral.LOW_PASS_ORDERS else {name}
            names = tuple(n for n in model.names if n not in gone)
            parent = dataclasses.replace(model, names=names)
            specs.append((names, model.lines, model.transient, parent))
            counts.append(sum(PARAMETER_COUNT[n] for n in gone if n in model.names))
        tested = None  # the transient test, run beside the fits
        if model.transient is not None:
            start = rec.residual(model.lines, None)[: rec.split]
            (tested,) = beside(functools.partial(_transient_test, start, rec.dt, model, floor))
        reduced_fits = _evaluate_many(rec, floor, specs)
        for name, k, reduced in zip(model.names, counts, reduced_fits, strict=True):
            score = _evidence(model, reduced, k, log_j)
            if weakest is None or score < weakest[0]:
                weakest = (score, name, reduced)
        if tested is not None:
            found = tested.result()
            score = found["evidence"] - PARAMETER_COUNT["startup_transient"] * log_j
            if weakest is None or score < weakest[0]:
                reduced = _evaluate(rec, floor, model.names, model.lines, None, model)
                weakest = (score, "startup_transient", reduced)
        if weakest is None or weakest[0] >= evidence:
            return model, removed
        removed.append({"effect": weakest[1], "evidence": float(weakest[0])})
        model = weakest[2]


LOW_FREQUENCY = ("gauss_markov", "random_walk", "flicker")
"""The effects that put their power at the lowest frequencies: on a record a few of their
time scales long, one can stand in for another."""


EXCHANGED = (*LOW_FREQUENCY, "exp_cosine")
"""The named effects the exchange tries the `LOW_FREQUENCY` ones in place of: an
exponential-cosine process too can stand in for a low-frequency one (its oscillation
frequency fitted near 0 it is a Gauss–Markov process; harness record 166663425, flicker
with a line, took it first, before the line was in and while the line's power favoured a
peaked spectrum, and kept it)."""


LOW_PASS = ("bandlimit", "filter_floor")
"""A low-pass with the white noise after it: one effect in the exchange. Its spectrum (a
level that falls at the corner onto a lower white floor) is what a Gauss–Markov process
over white noise makes too, and with a very low corner what a random walk or flicker makes;
only the roll-off's shape tells them apart, so each is tried in the other's place (a
low-pass of any order named; the second-order one tried)."""


def _units(model: _Model) -> list:
    """The named effects the exchange replaces: each of `EXCHANGED`, and a low-pass with
    the white noise after it."""
    units: list[tuple[str, ...]] = [(n,) for n in model.names if n in EXCHANGED]
    order_name = spectral.low_pass(model.names)
    if order_name is not None and "filter_floor" in model.names:
        units.append((order_name, "filter_floor"))
    return units


LEVEL_AND_ROLL_OFF = ("gauss_markov",)
"""The process whose spectrum over white noise is a level that rolls off onto a lower one,
as a low-pass with the white noise after it makes, with as many parameters: exchanged with
`LOW_PASS` (a random walk or flicker, whose power keeps rising to the lowest frequency, is
not; an exponential-cosine process, one parameter more, is exchanged with the Gauss–Markov
process)."""


def _substitutes(unit: tuple, model: _Model) -> list:
    """What the exchange tries in the place of `unit`: the unnamed `LOW_FREQUENCY` effects
    in the place of one of `EXCHANGED` or of a low-pass with its floor, and `LOW_PASS` in
    the place of one of `LEVEL_AND_ROLL_OFF`."""
    subs: list[tuple[str, ...]] = [(o,) for o in LOW_FREQUENCY if o not in model.names]
    if unit[0] in spectral.LOW_PASS_ORDERS:  # (a very low corner stands in for a walk too)
        return subs
    if unit[0] in LEVEL_AND_ROLL_OFF and spectral.low_pass(model.names) is None:
        subs.append(LOW_PASS)
    return subs


def _exchanges(rec, floor, model: _Model, log_j: float, evidence: float):
    """Each named effect of `EXCHANGED` against each unnamed `LOW_FREQUENCY` one in its
    place (the rest of the model kept, the substitute's fit started from the model's
    optimum): 2 ln B of the named effect over the substitute, 2 Δ ln L − (k − k') ln J on
    the whole record as in the forward selection. A substitute that beats the named effect
    by `evidence` or more replaces it (the forward path added the first that stood, not the
    best: a random walk with a start-up transient can look like flicker until the transient
    is in), and the exchange repeats; one within `evidence` either way is reported as a tie: the
    record cannot tell the two apart.

    Returns (model, exchanged: [{"effect", "by", "evidence"}], ties: [{"effect",
    "alternative", "evidence"}])."""
    exchanged, ties = [], []  # (ties: rebound by every pass)
    for _ in range(len(EXCHANGED) + 2):
        ties, best = [], None
        pairs, specs = [], []
        for unit in _units(model):
            rest = tuple(n for n in model.names if n not in unit)
            for other in _substitutes(unit, model):
                if len(unit) == len(other) == 1:  # in its place
                    names = tuple(other[0] if n == unit[0] else n for n in model.names)
                else:
                    names = (*rest, *other)
                parent = dataclasses.replace(model, names=rest)
                pairs.append((unit, other, parent))
                specs.append((names, model.lines, model.transient, parent))
        for (unit, other, parent), alt in zip(
            pairs, _evaluate_many(rec, floor, specs), strict=True
        ):
            # (a low-pass: with its floor)
            name, other_name = spectral.effect_name(unit[0]), spectral.effect_name(other[0])
            k = sum(PARAMETER_COUNT[n] for n in unit) - sum(PARAMETER_COUNT[n] for n in other)
            score = 2 * ((model.train + model.held) - (alt.train + alt.held)) - k * log_j
            # A low-pass with white noise after it stays only where it beats the best of a
            # Gauss–Markov process, a random walk or flicker in its place by the bar: the
            # two differ only in the roll-off (a first-order low-pass only by its bilinear
            # zero at the Nyquist frequency), and where the record cannot tell them apart
            # the process is named, with the tie reported.
            chain = unit[0] in spectral.LOW_PASS_ORDERS
            better = score < evidence if chain else score <= -evidence
            # (the preference for the process where the two tie needs no held-out check)
            if better and (chain or _held_out_z(alt, parent) >= -HELD_OUT_Z):
                if best is None or score < best[0]:
                    best = (score, alt, name, other_name)
            elif score < evidence:
                ties.append(
                    {
                        "effect": name,
                        "alternative": other_name,
                        "evidence": float(score),
                        "bar": float(evidence),
                    }
                )
        if best is None:
            return model, exchanged, ties
        score, model, name, other = best
        exchanged.append({"effect": name, "by": other, "evidence": float(-score)})
    named = {spectral.effect_name(n) for n in model.names}
    ties = [t for t in ties if t["effect"] in named and t["alternative"] not in named]
    return model, exchanged, ties


COMPANIONS = ("gauss_markov", "exp_cosine", "high_frequency_noise")
"""The processes that take up a low-pass's misfit beside it in the forward steps when its
shape is not the record's: a Gauss–Markov or exponential-cosine process the roll-off's, a
noise rising towards the Nyquist frequency the shape near Nyquist (a Bessel low-pass with
it fitted a first-order Butterworth record as well as the right order with it, and kept it:
harness records butterworth_0003 and _0006)."""


def _low_pass_order(rec, floor, model, log_j: float, evidence: float):
    """The final model with another low-pass in place of its second-order Butterworth one —
    a Butterworth one of order 1, 3 or 4, a Bessel one of order 2–4, a moving average
    (`spectral.LOW_PASS_ORDERS`) — where that fits the whole record better by `evidence` in
    2 ln B: in its place, the rest of the model refitted from its optimum, and also without
    each process beside it (a second-order low-pass on a steeper or gentler roll-off leaves
    a misfit that such a companion takes up in the forward steps; without one, refitted
    from its optimum and from the structure's own starts). Tried once the selection is
    done: in the forward steps a gentler roll-off takes up a Gauss–Markov process beside
    the low-pass instead (harness records). The Butterworth orders are each tried so; the
    other shapes (the moving averages whose −3 dB point lies near the fitted corner:
    `_other_shapes`) first without every companion, then the best of them as the orders
    are. Returns (model, the companions dropped: [{"effect", "evidence"}], the other
    shapes the record cannot tell from the one kept: `_ties`)."""
    if "bandlimit" not in model.names:
        return model, [], []
    companions = tuple(n for n in model.names if n in COMPANIONS)

    def spec(shape, dropped, own_starts):
        names = tuple(shape if n == "bandlimit" else n for n in model.names if n not in dropped)
        rest = tuple(n for n in names if n != shape)
        parent = None if own_starts else dataclasses.replace(model, names=rest)
        return (names, model.lines, model.transient, parent)

    def variants(shape, drops):
        out = []
        for dropped in drops:
            out.append((shape, dropped, False))
            if dropped:
                # also from its own starts: the companion may hold the white noise, whose
                # slot the refit from the optimum inherits collapsed (docs/findings.md,
                # signal chain)
                out.append((shape, dropped, True))
        return out

    single = ((), *((c,) for c in companions))
    if len(companions) > 1:  # and every one (the other shapes are screened so)
        single = (*single, companions)
    orders = [o for o in spectral.BUTTERWORTH_ORDERS if o != "bandlimit"]
    trials = [t for o in orders for t in variants(o, single)]

    def score(dropped, alt):
        k = sum(PARAMETER_COUNT[n] for n in dropped)  # the parameters it saves
        return 2 * ((alt.train + alt.held) - (model.train + model.held)) + k * log_j

    def run(tried):
        fits = _evaluate_many(rec, floor, [spec(*t) for t in tried])
        return [(score(t[1], alt), t, alt) for t, alt in zip(tried, fits, strict=True)]

    scored = run(trials)
    # the other shapes, without every companion (a companion took up the roll-off's misfit
    # and moved the fitted corner: the orders' refits give the corner again)
    others = _other_shapes([model.z] + [alt.z for *_, alt in scored])
    screen = [t for o in others for t in variants(o, (companions,))]
    found = run(screen)
    scored += found
    if companions:
        # the best other shape, also with the companions kept and each one dropped
        lead = max(found, key=lambda s: s[0])[1][0]
        scored += run([t for t in variants(lead, single) if t not in screen])
    best, gone, top = model, (), evidence
    for value, (_, dropped, _), alt in scored:
        if value >= top:
            best, gone, top = alt, dropped, value
    chosen = spectral.low_pass(best.names) or "bandlimit"
    won = top if best is not model else 0.0
    scores = {"bandlimit": 0.0}
    for value, (shape, *_), _ in scored:
        scores[shape] = max(scores.get(shape, -math.inf), value)
    gone = [{"effect": c, "evidence": float(-top)} for c in gone]
    return best, gone, _ties(scores, chosen, won, evidence)


def low_pass_shape(name: str) -> dict:
    """A low-pass of `spectral.LOW_PASS_ORDERS` as `{"shape", "order"}` (a moving average:
    `"taps"`; a decimating average: its stages as `"order"` and its `"ratio"`)."""
    shape, n = chain_filters.code_kind(spectral.LOW_PASS_ORDERS[name])
    if shape == "moving_average":
        return {"shape": shape, "order": None, "taps": n}
    if shape == "decimating_average":
        stages, ratio = divmod(n, 100)
        return {"shape": shape, "order": stages, "ratio": ratio}
    return {"shape": shape, "order": n}


def _ties(scores: dict, chosen: str, won: float, evidence: float) -> list[dict]:
    """The low-pass shapes other than `chosen` whose best penalised score (`scores`, by
    low-pass name) lies within `evidence` of the chosen one's (`won`): the record cannot
    tell them apart. Each with `evidence`, 2 ln B of the chosen over it; best first. The
    decimating averages of one number of stages are one entry with their `ratios` (the
    chosen one's other ratios too: the record barely tells R, and not at all where the
    response is a first-order moving average, K = 2 or K = 3 with R = 2)."""
    out = {}
    for name, value in sorted(scores.items(), key=lambda item: -item[1]):
        shape = low_pass_shape(name)
        if name == chosen or won - value >= evidence:
            continue
        key = (shape["shape"], shape["order"], shape.get("taps"))
        if key in out:
            if "ratios" in out[key]:
                out[key]["ratios"].append(shape["ratio"])
            continue
        entry = {**shape, "evidence": float(won - value)}
        if "ratio" in entry:
            entry["ratios"] = [entry.pop("ratio")]
        out[key] = entry
    return list(out.values())


MOVING_AVERAGE_SPREAD = 2
"""Moving averages tried on each side of the one whose −3 dB point lies nearest the
second-order low-pass's fitted corner."""


def _other_shapes(zs) -> list[str]:
    """The low-pass shapes other than Butterworth tried in its place: a Bessel low-pass of
    each order, and the moving averages whose −3 dB point is nearest each fitted corner f_b
    of `zs` (z[8] = logit(2 f_b Δ)), with `MOVING_AVERAGE_SPREAD` taps either side of the
    first (the selected model's) and one either side of the others, and the decimating
    averages whose logged −3 dB point lies within `DECIMATION_SPREAD` of a fitted corner."""
    corners = [0.5 / (1 + math.exp(-float(z[8]))) for z in zs]  # f_b Δ
    taps = set()
    for i, corner in enumerate(corners):
        nearest = chain_filters.nearest_taps(corner)
        spread = MOVING_AVERAGE_SPREAD if i == 0 else 1
        lo = max(2, nearest - spread)
        taps.update(range(lo, min(chain_filters.MAX_TAPS, nearest + spread) + 1))
    bessel = [f"bandlimit_bessel{n}" for n in chain_filters.BESSEL_ORDERS]
    decimations = [
        name
        for name in _decimations()
        if any(
            abs(math.log(chain_filters.folded_corner(*_stages_ratio(name)) / c))
            <= math.log(DECIMATION_SPREAD)
            for c in corners
        )
    ]
    return bessel + [f"bandlimit_taps{m}" for m in sorted(taps)] + decimations


DECIMATION_SPREAD = 1.25
"""Decimating averages are tried where their logged −3 dB point lies within this factor of
a fitted corner (`chain_filters.folded_corner`)."""


def _stages_ratio(name: str) -> tuple[int, int]:
    return divmod(spectral.LOW_PASS_ORDERS[name] - chain_filters.DECIMATION_CODE, 100)


LOW_BAND = 0.1
"""The record's low band, as a fraction of the Nyquist frequency: where every low-pass of
the signal chain passes the sensor's noise nearly unchanged."""

FLAT_LOW_BAND = 2.0
"""A fitted spectrum that varies by less than this ratio over the low band is flat there:
the record's low band supports a white level at its height."""

COLLAPSED_WHITE = 0.25
"""A fitted white σ below this fraction of the σ the flat low band supports: the white
floor collapsed into a coloured process (a fit failure, `white_floor`)."""


def _white_floor(model: _Model, dt: float) -> dict | None:
    """The fitted white noise against what the record's low band supports (the fitted
    spectrum over 0 < f ≤ `LOW_BAND` × Nyquist, the low-pass's gain included): σ of
    each, the coloured process that carries most of the band, and `collapsed` where the
    band is flat (by `FLAT_LOW_BAND`) and the white σ lies below `COLLAPSED_WHITE` of its
    level — the white floor gone into a process that is white over the band, which no
    sensor's noise does (its signal chain's response, unmodelled, the likely cause). None
    where the model has a random walk or flicker (never flat at low frequencies) or no
    coloured process."""
    mask = spectral._mask(model.names)
    noise, low_pass, _ = spectral.component_models(model.z, mask, dt)
    parts = getattr(noise, "components", (noise,))
    coloured = parts[1:]
    if not coloured or not all(p.stationary for p in coloured):
        return None
    omega = np.linspace(math.pi * LOW_BAND / 64, math.pi * LOW_BAND, 64)
    gain = 1.0 if low_pass is None else np.asarray(low_pass.gain(omega, dt))
    white = math.exp(float(model.z[0]))  # z[0] = ln σ_w²
    each = {p.name: np.asarray(p.spectrum(omega, dt)) * gain for p in coloured}
    total = white * gain + sum(each.values())
    level = float(np.mean(total))
    flat = float(np.max(total) / np.min(total)) <= FLAT_LOW_BAND
    return {
        "white_sigma": math.sqrt(white),
        "low_band_sigma": math.sqrt(level),
        "carried_by": max(each, key=lambda n: float(np.mean(each[n]))),
        "low_band_flat": flat,
        "collapsed": bool(flat and math.sqrt(white) < COLLAPSED_WHITE * math.sqrt(level)),
    }


DECIMATION_RATIOS = (2, 3, 4, 6, 8, 16, 32)
"""The decimation ratios R tried for each number of stages (the logged response barely
changes beyond R ≈ 8: `chain_filters.decimation_correlation`)."""


def _decimations() -> list[str]:
    return [
        f"bandlimit_decimation{k}x{r}"
        for k in chain_filters.DECIMATION_STAGES
        for r in DECIMATION_RATIOS
    ]


def _floor_shapes() -> list[str]:
    """The low-passes tried in a collapsed floor's place: the Butterworth ones of order
    1–4, the Bessel ones of order 2–4 (each from its corner grid) and `_decimations`."""
    bessel = [f"bandlimit_bessel{n}" for n in chain_filters.BESSEL_ORDERS]
    return [*spectral.BUTTERWORTH_ORDERS, *bessel, *_decimations()]


def _collapsed_floor(rec, floor, model, dt: float, log_j: float, evidence: float):
    """Where the selected model has no low-pass and its white floor collapsed
    (`_white_floor`): the signal chain's low-passes (`_floor_shapes`: Butterworth, Bessel
    and the decimating averages) with the white noise after them in place of the processes
    beside the white noise that took it (`COMPANIONS`), refitted from their own starts;
    the best replaces the model where it fits the whole record better in 2 ln B (the
    parameters saved counted as in `_low_pass_order`; no bar: the model in place is a fit
    failure). Returns (model, the processes dropped, its 2 ln B over the model given, the
    shapes the record cannot tell from it: `_ties`)."""
    if spectral.low_pass(model.names) is not None:
        return model, (), 0.0, []
    check = _white_floor(model, dt)
    if check is None or not check["collapsed"]:
        return model, (), 0.0, []
    dropped = tuple(n for n in model.names if n in COMPANIONS)
    rest = tuple(n for n in model.names if n not in dropped)
    shapes = _floor_shapes()
    specs = [
        ((*rest, shape, "filter_floor"), model.lines, model.transient, None) for shape in shapes
    ]
    fits = _evaluate_many(rec, floor, specs)
    added = PARAMETER_COUNT["bandlimit"] + PARAMETER_COUNT["filter_floor"]
    k = sum(PARAMETER_COUNT[n] for n in dropped) - added
    scores = [2 * ((a.train + a.held) - (model.train + model.held)) + k * log_j for a in fits]
    best = int(np.argmax(scores))
    if scores[best] <= 0:  # (the model in place is a fit failure: no bar to clear)
        return model, (), 0.0, []
    by_name = dict(zip(shapes, scores, strict=True))
    chosen = shapes[best]
    return fits[best], dropped, float(scores[best]), _ties(by_name, chosen, scores[best], evidence)
