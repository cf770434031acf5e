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
from pwm.config import DEFAULTS as REFINEMENT_DEFAULTS
from pwm.io.labels import target_frame
from pwm.io.spice_geometry import ellipsoid_of
from pwm.io.spice_kernels import KernelError, kernel_pool, spice_message, stated_knowledge
from pwm.knowledge import (
    IndependentErrors,
    KnowledgeErrors,
    NavigationErrors,
    format_knowledge_errors,
    shared_frame_sigma,
)
from pwm.mesh import Mesh
from pwm.spg import stereo_photogrammetry
from pwm.spg.config import SPG_DEFAULTS, SpgConfig
from pwm.spg.photogrammetry import adjust_poses
from pwm.spg.pose_models import PoseModel, free_poses, navigation_poses
from pwm.spg.ties import MeasuredSurface
from pwm.spg.triangulation import Tracks
from pwm.spg.uncertainty import prior_sigmas
from pwm.views import View
from service.db import session_scope
from service.kernels import accepted_kernels
from service.lidar_shots import catalog_spots
from service.rows import (
    Acceptance,
    Coverage,
    Downlink,
    GeometryStatus,
    Image,
    ImageStatus,
    Kernel,
    KernelKind,
    Maplet,
    MapletRevision,
    ModelKind,
    ModelVersion,
    utcnow,
)
from service.versions import get_version, latest_version, publish_version, version_mesh
from service.views import catalog_views

log = logging.getLogger(__name__)


def photogrammetry_version(sessions: sessionmaker[Session], *, data_dir: Path,
                           image_ids: Collection[int] | None = None, figure: Mesh | None = None,
                           knowledge: KnowledgeErrors | None = None, config: SpgConfig = SPG_DEFAULTS) -> int:
    """Run stereo photogrammetry on the accepted images with geometry (those of image_ids, or
    all) from the latest version, or from the body's `figure` (its PCK ellipsoid) when the catalog
    has none, over which the points are interpolated everywhere; publish the model
    as a version of kind photogrammetric (parent: that version) and store each image's pose
    correction. Its version number.

    knowledge: the stated pose knowledge of the images' current poses (pwm.knowledge), modelled
    as `adjust_downlink` models it; without it, config.sigma_position_km and
    config.sigma_pointing_rad: the 1-sigma pose knowledge assumed per axis (km, rad). config: the
    photogrammetry's settings (pwm.spg.config).
    Raises LookupError when the catalog has no version and no figure is given, ValueError when
    photogrammetry cannot work (fewer than two images, no pair that overlaps).
    """
    with sessions() as session:
        base = latest_version(session)
        if base is not None:
            previous = version_mesh(data_dir, base)
        elif figure is not None:
            previous = figure
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
                                   pose_model=None if knowledge is None else _pose_model(knowledge,
                                                                                         [views[i] for i in ids]),
                                   from_figure=base_id is None, config=config)
    with session_scope(sessions) as session:
        images = session.scalars(select(Image).where(Image.id.in_(ids)).order_by(Image.id)).all()
        now = utcnow()
        for image in images:
            _store_correction(image, result.corrections[views[image.id].name])
            sigma_before, sigma_after = result.sigmas[views[image.id].name]
            image.pose_sigma = {"prior": sigma_before.as_dict(), "posterior": sigma_after.as_dict(),
                                **({} if knowledge is None else {"knowledge": format_knowledge_errors(knowledge)})}
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


