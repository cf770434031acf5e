"""Read a downlink directory (PDS4 images + SPICE kernels with a meta-kernel) into views:
image arrays with their camera, pose and Sun direction, ready for refinement."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import spiceypy as sp

from pwm.camera import Camera, Pose, PoseCorrection
from pwm.io.pds4 import ProductError, read_image_product
from pwm.io.spice_geometry import camera_from_kernel, camera_pose, sun_direction
from pwm.io.spice_kernels import kernel_pool


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


def read_views(directory: str | Path, *, instrument_id: int, target: str, body_frame: str,
               corrections: Mapping[str, PoseCorrection] | None = None) -> list[View]:
    """Every image of `instrument_id` in a downlink, with geometry from its meta-kernel.

    Products that are not images are skipped; an image whose geometry fails raises, because a
    refinement on a partial, silently chosen image set would be wrong without saying so.
    `corrections` (by view name, e.g. from `pwm spg`) are applied to the SPICE poses.
    """
    directory = Path(directory)
    metakernels = sorted(directory.rglob("*.tm"))
    if len(metakernels) != 1:
        raise ValueError(f"{directory}: expected one meta-kernel (*.tm), found {len(metakernels)}")
    views = []
    with kernel_pool(metakernels):
        detector = camera_from_kernel(instrument_id)
        for label in sorted(directory.rglob("*.xml")):
            try:
                product = read_image_product(label)
            except ProductError as exc:
                if exc.code == "not_image":
                    continue
                raise
            with sp.no_found_check():
                code, found = sp.bodn2c(product.instrument_name or "")
            if not found or code != instrument_id:
                continue
            et = (sp.utc2et(product.start_utc.rstrip("Z")) + sp.utc2et(product.stop_utc.rstrip("Z"))) / 2
            camera = detector.subframe(first_sample=product.first_sample, first_line=product.first_line,
                                       samples=product.samples, lines=product.lines)
            pose = camera_pose(et=et, instrument_id=instrument_id, target=target, body_frame=body_frame)
            if corrections is not None and label.stem in corrections:
                pose = corrections[label.stem].apply(pose)
            views.append(View(name=label.stem, image=product.data, camera=camera, pose=pose,
                              sun=sun_direction(et=et, target=target, body_frame=body_frame), et=et))
    return views

