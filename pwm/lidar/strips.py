"""Strip adjustment: each track's rigid correction by robust point-to-plane ICP to a model, and
the model -> tracks -> model loop (the seed's, after Besl and McKay's ICP with Chen and Medioni's
point-to-plane distance).

Closest points: each shot's ray is cast on the model (Embree, pwm.raytrace) and the spot's
residual is its distance along the normal of the face hit (pwm.lidar.model.along_shots): the
point-to-plane distance on the very face the spot lies over, with no densified copy of the model
to sample it (a KD tree over surface samples errs by their spacing). Measured: 64 tracks of
100,000 shots registered to a 4,000-face model in about a second (bench/lidar_strips.py).

A correction rotates the track by R about `about_km`, the centroid of the track's spots, and
translates it by t: x -> R (x - about) + about + t, applied to the spots and to the instrument's
positions (and R to the shots' directions), so ranges keep their measured values. About the
centroid, because there the rotation and the translation are nearly uncorrelated in the normal
equations, so each sigma means what it says; an attitude error (a rotation about the spacecraft)
is the same R with the translation (R - I)(about - s) added (`Correction.translation_about`).

The normal equations of the linearised residuals (Huber weights on the residuals over their
range sigmas, scaled by their median absolute deviation; the data's weight scaled by the
residuals' variance) and a prior of the knowledge errors' size (LidarConfig.prior_rotation_rad,
prior_translation_km) are solved over the directions they constrain: a direction the shots
barely see (a profile's turn about itself) stays near zero with about the prior's sigma, and one
whose eigenvalue is below LidarConfig.condition of the largest (a profile sliding along a flat
surface, without a prior) keeps no correction and an infinite sigma. A track of fewer than
LidarConfig.min_shots shots that meet the model is not corrected at all (every sigma infinite).
Sigmas are the inverse of those normal equations, widened per parameter to the cluster-robust
(sandwich) covariance over runs of consecutive shots where that is wider (`_robust`:
LidarConfig.sigma_segments). Lengths in km, angles in radians, body-fixed frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from pwm.lidar.config import LIDAR, LidarConfig
from pwm.lidar.model import along_shots, model_from_spots, usable
from pwm.lidar.shots import Shots
from pwm.lidar.tracks import NO_TRACK, track_ids
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer

_MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class Correction:
    """A track's rigid correction x -> R (x - about_km) + about_km + translation_km, with R the
    rotation by the vector rotation_rad.

    sigma: 1 sigma of (rotation_rad, translation_km) (6,), inf along what the shots leave
    unconstrained; covariance (6, 6) of the constrained part. shots: the shots that met the model
    in the last linearisation; rms_km: their weighted residual RMS after the correction;
    extent_km: the RMS distance of the track's spots from about_km (a rotation's lever arm).
    """

    track: int
    rotation_rad: np.ndarray
    translation_km: np.ndarray
    about_km: np.ndarray
    sigma: np.ndarray
    covariance: np.ndarray
    shots: int
    rms_km: float
    extent_km: float

    @property
    def matrix(self) -> np.ndarray:
        return Rotation.from_rotvec(self.rotation_rad).as_matrix()

    @property
    def placement_km(self) -> float:
        """1 sigma of the track's place per axis: the RMS of its translation's three sigmas (inf
        where one is unconstrained)."""
        return float(np.sqrt(np.mean(self.sigma[3:] ** 2)))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points corrected."""
        return (points - self.about_km) @ self.matrix.T + self.about_km + self.translation_km

    def translation_about(self, centre_km: np.ndarray) -> np.ndarray:
        """The translation of this correction written as a rotation about centre_km."""
        return self.translation_km + (self.matrix - np.eye(3)) @ (centre_km - self.about_km)

    def change_km(self, other: Correction | None) -> float:
        """How far this correction moves the track from where `other` (None: no correction) puts
        it: the largest of the translations' difference and the rotations' times the extent."""
        other = identity(self.track, self.about_km) if other is None else other
        rotation = Rotation.from_rotvec(self.rotation_rad) * Rotation.from_rotvec(other.rotation_rad).inv()
        shift = self.translation_km - other.translation_about(self.about_km)
        return float(max(np.linalg.norm(shift), np.linalg.norm(rotation.as_rotvec()) * self.extent_km))


def identity(track: int, about_km: np.ndarray, extent_km: float = 0.0) -> Correction:
    """No correction (every sigma infinite: nothing measured it)."""
    return Correction(track, np.zeros(3), np.zeros(3), np.asarray(about_km, dtype=float), np.full(6, np.inf),
                      np.zeros((6, 6)), 0, float("nan"), extent_km)


def corrected(shots: Shots, correction: Correction) -> Shots:
    """The shots with the correction applied to their origins and directions (ranges kept)."""
    return replace(shots, origin_km=correction.apply(shots.origin_km), direction=shots.direction @ correction.matrix.T)


def _huber(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))