def start_from_images(sessions: sessionmaker[Session], *, data_dir: Path, downlink_id: int,
                      configured: KnowledgeErrors | None = None, config: SpgConfig = SPG_DEFAULTS) -> int | None:
    """When the catalog has no model version: stereo photogrammetry on every catalogued image
    with geometry, from the images' target's PCK ellipsoid, published as the first version (kind
    photogrammetric, pose corrections stored), under the downlink's pose knowledge
    (`downlink_knowledge`; where none is stated or configured, `assumed_knowledge`, recorded as
    the downlink's pose adjustment so that the feedback works under it too). Its number, or None when photogrammetry
    cannot work (too few images, too little overlap, no target radii); the downlink's model_note
    says what happened either way, and the next downlink tries again with every image so far.
    config: the photogrammetry's settings (pwm.spg.config).
    """
    with sessions() as session:
        knowledge, source = downlink_knowledge(session, downlink_id, configured)
        if knowledge is None:
            knowledge, source = assumed_knowledge(config), ASSUMED
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
                # the label's name ("(4769) Castalia"), as ingest resolves it to the body's id
                code, _ = target_frame(str(target))
                ellipsoid = ellipsoid_of(str(target) if code is None else str(code))
        except sp.utils.exceptions.SpiceyError as exc:
            note = f"no model: no radii of {target} in the kernels ({spice_message(exc)})"
        else:
            try:
                number = photogrammetry_version(sessions, data_dir=data_dir, figure=ellipsoid.mesh(),
                                                knowledge=knowledge, config=config)
            except ValueError as exc:
                note = f"no model: stereo photogrammetry cannot work yet: {exc}"
    if number is not None and made is None:
        note = f"version {number} (photogrammetric) made from the images, with no model before"
    with session_scope(sessions) as session:
        downlink = session.get_one(Downlink, downlink_id)
        downlink.model_note = note
        if number is not None and made is None and knowledge is not None:
            downlink.pose_adjustment = _start_report(session, downlink_id, number, knowledge, source)
    log.info("downlink %d: %s", downlink_id, note)
    return number


def _start_report(session: Session, downlink_id: int, version: int, knowledge: KnowledgeErrors,
                  source: str) -> dict:
    """What the start from nothing did to a downlink's poses, as `adjust_downlink` reports its
    own: the knowledge, the line of sight before and after (medians over the downlink's images),
    and the adjustment's figures and unknowns (the photogrammetric version's statistics)."""
    stats = get_version(session, version).statistics
    sigmas = [image.pose_sigma for image in session.scalars(select(Image).where(Image.downlink_id == downlink_id))
              if image.pose_sigma]
    return {"knowledge": format_knowledge_errors(knowledge), "source": source, "images": len(sigmas),
            "note": f"adjusted by the stereo photogrammetry of version {version}, from nothing",
            "los_prior_px": float(np.median([s["prior"]["los_px"] for s in sigmas])) if sigmas else 0.0,
            "los_posterior_px": float(np.median([s["posterior"]["los_px"] for s in sigmas])) if sigmas else 0.0,
            **{key: stats[key] for key in ("residual_rms_px", "tracks", "observations", "seconds", "unknowns")
               if key in stats}}


TIE_FIGURES = ("ties", "tie_rms_m", "tie_frame_shift_m", "tie_frame_turn_urad")
"""What an adjustment with the lidar's spots reports of its ties (pwm.spg.photogrammetry.adjust_poses)."""

ASSUMED = "assumed by the photogrammetry from nothing (none stated or configured)"
"""The source of the pose knowledge a start from nothing assumes where none is stated."""


def assumed_knowledge(config: SpgConfig) -> IndependentErrors:
    """The knowledge the photogrammetry assumes of images whose kernels state none
    (config.sigma_position_km and config.sigma_pointing_rad per axis): a start from nothing
    corrects their poses under it, and so leaves them that uncertain, until the maplets'
    registrations are fed back under it too (`feed_back_registrations`)."""
    return IndependentErrors(position_m=config.sigma_position_km * 1e3, pointing_rad=config.sigma_pointing_rad)


