"""Why the paper's batch loop does not settle at the true gyro correlation time: its
identification step predicted from the spectra (`accel_jax.kalman.smoothed_autocovariance`).

One step of the loop (noise_identification.filter_identification_loop) smooths a log with
the current model and applies rule (15) to the sample autocovariance of the smoothed Δa
and Δω. Away from the log's ends the RTS smoother is the Wiener smoother of the current
model, so the expected autocovariance of those estimates, over a log of the same length
from the true channel, follows from the two models' spectra alone; rule (15) applied to it
predicts the next model without a log. Run from the loop's start, that map is compared
with the loop itself on more logs (the median identified τ_ω per iteration): where they
agree, the bias is that map, not one log's noise.
The same map at the true models, with and without the smoother's posterior
autocovariance added (what an EM step would add), separates the smoothing's part of the
bias from rule (15)'s own on a record of that length.

Assumptions, stated in the output: a steady-state smoother (the log's ends ignored), rule
(15) applied to the expected autocovariance (not the expectation of the rule over logs:
rule (15) takes logarithms, so the median over logs sits above the map's value by ~10-20 %
at 48 h, measured 2026-12-04),
lags 1..min(n/10, 2000) while r_j > e⁻¹ as in the loop, NumPy float64 on a frequency grid
of `fft_size` points.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from accel_jax.kalman import (
    INSChannel,
    expected_sample_autocovariance,
    ins_initial_covariance,
    kalman_filter,
    rts_smoother,
    simulate_linear_gaussian,
    smoothed_autocovariance,
)
from accel_jax.noise import GaussMarkov, autocorrelation, fit_gauss_markov_paper

_FIELDS = ("accel_sigma", "accel_correlation_time", "gyro_sigma", "gyro_correlation_time")
_SENSORS = (("accelerometer", "accel"), ("gyro", "gyro"))


def _rule(autocovariance, dt: float) -> dict:
    fit = fit_gauss_markov_paper(
        np.asarray(autocovariance), dt, min_correlation=float(np.exp(-1)), throw=False
    )
    return {"sigma": float(fit.model.sigma), "tau_s": float(fit.model.correlation_time)}


def _channel(fields: dict, velocity_noise: float) -> INSChannel:
    return INSChannel(**{k: float(fields[k]) for k in _FIELDS}, velocity_noise=velocity_noise)


def _step(assumed, truth, dt, n, max_lag, fft_size, posterior=False) -> dict:
    """The model rule (15) identifies from `assumed`'s smoothed estimates of a log of n
    samples from `truth`: {sensor: {sigma, tau_s}}."""
    got = smoothed_autocovariance(
        assumed.discretise(dt),
        truth.discretise(dt),
        (2, 3),
        max_lag,
        record_length=n,
        fft_size=fft_size,
    )
    r = got.estimate + got.posterior if posterior else got.estimate
    return {name: _rule(r[i], dt) for i, (name, _) in enumerate(_SENSORS)}


def _as_fields(step: dict) -> dict:
    return {
        f"{short}_{key}": step[name][field]
        for name, short in _SENSORS
        for key, field in (("sigma", "sigma"), ("correlation_time", "tau_s"))
    }


def _retuned(channel: INSChannel, step: dict) -> INSChannel:
    values = _as_fields(step)
    return eqx.tree_at(
        lambda c: tuple(getattr(c, k) for k in _FIELDS),
        channel,
        tuple(jnp.asarray(values[k], jnp.float64) for k in _FIELDS),
    )


def loop_over_logs(
    truth: INSChannel, start: INSChannel, dt: float, n: int, iterations: int, logs: int, key
) -> dict:
    """The loop's identification alone (rule (15) on the RTS-smoothed Δa, Δω over lags
    1..min(n/10, 2000) while r_j > e⁻¹, no consistency runs) on `logs` logs of n samples:
    per iteration the median and quartiles of the identified τ_ω. float64 (the caller's
    `jax.enable_x64`)."""
    max_lag = min(n // 10, 2000)
    zeros = jnp.zeros(4)
    true_model = truth.discretise(dt)

    @eqx.filter_jit
    def identified(channel, observations):
        model = channel.discretise(dt)
        out = kalman_filter(model, observations, zeros, ins_initial_covariance(channel))
        x = rts_smoother(model, out).smoothed_means[:, 2:]
        r = jax.vmap(lambda s: autocorrelation(s, max_lag), in_axes=1)(x)
        fits = jax.vmap(
            lambda r: fit_gauss_markov_paper(
                r, dt, min_correlation=float(np.exp(-1)), throw=False
            )
        )(r)
        return fits.model.sigma, fits.model.correlation_time

    taus = np.empty((logs, iterations))
    for i, k in enumerate(jax.random.split(key, logs)):
        _, observations = simulate_linear_gaussian(
            true_model, zeros, ins_initial_covariance(truth), n, key=k
        )
        channel = start
        for it in range(iterations):
            sigma, tau = (np.asarray(v) for v in identified(channel, observations))
            step = {
                name: {"sigma": float(sigma[j]), "tau_s": float(tau[j])}
                for j, (name, _) in enumerate(_SENSORS)
            }
            taus[i, it] = step["gyro"]["tau_s"]
            channel = _retuned(channel, step)
    return {
        "logs": logs,
        "gyro_tau_s_median": np.median(taus, 0).tolist(),
        "gyro_tau_s_quartiles": np.percentile(taus, [25, 75], axis=0).T.tolist(),
    }


def batch_bias(
    loop: dict, truth_fields: dict, dt: float, *, logs: int, key, fft_size: int | None = None
) -> dict:
    """The loop's identification map from the spectra, beside what the loop identified
    (`loop`: filter_identification_loop's result with rule (15)) and beside the loop run on
    `logs` more logs; `truth_fields`: the true INSChannel's fields (velocity_noise
    included)."""
    n = int(loop["log_hours"] * 3600 / dt)
    max_lag = min(n // 10, 2000)
    velocity_noise = float(truth_fields["velocity_noise"])
    truth = _channel(truth_fields, velocity_noise)
    rows = loop["iterations"]
    steps = []
    for current, following in zip(rows[:-1], rows[1:]):
        model = _channel(current["model"], velocity_noise)
        predicted = _step(model, truth, dt, n, max_lag, fft_size)
        steps.append(
            {
                "from_iteration": current["iteration"],
                "predicted": predicted,
                "identified": {
                    name: {
                        "sigma": following["model"][f"{short}_sigma"],
                        "tau_s": following["model"][f"{short}_correlation_time"],
                    }
                    for name, short in _SENSORS
                },
            }
        )
    # The map run on its own from the loop's start, with and without the posterior part.
    start = _channel(rows[0]["model"], velocity_noise)
    chains = {}
    for posterior in (False, True):
        model, chain = start, []
        for _ in range(len(rows) - 1):
            step = _step(model, truth, dt, n, max_lag, fft_size, posterior)
            chain.append(step)
            model = _channel(_as_fields(step), velocity_noise)
        chains["with_posterior" if posterior else "smoothed_means"] = chain
    # Rule (15) on the true errors themselves: the Gauss–Markov models' own autocovariance.
    lag_times = np.arange(n) * dt
    rule_alone = {
        name: _rule(
            expected_sample_autocovariance(
                GaussMarkov(
                    truth_fields[f"{short}_sigma"], truth_fields[f"{short}_correlation_time"]
                ).autocovariance(lag_times),
                n,
                max_lag,
            ),
            dt,
        )
        for name, short in _SENSORS
    }
    over_logs = loop_over_logs(truth, start, dt, n, len(rows) - 1, logs, key)
    chain_tau = [c["gyro"]["tau_s"] for c in chains["smoothed_means"]]
    ratios = [m / c for m, c in zip(over_logs["gyro_tau_s_median"], chain_tau)]
    return {
        "steps": steps,
        "map_from_the_start": chains,
        "over_logs": over_logs,
        "median_over_map_gyro_tau": ratios,
        "agree": all(1 / 1.3 <= r <= 1.3 for r in ratios),
        "agreement_criterion": f"the median τ_ω over {logs} logs within a factor 1.3 of the "
        "map's at every iteration (the rule's nonlinearity alone: ~1.1-1.2)",
        "at_the_true_models": {
            "smoothed_means": _step(truth, truth, dt, n, max_lag, fft_size),
            "with_posterior": _step(truth, truth, dt, n, max_lag, fft_size, posterior=True),
            "rule_15_on_the_true_errors": rule_alone,
        },
        "assumptions": (
            f"steady-state (Wiener) smoother of each iteration's model, the log's ends "
            f"ignored; expected sample autocovariance over the {loop['log_hours']:g} h log "
            f"({n} samples at {dt:g} s), rule (15) over lags 1..{max_lag} while r_j > e⁻¹ "
            "applied to that expectation (not the mean of the rule over logs); NumPy "
            f"float64 on a grid of {fft_size or 'the default ≥ 2^20'} frequencies"
        ),
    }


def _joined(values, digits=3) -> str:
    return ", ".join(f"{v:.{digits}g}" for v in values)


def batch_bias_row(bias: dict, true_tau: float) -> dict:
    """The study's row: the map's τ_ω beside the loop's over logs and on the report's log,
    and the map at the true models."""
    steps, truth = bias["steps"], bias["at_the_true_models"]
    chain = bias["map_from_the_start"]
    over = bias["over_logs"]
    single = [s["identified"]["gyro"]["tau_s"] / s["predicted"]["gyro"]["tau_s"] for s in steps]
    return {
        "quantity": "the batch loop's τ_ω per iteration [s]: the map from the spectra / the "
        f"median over {over['logs']} logs",
        "ours": f"{_joined(c['gyro']['tau_s'] for c in chain['smoothed_means'])} / "
        f"{_joined(over['gyro_tau_s_median'])}",
        "paper": "—",
        "note": f"median / map {_joined(bias['median_over_map_gyro_tau'])}; the report's "
        f"own log identifies {_joined(s['identified']['gyro']['tau_s'] for s in steps)}, "
        f"{_joined(single, 2)} × the map's one step ahead from its own models (the same "
        "log every iteration, so its deviation persists). At the true models one step "
        f"gives τ_ω {truth['smoothed_means']['gyro']['tau_s']:.3g} s and σ_ω "
        f"{truth['smoothed_means']['gyro']['sigma']:.2g} (true {true_tau:g} s): the smoothed "
        "means are low-passed, so rule (15) over the first lags reads a slower decay. With "
        "the smoother's posterior autocovariance added (an EM step's correction) the true "
        f"models give {truth['with_posterior']['gyro']['tau_s']:.4g} s, as rule (15) does on "
        "the true errors of such a log "
        f"({truth['rule_15_on_the_true_errors']['gyro']['tau_s']:.4g} s: its own bias); "
        "from the start that corrected map reads "
        f"{_joined(c['gyro']['tau_s'] for c in chain['with_posterior'])}. Agreement: "
        f"{bias['agreement_criterion']}. {bias['assumptions']}",
        "status": "explained" if bias["agree"] else "differs",
    }
