"""Truth simulator for a blind validation of accelerometer signal-chain diagnosis.

It simulates static records (no input motion) of an accelerometer's output noise as it
reaches a data logger. The sensor's own noise is white; the chain shapes it with a
low-pass (digital Butterworth, Bessel, a moving average, or a CIC-like cascade of boxcar
averages followed by decimation) and then adds its own white noise (ADC, amplifier)
after the filter. Two further classes carry no chain filter: "nyquist_hump" (white noise
plus a high-passed noise that rises towards Nyquist) and "white" (the false-alarm class).
Conventions are randomised per record: sample rate, length, unit (g, m/s2 or volts
through a gain), static level and quantisation.

    draw(seed, kind)    -> {"x": record, "dt": seconds, "truth": JSON-serialisable facts}
    density(truth, f)   -> the record's exact two-sided noise density (unit**2 / Hz)

This file was written from the physics alone, without reading the diagnosing library,
its tests, its studies or its docs. It uses only numpy and scipy.
"""
import sys

import numpy as np
from scipy import signal

KINDS = ("butterworth", "bessel", "moving_average", "decimated", "nyquist_hump", "white")
RATES_HZ = (50, 100, 200, 400, 1000)
G0 = 9.80665  # m/s2 per g
CHAINED = ("butterworth", "bessel", "moving_average", "decimated")
FILTER_NAME = {"butterworth": "butterworth", "bessel": "bessel",
               "moving_average": "moving_average", "decimated": "cic",
               "nyquist_hump": "highpass_hump", "white": "none"}


def _loguniform(rng, lo, hi):
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _chain(t):
    """The record's filter as (tag, coefficients) and its simulation rate, from the facts."""
    fs = float(t["sample_rate_Hz"] * t["decimation"])
    name, order, R = t["filter"], t["order"], t["decimation"]
    if name == "butterworth":
        return ("sos", signal.butter(order, t["corner_Hz"], output="sos", fs=fs)), fs
    if name == "bessel":
        sos = signal.bessel(order, t["corner_Hz"], norm="phase", output="sos", fs=fs)
        return ("sos", sos), fs
    if name == "highpass_hump":
        sos = signal.butter(2, t["hump_corner_Hz"], btype="highpass", output="sos", fs=fs)
        return ("sos", sos), fs
    b = np.ones(1)
    if name == "moving_average":
        b = np.ones(order) / order
    elif name == "cic":
        for _ in range(order):
            b = np.convolve(b, np.ones(R) / R)
    return ("fir", b), fs


def _gain2(filt, f_Hz, fs):
    """|H(f)|**2 of the filter at frequencies f_Hz (any sign, any value) for rate fs."""
    tag, c = filt
    f = np.atleast_1d(np.abs(np.asarray(f_Hz, dtype=float)))
    if tag == "sos":
        _, h = signal.freqz_sos(c, worN=f, fs=fs)
    else:
        _, h = signal.freqz(c, 1.0, worN=f, fs=fs)
    return np.abs(h) ** 2


def _apply(filt, x):
    tag, c = filt
    return signal.sosfilt(c, x) if tag == "sos" else signal.lfilter(c, 1.0, x)


def _warmup(filt):
    """Samples to discard: 20 longest time constants (IIR) or the FIR length, >= 2000."""
    tag, c = filt
    if tag == "fir":
        return max(2000, len(c))
    r = float(np.max(np.abs(signal.sos2zpk(c)[1])))
    tau = -1.0 / np.log(r) if 0.0 < r < 1.0 else 0.0
    return max(2000, int(np.ceil(20.0 * tau)))


def _f3db(filt, fs):
    """First frequency (Hz) where |H|**2 falls to half its DC value (linear interpolation)."""
    f = np.linspace(0.0, fs / 2.0, 200001)
    g = _gain2(filt, f, fs)
    g = g / g[0]
    below = np.nonzero(g <= 0.5)[0]
    if below.size == 0:
        return fs / 2.0
    i = int(below[0])
    if i == 0:
        return 0.0
    return float(f[i - 1] + (g[i - 1] - 0.5) / (g[i - 1] - g[i]) * (f[i] - f[i - 1]))


def draw(seed: int, kind: str) -> dict:
    """One static record of the given kind, everything drawn from default_rng(seed)."""
    return _draw(seed, kind, quantise=True)


