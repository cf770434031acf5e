"""Catalogued images as views (pwm.views.View): camera of the array read out, pose and Sun
from the stored geometry, with the image's pose correction applied, and optionally the pixels.

The one place that turns catalog rows into what the refinement chain takes, for the coverage
rows at ingest (no pixels) and for the refinement of a maplet (pixels read from the PDS4 product,
or from the ISIS cube: resampled onto the cube's ideal pinhole camera, pwm.io.isis).

The stored geometry is a PDS4 product's from the kernels and a cube's from the cube itself (its
attached SPICE, read at ingest): `kernel_pose` is the pose as the image's source gave it.
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload

from pwm.camera import Camera, Pose
from pwm.io.isis import is_cube, read_cube, read_cube_pixels
from pwm.io.pds4 import read_array, read_image_label
from pwm.views import Cones, View
from service.rows import GeometryStatus, Image, ImageGeometry, ImageStatus
from service.settings import get_settings


def kernel_pose(image: Image) -> Pose:
    """The image's camera pose as its kernels (a cube: its attached SPICE) give it (body-fixed,
    km; body -> image frame)."""
    g = image.geometry
    if g is None:
        raise ValueError(f"image {image.lidvid} has no geometry")
    return Pose(position=np.array([g.camera_x_km, g.camera_y_km, g.camera_z_km]),
                rotation=np.asarray(g.camera_rotation, float).reshape(3, 3))


def image_pose(image: Image) -> Pose:
    """The image's camera pose (`kernel_pose`) with its bundle-adjustment correction
    (Image.pose_d*_km, pose_r*_rad) applied when set (pwm.camera.corrected_pose)."""
    pose = kernel_pose(image)
    correction = image.pose_correction()
    return pose if correction is None else correction.apply(pose)


def catalog_views(session: Session, *, image_ids: Collection[int] | None = None,
                  pixels: bool = False, kernel_poses: bool = False) -> dict[int, View]:
    """The accepted images with geometry (those of image_ids, or all) as views, by image id.
    Without pixels the views' image is an empty array (geometry only); with kernel_poses their
    poses are the kernels' (`kernel_pose`), without the stored corrections."""
    query = select(Image).where(
        Image.status == ImageStatus.ACCEPTED, Image.geometry_status == GeometryStatus.COMPUTED,
        Image.instrument_id.is_not(None)).options(
        selectinload(Image.geometry), selectinload(Image.instrument)).order_by(Image.id)
    if image_ids is not None:
        query = query.where(Image.id.in_(list(image_ids)))
    return {image.id: image_view(image, pixels=pixels, kernel_poses=kernel_poses) for image in session.scalars(query)}


def catalog_cones(session: Session) -> tuple[np.ndarray, Cones]:
    """The ids (N,) of the accepted images with geometry and their stored cones (pwm.views.Cones;
    nan half-angle where none was stored), in one query of plain columns: what coverage planning
    selects images by, for a catalog of any size."""
    g = ImageGeometry
    rows = session.execute(select(
        Image.id, g.camera_x_km, g.camera_y_km, g.camera_z_km, g.cone_axis_x, g.cone_axis_y, g.cone_axis_z,
        g.cone_half_angle_rad).join(g, g.image_id == Image.id).where(
        Image.status == ImageStatus.ACCEPTED, Image.geometry_status == GeometryStatus.COMPUTED,
        Image.instrument_id.is_not(None)).order_by(Image.id)).all()
    table = np.array([[np.nan if v is None else v for v in row] for row in rows], float).reshape(-1, 8)
    axis = np.nan_to_num(table[:, 4:7], nan=0.0)
    axis[~np.isfinite(table[:, 7])] = (0.0, 0.0, 1.0)
    return table[:, 0].astype(np.int64), Cones(apex=table[:, 1:4], axis=axis, half_angle=table[:, 7])


def image_view(image: Image, *, pixels: bool = False, kernel_poses: bool = False) -> View:
    """One catalogued image (accepted, with geometry) as a view; see `catalog_views`."""
    g, inst = image.geometry, image.instrument
    if g is None or inst is None or image.start_et is None or image.stop_et is None:
        raise ValueError(f"image {image.lidvid} lacks its geometry, instrument or times")
    # The label is read for the array, or for the window of an image catalogued before the
    # window was kept; within the limits ingest accepted it under. A cube's camera is its own
    # (the grid its pixels are resampled onto), its label read for it.
    window = image.window()
    data = None
    if is_cube(Path(image.label_path)):
        limits = get_settings().ingest_limits()
        cube = read_cube(Path(image.label_path), max_label_bytes=limits.max_label_bytes, max_pixels=limits.max_pixels)
        camera = cube.camera
        data = read_cube_pixels(cube) if pixels else None
    else:
        if pixels or window is None:
            limits = get_settings().ingest_limits()
            label = read_image_label(Path(image.label_path), max_label_bytes=limits.max_label_bytes,
                                     max_pixels=limits.max_pixels,
                                     max_fits_header_bytes=limits.max_fits_header_bytes)
            window = (label.first_line, label.first_sample, label.lines, label.samples)
            data = read_array(label).data if pixels else None
        first_line, first_sample, lines, samples = window
        camera = Camera(width=inst.width_px, height=inst.height_px, fx=inst.fx_px, fy=inst.fy_px,
                        cx=inst.cx_px, cy=inst.cy_px).subframe(
            first_sample=first_sample, first_line=first_line, samples=samples, lines=lines)
    sun = np.array([g.sun_x, g.sun_y, g.sun_z])
    return View(name=image.lidvid, image=np.empty((0, 0)) if data is None else data,
                camera=camera, pose=kernel_pose(image) if kernel_poses else image_pose(image),
                sun=sun / np.linalg.norm(sun),
                et=0.5 * (image.start_et + image.stop_et), los_sigma_px=image.los_sigma_px())
