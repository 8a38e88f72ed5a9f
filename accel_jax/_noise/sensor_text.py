"""The sensor-noise findings in words: one sentence per screen's finding, for the
diagnosis's notes and the `accel-jax noise` command."""

from __future__ import annotations

import math


def saturation_sentence(rail: dict, unit: str = "g") -> str:
    """One rail of `held_out.saturation` in words (the CLI and the diagnosis alike)."""
    pile = (
        "at exactly that value"
        if rail["inner_count"] is None
        else f"against {rail['inner_count']} on the output level next inside it"
    )
    return (
        f"the output sits on a rail at {rail['level']:.6g} {unit} ({rail['count']} samples, "
        f"{100 * rail['fraction']:.2g} % of the record, {pile}): clipped by a range limit, "
        "outside the library; the fitted noise is biased low"
    )


def non_gaussian_sentence(found: dict) -> str:
    """`held_out.non_gaussian` in words, when significant (the CLI and the diagnosis)."""
    g2, z2 = found["excess_kurtosis"], found["excess_kurtosis_z"]
    g1, z1 = found["skewness"], found["skewness_z"]
    if abs(z2) >= abs(z1):
        what = f"excess kurtosis {g2:+.2f}, {abs(z2):.0f} standard errors from a Gaussian's"
        cause = (
            "two or more levels, as a random telegraph (popcorn) noise makes"
            if g2 < 0
            else "heavier tails than any Gaussian effect"
        )
    else:
        what = f"skewness {g1:+.2f}, {abs(z1):.0f} standard errors from a Gaussian's"
        cause = "an asymmetric distribution"
    return (
        f"the residual is not Gaussian ({what}): {cause}, outside the library; the fitted "
        "spectrum may be right, its Gaussian likelihood is not"
    )


def spectral_change_sentence(found: dict, duration_s: float) -> str:
    """`held_out.spectral_change` in words, when significant (the CLI and the diagnosis)."""
    low, high = found["band_Hz"]
    factor = math.exp(found["log_ratio_second_to_first"])
    half = duration_s / 2
    return (
        f"the spectrum changes during the record: {low:.3g}–{high:.3g} Hz carries "
        f"{factor:.2g} times the power after {half:.4g} s that it carried before (family-wise "
        f"p {found['p_family']:.1g}): a line or resonance that moves, a vibration that starts "
        "or stops; every model of the library is stationary, outside the library"
    )


def level_shift_sentence(shift: dict, unit: str = "g") -> str:
    """One level shift of `held_out.level_shifts` in words (the CLI and the diagnosis
    say it alike)."""
    what = (
        "taken out before the effects were selected"
        if shift.get("taken_out", True)
        else "under half the output grid's step, left in"
    )
    return (
        f"the level steps by {shift['size']:.3g} {unit} at {shift['time_s']:.4g} s "
        f"(|z| = {abs(shift['z']):.1f} against the model's own wander over "
        f"{shift['window_s']:.3g} s windows): outside the library; {what}"
    )


def low_pass_words(band: dict) -> str:
    """A low-pass's shape in words: "Butterworth, order 2", "Bessel, order 3", "a moving
    average of 5 samples", "a decimating average of 3 stages, ratio 4" (the ratios the
    record cannot tell apart joined by "/")."""
    shape = band.get("shape", "butterworth")
    if shape == "moving_average":
        return f"a moving average of {band['taps']} samples"
    if shape == "decimating_average":
        ratios = band.get("ratios") or [band.get("ratio")]
        return (
            f"a decimating average of {band['order']} stages, ratio "
            + "/".join(str(r) for r in ratios)
        )
    return f"{shape.capitalize()}, order {band['order']}"


def low_pass_ties_sentence(ties: list[dict]) -> str:
    """`held_out.low_pass_ties` in words (the CLI and the diagnosis)."""
    shapes = "; ".join(f"{low_pass_words(t)} (2 ln B {t['evidence']:.1f})" for t in ties)
    return f"the record fits these low-passes as well, within the bar: {shapes}"


def white_floor_sentence(floor: dict, unit: str = "g") -> str:
    """`held_out.white_floor` in words, when collapsed: a fit failure."""
    return (
        f"fit failure: the white noise (σ {floor['white_sigma']:.3g} {unit}) lies far below "
        f"the {floor['low_band_sigma']:.3g} {unit} the record's flat low band supports; "
        f"{floor['carried_by']} took it, white over that band: a response of the signal "
        "chain the library does not model is the likely cause"
    )
