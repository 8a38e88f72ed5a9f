"""The words of the report and the command line, as a reader meets them.

One list, rendered at the top of the report (`_html.py`) and kept in the README's
"Glossary" section (a test checks that every term here is there).
"""

from __future__ import annotations

GLOSSARY: tuple[tuple[str, str], ...] = (
    (
        "2 ln B (evidence)",
        "twice the log Bayes factor of a model with an effect against the nominal model, "
        "approximated by BIC: 2Δln L − k ln n (k added parameters, n fitted samples). "
        "Above 10 is strong evidence (Kass & Raftery 1995); two effects within 6 of each "
        "other are a tie.",
    ),
    (
        "held-out",
        "the part of a record the fit never saw (every third test-voltage segment of a step "
        "record, the last third of a noise record, one row left out of a vibration table): "
        "a model is judged by how it predicts that part.",
    ),
    (
        "gap (held-out gap)",
        "the RMS held-out prediction error in excess of the noise floor: what the model "
        "misses beyond the noise.",
    ),
    (
        "shrink",
        "1 − gap after / gap before: the share of the nominal model's held-out gap an "
        "effect removes (1: all of it; 0: none; negative: it predicts worse).",
    ),
    (
        "explained fraction",
        "the share of the held-out excess (mean square above the floor) the chosen model removes.",
    ),
    (
        "noise floor",
        "the record's noise measured without any model (differences of block means, the "
        "ADC step's q/√12), or the variance a noise model predicts for its one-step errors.",
    ),
    (
        "refit",
        "the nominal device's uncertain values (J, μ, c, k_dm) fitted to the record under "
        "their prior; a shift is given in % and in σ of that prior (beyond 5σ: not "
        "credible).",
    ),
    (
        "nuisance",
        "a quantity fitted in every model but never reported as physics: test-winding "
        "polarity and gain, output offset, initial state, change times.",
    ),
    (
        "verdict",
        "the diagnosis's answer: none (nothing missing: the nominal model predicts the "
        "held-out part to the noise floor), an effect's name, cannot_tell (two effects fit "
        "equally well; both are named) or unexplained (the gap is real and no library "
        "effect closes it).",
    ),
    (
        "discovery",
        "for an unexplained step record, the missing term found in a library of terms at "
        "named places in the loop (pickoff, spring, damping, torquer, output, forcing): a "
        "hypothesis, rated credible (held-out gap at the noise floor, stable, evidence ≥ "
        "10), tentative or nothing found; the verdict stays unexplained. A record named a "
        "noise effect whose misfit a predictor partly foresees is searched too, and becomes "
        "unexplained where a credible term brings the held-out gap to the floor and the "
        "noise does not. Each term comes "
        "with what it means for a designer (the static transfer function's coefficient it "
        "implies, its vibration error against the paper's limit) and, when the record "
        "barely measures it, the record that would excite it.",
    ),
    (
        "δK_a",
        "relative error of the identified scale factor K_a against the true one, in %.",
    ),
    (
        "δ_V",
        "the vibration (rectification) error: the shift of the mean output under vibration "
        "caused by the nonlinearity k2..k5 and the cross-coupling, in g or ppm of 1 g.",
    ),
    (
        "ADEV",
        "Allan deviation σ(τ) of a static record; its intervals come from the equivalent "
        "degrees of freedom (EDF) of the overlapping estimator.",
    ),
    (
        "Ljung–Box",
        "the test that a residual is white: Q = n(n+2) Σ r_k²/(n−k) over the first lags "
        "against χ²; p < 0.05 means not white.",
    ),
    (
        "NEES",
        "normalised estimation error squared of a Kalman filter; ≈ the state dimension when "
        "the filter's covariance is consistent with its errors.",
    ),
    (
        "fit %",
        "100·(1 − ‖y − ŷ‖/‖y − ȳ‖), as MATLAB's compare: 100 is a perfect fit.",
    ),
    (
        "status",
        "of a number beside a published one: reproduced (within its stated tolerance), "
        "explained (differs, for a cause the study shows), differs (unexplained), met / "
        "missed (a target).",
    ),
)
"""(term, meaning) pairs, in reading order."""
