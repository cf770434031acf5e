"""Pose knowledge errors of a simulated downlink: what its SPK and CK say minus the truth.

The images are rendered from the true poses; the downlink's kernels carry the poses perturbed
here. Pure functions on arrays, no I/O. Two modes:

- `IndependentErrors`: independent Gaussian errors per image, position per axis (m) and pointing
  per axis (rad), as `pwm simulate --knowledge-error POS_M,POINT_RAD` always drew them.
- `NavigationErrors`: errors as navigation delivers them, smooth in time. The observations are
  grouped into arcs (a new arc after a gap of more than `arc_gap_s` without images, default
  `ARC_GAP_S`: a longer silence stands for a new orbit-determination arc). Per arc, the position
  error along-track, cross-track and radial is each a constant + a linear drift + a
  once-per-orbit sinusoid of random coefficients, scaled so that its RMS over the arc's images is
  `along_m`, `cross_m` and `RADIAL_FRACTION * cross_m` (radial is the best-determined component
  of a small-body orbit). The orbit period is `orbit_period_s`; the scenarios fly no orbit
  (their images are views placed in time, not samples of a trajectory), so by default it is the
  arc's duration: one slow cycle per arc. Along-track is the direction of the spacecraft's
  velocity relative to the body, estimated from consecutive true positions (body-fixed; central
  differences, second-order one-sided ones at the arc's ends); an arc of one image takes the direction perpendicular
  to its position and the spin axis (body-fixed +z), the local direction of a body-fixed circle
  about the pole. Cross-track is perpendicular to the position and along-track (the orbit normal),
  radial completes the right-handed triad (along, cross, radial).
  The pointing error is one camera-to-bus misalignment, the same rotation vector for every image
  (norm `misalign_urad`, random direction), composed with a drift that grows linearly from zero
  at the downlink's first image to `drift_urad` (random direction) at its last.

Either error turns the camera as `Rot(e) @ rotation` (rotation: body-fixed -> instrument frame,
so e is a rotation vector in the instrument frame) and moves the camera centre by the position
error (km). In body-fixed axes the same error is b = rotation.T @ e: the downlink's rotation is
the true one @ Rot(b), and a `pwm.camera.PoseCorrection` that restores the truth is
(-position error, +b).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

ARC_GAP_S = 2 * 86400.0  # a gap in the images longer than this starts a new navigation arc
RADIAL_FRACTION = 0.5  # radial RMS as a fraction of the cross-track RMS
SPIN_AXIS = (0.0, 0.0, 1.0)  # the body's pole in its body-fixed frame


def _check(name: str, value: float) -> None:
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a finite non-negative number, not {value}")


@dataclass(frozen=True)
class IndependentErrors:
    """Independent Gaussian errors per image: 1 sigma per axis, position (m) and pointing (rad)."""

    position_m: float = 0.0
    pointing_rad: float = 0.0

    def __post_init__(self) -> None:
        _check("position_m", self.position_m)
        _check("pointing_rad", self.pointing_rad)


EXACT = IndependentErrors()
"""No knowledge error: the downlink's kernels carry the true poses."""


@dataclass(frozen=True)
class NavigationErrors:
    """Navigation-like errors (see the module's docstring): RMS per arc along-track and
    cross-track (m), the misalignment's norm and the drift over the downlink (microradians)."""

    along_m: float
    cross_m: float
    misalign_urad: float
    drift_urad: float
    orbit_period_s: float | None = None  # None: each arc's duration
    arc_gap_s: float = ARC_GAP_S

    def __post_init__(self) -> None:
        for name in ("along_m", "cross_m", "misalign_urad", "drift_urad"):
            _check(name, getattr(self, name))
        if self.orbit_period_s is not None and not (math.isfinite(self.orbit_period_s) and self.orbit_period_s > 0):
            raise ValueError(f"orbit_period_s must be positive, not {self.orbit_period_s}")
        if not self.arc_gap_s > 0:
            raise ValueError(f"arc_gap_s must be positive, not {self.arc_gap_s}")