def downlink_knowledge(session: Session, downlink_id: int,
                       configured: KnowledgeErrors | None) -> tuple[KnowledgeErrors | None, str]:
    """The pose knowledge of a downlink's images and where it came from: what its accepted SPKs
    and CKs state (pwm.io.spice_kernels.stated_knowledge; the first that states one), else
    `configured` (PWM_POSE_KNOWLEDGE), else None."""
    kernels = session.scalars(select(Kernel).where(
        Kernel.downlink_id == downlink_id, Kernel.status == Acceptance.ACCEPTED,
        Kernel.retired_at.is_(None),
        Kernel.kind.in_([KernelKind.SPK, KernelKind.CK])).order_by(Kernel.id)).all()
    for kernel in kernels:
        try:
            stated = stated_knowledge(kernel.path)
        except KernelError as exc:
            log.warning("downlink %d: %s", downlink_id, exc)
            continue
        if stated is not None:
            return stated, f"stated in {Path(kernel.path).name}"
    return configured, "configured" if configured is not None else "none stated"


def adjust_downlink(sessions: sessionmaker[Session], *, shape: Mesh, downlink_id: int, data_dir: Path,
                    configured: KnowledgeErrors | None, config: SpgConfig = SPG_DEFAULTS) -> list[int]:
    """Adjust the poses of a downlink's images on `shape` under their pose knowledge
    (`downlink_knowledge`): a navigation-like knowledge is modelled per arc with one shared
    misalignment and drift, an independent one per image (pwm.spg.pose_models), and the block is
    tied to `shape` (pwm.spg.photogrammetry.adjust_poses' anchor) and, where the catalog holds
    strip-adjusted lidar, its points to the lidar's spots (service.lidar_shots.catalog_spots), which
    place it absolutely. The images' corrections are composed onto their stored ones, each image
    keeps its prior and posterior sigmas (which size its registration search,
    Image.los_sigma_px) and loses its coverage weighing; the downlink keeps what was done
    (Downlink.pose_adjustment, an earlier report under "before"). Nothing is adjusted when no
    knowledge is stated, or when the knowledge already keeps every image's line of sight within
    a pixel (three sigma), or when the same images were adjusted before with as many spots (a
    downlink ingested again; new lidar adjusts them again, from their kernels' poses, the new
    corrections replacing the stored ones). config: the photogrammetry's
    settings (pwm.spg.config). The ids of
    the images corrected.
    """
    with sessions() as session:
        knowledge, source = downlink_knowledge(session, downlink_id, configured)
        done = session.get_one(Downlink, downlink_id).pose_adjustment
        if knowledge is None and done is not None and done.get("source") == ASSUMED:  # a start from nothing's
            knowledge, source = assumed_knowledge(config), ASSUMED
        if knowledge is None:
            return []
        ids = list(session.scalars(select(Image.id).where(
            Image.downlink_id == downlink_id, Image.status == ImageStatus.ACCEPTED,
            Image.geometry_status == GeometryStatus.COMPUTED)))
        spots = catalog_spots(session, data_dir=data_dir)
        lidar = 0 if spots is None else len(spots)
        if (done is not None and done.get("images") == len(ids) and done.get("lidar_spots", 0) == lidar
                and done.get("knowledge") == format_knowledge_errors(knowledge)):
            return []
        # adjusted again (new lidar): from the kernels' poses, one adjustment with all the data, not a
        # second on top of the first, which would count the same images twice
        again = done is not None
        views = catalog_views(session, image_ids=ids, kernel_poses=again)  # geometry only, until pixels are needed
    ids = list(views)
    report: dict = {"knowledge": format_knowledge_errors(knowledge), "source": source, "images": len(ids),
                    "lidar_spots": lidar}
    if done:
        report["before"] = {key: value for key, value in done.items() if key != "before"}
    view_list = [views[i] for i in ids]
    pose_model = _pose_model(knowledge, view_list)
    ranges = np.array([_range(v, shape) for v in view_list])
    priors = dict(zip(ids, prior_sigmas(pose_model, [v.camera for v in view_list], [v.pose for v in view_list],
                                        ranges), strict=True))
    prior_los = np.array([priors[i].los_px for i in ids])
    report["los_prior_px"] = float(np.median(prior_los)) if len(ids) else 0.0
    corrected: list[int] = []
    if len(ids) < 2:
        report["note"] = f"not adjusted: {len(ids)} image(s) with geometry, two or more needed"
    elif within_a_pixel(prior_los):
        report["note"] = "not adjusted: the knowledge keeps every line of sight within a pixel"
    else:
        with sessions() as session:
            views = catalog_views(session, image_ids=ids, pixels=True, kernel_poses=again)
        view_list = [views[i] for i in ids]
        try:
            result = adjust_poses(view_list, shape, pose_model=pose_model, anchor=True,
                                  surface=None if spots is None else _surface(spots, knowledge, view_list, shape),
                                  config=config)
        except ValueError as exc:
            report["note"] = f"not adjusted: {exc}"
        else:
            corrected = ids
            stats = result.stats
            posterior = np.array([result.sigmas[v.name][1].los_px for v in view_list])
            report.update(note="adjusted", los_posterior_px=float(np.median(posterior)),
                          residual_rms_px=stats["residual_rms_px"], tracks=stats["tracks"],
                          observations=stats["observations"], seconds=stats["seconds"],
                          anchor_shift_m=stats["anchor_shift_m"], anchor_measured_m=stats["anchor_measured_m"],
                          unknowns=stats.get("unknowns", []),
                          **{key: stats[key] for key in TIE_FIGURES if key in stats})
    with session_scope(sessions) as session:
        now = utcnow()
        for image in session.scalars(select(Image).where(Image.id.in_(ids))):
            if corrected:
                name = views[image.id].name
                _store_correction(image, result.corrections[name], replace=again)
                prior, posterior_sigma = result.sigmas[name]
                image.pose_sigma = {"prior": prior.as_dict(), "posterior": posterior_sigma.as_dict(),
                                    "knowledge": report["knowledge"]}
                image.pose_corrected_at = now
                image.coverage_computed_at = None  # weighed again with the corrected pose
            else:  # not adjusted: the registration searches what the knowledge allows
                known = priors[image.id].as_dict()
                image.pose_sigma = {"prior": known, "posterior": known, "knowledge": report["knowledge"]}
        session.get_one(Downlink, downlink_id).pose_adjustment = report
    log.info("downlink %d: pose knowledge %s (%s): %s; line of sight %.2f -> %s px", downlink_id,
             report["knowledge"], source, report["note"], report["los_prior_px"],
             f"{report['los_posterior_px']:.2f}" if "los_posterior_px" in report else "-")
    return corrected


