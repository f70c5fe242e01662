"""Trajectory features of a swimming fish, measured identically on real markers and simulated bodies.

Input, real or simulated: the two head markers (marker 0 at the front, marker 1 behind it, 0.142 m
apart on the rigid head) over time, the beat clock (tail-beat frequency f, phase 2 pi f t, t = 0
at the clip start, the same phase origin the prescribed gait is fitted in), and the tail tip's
lateral position in the head frame (the phase reference "the tail").

Signals (data.line_speed's axis): the head point (mean of markers 0 and 1) projected
on the principal axis of its path, oriented along the mean heading (s, forward), and on the normal
to it (l, lateral); the head's heading angle (marker 1 -> marker 0, unwrapped; yaw). A slow
polynomial trend (degree TREND_DEGREE, fitted jointly with the harmonics over the whole clip) is
removed from each: the real robot turns and crabs, the symmetric model only drifts slowly.

Per complete beat (t in [b/f, (b+1)/f)) a least-squares constant, slope (what is left of the trend
within the beat) and harmonics 1..3 of the beat clock gives complex amplitudes; the tail tip's first
harmonic of the same beat sets the phase reference, so a phase is "relative to the tail" (harmonic k is
referred to the tail phase times k).
Features of a clip (FEATURES): the mean over its beats; their spread over the beats is the noise.

  speed        cruising speed [m/s]: slope of the straight-line fit of the head position along the
               path axis over the whole clip (the headline, data.measured_speed); per beat: the
               linear term of a line-plus-harmonics fit of s over that beat
  yaw_amp      amplitude of the heading angle at the beat frequency [rad]
  yaw_phase    its phase relative to the tail tip's lateral motion [rad]
  sway_amp     amplitude of the head point's lateral motion at the beat frequency [m]
  sway_phase   its phase relative to the tail [rad]
  surge2_amp   amplitude of the forward speed at twice the beat frequency [m/s] (speed profile
               within the beat: the head surges twice per beat, once per tail stroke)
  surge2_phase its phase relative to the tail's second power [rad]
  surge1_amp   amplitude of the forward speed at the beat frequency [m/s] (left-right asymmetry of
               the stroke)
  surge1_phase its phase [rad]

The model is left-right symmetric, so turn rate and crab angle are not features (the trend removal
drops them). Known bias: on a turning path the fixed path axis mixes the sway, modulated by the
slow turn, into the forward signal within a beat; the 2f surge amplitude reads ~1.7 % low per
0.01 rad/s of turn (tests/test_swimmer_features.py), small against its beat-to-beat noise (~40 %).
"""
from __future__ import annotations

import numpy as np

from wrenorm.tasks.swimmer import data

TREND_DEGREE = 2
HARMONICS = 3
FEATURES = ("speed", "yaw_amp", "yaw_phase", "sway_amp", "sway_phase", "surge2_amp", "surge2_phase",
            "surge1_amp", "surge1_phase")
UNITS = {"speed": "m/s", "yaw_amp": "rad", "yaw_phase": "rad", "sway_amp": "m", "sway_phase": "rad",
         "surge2_amp": "m/s", "surge2_phase": "rad", "surge1_amp": "m/s", "surge1_phase": "rad"}
PHASES = tuple(f for f in FEATURES if f.endswith("_phase"))
# need the head's heading and lateral motion in the world: a head-frame clip (rotatedMarkers, data.Rate.frame
# "head") holds the heading constant by construction, so its yaw is zero and its "sway" is not the head's
WORLD_FRAME = ("yaw_amp", "yaw_phase", "sway_amp", "sway_phase")


def unmeasurable(rates) -> tuple[str, ...]:
    """The FEATURES these clips cannot measure: WORLD_FRAME where any clip is in the head frame."""
    return WORLD_FRAME if any(getattr(r, "frame", "world") == "head" for r in rates) else ()


