"""What the bundle adjustment may change of the poses: a pose model.

The corrections of n images (6 n: per image dx, dy, dz km and wx, wy, wz rad, body-fixed, as
`pwm.camera.corrected_pose` applies them) are a linear function of a few unknowns,
corrections = design @ theta, with theta ~ N(0, I) a priori (each column of the design carries
its unknown's 1-sigma prior). Two models:

- `free_poses`: every image its own position and pointing (independent knowledge errors).
- `navigation_poses`: what orbit determination and star trackers deliver: per arc
  (pwm.trajectory.arcs) the position error along-track, cross-track and radial as a smooth
  function of time (pwm.trajectory.smooth_basis, in the arc's track frames), one camera-to-bus
  misalignment shared by every image and a pointing drift growing linearly over the downlink.
  A pointing error e in the instrument frame is R^T e in body-fixed axes (R: the image's
  body-fixed -> instrument rotation), so the shared misalignment turns each image's axes about
  a different body-fixed direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from pwm.camera import Pose
from pwm.knowledge import NavigationErrors
from pwm.trajectory import BASIS_TERMS, arc_period, arcs, smooth_basis, track_frames

TRACK_AXES = ("along", "cross", "radial")
BASIS_NAMES = ("constant", "linear", "cos", "sin")


@dataclass(frozen=True)
class PoseModel:
    """Corrections (6 n_images) = design @ theta, theta ~ N(0, I) a priori. names: one label per
    unknown; scale: its 1-sigma prior (km or rad), so that theta * scale is its value."""

    design: sparse.csr_matrix
    names: tuple[str, ...]
    scale: np.ndarray

    @property
    def n_images(self) -> int:
        return self.design.shape[0] // 6

    def corrections(self, theta: np.ndarray) -> np.ndarray:
        """(n_images, 6) corrections of the unknowns theta (sigma units)."""
        return np.asarray(self.design @ theta).reshape(-1, 6)

    def prior_blocks(self) -> np.ndarray:
        """(n_images, 6, 6): each image's own prior covariance of its corrections (km, rad)."""
        return np.array([(rows @ rows.T).toarray() for rows in
                         (self.design[6 * i:6 * i + 6] for i in range(self.n_images))]).reshape(-1, 6, 6)


def free_poses(n_images: int, *, sigma_position_km: float, sigma_pointing_rad: float) -> PoseModel:
    """Every image's own six corrections, with independent priors per axis."""
    sigma = np.tile([sigma_position_km] * 3 + [sigma_pointing_rad] * 3, n_images)
    names = tuple(f"image {i} {axis}" for i in range(n_images) for axis in ("dx", "dy", "dz", "wx", "wy", "wz"))
    return PoseModel(design=sparse.diags(sigma).tocsr(), names=names, scale=sigma)


def navigation_poses(times: np.ndarray, poses: list[Pose], knowledge: NavigationErrors) -> PoseModel:
    """Per arc, BASIS_TERMS coefficients of each track axis with knowledge's per-arc sigma (m);
    one misalignment and one drift at the last image, 3 axes each, in the instrument frame.
    Unknowns of zero prior are left out (known exactly)."""
    times = np.asarray(times, float)
    positions = np.array([p.position for p in poses])
    n = len(times)
    frames = track_frames(times, positions, gap_s=knowledge.arc_gap_s)
    columns: list[np.ndarray] = []
    names: list[str] = []
    scale: list[float] = []
    axis_sigma_km = np.array([knowledge.along_m, knowledge.cross_m, knowledge.radial_m]) * 1e-3
    for a, arc in enumerate(arcs(times, gap_s=knowledge.arc_gap_s)):
        t = times[arc]
        basis = smooth_basis(t, arc_period(t, knowledge.orbit_period_s))
        for b in range(min(BASIS_TERMS, len(arc))):
            for axis in range(3):
                if axis_sigma_km[axis] == 0:
                    continue
                column = np.zeros((n, 6))
                column[arc, :3] = basis[:, b, None] * frames[arc, axis] * axis_sigma_km[axis]
                columns.append(column.ravel())
                names.append(f"arc {a} {TRACK_AXES[axis]} {BASIS_NAMES[b]}")
                scale.append(axis_sigma_km[axis])
    span = float(times.max() - times.min()) if n else 0.0
    ramp = (times - times.min()) / span if span > 0 else np.zeros(n)
    rotations = np.array([p.rotation for p in poses])
    for label, sigma, weight in (("misalignment", knowledge.misalign_urad * 1e-6, np.ones(n)),
                                 ("drift", knowledge.drift_urad * 1e-6, ramp)):
        if sigma == 0 or not weight.any():
            continue
        for axis in range(3):
            column = np.zeros((n, 6))
            column[:, 3:] = rotations[:, axis, :] * (weight * sigma)[:, None]  # R^T e_axis, row `axis` of R
            columns.append(column.ravel())
            names.append(f"{label} {'xyz'[axis]}")
            scale.append(sigma)
    design = sparse.csr_matrix(np.column_stack(columns)) if columns else sparse.csr_matrix((6 * n, 0))
    return PoseModel(design=design, names=tuple(names), scale=np.array(scale))
