"""The lidar stage on the catalog: each catalogued track strip-adjusted to a published version
(pwm.lidar.strips.adjust, the model kept: one round of robust point-to-plane ICP per track, to
convergence), its correction and 1 sigma stored on its row (service.rows.LidarTrack), and the
tracks' residuals on that version measured with the corrections applied
(service.publish.lidar_statistics). The shots stay as ingest placed them (the artifact store's
shots file); wherever they are read, they are placed again with the spacecraft positions the
images of their time were corrected to (service.lidar_shots.placed_shots), and a track's spots by its
stored correction.

When it runs is the conductor's rule (service.conductor.adjust_lidar). And where the catalog
has no model, the lidar may start one (`start_from_lidar`): a closed model of the catalogued
spots (pwm.lidar.model.model_from_spots), strip-adjusted to itself (pwm.lidar.strips.adjust, the
model rebuilt each round), published as a version of kind `lidar`: the first where the images
cannot make one, or the one after the images' own start where it is the better founded of the
two (`finer_start`). Lengths in km, angles in radians, body-fixed frame.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from pwm.lidar.config import LIDAR, LidarConfig
from pwm.lidar.model import usable
from pwm.lidar.shots import Shots
from pwm.lidar.strips import Correction, adjust
from pwm.lidar.tracks import NO_TRACK
from pwm.mesh import Mesh
from service.db import session_scope
from service.lidar_shots import placed_shots, usable_lidar_products
from service.publish import lidar_statistics
from service.rows import Acceptance, Downlink, LidarProduct, LidarTrack, ModelKind
from service.versions import get_version, latest_version, publication_lock, publish_version, version_mesh

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LidarAdjustment:
    """What one strip adjustment did: the version the tracks were registered to, the tracks
    corrected (and those too short or too far off the model to be), the largest correction
    (km, pwm.lidar.strips.Correction.change_km from none), the residual RMS of the adjusted
    spots on the version (km; None without a measured spot) and the seconds taken."""

    version: int
    tracks: int
    uncorrected: int
    largest_km: float
    rms_km: float | None
    seconds: float

    def summary(self) -> str:
        rms = "-" if self.rms_km is None else f"{self.rms_km * 1e3:.2f} m"
        return (f"lidar: {self.tracks} tracks strip-adjusted to version {self.version} ({self.uncorrected} left "
                f"uncorrected), largest correction {self.largest_km * 1e3:.2f} m, residual RMS {rms}; "
                f"{self.seconds:.1f} s")


def adjust_tracks(sessions: sessionmaker[Session], *, data_dir: Path, version: int,
                  product_ids: Collection[int] | None = None, config: LidarConfig = LIDAR) -> LidarAdjustment | None:
    """Strip-adjust the tracks of the accepted lidar products (of product_ids, or all) to
    `version`'s mesh, store each track's correction and sigma (unconstrained parts null), and
    measure the tracks' residuals on it (service.publish.lidar_statistics, which records them on
    the rows). None where there is no track to adjust."""
    clock = time.perf_counter()
    with session_scope(sessions) as session:
        products = usable_lidar_products(session, product_ids)
        if not products:  # a catalog without lidar reads no mesh
            return None
        mesh = version_mesh(data_dir, get_version(session, version))
        corrected = uncorrected = 0
        largest = 0.0
        for product in products:
            if product.shots_artifact is None or not product.tracks:  # none, by the query; no valid shot
                continue
            shots, _ = placed_shots(session, data_dir, product)
            adjustment = adjust(shots, mesh, config=config, rebuild=False)
            for row in product.tracks:
                change = _store(row, adjustment.corrections.get(row.track))
                corrected += change is not None
                uncorrected += change is None
                largest = max(largest, change or 0.0)
        if not corrected + uncorrected:
            return None
        session.flush()
        figures = lidar_statistics(session, data_dir=data_dir, mesh=mesh, version=version)
    report = LidarAdjustment(version=version, tracks=corrected, uncorrected=uncorrected, largest_km=largest,
                             rms_km=None if figures is None else figures["rms_km"],
                             seconds=time.perf_counter() - clock)
    log.info("%s", report.summary())
    return report


def _store(row: LidarTrack, correction: Correction | None) -> float | None:
    """Store a track's correction and sigma on its row; how far it moves the track (km), or None
    (and nothing stored) where too few shots met the model."""
    if correction is None or not np.isfinite(correction.sigma).any():
        return None
    row.store_strip_correction(correction)
    return correction.change_km(None)


def start_from_lidar(sessions: sessionmaker[Session], *, data_dir: Path, downlink_id: int,
                     over: int | None = None, config: LidarConfig = LIDAR) -> int | None:
    """A start from the lidar (the module's docstring): a closed model of every accepted lidar
    product's spots (one body-fixed frame), strip-adjusted to itself, its tracks' corrections
    stored, published as the next version (kind lidar). Made where the catalog has no model
    version (over None), or where its only one is the photogrammetric start the images just made
    from nothing (over: its number), and then published, and started from, only where it is the
    better founded (`finer_start`); the choice goes into the downlink's model_note and the
    version's statistics either way. Its number, or None where it is not made, not chosen, or the
    catalog has no lidar or its spots do not enclose the body (the model_note then adds why)."""
    with session_scope(sessions) as session:
        publication_lock(session)
        latest = latest_version(session)
        # only over this downlink's own start from its images (not over one another ingest made meanwhile)
        if latest is not None and (latest.version != over or latest.kind is not ModelKind.PHOTOGRAMMETRIC
                                   or downlink_id not in {d.id for d in latest.downlinks}):
            return None
        products = usable_lidar_products(session)
        parts = [placed_shots(session, data_dir, p) for p in products]
        if not parts:
            return None
        downlink = session.get_one(Downlink, downlink_id)
        try:
            shots = Shots.joined([part for part, _ in parts])
            adjustment = adjust(shots, config=config)
        except ValueError as exc:
            _note(downlink, f"no model from the lidar: {exc}")
            return None
        spots = int(usable(shots).sum())
        choice = None
        if latest is not None:
            choice = finer_start(images=version_mesh(data_dir, latest), points=int(latest.statistics.get("points", 0)),
                                 lidar=adjustment.model, spots=spots)
            if choice["chosen"] != "lidar":
                _note(downlink, f"the start stays version {latest.version}: {choice['why']}")
                latest.statistics = {**latest.statistics, "start_choice": choice}
                return None
        tracks = corrected = 0
        start = 0
        for product, (_, track) in zip(products, parts, strict=True):
            # the adjustment numbers the tracks of all the products together: a catalogued track
            # is the one most of its shots fell in
            theirs = adjustment.track[start:start + len(track)]
            start += len(track)
            for row in product.tracks:
                tracks += 1
                ids, counts = np.unique(theirs[(track == row.track) & (theirs != NO_TRACK)], return_counts=True)
                correction = adjustment.corrections.get(int(ids[np.argmax(counts)])) if len(ids) else None
                corrected += _store(row, correction) is not None
        session.flush()
        # checked against the adjusted spots as the version it is about to be (none after it, under the lock)
        number = 1 if latest is None else latest.version + 1
        figures = lidar_statistics(session, data_dir=data_dir, mesh=adjustment.model, version=number)
        version = publish_version(session, data_dir=data_dir, mesh=adjustment.model, kind=ModelKind.LIDAR,
                                  parent=latest,
                                  statistics={"products": len(products), "shots": spots, "tracks": tracks,
                                              "tracks_corrected": corrected, "loop_changes_km": adjustment.changes,
                                              "converged": adjustment.converged,
                                              **({"start_choice": choice} if choice is not None else {}),
                                              **({"lidar": figures} if figures is not None else {})},
                                  downlinks=[downlink])
        if choice is None:
            downlink.model_note = None
            _note(downlink, f"version {version.version} (lidar) made from the lidar, with no model before and none "
                            "from the images")
        else:
            _note(downlink, f"version {version.version} (lidar) made from the lidar is the start: {choice['why']}")
        return version.version


def finer_start(*, images: Mesh, points: int, lidar: Mesh, spots: int) -> dict:
    """Which of two starts from nothing is the better founded: the one whose measurements sample
    the body more finely (the square root of its model's area over their count), the images'
    stereo points or the lidar's spots. Both are closed models of the whole body; what holds a
    start's shape between its samples is only interpolation, which the refinement must then
    undo, and a start's placement is as good as its samples' (the lidar's by range, the images'
    by their poses). {"chosen": "lidar" | "images", "images_spacing_m", "lidar_spacing_m", "why"}."""
    def spacing_m(mesh: Mesh, count: int) -> float:
        return float(np.sqrt(mesh.face_areas().sum() / count) * 1e3) if count > 0 else float("inf")

    image_spacing, lidar_spacing = spacing_m(images, points), spacing_m(lidar, spots)
    chosen = "lidar" if lidar_spacing < image_spacing else "images"
    finer, coarser = ("the lidar's", "the images'") if chosen == "lidar" else ("the images'", "the lidar's")
    why = (f"{finer} measurements sample the body more finely than {coarser} ({spots} spots every "
           f"{lidar_spacing:.1f} m, {points} stereo points every {image_spacing:.1f} m)")
    return {"chosen": chosen, "why": why, **{key: value if np.isfinite(value) else None for key, value in
                                            (("images_spacing_m", image_spacing), ("lidar_spacing_m", lidar_spacing))}}


def _note(downlink: Downlink, note: str) -> None:
    """Add to a downlink's model_note."""
    downlink.model_note = f"{downlink.model_note}; {note}" if downlink.model_note else note
    log.info("downlink %d: %s", downlink.id, note)


def products_of(session: Session, downlink_id: int) -> list[int]:
    """The ids of a downlink's accepted lidar products."""
    return list(session.scalars(select(LidarProduct.id).where(LidarProduct.downlink_id == downlink_id,
                                                              LidarProduct.status == Acceptance.ACCEPTED)))
