"""Catalogued images as views (pwm.views.View): camera of the array read out, pose and Sun
from the stored geometry, with the image's pose correction applied, and optionally the pixels.

The one place that turns catalog rows into what the refinement chain takes, for the coverage
rows at ingest (no pixels) and for the refinement of a maplet (pixels read from the PDS4 product).
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload

from pwm.camera import Camera, Pose
from pwm.io.pds4 import read_array, read_image_label
from pwm.views import View
from service.models import GeometryStatus, Image, ImageStatus
from service.settings import get_settings


def image_pose(image: Image) -> Pose:
    """The image's camera pose (body-fixed, km; body -> image frame), with its bundle-adjustment
    correction (Image.pose_d*_km, pose_r*_rad) applied when set (pwm.camera.corrected_pose)."""
    g = image.geometry
    if g is None:
        raise ValueError(f"image {image.lidvid} has no geometry")
    pose = Pose(position=np.array([g.camera_x_km, g.camera_y_km, g.camera_z_km]),
                rotation=np.asarray(g.camera_rotation, float).reshape(3, 3))
    correction = image.pose_correction()
    return pose if correction is None else correction.apply(pose)


def catalog_views(session: Session, *, image_ids: Collection[int] | None = None,
                  pixels: bool = False) -> dict[int, View]:
    """The accepted images with geometry (those of image_ids, or all) as views, by image id.
    Without pixels the views' image is an empty array (geometry only)."""
    query = select(Image).where(
        Image.status == ImageStatus.ACCEPTED, Image.geometry_status == GeometryStatus.COMPUTED,
        Image.instrument_id.is_not(None)).options(
        selectinload(Image.geometry), selectinload(Image.instrument)).order_by(Image.id)
    if image_ids is not None:
        query = query.where(Image.id.in_(list(image_ids)))
    return {image.id: image_view(image, pixels=pixels) for image in session.scalars(query)}


def image_view(image: Image, *, pixels: bool = False) -> View:
    """One catalogued image (accepted, with geometry) as a view; see `catalog_views`."""
    g, inst = image.geometry, image.instrument
    if g is None or inst is None or image.start_et is None or image.stop_et is None:
        raise ValueError(f"image {image.lidvid} lacks its geometry, instrument or times")
    # The catalog keeps the detector, not the array's window: the label gives it. Read within
    # the limits ingest accepted it under; the array only when asked for.
    limits = get_settings().ingest_limits()
    label = read_image_label(Path(image.label_path), max_label_bytes=limits.max_label_bytes,
                             max_pixels=limits.max_pixels)
    product = read_array(label) if pixels else None
    camera = Camera(width=inst.width_px, height=inst.height_px, fx=inst.fx_px, fy=inst.fy_px,
                    cx=inst.cx_px, cy=inst.cy_px).subframe(
        first_sample=label.first_sample, first_line=label.first_line,
        samples=label.samples, lines=label.lines)
    sun = np.array([g.sun_x, g.sun_y, g.sun_z])
    return View(name=image.lidvid, image=np.empty((0, 0)) if product is None else product.data,
                camera=camera, pose=image_pose(image), sun=sun / np.linalg.norm(sun),
                et=0.5 * (image.start_et + image.stop_et))
