"""A view: one image with what photoclinometry needs to use it. The core's type for an image,
whatever its source: a downlink read through its SPICE kernels (pwm.io.downlink) or the
catalog (service.views)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pwm.camera import Camera, Pose


@dataclass
class View:
    """One image ready for photoclinometry. image: reflectance-like values [line, sample], NaN
    where missing; camera: of the pixels read out (detector window applied); pose: body-fixed,
    image frame; sun: unit vector towards the Sun, body-fixed; et: mid-exposure, ET s."""

    name: str
    image: np.ndarray
    camera: Camera
    pose: Pose
    sun: np.ndarray
    et: float