def _robust(inverse: np.ndarray, scores: np.ndarray, et: np.ndarray, prior: np.ndarray, *,
            segments: int) -> np.ndarray:
    """The covariance `inverse` of the normal equations, widened where the residuals say it is
    too narrow: the cluster-robust (sandwich) covariance inverse @ meat @ inverse, with each
    shot's score (design row times weighted residual) summed over `segments` runs of
    consecutive shots and the prior's information added, is taken per parameter where it is the
    larger (the matrix scaled accordingly). The formal one trusts each shot as independent, but
    a model's error, or what a footprint averages over, is shared by neighbouring shots and does
    not shrink with their number."""
    order = np.argsort(et, kind="stable")
    runs = np.array_split(order, min(segments, len(order)))
    sums = np.array([scores[run].sum(axis=0) for run in runs])
    robust = inverse @ (sums.T @ sums + np.diag(prior)) @ inverse
    formal_var = np.diag(inverse)
    # a parameter without variance (none measured it) has none in the sandwich either: kept as it is
    widen = np.sqrt(np.maximum(np.diag(robust) / np.where(formal_var > 0, formal_var, 1.0), 1.0))
    return inverse * np.outer(widen, widen)


def register_track(shots: Shots, tracer: RayTracer, *, track: int = 0, config: LidarConfig = LIDAR,
                   start: Correction | None = None) -> Correction:
    """The rigid correction that brings one track's valid spots onto the tracer's mesh (module
    docstring), starting from `start` (its `about_km` is kept) or none."""
    valid = usable(shots)
    spots = shots.spots_km()[valid]
    if start is not None:
        about = start.about_km
    else:
        about = spots.mean(axis=0) if len(spots) else np.zeros(3)
    extent = float(np.sqrt(np.mean(np.sum((spots - about) ** 2, axis=1)))) if len(spots) else 0.0
    current = start if start is not None else identity(track, about, extent)
    if valid.sum() < config.min_shots:
        return identity(track, about, extent)
    own = shots.take(valid)
    # rotation columns in km (times the extent) so that the eigenvalues compare like with like
    scale = np.r_[np.full(3, max(extent, 1e-12)), np.ones(3)]
    prior = 1.0 / (np.r_[np.full(3, config.prior_rotation_rad), np.full(3, config.prior_translation_km)] * scale) ** 2
    for _ in range(config.icp_iterations):
        moved = corrected(own, current)
        r, n = along_shots(moved, tracer, near_km=config.intercept_km)
        met = np.isfinite(r)
        if met.sum() < config.min_shots:
            return identity(track, about, extent)
        p, r, n, sig = moved.spots_km()[met], r[met], n[met], own.sigma_km[met]
        design = np.hstack([np.cross(p - current.about_km, n), n]) / scale
        normalised = r / sig
        spread = _MAD_TO_SIGMA * np.median(np.abs(normalised - np.median(normalised)))
        w = _huber(normalised / max(spread, 1.0), config.huber_k) / sig ** 2
        # the data's weights scaled by how well the residuals match them (the range sigmas may be
        # optimistic), the prior's as given; at convergence the residuals are the final ones
        dof = max(len(r) - 6, 1)
        variance = max(float(np.sum(w * r ** 2) / dof), 1e-300)
        normal = design.T @ (design * w[:, None]) / variance
        state = np.r_[current.rotation_rad, current.translation_km] * scale
        values, vectors = np.linalg.eigh(normal + np.diag(prior))
        constrained = values > config.condition * values[-1]
        basis = vectors[:, constrained]
        step = -basis @ ((basis.T @ (design.T @ (w * r) / variance + prior * state)) / values[constrained]) / scale
        increment = Rotation.from_rotvec(step[:3])
        rotation = increment * Rotation.from_rotvec(current.rotation_rad)
        translation = increment.apply(current.translation_km) + step[3:]
        after = r + design @ (step * scale)
        inverse = _robust((basis / values[constrained]) @ basis.T, design * (w * after / variance)[:, None],
                          own.et[met], prior, segments=config.sigma_segments) / np.outer(scale, scale)
        sigma = np.sqrt(np.diag(inverse))
        # a parameter that an unconstrained direction moves is not measured
        free = (np.abs(vectors[:, ~constrained]) > np.sqrt(config.condition)).any(axis=1)
        sigma = np.where(free, np.inf, sigma)
        current = Correction(track, rotation.as_rotvec(), translation, current.about_km, sigma, inverse,
                             int(met.sum()), float(np.sqrt(np.sum(w * after ** 2) / np.sum(w))), extent)
        if max(np.linalg.norm(step[3:]), np.linalg.norm(step[:3]) * extent) < config.icp_tolerance_km:
            break
    return current


@dataclass
class Adjustment:
    """The loop's outcome: the adjusted shots, each shot's track, each track's correction (of the
    shots as given), the model they were last registered to (rebuilt from the adjusted spots
    when the loop made its own), the largest change of a correction per round (km), and whether
    the last was below the tolerance (a kept model needs one round: ICP ran to convergence)."""

    shots: Shots
    track: np.ndarray
    corrections: dict[int, Correction]
    model: Mesh
    changes: list[float] = field(default_factory=list)
    converged: bool = False


