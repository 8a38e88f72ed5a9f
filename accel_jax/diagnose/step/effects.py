"""The effects of the `step` kind: each an extension of the nominal loop that is exactly the
nominal loop at zero (the package `step` describes the kind; `fit` applies the hooks).

- `torquer_lag`: T_dm other than the nominal device's (inside the loop: changes the
  overshoot as well as the delay);
- `output_filter`: T_f other than the nominal device's (outside the loop: delays the output
  only);
- `stop_saturation`: mechanical stops, upper and lower (`_simulate.sequence.stop_record`);
- `disturbance_drift`: a drifting external moment, M(t) = M + Ṁ t;
- `colored_noise`: correlated output noise, white + first-order Gauss–Markov (AR(1)),
  fitted through its one-step prediction errors (an ARMA(1,1) recursion);
- `moment_noise`: a Gauss–Markov moment inside the loop (filtered by it) on top of white
  output noise, fitted through a Kalman filter of the loop's states over the blocks
  (`innovations.moment_noise_terms`; a program of its own, `fit.fit_moment`);
- `stop_contact`: compliant stops, a unilateral spring-damper at each stop, each side at
  its own clearance (one side may be out of reach): `_simulate.contact.contact_record`.
  Fitted only where the inelastic clamp of `stop_saturation` was fitted and does not
  explain the record (`entry`).

Adding an effect: subclass `AbstractStepEffect`, set `name`, `parameter_names`, `description`,
`starts`, override one hook and `physical`, decorate with `register_effect`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._params import ServoParams
from ..base import AbstractEffect, effect_library, register_effect
from .innovations import moment_kalman, moment_noise_model
from .layout import SLOT

if TYPE_CHECKING:
    from .state import CandidateHost, RecordHost


class AbstractStepEffect(AbstractEffect):
    """An effect on a step record. Hooks (each the identity at z = 0; override one):

    - `device(params, z, ctx)`: change the loop's `ServoParams` (lags);
    - `drift(z, ctx)`: the external moment's change over the record, r [V];
    - `inverse_stop(z, ctx)`: 1/h in units of the training output's half range (0 for
        none), with symmetric stops at deflection ±h; an effect with stops is `nonlinear`;
    - `output_offset(z, ctx)`: an offset c [V] added to the output (U_out = v + c);
    - `noise(z, ctx)`: (φ, θ, ln V₀) of the output noise's ARMA(1,1) on the block means
        (`block_noise`; 0, 0, 0: white);
    - `contact(z, ctx)`: (1/h_hi, 1/h_lo, κ, ζ_c) of compliant stops (clearances in units
        of the training output's half range, 0: none on that side; κ the stiffness over
        the loop's, ζ_c the damping ratio); an effect with it sets `contact`.
    - `moment_noise(z, ctx)`: (λ², φ_block) of a Gauss–Markov moment inside the loop
        (`innovations.moment_noise_model`; λ² = 0: none); an effect with it sets
        `loop_noise`.

    Class attributes: `nonlinear` (simulated with stops, sample by sample), `contact`
    (its stops compliant: a program of its own, `fit.fit_contact`), `loop_noise` (its
    noise inside the loop: a program of its own, `fit.fit_moment`), `stochastic`
    (changes the noise model, not the prediction), `starts` (the starting points of its
    parameters, one tuple per start), `bounds` (|z| beyond which a steep penalty acts),
    `held_out_nuisance`
    (indices of its parameters that are nuisances: refitted on the held-out part with the
    change times).
    """

    kind = "step"
    nonlinear: ClassVar[bool] = False
    contact_stops: ClassVar[bool] = False
    loop_noise: ClassVar[bool] = False
    stochastic: ClassVar[bool] = False
    starts: ClassVar[tuple] = ((0.0,), (0.0,))
    bounds: ClassVar[tuple] = (10.0, 10.0)
    held_out_nuisance: ClassVar[tuple] = ()

    def device(self, params: ServoParams, z, ctx) -> ServoParams:
        return params

    def drift(self, z, ctx):
        return jnp.zeros_like(z[0])

    def inverse_stop(self, z, ctx):
        return jnp.zeros_like(z[0])

    def output_offset(self, z, ctx):
        return jnp.zeros_like(z[0])

    def contact(self, z, ctx):
        zero = jnp.zeros_like(z[0])
        return zero, zero, zero, zero

    def moment_noise(self, z, ctx):
        zero = jnp.zeros_like(z[0])
        return zero, zero

    def prior(self, z, ctx):
        """Prior residuals of its parameters (shape (SLOT,), the slot's; default none)."""
        return jnp.zeros(SLOT, z.dtype)

    def record_starts(self, host: RecordHost) -> tuple:
        """The starting points for one record (default `starts`), from its scales
        (`state.RecordHost`, made by `record.prepare`)."""
        return self.starts

    def noise(self, z, ctx):
        """The output noise's one-step model on the block means, ARMA(1,1): (φ, θ, ln V₀),
        n_k − φ n_{k−1} = a_k − θ a_{k−1}, V₀ the first block's variance over σ_a²
        (0, 0, 0: white; see `innovations.innovation_terms`)."""
        zero = jnp.zeros_like(z[0])
        return zero, zero, zero

    def initial_guess(self, context):
        return np.asarray(self.starts[0])


def _lag(nominal, z, unit):
    """T = max(T₀ + unit·z, 0): the nominal device's lag T₀ moved by unit·z, never below 0.
    With T₀ = 0 this is unit·max(z, 0): a fit that wants no lag ends on the flat side
    instead of creeping towards a double zero (T ∝ z² converged slowly there), and the
    lag's first-order effect keeps the fit well conditioned for small T. With T₀ > 0 the
    departure may take either sign (a device faster than its data sheet)."""
    if isinstance(z, jax.Array) or isinstance(nominal, jax.Array):
        return jnp.maximum(nominal + unit * z, 0.0)
    return max(nominal + unit * z, 0.0)


class _AbstractLag(AbstractStepEffect):
    """A first-order lag in the `ServoParams` field `lag_field`: the nominal device's value
    T₀ (taken as known; 0 for an ideal loop) plus a departure, T = max(T₀ + lag_unit·z, 0).
    At z = 0 it is the nominal device exactly."""

    lag_field: ClassVar[str]
    starts = ((1.0,), (5.0,))
    bounds = (100.0,)

    def device(self, params, z, ctx):
        lag = _lag(getattr(params, self.lag_field), z[0], ctx.lag_unit)
        return eqx.tree_at(lambda p: getattr(p, self.lag_field), params, lag)

    def physical(self, z, context: CandidateHost):
        nominal = float(context.nominal_lag(self.lag_field))
        value = float(_lag(nominal, float(z[0]), context.lag_unit))
        return {
            self.parameter_names[0]: value,
            "nominal_" + self.parameter_names[0]: nominal,
            "change_s": value - nominal,
        }


@register_effect
class TorquerLag(_AbstractLag):
    """Torquer electrical lag T_dm inside the loop, departing from the nominal device's."""

    name = "torquer_lag"
    lag_field = "torquer_time_constant"
    parameter_names = ("torquer_time_constant_s",)
    description = "magnetoelectric torquer time constant T_dm inside the loop"


@register_effect
class OutputFilter(_AbstractLag):
    """Output filter T_f outside the loop, departing from the nominal device's."""

    name = "output_filter"
    lag_field = "filter_time_constant"
    parameter_names = ("filter_time_constant_s",)
    description = "output (amplifier) filter time constant T_f outside the loop"


OFFSET_PRIOR = 0.02
"""σ [V] of the prior of an output (ADC) offset in the stop model."""


@register_effect
class StopSaturation(AbstractStepEffect):
    """Inelastic mechanical stops at deflection ±h (h = half/|z₀|, symmetric: ±h_max), seen
    through an output offset c = 0.1·scale·z₁ (U_out = v + c): an ADC offset moves both
    stops in the record, and the external moment moves the deflection between them."""

    name = "stop_saturation"
    parameter_names = ("stop_V", "output_offset_V")
    description = "mechanical stops reached (the pendulum held at ±h_max)"
    nonlinear = True
    starts = ((1.02, 0.0), (1.02, 0.0))
    # The output offset is a nuisance that only a contact reveals; a training part that
    # reaches one stop cannot tell it from the external moment.
    held_out_nuisance = (1,)

    def inverse_stop(self, z, ctx):
        return jnp.abs(z[0])

    def prior(self, z, ctx):
        # A stop the training part never reaches is not measured: a weak pull moves it out
        # of reach (1/z → ∞) instead of leaving it where the fit started, at the training
        # peak. The output offset has a N(0, OFFSET_PRIOR) prior: with only one stop
        # reached it is not told from the external moment, and no offset is the default.
        zero = jnp.zeros_like(z[0])
        return jnp.stack([0.1 * z[0], self.output_offset(z, ctx) / OFFSET_PRIOR, zero, zero])

    def output_offset(self, z, ctx):
        return 0.1 * ctx.scale * z[1]

    def record_starts(self, host: RecordHost):
        # The offset at the middle of the training output's range: the stops are symmetric
        # about it when both are reached.
        offset = host.mid / (0.1 * host.scale)
        return tuple((s[0], offset) for s in self.starts)

    def physical(self, z, context: CandidateHost):
        stop = context.half / abs(float(z[0])) if abs(float(z[0])) > 1e-9 else float("inf")
        offset = 0.1 * context.scale * float(z[1])
        return {
            "stop_V": stop,
            "stop_displacement_m": stop / context.gain,
            "output_offset_V": offset,
            "stop_high_V": offset + stop,
            "stop_low_V": offset - stop,
        }


@register_effect
class DisturbanceDrift(AbstractStepEffect):
    """External moment drifting linearly; z = 1 moves the settled output ≈ 10 mV over the
    record."""

    name = "disturbance_drift"
    parameter_names = ("moment_rate_Nm_per_s",)
    description = "slow drift of the external moment, M(t) = M + Ṁ t"
    starts = ((0.0,),)

    def drift(self, z, ctx):
        return 1e-2 * z[0]

    def physical(self, z, context: CandidateHost):
        change = 1e-2 * float(z[0])  # V of M/k_dm over the record
        return {
            "moment_rate_Nm_per_s": change * context.torquer_gain / context.duration,
            # The moment's settled output is k_test M/k_dm: no test winding (its gain and
            # polarity) on its way.
            "output_drift_V_per_s": change * context.k_test / context.duration,
        }


@register_effect
class ColoredNoise(AbstractStepEffect):
    """White + Gauss–Markov output noise, each sampled at the record's rate and averaged
    over the fit's blocks of m samples: the Gauss–Markov part's standard deviation is
    λ = max(z₀, 0) times the white part's (per sample), its block-to-block coefficient
    φ = |tanh z₁| (per sample φ^{1/m}). The block means of such noise are exactly
    ARMA(1,1) (`block_noise`), with a moving-average part of either sign: the averaging
    of the correlated part gives the opposite sign to the white part's."""

    name = "colored_noise"
    parameter_names = ("correlated_over_white", "ar1_coefficient")
    description = "correlated (Gauss–Markov) output noise on top of the white noise"
    stochastic = True
    starts = ((1.0, 1.5), (1.0, 3.0))
    bounds = (30.0, 5.0)

    def noise(self, z, ctx):
        ratio = jnp.maximum(z[0], 0.0) ** 2
        phi, theta, first, _ = block_noise(ratio, jnp.tanh(z[1]), ctx.block, ctx.max_block)
        return jnp.asarray(phi), jnp.asarray(theta), jnp.log(first)

    def physical(self, z, context: CandidateHost):
        ratio = max(float(z[0]), 0.0) ** 2
        m = context.block_samples
        phi, _, first, unit = (
            float(v) for v in block_noise(ratio, np.tanh(float(z[1])), m, max(m, 1))
        )
        tau = -context.dt / math.log(phi) if 0 < phi < 1 else float("nan")
        white = context.innovation_variance / unit  # one sample's white variance [V²]
        # A block mean's variance is first·unit per unit white variance, 1/m of it white.
        gm_block = max(first * unit - 1 / m, 0.0) * white
        return {
            "ar1_coefficient": phi,
            "correlation_time_s": float(tau),
            "sigma_white_V": math.sqrt(white / m),
            "sigma_correlated_V": math.sqrt(gm_block),
            "sigma_white_per_sample_V": math.sqrt(white),
            "sigma_correlated_per_sample_V": math.sqrt(ratio * white),
        }


CONTACT_STIFFNESS = 300.0
"""κ of a compliant stop at z₂ = 0 (its stiffness over the loop's static stiffness)."""

CONTACT_DAMPING = 0.3
"""ζ_c of a compliant stop at z₃ = 0."""


@register_effect
class StopContact(AbstractStepEffect):
    """Compliant stops: beyond each stop a unilateral spring-damper (it pushes, never
    pulls) of stiffness κ times the loop's static stiffness and damping ratio ζ_c, the
    upper stop at deflection voltage h_hi = half/|z₀| and the lower at −h_lo = −half/|z₁|
    (half: the training output's half range; z = 0: no stop on that side, so a stop on one
    side only is z₁ → 0), κ = `CONTACT_STIFFNESS`·e^{2 z₂}, ζ_c = `CONTACT_DAMPING`·e^{1.5 z₃}.

    The clearances are measured from zero deflection, not from the output's level: the
    external moment (a nuisance of every model) carries the output's offset, so no offset
    parameter is needed and the two clearances may differ. A stop the record never
    reaches is not measured: a weak pull moves it out of reach (as `stop_saturation`'s),
    and its clearance is reported as not reached. κ and ζ_c have wide priors (σ of
    ln κ: 4, of ln ζ_c: 3); a stiff, well-damped contact is close to the inelastic clamp."""

    name = "stop_contact"
    parameter_names = (
        "stop_high_V",
        "stop_low_V",
        "contact_stiffness_over_loop",
        "contact_damping_ratio",
    )
    description = (
        "compliant mechanical stops (a spring-damper contact at each stop, each side at its "
        "own clearance, or one side only)"
    )
    nonlinear = True
    contact_stops = True
    starts = ((1.02, 1.02, 0.0, 0.0), (0.75, 0.75, -1.15, -0.73))
    """(reach, reach, z₂, z₃): each stop at `reach` times the training output's extreme on
    its side; the second start deep inside it, soft (κ ≈ 30) and bouncing (ζ_c ≈ 0.1): a
    soft contact lets the pendulum well past its clearance."""
    bounds = (10.0, 10.0, 3.0, 3.0)

    def contact(self, z, ctx):
        stiffness = CONTACT_STIFFNESS * jnp.exp(2.0 * z[2])
        damping = CONTACT_DAMPING * jnp.exp(1.5 * z[3])
        return jnp.abs(z[0]), jnp.abs(z[1]), stiffness, damping

    def prior(self, z, ctx):
        # Weak pulls on the inverse clearances (a stop not reached moves out of reach) and
        # wide priors on the contact's ln κ and ln ζ_c.
        return jnp.stack([0.1 * z[0], 0.1 * z[1], 0.5 * z[2], 0.5 * z[3]])

    def record_starts(self, host: RecordHost):
        # Each stop just beyond the training output's extreme on its side (measured from
        # zero deflection), at the contact's middling stiffness, then a stiffer one.
        top, bottom = host.mid + host.half, host.mid - host.half

        def inverse(extreme, reach):  # 1/h of a stop at reach × the extreme (0: none)
            return host.half / (reach * max(abs(extreme), 1e-3 * host.half))

        return tuple(
            (
                inverse(top, s[0]) if top > 0 else 0.0,
                inverse(bottom, s[1]) if bottom < 0 else 0.0,
                s[2],
                s[3],
            )
            for s in self.starts
        )

    def physical(self, z, context: CandidateHost):
        # A clearance beyond the record's extreme output on its side (by more than 3σ of
        # the noise) was not reached: the record only says it lies beyond; reported as inf,
        # with `stop_*_reached` 0.
        def clearance(value, extreme):
            h = context.half / abs(float(value)) if abs(float(value)) > 1e-9 else np.inf
            margin = 3 * float(np.sqrt(max(context.innovation_variance, 0.0)))
            return (h, 1.0) if h < extreme + margin else (np.inf, 0.0)

        (high, high_reached), (low, low_reached) = (
            clearance(z[0], context.top),
            clearance(z[1], -context.bottom),
        )
        return {
            "stop_high_V": high,
            "stop_low_V": -low,
            "stop_high_reached": high_reached,
            "stop_low_reached": low_reached,
            "stop_high_displacement_m": high / context.gain,
            "stop_low_displacement_m": -low / context.gain,
            "contact_stiffness_over_loop": float(CONTACT_STIFFNESS * np.exp(2.0 * float(z[2]))),
            "contact_damping_ratio": float(CONTACT_DAMPING * np.exp(1.5 * float(z[3]))),
        }


@register_effect
class MomentNoise(AbstractStepEffect):
    """White output noise plus a Gauss–Markov moment inside the loop, which the closed loop
    filters before it reaches the output: the moment's low-frequency output is λ = max(z₀, 0)
    times the white part's standard deviation (per sample; `sigma_moment_static_V`, the
    output the moment would give through the loop's static gain; what reaches the output,
    filtered, is `sigma_correlated_per_sample_V`), its block-to-block coefficient
    φ = |tanh z₁| (rate −ln φ/(mΔ)). Fitted through a Kalman filter of the loop's states
    and the moment over the blocks (`innovations.moment_noise_terms`), with the fitted
    device's loop: where the moment is slow against the loop it is an output Gauss–Markov
    process (`colored_noise`) too, and the two places are not told apart; where it is fast,
    the loop shapes it (a resonance, a roll-off) and only this model whitens it."""

    name = "moment_noise"
    parameter_names = ("moment_over_white", "ar1_coefficient")
    description = "correlated (Gauss–Markov) moment noise inside the loop, on top of white noise"
    stochastic = True
    loop_noise = True
    starts = ((1.0, 1.5), (3.0, 0.5))
    bounds = (30.0, 5.0)

    def moment_noise(self, z, ctx):
        return jnp.maximum(z[0], 0.0) ** 2, jnp.tanh(z[1])

    def physical(self, z, context: CandidateHost):
        ratio = max(float(z[0]), 0.0) ** 2
        m = context.block_samples
        phi = abs(float(np.tanh(float(z[1]))))
        device = context.device
        if device is None:
            raise ValueError("moment_noise's physical values need the fitted device")
        _, _, _, loop_block, loop_sample = moment_noise_model(
            device, context.dt / m, m, max(m, 1), ratio, phi
        )
        # The one-step variance per unit white variance, from the filter run to its steady
        # state on a long stretch of zeros (the innovations' variance does not depend on
        # the data).
        _, s = moment_kalman(
            jnp.zeros(4096), device, context.dt / m, m, max(m, 1), ratio, phi
        )
        unit = float(s[-1])
        white = context.innovation_variance / unit  # one sample's white variance [V²]
        tau = -context.dt / math.log(phi) if 0 < phi < 1 else float("nan")
        return {
            "ar1_coefficient": phi,
            "correlation_time_s": float(tau),
            "sigma_white_V": math.sqrt(white / m),
            "sigma_correlated_V": math.sqrt(max(float(loop_block), 0.0) * white),
            "sigma_white_per_sample_V": math.sqrt(white),
            "sigma_moment_static_V": math.sqrt(ratio * white),
            "sigma_correlated_per_sample_V": math.sqrt(max(float(loop_sample), 0.0) * white),
        }


def _sums(phi_block, m, max_block):
    """(S, T) of the per-sample coefficient r = |φ_block|^{1/m}: S = Σ_{j<m} r^j,
    T = Σ_{0<d<m} (m − d) r^d, by powers masked to j < m (m ≤ max_block)."""
    xp = jnp if isinstance(phi_block, jax.Array) or isinstance(m, jax.Array) else np
    m = xp.asarray(m, dtype=float)
    log_r = xp.log(xp.maximum(phi_block**2, 1e-300)) / (2 * m)
    j = xp.arange(max_block, dtype=float)
    powers = xp.where(j < m, xp.exp(j * log_r), 0.0)
    return xp.sum(powers), xp.sum(xp.where(j > 0, (m - j) * powers, 0.0)), m


def block_noise(ratio, phi_block, m, max_block):
    """The exact ARMA(1,1) of the block means of white noise (variance 1 per sample) plus
    a sampled Gauss–Markov process (variance `ratio`, per-sample coefficient
    r = |φ_block|^{1/m}), m samples per block: (φ, θ, V₀, σ_a²) with φ = r^m, θ the
    invertible moving-average root, V₀ the stationary variance of a block mean over σ_a²,
    σ_a² the one-step prediction variance (per unit white variance).

    The block means' autocovariance: γ₀ = 1/m + λ²(m + 2T)/m², γ_k = λ² r S² φ^{k−1}/m²
    (k ≥ 1; S, T from `_sums`). Then u_k = n_k − φ n_{k−1} is MA(1) with c₀ = γ₀(1 + φ²)
    − 2φγ₁ and c₁ = γ₁ − φγ₀: θ/(1 + θ²) = −c₁/c₀ and σ_a² = c₀/(1 + θ²). For m = 1 this
    is white + AR(1) (θ of the white part's sign, ≥ 0); averaging makes the correlated
    part's contribution to −c₁ negative, and it dominates where the correlated part does."""
    xp = jnp if isinstance(phi_block, jax.Array) or isinstance(ratio, jax.Array) else np
    s, t, m = _sums(phi_block, m, max_block)
    phi = xp.abs(phi_block)
    r = xp.exp(xp.log(xp.maximum(phi, 1e-300)) / m)
    gamma0 = 1 / m + ratio * (m + 2 * t) / m**2
    gamma1 = ratio * r * s**2 / m**2
    c0 = gamma0 * (1 + phi**2) - 2 * phi * gamma1
    rho = xp.clip(-(gamma1 - phi * gamma0) / c0, -0.5 + 1e-12, 0.5 - 1e-12)
    theta = 2 * rho / (1 + xp.sqrt(1 - 4 * rho**2))
    variance = c0 / (1 + theta**2)
    return phi, theta, gamma0 / variance, variance



def step_effects() -> list[AbstractStepEffect]:
    """The registered step effects, in registration order."""
    return [cls() for cls in effect_library("step").values()]