KnowledgeErrors = IndependentErrors | NavigationErrors

USAGE = "expected POS_M,POINT_RAD (e.g. 1,1e-4) or nav:ALONG_M,CROSS_M,MISALIGN_URAD,DRIFT_URAD (e.g. nav:3,1,50,20)"


def parse_knowledge_errors(text: str) -> KnowledgeErrors:
    """`POS_M,POINT_RAD` or `nav:ALONG_M,CROSS_M,MISALIGN_URAD,DRIFT_URAD`; ValueError, with a
    message that says what is wrong, for anything else."""
    mode, sep, values = text.strip().rpartition(":")
    if sep and mode.strip().lower() != "nav":
        raise ValueError(f"unknown knowledge-error mode {mode.strip()!r}: {USAGE}")
    names = (("along_m", "cross_m", "misalign_urad", "drift_urad") if sep else ("position_m", "pointing_rad"))
    parts = [p.strip() for p in values.split(",")]
    if len(parts) != len(names):
        raise ValueError(f"{len(parts)} value(s) in {text!r}, {len(names)} wanted: {USAGE}")
    numbers = {}
    for name, part in zip(names, parts, strict=True):
        try:
            numbers[name] = float(part)
        except ValueError:
            raise ValueError(f"{name} {part!r} is not a number: {USAGE}") from None
        _check(name, numbers[name])
    return NavigationErrors(**numbers) if sep else IndependentErrors(**numbers)


@dataclass(frozen=True)
class Knowledge:
    """Perturbed poses and the errors drawn, per observation in the order given.

    positions_km, rotations: what the kernels carry. position_error_m: (n, 3) body-fixed;
    track_error_m: (n, 3) the same split along-track, cross-track, radial (`track_frames`).
    pointing_error_rad: (n, 3) rotation vectors in the instrument frame (rotations =
    Rot(e) @ true rotations); pointing_error_body_rad: the same in body-fixed axes.
    arcs: indices of each arc's observations in time order, with arc_periods_s their orbit
    periods (None for an arc of one image). misalignment_rad (3,), drift_rad (n, 3): the
    navigation mode's constant misalignment and its drift per observation, drift_end_rad the
    drift at the last one (all zero for the independent mode): each observation's pointing error
    is Rot(misalignment) @ Rot(drift).
    """

    positions_km: np.ndarray
    rotations: np.ndarray
    position_error_m: np.ndarray
    track_error_m: np.ndarray
    pointing_error_rad: np.ndarray
    pointing_error_body_rad: np.ndarray
    arcs: list[np.ndarray]
    arc_periods_s: list[float | None]
    misalignment_rad: np.ndarray
    drift_rad: np.ndarray
    drift_end_rad: np.ndarray


