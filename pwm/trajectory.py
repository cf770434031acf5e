"""How navigation knowledge errors vary over a downlink: arcs, track frames and the smooth basis.

Orbit determination delivers a trajectory per arc (a new arc after a gap in the observations
longer than `ARC_GAP_S`: a longer silence stands for a new orbit-determination solution), whose
errors are smooth over the arc: a constant, a linear drift and a once-per-orbit term, each
component along-track, cross-track and radial (`track_frames`). The simulator draws such errors
(pwm.simulate.knowledge) and the bundle adjustment models them (pwm.spg.pose_models) with the
same arcs, frames and basis.
"""

from __future__ import annotations

import numpy as np

ARC_GAP_S = 2 * 86400.0  # a gap in the images longer than this starts a new navigation arc
SPIN_AXIS = (0.0, 0.0, 1.0)  # the body's pole in its body-fixed frame
BASIS_TERMS = 4  # constant, linear, cosine and sine once per orbit
MIN_SPAN_KM = 0.2  # along-track from positions spanning at least this (see track_frames)


def arcs(times: np.ndarray, *, gap_s: float = ARC_GAP_S) -> list[np.ndarray]:
    """Indices of the observations in each arc, in time order: a new arc after a gap > gap_s."""
    times = np.asarray(times, float)
    order = np.argsort(times, kind="stable")
    if len(order) == 0:
        return []
    breaks = np.flatnonzero(np.diff(times[order]) > gap_s) + 1
    return [np.asarray(a) for a in np.split(order, breaks)]


def along_arcs(times: np.ndarray, sample_times: np.ndarray, values: np.ndarray, *,
               gap_s: float = ARC_GAP_S) -> np.ndarray:
    """`values` (n, k) known at `sample_times` (n,), interpolated linearly in time to `times`
    within the arcs the samples make (`arcs`): a time within gap_s of an arc's span takes that
    arc's values (its end values beyond its ends), any other time zeros; (len(times), k)."""
    times = np.asarray(times, float)
    sample_times = np.asarray(sample_times, float)
    values = np.asarray(values, float).reshape(len(sample_times), -1)
    out = np.zeros((len(times), values.shape[1]))
    for arc in arcs(sample_times, gap_s=gap_s):
        t = sample_times[arc]
        inside = (times >= t.min() - gap_s) & (times <= t.max() + gap_s)
        for k in range(values.shape[1]):
            out[inside, k] = np.interp(times[inside], t, values[arc, k])
    return out


def arc_period(times: np.ndarray, orbit_period_s: float | None = None) -> float | None:
    """The once-per-orbit period of an arc's basis: the stated orbit period, or else the arc's
    duration (one slow cycle per arc); None for an arc of no duration."""
    if orbit_period_s is not None:
        return orbit_period_s
    duration = float(times[-1] - times[0])
    return duration if duration > 0 else None


def smooth_basis(t: np.ndarray, period: float | None) -> np.ndarray:
    """(len(t), BASIS_TERMS): 1, linear (-1 .. 1 over the arc), cos and sin once per period, at
    the times t of one arc (in time order)."""
    duration = float(t[-1] - t[0])
    tau = (2 * (t - t[0]) / duration - 1) if duration > 0 else np.zeros_like(t)
    phase = 2 * np.pi * (t - t[0]) / period if period else np.zeros_like(t)
    return np.stack([np.ones_like(t), tau, np.cos(phase), np.sin(phase)], axis=1)


def _perpendicular(v: np.ndarray, hint: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to v, as close to hint as possible (any, if hint is parallel to v)."""
    u = v / np.linalg.norm(v)
    for h in (hint, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        w = h - (h @ u) * u
        if np.linalg.norm(w) > 1e-9 * max(float(np.linalg.norm(h)), 1.0):
            return w / np.linalg.norm(w)
    raise AssertionError("unreachable: x and y cannot both be parallel to v")


def track_frames(times: np.ndarray, positions_km: np.ndarray, *, gap_s: float = ARC_GAP_S,
                 spin_axis: tuple[float, float, float] = SPIN_AXIS, min_span_km: float = MIN_SPAN_KM) -> np.ndarray:
    """(n, 3, 3): per observation, rows along-track, cross-track and radial unit vectors
    (body-fixed), from the positions of its arc.

    Along-track is the direction of the spacecraft's motion relative to the body: a quadratic
    in time fitted to the observations about each (one side only at the arc's ends) spanning at
    least `min_span_km`. Over that span, positions metres off turn the direction by about a
    hundredth of a radian or less, so the frames of the kernels' positions are close to the true
    ones: what the simulator draws the errors in (pwm.simulate.knowledge), the adjustment
    models them in. An arc of one observation takes the direction perpendicular to its position
    and the spin axis, the local direction of a body-fixed circle about the pole. Cross-track is
    perpendicular to the position and along-track (the orbit normal); radial completes the
    right-handed triad (along, cross, radial).
    """
    times, positions = np.asarray(times, float), np.asarray(positions_km, float)
    spin = np.asarray(spin_axis, float)
    frames = np.empty((len(times), 3, 3))
    for arc in arcs(times, gap_s=gap_s):
        t, p = times[arc], positions[arc]
        if len(arc) > 1 and (np.diff(t) <= 0).any():
            raise ValueError("two observations at the same time")
        for i, k in enumerate(arc):
            v = _velocity(t, p, i, min_span_km) if len(arc) > 1 else np.cross(spin, p[i])
            if np.linalg.norm(v) < 1e-12 * max(float(np.linalg.norm(p[i])), 1.0):  # at rest, or over the pole
                v = _perpendicular(p[i], np.cross(spin, p[i]))
            along = v / np.linalg.norm(v)
            radial = _perpendicular(along, p[i])
            frames[k] = np.stack([along, np.cross(radial, along), radial])
    return frames


def _velocity(t: np.ndarray, p: np.ndarray, i: int, min_km: float) -> np.ndarray:
    """The motion at observation i of an arc: the derivative at t[i] of a quadratic in time
    fitted to the observations about i (a line through two), widened one observation at a time
    on both sides (while both have more) until they span min_km or the arc."""
    lo, hi = max(i - 1, 0), min(i + 1, len(p) - 1)
    while np.linalg.norm(p[hi] - p[lo]) < min_km and (lo > 0 or hi < len(p) - 1):
        lo, hi = max(lo - 1, 0), min(hi + 1, len(p) - 1)
    dt = t[lo:hi + 1] - t[i]
    scale = float(np.abs(dt).max())
    basis = np.vander(dt / scale, min(3, hi - lo + 1), increasing=True)
    coefficients, *_ = np.linalg.lstsq(basis, p[lo:hi + 1], rcond=None)
    return coefficients[1] / scale