def head_signals(m0: np.ndarray, m1: np.ndarray):
    """(..., N, 2) head markers -> s, l, yaw (..., N): forward and lateral head-point position along
    and across the principal axis of its path (oriented by the heading), and the heading angle."""
    head = 0.5 * (m0 + m1)
    ax = m0 - m1
    p = head - head.mean(axis=-2, keepdims=True)
    cxx = (p[..., 0] * p[..., 0]).sum(-1)
    cyy = (p[..., 1] * p[..., 1]).sum(-1)
    cxy = (p[..., 0] * p[..., 1]).sum(-1)
    ang = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
    d = np.stack([np.cos(ang), np.sin(ang)], -1)
    flip = (d * ax.sum(-2)).sum(-1) < 0
    d = np.where(flip[..., None], -d, d)
    s = (p * d[..., None, :]).sum(-1)
    l = -p[..., 0] * d[..., None, 1] + p[..., 1] * d[..., None, 0]
    yaw = np.unwrap(np.arctan2(ax[..., 1], ax[..., 0]), axis=-1)
    return s, l, yaw


def _harmonic_columns(t: np.ndarray, freq: float, k_max: int = HARMONICS) -> list:
    w = 2 * np.pi * freq
    return [f(k * w * t) for k in range(1, k_max + 1) for f in (np.cos, np.sin)]


_PINV: dict = {}


def _cached(key, build):
    """Designs depend only on the sample times and the frequency: the fit evaluates the same few
    thousands of times, so their pseudo-inverses are kept (bounded)."""
    got = _PINV.get(key)
    if got is None:
        if len(_PINV) > 512:
            _PINV.clear()
        got = _PINV[key] = build()
    return got


def _times_key(t: np.ndarray) -> tuple:
    return (len(t), float(t[0]), float(t[-1]), float(np.sum(t)))


def detrend(t: np.ndarray, y: np.ndarray, freq: float, degree: int = TREND_DEGREE) -> np.ndarray:
    """y (..., N) minus its slow polynomial trend, fitted jointly with harmonics 1..3 of the beat."""
    def build():
        tc = (t - t.mean()) / max(t.max() - t.min(), 1e-12)
        design = np.stack([tc ** d for d in range(degree + 1)] + _harmonic_columns(t, freq), 1)
        return np.linalg.pinv(design)[:degree + 1].T, design[:, :degree + 1].T

    pinv, trend = _cached(("trend", _times_key(t), float(freq), degree), build)
    return y - (y @ pinv) @ trend


def _beat_harmonics(t: np.ndarray, y: np.ndarray, freq: float, with_slope: bool = False):
    """Complex amplitudes c_k (..., K) of y = Re(c_k exp(i k w t)) + const (+ slope t) over one beat."""
    def build():
        cols = [np.ones_like(t)] + ([t - t.mean()] if with_slope else []) + _harmonic_columns(t, freq)
        return np.linalg.pinv(np.stack(cols, 1)).T

    coef = y @ _cached(("beat", _times_key(t), float(freq), with_slope), build)     # (..., columns)
    o = 2 if with_slope else 1
    c = coef[..., o::2] - 1j * coef[..., o + 1::2]                    # (..., K)
    return c, (coef[..., 1] if with_slope else None)


def beat_features(t: np.ndarray, m0: np.ndarray, m1: np.ndarray, tip_y: np.ndarray, freq: float) -> dict:
    """Per-beat complex features of one clip; markers (..., N, 2) (leading batch dims allowed), t (N,)
    from 0 on the beat clock, tip_y (N,) the tail tip's lateral head-frame position.

    Returns {"speed": (..., beats) per-beat speed, "yaw", "sway", "surge1", "surge2": (..., beats)
    complex amplitudes referred to the tail phase, "yaw_h", "sway_h", "surge_h": (..., beats, 3)
    harmonics 1..3 of yaw, sway and forward speed, harmonic k referred to the tail phase times k}."""
    w = 2 * np.pi * freq
    s, l, yaw = head_signals(m0, m1)
    s_d, l_d, y_d = (detrend(t, q, freq) for q in (s, l, yaw))
    out = {k: [] for k in ("speed", "yaw", "sway", "surge1", "surge2", "yaw_h", "sway_h", "surge_h")}
    k_pow = np.arange(1, HARMONICS + 1)
    for idx in data.beat_windows(t, freq):
        tt = t[idx]
        tip, _ = _beat_harmonics(tt, tip_y[idx], freq)
        rot = tip[0] / abs(tip[0])                              # the tail's phase this beat
        cs, speed = _beat_harmonics(tt, s[..., idx], freq, with_slope=True)
        cd, _ = _beat_harmonics(tt, s_d[..., idx], freq, with_slope=True)
        cl, _ = _beat_harmonics(tt, l_d[..., idx], freq, with_slope=True)
        cy, _ = _beat_harmonics(tt, y_d[..., idx], freq, with_slope=True)
        out["speed"].append(speed)
        out["yaw"].append(cy[..., 0] / rot)
        out["sway"].append(cl[..., 0] / rot)
        out["surge1"].append(1j * w * cd[..., 0] / rot)          # velocity = d/dt of position
        out["surge2"].append(2j * w * cd[..., 1] / rot ** 2)
        ref = rot ** k_pow                                        # harmonic k referred to the tail's phase k times
        out["yaw_h"].append(cy / ref)
        out["sway_h"].append(cl / ref)
        out["surge_h"].append(1j * w * k_pow * cd / ref)
    return {k: np.stack(v, -2 if k.endswith("_h") else -1) for k, v in out.items()}