def within_a_pixel(los_px: np.ndarray) -> bool:
    """Whether lines of sight with these 1-sigma errors (px, both axes together) all stay within
    a pixel, RefinementConfig.knowledge_sigmas per axis, as refinement searches them: then no
    adjustment can move an image by anything that matters."""
    sigmas = REFINEMENT_DEFAULTS.knowledge_sigmas  # no PWM_* setting changes it: the default is the effective one
    return bool(sigmas * np.max(los_px, initial=0.0) / np.sqrt(2) <= 1.0)


def feed_back_registrations(sessions: sessionmaker[Session], *, data_dir: Path, version: int, downlink_id: int,
                            configured: KnowledgeErrors | None, config: SpgConfig = SPG_DEFAULTS) -> list[int]:
    """Adjust a downlink's images again, once, after its maplets were first refined: the feature
    tracks with, as observations, where each image saw each maplet's landmark once registered to
    it (the revisions' `registrations`, pwm.pipeline.landmark_pixels), from the kernels' poses
    under the same knowledge as `adjust_downlink` (or the one a start from nothing assumed,
    `assumed_knowledge`), tied to version `version` (the refined model) and to the catalog's
    lidar spots as `adjust_downlink` ties them. The
    maplets' registration works across lighting where features do not match, so it determines
    what the features could not; its new corrections replace the stored ones, and the maplets
    that the images weigh into are due again (their input changed).

    Only when some image of the downlink is still not known within a pixel (`within_a_pixel` of
    its posterior, or of its prior where nothing adjusted it) and the downlink was not fed back
    before; the downlink's pose_adjustment keeps what was done under "feedback". config: the
    photogrammetry's settings (pwm.spg.config). The ids of the images corrected.
    """
    with sessions() as session:
        knowledge, source = downlink_knowledge(session, downlink_id, configured)
        downlink = session.get_one(Downlink, downlink_id)
        report = dict(downlink.pose_adjustment or {})
        if knowledge is None and report.get("source") == ASSUMED:
            knowledge = assumed_knowledge(config)
        if knowledge is None or "feedback" in report:
            return []
        images = session.scalars(select(Image).where(
            Image.downlink_id == downlink_id, Image.status == ImageStatus.ACCEPTED,
            Image.geometry_status == GeometryStatus.COMPUTED, Image.instrument_id.is_not(None))
            .order_by(Image.id)).all()  # catalog_views' images, in its order
        los = np.array([image.los_sigma_px() for image in images]) * np.sqrt(2)
        if len(images) < 2 or within_a_pixel(los):
            return []
        ids = [image.id for image in images]
        landmarks = landmark_tracks(session, {image.lidvid: k for k, image in enumerate(images)})
        views: list[View] = []
        shape: Mesh | None = None
        spots = None
        if landmarks.n_points:  # pixels and the model only when there is something to adjust with
            by_id = catalog_views(session, image_ids=ids, pixels=True, kernel_poses=True)
            views = [by_id[i] for i in ids]
            shape = version_mesh(data_dir, get_version(session, version))
            spots = catalog_spots(session, data_dir=data_dir)
    feedback: dict = {"landmarks": landmarks.n_points, "observations": len(landmarks.image),
                      "los_before_px": float(np.median(los))}
    result = None
    if shape is None:
        feedback["note"] = "not adjusted: no maplet registered two of the images"
    else:
        try:
            result = adjust_poses(views, shape, pose_model=_pose_model(knowledge, views), anchor=True,
                                  landmarks=landmarks,
                                  surface=None if spots is None else _surface(spots, knowledge, views, shape),
                                  config=config)
        except ValueError as exc:
            feedback["note"] = f"not adjusted: {exc}"
        else:
            stats = result.stats
            feedback.update(note="adjusted",
                            los_posterior_px=float(np.median([result.sigmas[v.name][1].los_px for v in views])),
                            feature_tracks=stats["feature_tracks"], residual_rms_px=stats["residual_rms_px"],
                            seconds=stats["seconds"], anchor_shift_m=stats["anchor_shift_m"],
                            unknowns=stats.get("unknowns", []),
                            **{key: stats[key] for key in TIE_FIGURES if key in stats})
    with session_scope(sessions) as session:
        if result is not None:
            now = utcnow()
            for image in session.scalars(select(Image).where(Image.id.in_(ids))):
                name = image.lidvid
                _store_correction(image, result.corrections[name], replace=True)
                prior, posterior = result.sigmas[name]
                image.pose_sigma = {"prior": prior.as_dict(), "posterior": posterior.as_dict(),
                                    "knowledge": format_knowledge_errors(knowledge)}
                image.pose_corrected_at = now
                image.coverage_computed_at = None  # weighed again with the corrected pose
        report.setdefault("knowledge", format_knowledge_errors(knowledge))
        report.setdefault("source", source)
        report["feedback"] = feedback
        session.get_one(Downlink, downlink_id).pose_adjustment = report
    log.info("downlink %d: registrations fed back (%d landmarks): %s; line of sight %.2f -> %s px", downlink_id,
             landmarks.n_points, feedback["note"], feedback["los_before_px"],
             f"{feedback['los_posterior_px']:.2f}" if "los_posterior_px" in feedback else "-")
    return ids if result is not None else []


