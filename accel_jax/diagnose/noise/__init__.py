"""The `noise` kind: a static record, its nominal model (white noise) and its effects.

**Nominal model** (what a white-noise assumption means, docs/models.md §4): the indicated
acceleration of a static sensor is an unknown constant level plus white noise,

    a_out(t_k) = ℓ + σ_w w_k                                                          [g].

The level has a diffuse prior in every model (the record's mean is not known in advance),
so that all candidates are compared on the same terms, by the exact Gaussian likelihood of
the record conditional on its first sample, log p(x_2..x_N | x_1), as
`accel_jax._noise.log_likelihood` defines it.

**Effects** (each adds one process of `accel_jax._noise` to the white noise and is exactly
the nominal model when its amplitude is zero):

- `gauss_markov`: + first-order Gauss–Markov noise, R(τ) = σ² e^{−|τ|/τ_c};
- `exp_cosine`: + exponential-cosine noise, R(τ) = σ² e^{−α|τ|} cos βτ (the paper's
  "structured residual" model, Chernodarov et al. (16));
- `random_walk`: the level itself walks, ℓ_{k+1} = ℓ_k + √(qΔ) w_k (at q = 0 it is the
  nominal constant level, exactly).

An exponential-cosine noise at β = 0 is a Gauss–Markov noise, and a Gauss–Markov noise whose
τ_c outgrows the record looks like a random walk; those nested pairs are told apart by a
likelihood-ratio test when the evidence alone ties (`rank_candidates(nested=...)`).

**Fit** (`fit`): exact maximum likelihood on the training part (the first
`1 − HELD_OUT_FRACTION` of the record): a Whittle (frequency-domain) fit of the differenced
record gives the start, then BFGS (optimistix) on the exact likelihood polishes it. The
likelihood is the Kalman filter of the state-space forms of `accel_jax._noise` (state:
level, the two components of the exponential-cosine rotation — a Gauss–Markov noise is its
β = 0 case), written out for this three-state model with a scalar observation so that a
batch of records × candidates runs as one fused loop (the generic
`accel_jax._kalman.kalman_filter` gives the same numbers — the tests check it against
`accel_jax._noise.log_likelihood` — about ten times slower). Parameters are scaled so that
zero is reachable: the effect's standard deviation is z·s₀ (s₀ the record's RMS), the
random walk's increment RMS z·s₀.

**Held out**: the last `HELD_OUT_FRACTION` of the record. The filter with the training fit
runs over the whole record, and the one-step prediction errors (innovations) of the
held-out part are the held-out errors: the gap is the RMS innovation above the noise floor
(the innovation variance the best model leaves on the training part).

**Beyond the three noises** (`sensor`): the forward selection of the effects real sensors
show (output grid, lines, low-pass, flicker, start-up transient) where the exact verdict
leaves a record open, and alone on records over `EXACT_LIMIT` samples.

**Modules.** `entry` (`diagnose_noise`), `record` (a record read into a `NoiseRecord`, the
typed state of `state`), `effects`, `verdict` (the evidence, the open-world decision, the
refit), `localise` (where the white-noise residual departs from white), `sensor` (the
forward selection and the Allan deviation); the fit itself is `accel_jax.diagnose.noise.fit`.

Float64 throughout (log-likelihoods of thousands of samples compared to within a unit).
"""

from __future__ import annotations

from .effects import STARTS as STARTS
from .effects import AbstractNoiseEffect as AbstractNoiseEffect
from .effects import ExpCosineNoise as ExpCosineNoise
from .effects import GaussMarkovNoise as GaussMarkovNoise
from .effects import NoiseComponents as NoiseComponents
from .effects import RandomWalkNoise as RandomWalkNoise
from .entry import BATCH_CHUNK as BATCH_CHUNK
from .entry import EXACT_LIMIT as EXACT_LIMIT
from .entry import diagnose_noise as diagnose_noise
from .record import HELD_OUT_FRACTION as HELD_OUT_FRACTION
from .verdict import NESTED as NESTED
