"""What a bundle adjustment determined about each camera pose: posterior sigmas of the lateral and
along-boresight position, of the pointing, and of the line of sight, next to their priors.

With a narrow field at long range, moving a camera sideways by d and turning it by d / range
move the image alike, so the images fix their combination (the line of sight) and leave the split
to the priors. `pose_uncertainty` shows it from the adjustment's normal matrix: the correlation
between lateral position and pointing, and the pointing sigma the images would give if the
positions were known.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from pwm.camera import Camera, Pose, corrected_pose, project
from pwm.spg.adjustment import Adjustment
from pwm.spg.pose_models import PoseModel


@dataclass(frozen=True)
class PoseSigma:
    """1-sigma figures of one camera pose: lateral position (m, RSS over the two axes across the
    boresight), position along the boresight (m), pointing (urad, RSS over the two axes across
    the boresight) and line of sight (px, the image motion of the boresight's ground point)."""

    lateral_m: float
    along_m: float
    pointing_urad: float
    los_px: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


DETERMINED = 0.5
"""A pose figure counts as determined by the images when its posterior sigma is under this
fraction of its prior."""


def determined(prior: PoseSigma, posterior: PoseSigma) -> list[str]:
    """The figures (PoseSigma field names) that the images determined (see DETERMINED)."""
    return [name for name, value in posterior.as_dict().items() if value < DETERMINED * getattr(prior, name)]


def image_sigmas(adjusted: Adjustment, cameras: list[Camera], poses: list[Pose], ranges_km: np.ndarray, *,
                 noise_px: float) -> tuple[list[PoseSigma], list[PoseSigma]]:
    """Each image's prior and posterior 1-sigma figures (see `PoseSigma`), for image
    measurements with `noise_px` (px per axis) and the ground at `ranges_km` along each
    boresight; a posterior well under its prior is what the images determined."""
    posterior = adjusted.covariance(noise_px)
    blocks = np.array([posterior[6 * i:6 * i + 6, 6 * i:6 * i + 6] for i in range(len(poses))]).reshape(-1, 6, 6)
    return (prior_sigmas(adjusted.model, cameras, poses, ranges_km),
            _sigmas(blocks, cameras, poses, ranges_km))


def prior_sigmas(model: PoseModel, cameras: list[Camera], poses: list[Pose], ranges_km: np.ndarray) -> list[PoseSigma]:
    """Each image's 1-sigma figures (see `PoseSigma`) that the pose model's priors allow, for the
    ground at `ranges_km` along each boresight."""
    return _sigmas(model.prior_blocks(), cameras, poses, ranges_km)


def _sigmas(blocks: np.ndarray, cameras: list[Camera], poses: list[Pose], ranges_km: np.ndarray) -> list[PoseSigma]:
    """The figures of each image's own covariance block (n, 6, 6; body-fixed km and rad)."""
    out = []
    for own, cam, pose, r in zip(blocks, cameras, poses, ranges_km, strict=True):
        jac = _los_jacobian(cam, pose, float(r))
        c = _to_camera(own, pose)
        out.append(PoseSigma(lateral_m=float(np.sqrt(c[0, 0] + c[1, 1])) * 1e3, along_m=float(np.sqrt(c[2, 2])) * 1e3,
                             pointing_urad=float(np.sqrt(c[3, 3] + c[4, 4])) * 1e6,
                             los_px=float(np.sqrt(np.trace(jac @ own @ jac.T)))))
    return out


def pose_uncertainty(adjusted: Adjustment, cameras: list[Camera], poses: list[Pose], ranges_km: np.ndarray, *,
                     noise_px: float) -> dict[str, float]:
    """Medians over the images of prior and posterior 1-sigma figures, for image measurements
    with `noise_px` (px per axis): lateral and along-boresight position (m; RSS over the two
    lateral axes), pointing (urad, RSS over the two axes across the boresight), line of sight
    (px, RSS of the image motion of the boresight's ground point at `ranges_km`). A shift, turn
    or scaling of the whole block of cameras and points leaves the images unchanged: only the
    priors see it, which bounds the posteriors from below whatever the images.

    Then one image against the others held known (the most favourable case): its line of sight
    ("los_one_image_px"), its pointing with its position free ("pointing_one_image_urad") and
    with its position known too ("pointing_alone_urad"), and the |correlation| of lateral
    position with the pointing that mimics it ("lateral_pointing_correlation")."""
    priors, posteriors = image_sigmas(adjusted, cameras, poses, ranges_km, noise_px=noise_px)
    out: dict[str, list[float]] = {f"{k}_{which}": [getattr(s, k) for s in sigmas]
                                   for k in ("lateral_m", "along_m", "pointing_urad", "los_px")
                                   for which, sigmas in (("prior", priors), ("posterior", posteriors))}
    for k in ("los_one_image_px", "pointing_one_image_urad", "pointing_alone_urad", "lateral_pointing_correlation"):
        out[k] = []
    jac = [_los_jacobian(cam, pose, float(r)) for cam, pose, r in zip(cameras, poses, ranges_km, strict=True)]
    prior = adjusted.model.prior_blocks()
    information = adjusted.information(noise_px)
    for i, pose in enumerate(poses):
        own = slice(6 * i, 6 * i + 6)
        prior_information = np.linalg.pinv(prior[i])
        block = information[own, own] + prior_information
        one_body = np.linalg.pinv(block)
        one = _to_camera(one_body, pose)
        out["los_one_image_px"].append(float(np.sqrt(np.trace(jac[i] @ one_body @ jac[i].T))))
        alone_body = np.pad(np.linalg.pinv(block[3:, 3:]), ((3, 0), (3, 0)))
        alone = _to_camera(alone_body, pose)
        corr = one / np.sqrt(np.outer(np.diag(one), np.diag(one)))
        out["pointing_one_image_urad"].append(float(np.sqrt(one[3, 3] + one[4, 4])) * 1e6)
        out["pointing_alone_urad"].append(float(np.sqrt(alone[3, 3] + alone[4, 4])) * 1e6)
        out["lateral_pointing_correlation"].append(float(max(abs(corr[0, 4]), abs(corr[1, 3]))))
    return {k: float(np.median(v)) for k, v in out.items()}


def _to_camera(cov: np.ndarray, pose: Pose) -> np.ndarray:
    """A (position, rotation vector) covariance from body-fixed to camera axes."""
    rot = np.zeros((6, 6))
    rot[:3, :3] = rot[3:, 3:] = pose.rotation
    return rot @ cov @ rot.T


def _los_jacobian(camera: Camera, pose: Pose, range_km: float) -> np.ndarray:
    """d(pixel of the boresight ground point) / d(dx, dy, dz km, wx, wy, wz rad), (2, 6)."""
    ground = pose.position + pose.boresight * range_km
    jac = np.empty((2, 6))
    for k, h in enumerate([1e-6] * 3 + [1e-7] * 3):
        e = np.zeros(6)
        e[k] = h
        plus = project(ground, camera, corrected_pose(pose, e[:3], e[3:]))
        minus = project(ground, camera, corrected_pose(pose, -e[:3], -e[3:]))
        jac[:, k] = (plus - minus) / (2 * h)
    return jac