def fed_back(session: Session, downlink_id: int) -> bool:
    """Whether `feed_back_registrations` corrected the downlink's poses."""
    report = session.get_one(Downlink, downlink_id).pose_adjustment or {}
    return bool(report.get("feedback", {}).get("note") == "adjusted")


def landmark_tracks(session: Session, index: dict[str, int]) -> Tracks:
    """The maplets' landmarks as tracks over the images named in `index` (name: its index): for
    each maplet that two of them weigh into, where its current revision registered each of them
    (pwm.pipeline.landmark_pixels)."""
    maplet_ids = select(Coverage.maplet_id).join(Image, Image.id == Coverage.image_id).where(
        Image.lidvid.in_(list(index)), Coverage.weight > 0)
    revisions = session.scalars(select(MapletRevision.statistics).join(
        Maplet, Maplet.current_revision_id == MapletRevision.id).where(Maplet.id.in_(maplet_ids)).order_by(Maplet.id))
    point: list[int] = []
    image: list[int] = []
    xy: list[list[float]] = []
    landmark = 0
    for statistics in revisions:
        seen = [(index[name], at) for name, at in (statistics.get("registrations") or {}).items() if name in index]
        if len(seen) < 2:
            continue
        for k, at in seen:
            point.append(landmark)
            image.append(k)
            xy.append(at)
        landmark += 1
    return Tracks(point=np.asarray(point, np.int64), image=np.asarray(image, np.int64),
                  xy=np.asarray(xy, float).reshape(-1, 2))


