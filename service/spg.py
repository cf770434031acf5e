"""Stereo photogrammetry on the catalog: a photogrammetric model version and stored pose
corrections from the catalogued images (pwm.spg on the catalog's views).

The run starts from the latest version and from each image's current pose (its stored
correction applied, service.views.image_pose), so a second run refines the first: the new
correction is composed onto the stored one. Corrected images lose their coverage weighing
(Image.coverage_computed_at), so the next ingest with a shape weighs them again with their new
poses; and since a maplet's input hash includes its images' pose corrections, the maplets they
weigh into become stale (service.refinement.stale_maplets) and are refined with the corrected
poses.
"""

from __future__ import annotations

import logging
from collections.abc import Collection
from pathlib import Path

import numpy as np
import spiceypy as sp
from scipy.spatial.transform import Rotation
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from pwm.camera import PoseCorrection
from pwm.io.spice_geometry import ellipsoid_of
from pwm.io.spice_kernels import kernel_pool, spice_message
from pwm.mesh import Mesh
from pwm.spg import stereo_photogrammetry
from service.db import session_scope
from service.kernels import accepted_kernels
from service.models import Downlink, GeometryStatus, Image, ImageStatus, ModelKind, ModelVersion, utcnow
from service.versions import latest_version, publish_version, version_mesh
from service.views import catalog_views

log = logging.getLogger(__name__)


def photogrammetry_version(sessions: sessionmaker[Session], *, data_dir: Path,
                           image_ids: Collection[int] | None = None, prior: Mesh | None = None,
                           sigma_position_km: float = 1e-3, sigma_pointing_rad: float = 1e-4,
                           max_features: int = 8192, first_octave: int | None = None, per_image: int = 6,
                           threads: int = 2) -> int:
    """Run stereo photogrammetry on the accepted images with geometry (those of image_ids, or
    all) from the latest version, or from `prior` when the catalog has none; publish the model
    as a version of kind photogrammetric (parent: that version) and store each image's pose
    correction. Its version number.

    sigma_position_km, sigma_pointing_rad: 1-sigma pose knowledge per axis (km, rad) about the
    images' current poses; the other options are pwm.spg.stereo_photogrammetry's.
    Raises LookupError when the catalog has no version and no prior is given, ValueError when
    photogrammetry cannot work (fewer than two images, no pair that overlaps).
    """
    with sessions() as session:
        base = latest_version(session)
        if base is not None:
            previous = version_mesh(data_dir, base)
        elif prior is not None:
            previous = prior
        else:
            raise LookupError("the catalog has no model version to start from: ingest with a "
                              "start model (pwm run) or pwm import one")
        base_id = None if base is None else base.id
        views = catalog_views(session, image_ids=image_ids, pixels=True)
    if len(views) < 2:
        raise ValueError(f"stereo photogrammetry needs two images or more, the catalog has "
                         f"{len(views)}")
    ids = list(views)
    result = stereo_photogrammetry([views[i] for i in ids], previous,
                                   sigma_position_km=sigma_position_km,
                                   sigma_pointing_rad=sigma_pointing_rad,
                                   max_features=max_features, first_octave=first_octave,
                                   per_image=per_image, threads=threads)
    with session_scope(sessions) as session:
        images = session.scalars(select(Image).where(Image.id.in_(ids)).order_by(Image.id)).all()
        now = utcnow()
        for image in images:
            _store_correction(image, result.corrections[views[image.id].name])
            sigma_before, sigma_after = result.sigmas[views[image.id].name]
            image.pose_sigma = {"prior": sigma_before.as_dict(), "posterior": sigma_after.as_dict()}
            image.pose_corrected_at = now
            # weighed again, with the corrected pose, at the next ingest with a shape
            image.coverage_computed_at = None
        parent = None if base_id is None else session.get_one(ModelVersion, base_id)
        downlinks = {image.downlink.id: image.downlink for image in images if image.downlink}
        version = publish_version(session, data_dir=data_dir, mesh=result.mesh,
                                  kind=ModelKind.PHOTOGRAMMETRIC, parent=parent,
                                  statistics={**result.stats, "images": len(ids),
                                              "base_version": None if parent is None else parent.version},
                                  downlinks=downlinks.values())
        log.info("photogrammetric version %d from %s: %d images corrected", version.version,
                 "the prior shape" if parent is None else f"version {parent.version}", len(images))
        return version.version


def start_from_images(sessions: sessionmaker[Session], *, data_dir: Path, downlink_id: int) -> int | None:
    """When the catalog has no model version: stereo photogrammetry on every catalogued image
    with geometry, from the images' target's PCK ellipsoid, published as the first version (kind
    photogrammetric, pose corrections stored). Its number, or None when photogrammetry cannot
    work (too few images, too little overlap, no target radii); the downlink's model_note says
    what happened either way, and the next downlink tries again with every image so far.
    """
    with sessions() as session:
        made = latest_version(session)
        targets = set(session.scalars(select(Image.target).where(
            Image.status == ImageStatus.ACCEPTED, Image.geometry_status == GeometryStatus.COMPUTED)))
        kernels = [Path(k.path) for k in accepted_kernels(session)]
    note, number = None, None
    if made is not None:  # another ingest made one meanwhile: start from it
        number = made.version
        note = f"version {number} ({made.kind.value}) was made meanwhile, by another ingest"
    elif len(targets) != 1 or None in targets:
        note = (f"no model: photogrammetry needs the images of one target, the catalog has "
                f"{len(targets - {None})} ({', '.join(sorted(t for t in targets if t))})")
    else:
        (target,) = targets
        try:
            with kernel_pool(kernels):
                ellipsoid = ellipsoid_of(str(target))
        except sp.utils.exceptions.SpiceyError as exc:
            note = f"no model: no radii of {target} in the kernels ({spice_message(exc)})"
        else:
            try:
                number = photogrammetry_version(sessions, data_dir=data_dir, prior=ellipsoid.mesh())
            except ValueError as exc:
                note = f"no model: stereo photogrammetry cannot work yet: {exc}"
    if number is not None and made is None:
        note = f"version {number} (photogrammetric) made from the images, with no model before"
    with session_scope(sessions) as session:
        session.get_one(Downlink, downlink_id).model_note = note
    log.info("downlink %d: %s", downlink_id, note)
    return number


def _store_correction(image: Image, new: PoseCorrection) -> None:
    """Compose `new` (estimated about the image's corrected pose) onto its stored correction:
    positions add; rotations compose as R(total) = R(new) R(stored), so that
    rotation @ R(total)^T = (rotation @ R(stored)^T) @ R(new)^T (pwm.camera.corrected_pose)."""
    stored = image.pose_correction() or PoseCorrection(position_km=(0.0, 0.0, 0.0), rotation_rad=(0.0, 0.0, 0.0))
    dp = np.asarray(stored.position_km) + np.asarray(new.position_km)
    w = (Rotation.from_rotvec(np.asarray(new.rotation_rad))
         * Rotation.from_rotvec(np.asarray(stored.rotation_rad))).as_rotvec()
    image.pose_dx_km, image.pose_dy_km, image.pose_dz_km = map(float, dp)
    image.pose_rx_rad, image.pose_ry_rad, image.pose_rz_rad = map(float, w)