def _draw(seed, kind, quantise):
    if kind not in KINDS:
        raise ValueError(f"unknown kind {kind!r}; expected one of {KINDS}")
    rng = np.random.default_rng(seed)
    # Conventions (all drawn in the same order for every kind).
    fs = float(rng.choice(RATES_HZ))
    n = int(round(_loguniform(rng, 20000, 60000)))
    s_g = _loguniform(rng, 1e-4, 1e-2)  # sensor white sigma per logged sample, in g
    unit = str(rng.choice(["g", "m/s2", "V"]))
    gain = _loguniform(rng, 0.5, 5.0)  # V/g, used only when unit == "V"
    upg = {"g": 1.0, "m/s2": G0, "V": gain}[unit]
    level = float(rng.uniform(-1.2, 1.2) * upg)
    quantised = bool(rng.random() < 0.5) and quantise
    lsb_frac = _loguniform(rng, 0.02, 0.25)
    after_ratio = _loguniform(rng, 0.05, 0.5)
    s = s_g * upg
    t = {"kind": kind, "seed": int(seed), "sample_rate_Hz": fs, "dt": 1.0 / fs, "n": n,
         "unit": unit, "unit_per_g": float(upg), "level": level, "lsb": 0.0,
         "sensor_white_sigma": float(s),
         "after_white_sigma": float(after_ratio * s) if kind in CHAINED else 0.0,
         "filter": FILTER_NAME[kind], "order": 0, "corner_Hz": 0.0, "decimation": 1,
         "hump_sigma": 0.0, "hump_corner_Hz": 0.0}
    # Kind-specific filter parameters.
    if kind == "butterworth":
        t["order"] = int(rng.integers(1, 5))
        t["corner_Hz"] = _loguniform(rng, 0.2, 0.7) * fs / 2.0
    elif kind == "bessel":
        t["order"] = int(rng.integers(2, 5))
        t["corner_Hz"] = _loguniform(rng, 0.2, 0.6) * fs / 2.0
    elif kind == "moving_average":
        t["order"] = int(rng.integers(2, 9))
    elif kind == "decimated":
        t["decimation"] = int(rng.choice([2, 4, 8]))
        t["order"] = int(rng.integers(1, 4))
    elif kind == "nyquist_hump":
        t["order"] = 2
        t["hump_corner_Hz"] = _loguniform(rng, 0.2, 0.5) * fs / 2.0
        t["corner_Hz"] = t["hump_corner_Hz"]
        t["hump_sigma"] = _loguniform(rng, 2.0, 6.0) * s
    filt, fs_sim = _chain(t)
    if kind in ("moving_average", "decimated"):
        t["corner_Hz"] = _f3db(filt, fs_sim)
    # -3 dB of the filter as designed/logged (differs from corner_Hz for Bessel, norm=phase).
    t["f3dB_Hz"] = _f3db(filt, fs_sim) if kind in CHAINED else 0.0
    # Noise, in record units.
    warm = _warmup(filt)
    if kind == "white":
        noise = s * rng.standard_normal(n)
    elif kind == "nyquist_hump":
        m = n + warm
        white = s * rng.standard_normal(m)
        hump = _apply(filt, t["hump_sigma"] * rng.standard_normal(m))
        noise = (white + hump)[warm:]
    else:
        R = t["decimation"]
        z = _apply(filt, s * np.sqrt(R) * rng.standard_normal((n + warm) * R))
        noise = z[warm * R::R][:n] + t["after_white_sigma"] * rng.standard_normal(n)
    t["total_sigma"] = float(np.std(noise))
    # Logged density at Nyquist over DC: 1 means no spectral signature (e.g. cic with K=1,
    # whose non-overlapping block averages are white).
    d0, dn = density(t, np.array([0.0, fs / 2.0]))
    t["nyquist_to_dc"] = float(dn / d0)
    x = level + noise
    if quantised:
        t["lsb"] = float(lsb_frac * t["total_sigma"])
        x = t["lsb"] * np.round(x / t["lsb"])
    return {"x": np.asarray(x, dtype=np.float64), "dt": 1.0 / fs, "truth": t}


def density(truth: dict, f_Hz: np.ndarray) -> np.ndarray:
    """True two-sided noise PSD of the record (record units**2 / Hz), |f| <= Nyquist.

    Exact filter responses; for "decimated" the oversampled filtered density is folded
    into the logged band (sum of the R images f + k*fs). Quantisation is not included.
    """
    f = np.asarray(f_Hz, dtype=float)
    fs, dt, R = truth["sample_rate_Hz"], truth["dt"], truth["decimation"]
    s2, a2 = truth["sensor_white_sigma"] ** 2, truth["after_white_sigma"] ** 2
    filt, fs_sim = _chain(truth)
    if truth["filter"] == "highpass_hump":
        out = dt * (s2 + truth["hump_sigma"] ** 2 * _gain2(filt, f, fs_sim))
    else:
        g2 = sum(_gain2(filt, f + k * fs, fs_sim) for k in range(R))
        out = dt * (s2 * g2 + a2)
    return out.reshape(f.shape)


def check(seed=0, nperseg=1024, nbands=8):
    """Welch vs density on unquantised records: per kind, the band median ratio furthest
    from 1 (positive frequencies split into nbands equal bands, DC bin excluded)."""
    worst = {}
    for kind in KINDS:
        rec = _draw(seed, kind, quantise=False)
        t = rec["truth"]
        f, p = signal.welch(rec["x"], fs=t["sample_rate_Hz"], nperseg=nperseg,
                            return_onesided=False)
        keep = f > 0
        ratio = p[keep] / density(t, f[keep])
        meds = [float(np.median(b)) for b in np.array_split(ratio, nbands)]
        worst[kind] = max(meds, key=lambda m: abs(np.log(m)))
        print(f"{kind:15s} worst band median Welch/density = {worst[kind]:.3f}  "
              f"(bands {min(meds):.3f}..{max(meds):.3f})")
    return worst


if __name__ == "__main__":
    for k in KINDS:
        print(draw(1, k)["truth"])
    if "--check" in sys.argv:
        check()
