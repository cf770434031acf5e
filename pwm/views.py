"""A view: one image with what photoclinometry needs to use it. The core's type for an image,
whatever its source: a downlink read through its SPICE kernels (pwm.io.downlink) or the
catalog (service.views)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pwm.camera import Camera, Pose
from pwm.geometry import view_cone


@dataclass
class View:
    """One image ready for photoclinometry. image: reflectance-like values [line, sample], NaN
    where missing; camera: of the pixels read out (detector window applied); pose: body-fixed,
    image frame; sun: unit vector towards the Sun, body-fixed; et: mid-exposure, ET s;
    los_sigma_px: 1 sigma (per image axis) of how far the image may be off its pose, from the
    stated pose knowledge and the adjustment (0: not known to be off)."""

    name: str
    image: np.ndarray
    camera: Camera
    pose: Pose
    sun: np.ndarray
    et: float
    los_sigma_px: float = 0.0


CONE_MARGIN_RAD = 2e-3
"""Added to each cone's half-angle: pose corrections (microradians to a fraction of a
milliradian) move a view's rays after its cone was stored."""


@dataclass(frozen=True)
class Cones:
    """The cones that hold what each of N views can see (pwm.geometry.view_cone): apex (N, 3)
    body-fixed km, unit axis (N, 3), half-angle (N,) rad; a nan half-angle (not known) holds
    everything. A cheap, conservative footprint for choosing views by place without a shape."""

    apex: np.ndarray
    axis: np.ndarray
    half_angle: np.ndarray

    @classmethod
    def of(cls, views: Sequence[View]) -> Cones:
        cones = [view_cone(v.camera, v.pose) for v in views]
        return cls(apex=np.array([v.pose.position for v in views], float).reshape(-1, 3),
                   axis=np.array([a for a, _ in cones], float).reshape(-1, 3),
                   half_angle=np.array([h for _, h in cones], float))

    def seeing(self, centres_km: np.ndarray, radius_km: float | np.ndarray) -> np.ndarray:
        """(N, M) whether each cone meets each of M balls (centres (M, 3), radii scalar or (M,))."""
        centres = np.asarray(centres_km, float).reshape(-1, 3)
        radius = np.broadcast_to(np.asarray(radius_km, float), (len(centres),))
        half = np.where(np.isfinite(self.half_angle), self.half_angle, np.inf) + CONE_MARGIN_RAD
        out = np.empty((len(self.apex), len(centres)), dtype=bool)
        step = max(1, _PAIRS_AT_ONCE // max(len(centres), 1))
        for n in range(0, len(self.apex), step):
            d = centres[None, :, :] - self.apex[n : n + step, None, :]
            distance = np.maximum(np.linalg.norm(d, axis=2), 1e-300)
            cos_angle = np.einsum("nmk,nk->nm", d, self.axis[n : n + step]) / distance
            angle = np.arccos(np.clip(cos_angle, -1.0, 1.0))
            reach = np.arcsin(np.clip(radius[None, :] / distance, 0.0, 1.0))
            out[n : n + step] = (angle <= half[n : n + step, None] + reach) | (distance <= radius[None, :])
        return out


_PAIRS_AT_ONCE = 1 << 20
