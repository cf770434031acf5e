"""Pose knowledge errors of a simulated downlink: what its SPK and CK say minus the truth.

The images are rendered from the true poses; the downlink's kernels carry the poses perturbed
here. Pure functions on arrays, no I/O. Two modes:

- `IndependentErrors`: independent Gaussian errors per image, position per axis (m) and pointing
  per axis (rad), as `pwm simulate --knowledge-error POS_M,POINT_RAD` always drew them.
- `NavigationErrors`: errors as navigation delivers them, smooth in time. The observations are
  grouped into arcs (`pwm.trajectory.arcs`, a new arc after a gap of more than `arc_gap_s`).
  Per arc, the position error along-track, cross-track and radial (`pwm.trajectory.track_frames`
  of the kernels' trajectory: navigation states its errors in its own solution's frames) is each
  a constant + a linear drift + a once-per-orbit sinusoid (`pwm.trajectory.smooth_basis`) of
  random coefficients, scaled so that its RMS over the arc's
  images is `along_m`, `cross_m` and its `radial_m` (radial is the best-determined
  component of a small-body orbit). The orbit period is `orbit_period_s`; the scenarios fly no
  orbit (their images are views placed in time, not samples of a trajectory), so by default it
  is the arc's duration: one slow cycle per arc.
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

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from pwm.knowledge import IndependentErrors, KnowledgeErrors, NavigationErrors
from pwm.trajectory import ARC_GAP_S, arc_period, arcs, smooth_basis, track_frames


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


FRAME_ROUNDS = 4  # fixed-point rounds for the kernels' track frames (see perturb)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


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
            periods.append(arc_period(times[arc]))
    else:
        track_m = np.zeros((n, 3))
        targets = np.array([errors.along_m, errors.cross_m, errors.radial_m])
        for arc in groups:
            t = times[arc]
            period = arc_period(t, errors.orbit_period_s)
            periods.append(period)
            coefficients = rng.normal(size=(3, 4))
            track = smooth_basis(t, period) @ coefficients.T  # (len(arc), 3)
            rms = np.sqrt((track**2).mean(axis=0))
            track = track * np.divide(targets, rms, out=np.zeros(3), where=rms > 0)
            track_m[arc] = track
        # navigation states its errors in the track frames of its own solution, the kernels'
        # trajectory: a few rounds from the true trajectory's frames find them
        position_error_m = np.einsum("ki,kij->kj", track_m, frames)
        for _ in range(FRAME_ROUNDS):
            frames = track_frames(times, positions + position_error_m * 1e-3, gap_s=gap_s)
            position_error_m = np.einsum("ki,kij->kj", track_m, frames)
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
            "radial_m": errors.radial_m, "misalign_urad": errors.misalign_urad,
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

