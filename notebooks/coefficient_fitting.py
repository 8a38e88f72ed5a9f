# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Fitting the static transfer-function coefficients from a test table
#
# docs/models.md §3, eq. (1): a_F = a0 + (1 + 0.5 A1 sign a3 + δ) a3 + k2 a3² + … + k5 a3⁵ [g].
# From a table of tests (the `vibration` CSV format: `a_in, vib_amp, vib_freq, vib_rms,
# a_out`) the coefficients are fitted by least squares on the exact expectation of the
# output under vibration (optimistix Levenberg–Marquardt), with standard errors and
# correlations.
#
# The point a test engineer needs first: **which plan makes which coefficient
# identifiable.** At ±1 g alone, k3·a³ is indistinguishable from the scale factor
# (a³ = a at a = ±1), k2 from the bias, and so on. Intermediate inputs (a tumble test)
# or vibration levels separate them. Precision: float64 (ppm-level coefficients of
# O(1 g) outputs).

# %%
import jax

jax.config.update("jax_enable_x64", True)
import matplotlib.pyplot as plt
import numpy as np

import accel_jax as aj

truth = aj.StaticTransferFunction.aks05()  # Table 4 passport values as the "true" unit
NOISE_G = 2e-6  # standard deviation of each row's mean output [g]
rng = np.random.default_rng(0)


def plan(a_in, vib_amp=0.0, vib_rms=0.0):
    """A test plan: one row per (input, vibration) condition, a_out still to be measured."""
    a_in, vib_amp, vib_rms = np.broadcast_arrays(
        np.asarray(a_in, float), np.asarray(vib_amp, float), np.asarray(vib_rms, float)
    )
    return {
        "a_in": a_in,
        "vib_amp": vib_amp,
        "vib_freq": np.where(vib_amp > 0, 30.0, 0.0),
        "vib_rms": vib_rms,
        "a_out": np.zeros_like(a_in),
    }


def measure(table):
    """Simulate the test: the exact mean output of the true unit plus measurement noise."""
    out = dict(table)
    out["a_out"] = np.asarray(
        aj.vibration.predict_table(truth, table)
    ) + NOISE_G * rng.standard_normal(len(table["a_in"]))
    return out


# %% [markdown]
# ## 1. Identifiability of three test plans
# `aj.vibration.identifiability` projects each coefficient's design column on the others: an
# unexplained fraction of 0 means the plan cannot tell that coefficient from the rest.

# %%
plans = {
    "±1 g only": plan(np.repeat([-1.0, 1.0], 6)),
    "tumble −1..1 g (13 angles)": plan(np.sin(np.linspace(-np.pi / 2, np.pi / 2, 13))),
    "tumble + shaker 2/4 g at ±1 g": plan(
        np.concatenate([np.sin(np.linspace(-np.pi / 2, np.pi / 2, 13)), [1, 1, -1, -1]]),
        np.concatenate([np.zeros(13), [2.0, 4.0, 2.0, 4.0]]),
    ),
}
for name, table in plans.items():
    ident = aj.vibration.identifiability(table, noise=NOISE_G)
    cells = ", ".join(
        f"{n}: {'ok' if ok else 'NOT'} ({f:.2g})"
        for n, ok, f in zip(
            ident.names,
            np.asarray(ident.identifiable),
            np.asarray(ident.unexplained_fraction),
            strict=True,
        )
    )
    print(f"{name:>32}: {cells}")

# %% [markdown]
# ## 2. Simulate, fit, recover
# On the plan that separates everything, fit the coefficients and compare with the truth
# in units of their standard errors.

# %%
table = measure(plans["tumble + shaker 2/4 g at ±1 g"])
fit = aj.vibration.fit_coefficients(table, noise=NOISE_G)
print(f"{'coefficient':>20} {'true':>10} {'fitted':>10} {'std err':>9} {'z':>6}   [ppm units]")
z_scores = []
for name, est, se in zip(
    fit.names, np.asarray(fit.estimate_ppm), np.asarray(fit.standard_error_ppm), strict=True
):
    true = float(getattr(truth, name)) / aj.PPM
    z_scores.append((est - true) / se)
    print(f"{name:>20} {true:10.4g} {est:10.4g} {se:9.2g} {z_scores[-1]:6.2f}")
print(f"residual RMS: {float(fit.residual_rms):.3g} g (noise {NOISE_G:g} g)")
assert np.all(np.abs(z_scores) < 5), "a coefficient was not recovered within 5 standard errors"

# %% [markdown]
# ## 3. Correlations
# Large |correlation| between two coefficients means the plan barely separates them:
# add rows where their design columns differ (other input levels, other vibration levels).

# %%
fig, ax = plt.subplots(figsize=(5.5, 4.6))
image = ax.imshow(np.asarray(fit.correlation), vmin=-1, vmax=1, cmap="RdBu_r")
ax.set_xticks(range(len(fit.names)), fit.names, rotation=45, ha="right")
ax.set_yticks(range(len(fit.names)), fit.names)
fig.colorbar(image, ax=ax, label="correlation [1]")
ax.set_title("Correlation of the fitted coefficients")
fig.tight_layout()
fig.savefig("coefficient_correlation.png", dpi=110)