def _pose_model(knowledge: KnowledgeErrors, views: list[View]) -> PoseModel:
    if isinstance(knowledge, NavigationErrors):
        return navigation_poses(np.array([v.et for v in views]), [v.pose for v in views], knowledge)
    return free_poses(len(views), sigma_position_km=knowledge.position_m * 1e-3,
                      sigma_pointing_rad=knowledge.pointing_rad)


def _surface(spots_km: np.ndarray, knowledge: KnowledgeErrors, views: list[View], shape: Mesh) -> MeasuredSurface:
    """The lidar's spots as a surface to tie the images' points to, its frame placed as well as
    the same knowledge places the spacecraft (pwm.knowledge.shared_frame_sigma, at the views'
    median range and the shape's mean radius)."""
    frame_km, frame_rad = shared_frame_sigma(knowledge, range_km=float(np.median([_range(v, shape) for v in views])),
                                             radius_km=float(np.linalg.norm(shape.vertices, axis=1).mean()))
    return MeasuredSurface(spots_km=spots_km, frame_km=frame_km, frame_rad=frame_rad)


def _range(view: View, shape: Mesh) -> float:
    """Distance (km) from a view to the body's centre less the shape's mean radius: the range
    to the ground near its boresight, without tracing."""
    return max(float(np.linalg.norm(view.pose.position) - np.linalg.norm(shape.vertices, axis=1).mean()), 1e-3)


def _store_correction(image: Image, new: PoseCorrection, *, replace: bool = False) -> None:
    """Compose `new` (estimated about the image's corrected pose) onto its stored correction:
    positions add; rotations compose as R(total) = R(new) R(stored), so that
    rotation @ R(total)^T = (rotation @ R(stored)^T) @ R(new)^T (pwm.camera.corrected_pose).
    replace: `new` was estimated about the kernels' pose, and replaces the stored one."""
    stored = image.pose_correction()
    if replace or stored is None:
        stored = PoseCorrection(position_km=(0.0, 0.0, 0.0), rotation_rad=(0.0, 0.0, 0.0))
    dp = np.asarray(stored.position_km) + np.asarray(new.position_km)
    w = (Rotation.from_rotvec(np.asarray(new.rotation_rad))
         * Rotation.from_rotvec(np.asarray(stored.rotation_rad))).as_rotvec()
    image.pose_dx_km, image.pose_dy_km, image.pose_dz_km = map(float, dp)
    image.pose_rx_rad, image.pose_ry_rad, image.pose_rz_rad = map(float, w)