def waveforms(beats: dict, samples: int = 64) -> dict:
    """Mean waveform over the beats, harmonics 1..3, against the beat phase relative to the tail
    (0: the tail tip's first harmonic at its maximum): {"phase": (samples,), "yaw" [rad], "sway" [m],
    "surge" [m/s, forward speed minus its mean]: (..., samples)}."""
    phase = np.arange(samples) / samples
    e = np.exp(2j * np.pi * np.arange(1, HARMONICS + 1)[:, None] * phase[None, :])  # (K, samples)
    out = {"phase": phase}
    for k in ("yaw", "sway", "surge"):
        c = beats[f"{k}_h"].mean(-2)                               # (..., K)
        out[k] = np.real(c @ e)
    return out


def clip_features(beats: dict, line_speed) -> dict:
    """Beat means -> the FEATURES of a clip (arrays with the batch shape)."""
    out = {"speed": np.asarray(line_speed, np.float64)}
    for k in ("yaw", "sway", "surge2", "surge1"):
        m = beats[k].mean(-1)
        out[f"{k}_amp"] = np.abs(m)
        out[f"{k}_phase"] = np.angle(m)
    return out


def beat_spread(beats: dict) -> dict:
    """Per-feature spread over the beats of one clip (sample std, ddof=1) and the beat count:
    amplitudes' std of |c_b|, phases' std of angle(c_b / mean c)."""
    n = beats["speed"].shape[-1]
    out = {"beats": n, "speed": float(np.std(beats["speed"], ddof=1)) if n > 1 else np.nan}
    for k in ("yaw", "sway", "surge2", "surge1"):
        c = beats[k]
        m = c.mean(-1, keepdims=True)
        out[f"{k}_amp"] = float(np.std(np.abs(c), ddof=1)) if n > 1 else np.nan
        with np.errstate(invalid="ignore", divide="ignore"):   # a feature that is exactly zero has no phase
            out[f"{k}_phase"] = float(np.std(np.angle(c / m), ddof=1)) if n > 1 else np.nan
    return out


def tip_lateral(rate) -> np.ndarray:
    """The tail-tip marker's lateral position in the head frame, per frame (real clips)."""
    return rate.meta["local"][:, rate.meta["tail_markers"][-1], 1]


def real_features(rate) -> tuple[dict, dict, dict]:
    """(features, spread over beats, per-beat values) of a real clip."""
    t = np.arange(len(rate.markers)) / rate.fps
    beats = beat_features(t, rate.markers[:, 0], rate.markers[:, 1], tip_lateral(rate), rate.tail_freq)
    feats = clip_features(beats, data.measured_speed(rate.markers, rate.fps))
    return {k: float(v) for k, v in feats.items()}, beat_spread(beats), beats


def feature_difference(sim: np.ndarray, real: np.ndarray, name: str) -> np.ndarray:
    """sim - real, phases wrapped into (-pi, pi]."""
    d = np.asarray(sim, np.float64) - real
    if name in PHASES:
        d = np.angle(np.exp(1j * d))
    return d