def arcs(times: np.ndarray, *, gap_s: float = ARC_GAP_S) -> list[np.ndarray]:
    """Indices of the observations in each arc, in time order: a new arc after a gap > gap_s."""
    times = np.asarray(times, float)
    order = np.argsort(times, kind="stable")
    if len(order) == 0:
        return []
    breaks = np.flatnonzero(np.diff(times[order]) > gap_s) + 1
    return [np.asarray(a) for a in np.split(order, breaks)]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _perpendicular(v: np.ndarray, hint: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to v, as close to hint as possible (any, if hint is parallel to v)."""
    u = v / np.linalg.norm(v)
    for h in (hint, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        w = h - (h @ u) * u
        if np.linalg.norm(w) > 1e-9 * max(float(np.linalg.norm(h)), 1.0):
            return w / np.linalg.norm(w)
    raise AssertionError("unreachable: x and y cannot both be parallel to v")


def track_frames(times: np.ndarray, positions_km: np.ndarray, *, gap_s: float = ARC_GAP_S,
                 spin_axis: tuple[float, float, float] = SPIN_AXIS) -> np.ndarray:
    """(n, 3, 3): per observation, rows along-track, cross-track and radial unit vectors
    (body-fixed), from the true positions of its arc (see the module's docstring)."""
    times, positions = np.asarray(times, float), np.asarray(positions_km, float)
    spin = np.asarray(spin_axis, float)
    frames = np.empty((len(times), 3, 3))
    for arc in arcs(times, gap_s=gap_s):
        t, p = times[arc], positions[arc]
        if len(arc) > 1:
            if (np.diff(t) <= 0).any():
                raise ValueError("two observations at the same time")
            velocity = np.gradient(p, t, axis=0, edge_order=2 if len(arc) > 2 else 1)
        else:
            velocity = np.cross(spin, p)
        for i, k in enumerate(arc):
            v = velocity[i]
            if np.linalg.norm(v) < 1e-12 * max(float(np.linalg.norm(p[i])), 1.0):  # at rest, or over the pole
                v = _perpendicular(p[i], np.cross(spin, p[i]))
            along = v / np.linalg.norm(v)
            radial = _perpendicular(along, p[i])
            frames[k] = np.stack([along, np.cross(radial, along), radial])
    return frames


def perturb(errors: KnowledgeErrors, *, times: np.ndarray, positions_km: np.ndarray, rotations: np.ndarray,
            rng: np.random.Generator) -> Knowledge:
    """The observations' poses as the downlink's kernels carry them, and the errors drawn.

    times: (n,) s (ET); positions_km: (n, 3) true camera centres, body-fixed km; rotations:
    (n, 3, 3) true body-fixed -> instrument-frame rotations. The independent mode draws, per
    observation in the order given, 3 position then 3 pointing normals: what the campaign always
    drew. The navigation mode draws, per arc in time order, 3 x 4 normals (along, cross, radial
    x constant, linear, cosine, sine), then the misalignment's and the drift's directions.
    """
    times = np.asarray(times, float)
    positions = np.asarray(positions_km, float)
    rotations = np.asarray(rotations, float)
    n = len(times)
    gap_s = errors.arc_gap_s if isinstance(errors, NavigationErrors) else ARC_GAP_S
    frames = track_frames(times, positions, gap_s=gap_s) if n else np.empty((0, 3, 3))
    groups = arcs(times, gap_s=gap_s)
    misalignment, drift, drift_end = np.zeros(3), np.zeros((n, 3)), np.zeros(3)
    periods: list[float | None] = []
    if isinstance(errors, IndependentErrors):
        dpos_km = np.empty((n, 3))
        pointing = np.empty((n, 3))
        noisy_pos = np.empty((n, 3))
        noisy_rot = np.empty((n, 3, 3))
        for k in range(n):
            dpos_km[k] = rng.normal(0.0, errors.position_m * 1e-3, 3)
            pointing[k] = rng.normal(0.0, errors.pointing_rad, 3)
            noisy_pos[k] = positions[k] + dpos_km[k]
            noisy_rot[k] = Rotation.from_rotvec(pointing[k]).as_matrix() @ rotations[k]
        position_error_m = dpos_km * 1e3
        for arc in groups:
            periods.append(_period(errors=None, times=times[arc]))
    else:
        position_error_m = np.zeros((n, 3))
        targets = np.array([errors.along_m, errors.cross_m, RADIAL_FRACTION * errors.cross_m])
        for arc in groups:
            t = times[arc]
            period = _period(errors=errors, times=t)
            periods.append(period)
            coefficients = rng.normal(size=(3, 4))
            track = np.stack([_smooth(c, t, period) for c in coefficients], axis=1)  # (len(arc), 3)
            rms = np.sqrt((track**2).mean(axis=0))
            track = track * np.divide(targets, rms, out=np.zeros(3), where=rms > 0)
            position_error_m[arc] = np.einsum("ki,kij->kj", track, frames[arc])
        misalignment = _unit(rng.normal(size=3)) * errors.misalign_urad * 1e-6
        drift_end = _unit(rng.normal(size=3)) * errors.drift_urad * 1e-6
        span = float(times.max() - times.min()) if n else 0.0
        drift = ((times - times.min()) / span if span > 0 else np.zeros(n))[:, None] * drift_end
        pointing, turns = np.zeros((n, 3)), np.zeros((n, 3, 3))
        for k in range(n):
            turn = Rotation.from_rotvec(misalignment) * Rotation.from_rotvec(drift[k])
            pointing[k], turns[k] = turn.as_rotvec(), turn.as_matrix()
        noisy_pos = positions + position_error_m * 1e-3
        noisy_rot = turns @ rotations
    return Knowledge(
        positions_km=noisy_pos, rotations=noisy_rot, position_error_m=position_error_m,
        track_error_m=np.einsum("kij,kj->ki", frames, position_error_m),
        pointing_error_rad=pointing, pointing_error_body_rad=np.einsum("kji,kj->ki", rotations, pointing),
        arcs=groups, arc_periods_s=periods, misalignment_rad=misalignment, drift_rad=drift, drift_end_rad=drift_end,
    )


def _period(*, errors: NavigationErrors | None, times: np.ndarray) -> float | None:
    if errors is not None and errors.orbit_period_s is not None:
        return errors.orbit_period_s
    duration = float(times[-1] - times[0])
    return duration if duration > 0 else None


def _smooth(c: np.ndarray, t: np.ndarray, period: float | None) -> np.ndarray:
    """c[0] + c[1] * (linear, -1 .. 1 over the arc) + c[2] cos + c[3] sin (once per period)."""
    duration = float(t[-1] - t[0])
    tau = (2 * (t - t[0]) / duration - 1) if duration > 0 else np.zeros_like(t)
    phase = 2 * np.pi * (t - t[0]) / period if period else np.zeros_like(t)
    return c[0] + c[1] * tau + c[2] * np.cos(phase) + c[3] * np.sin(phase)


def manifest_entries(errors: KnowledgeErrors, knowledge: Knowledge, names: list[str]) -> tuple[dict, list[dict]]:
    """What the truth manifest records: the mode with its parameters (and, for the navigation
    mode, the arcs, the misalignment and the drift at the last image), and per observation the
    errors drawn (position m, pointing microradians)."""
    summary: dict[str, Any]
    if isinstance(errors, IndependentErrors):
        summary = {"mode": "independent", "position_m": errors.position_m, "pointing_rad": errors.pointing_rad}
    else:
        summary = {
            "mode": "navigation", "along_m": errors.along_m, "cross_m": errors.cross_m,
            "radial_m": RADIAL_FRACTION * errors.cross_m, "misalign_urad": errors.misalign_urad,
            "drift_urad": errors.drift_urad, "orbit_period_s": errors.orbit_period_s, "arc_gap_s": errors.arc_gap_s,
            "misalignment_urad": (knowledge.misalignment_rad * 1e6).tolist(),
            "drift_at_end_urad": (knowledge.drift_end_rad * 1e6).tolist(),
            "arcs": [{"images": [names[k] for k in arc], "orbit_period_s": period}
                     for arc, period in zip(knowledge.arcs, knowledge.arc_periods_s, strict=True)],
        }
    per_image = [{
        "position_m": knowledge.position_error_m[k].tolist(),
        "along_m": float(knowledge.track_error_m[k, 0]), "cross_m": float(knowledge.track_error_m[k, 1]),
        "radial_m": float(knowledge.track_error_m[k, 2]),
        "pointing_urad": (knowledge.pointing_error_rad[k] * 1e6).tolist(),
        "pointing_body_urad": (knowledge.pointing_error_body_rad[k] * 1e6).tolist(),
        "pointing_norm_urad": float(np.linalg.norm(knowledge.pointing_error_rad[k]) * 1e6),
    } for k in range(len(names))]
    return summary, per_image