def apply_corrections(shots: Shots, track: np.ndarray, corrections: dict[int, Correction]) -> Shots:
    """The shots with each track's correction applied (shots of other tracks as they are)."""
    origin, direction = shots.origin_km.copy(), shots.direction.copy()
    for t, c in corrections.items():
        mine = track == t
        origin[mine] = c.apply(shots.origin_km[mine])
        direction[mine] = shots.direction[mine] @ c.matrix.T
    return replace(shots, origin_km=origin, direction=direction)


def corrected_spots(shots: Shots, track: np.ndarray, corrections: dict[int, Correction]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The usable spots (N, 3; km) of the tracks a correction placed, corrected, and each spot's
    height sigma (N,; km): its range's and its track's placement (`Correction.placement_km`)
    together; infinite where the placement is unconstrained. Spots of tracks without a correction
    are left out: only a strip adjustment puts a track where the model is."""
    placement = {t: c.placement_km for t, c in corrections.items()}
    take = usable(shots) & np.isin(track, list(placement))
    spots = apply_corrections(shots, track, corrections).spots_km()[take]
    return spots, np.hypot(shots.sigma_km[take], np.array([placement[int(t)] for t in track[take]], float))


def datum_motion(shots: Shots, track: np.ndarray, corrections: dict[int, Correction]) -> Correction | None:
    """The one rigid motion (Kabsch, over every usable spot of a track) that brings the corrected
    spots back onto the spots as given: the block's net motion, undone (None with under three
    spots). A model the tracks make of themselves has no datum of its own: a turn or shift of
    every track at once fits it as well, and the loop's rounds of registering to the model and
    rebuilding it let the block wander (a milliradian in five rounds, on the campaign's survey).
    Undone, the model stays where the tracks as given put it on average: placed by the kernels'
    many independent errors rather than by none."""
    use = usable(shots) & (track != NO_TRACK)
    if use.sum() < 3:
        return None
    given = shots.spots_km()[use]
    moved = apply_corrections(shots, track, corrections).spots_km()[use]
    given_centre, moved_centre = given.mean(axis=0), moved.mean(axis=0)
    turn, _ = Rotation.align_vectors(given - given_centre, moved - moved_centre)
    return replace(identity(NO_TRACK, moved_centre), rotation_rad=turn.as_rotvec(),
                   translation_km=given_centre - moved_centre)


def then(first: Correction, second: Correction) -> Correction:
    """`first` followed by the rigid motion `second`, as a correction about first's own centre
    (its sigma kept: `second` is the block's, not the track's)."""
    turn = Rotation.from_rotvec(second.rotation_rad) * Rotation.from_rotvec(first.rotation_rad)
    moved_about = second.apply((first.about_km + first.translation_km)[None])[0]
    return replace(first, rotation_rad=turn.as_rotvec(), translation_km=moved_about - first.about_km)


def adjust(shots: Shots, model: Mesh | None = None, *, config: LidarConfig = LIDAR,
           rebuild: bool | None = None) -> Adjustment:
    """The model -> tracks -> model loop: every track registered to the model, the model rebuilt
    from the adjusted spots (pwm.lidar.model.model_from_spots), until no correction changes by
    more than LidarConfig.loop_tolerance_km or after LidarConfig.loop_rounds rounds. Without a
    model the first is made from the spots as given, and in the end the block (tracks and model)
    is moved back where they put it (`datum_motion`); `rebuild` (default: only then) says whether
    the model is rebuilt between rounds, or kept (a model from the images, say, which is the datum)."""
    rebuild = model is None if rebuild is None else rebuild
    track = track_ids(shots, config)
    current = model_from_spots(shots, config) if model is None else model
    tracks = [int(t) for t in np.unique(track) if t != NO_TRACK]
    corrections: dict[int, Correction] = {}
    changes: list[float] = []
    converged = False
    for _ in range(config.loop_rounds):
        tracer = RayTracer(current)
        change = 0.0
        for t in tracks:
            own = shots.take(track == t)
            after = register_track(own, tracer, track=t, config=config, start=corrections.get(t))
            change = max(change, after.change_km(corrections.get(t)))
            corrections[t] = after
        changes.append(change)
        adjusted = apply_corrections(shots, track, corrections)
        if rebuild:
            current = model_from_spots(adjusted, config)
        converged = change < config.loop_tolerance_km
        if converged or not rebuild:
            break
    motion = datum_motion(shots, track, corrections) if model is None else None
    if motion is not None:  # the tracks and their model, moved back together
        corrections = {t: then(c, motion) for t, c in corrections.items()}
        adjusted = apply_corrections(shots, track, corrections)
        current = Mesh(motion.apply(current.vertices), current.faces, current.albedo)
    return Adjustment(adjusted, track, corrections, current, changes, converged or not rebuild)
