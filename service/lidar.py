"""The lidar stage on the catalog: each catalogued track strip-adjusted to a published version
(pwm.lidar.strips.adjust, the model kept: one round of robust point-to-plane ICP per track, to
convergence), its correction and 1 sigma stored on its row (service.rows.LidarTrack), and the
tracks' residuals on that version measured with the corrections applied
(service.publish.lidar_statistics). The shots stay as ingest placed them (the artifact store's
shots file); a track's spots are re-placed by its stored correction wherever they are read.

When it runs is the conductor's rule (service.conductor.adjust_lidar). Lengths in km, angles in
radians, body-fixed frame.
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

from pwm.io.lidar import read_shots
from pwm.lidar.config import LIDAR, LidarConfig
from pwm.lidar.strips import adjust
from service.artifacts import artifact_path
from service.db import session_scope
from service.publish import lidar_statistics
from service.rows import Acceptance, LidarProduct, utcnow
from service.versions import get_version, version_mesh

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
        query = select(LidarProduct).where(LidarProduct.status == Acceptance.ACCEPTED,
                                           LidarProduct.shots_artifact.is_not(None))
        if product_ids is not None:
            query = query.where(LidarProduct.id.in_(list(product_ids)))
        products = session.scalars(query.order_by(LidarProduct.id)).all()
        if not products:  # a catalog without lidar reads no mesh
            return None
        mesh = version_mesh(data_dir, get_version(session, version))
        corrected = uncorrected = 0
        largest = 0.0
        for product in products:
            if product.shots_artifact is None or not product.tracks:  # none, by the query; no valid shot
                continue
            shots, _ = read_shots(artifact_path(data_dir, product.shots_artifact, verify=True))
            adjustment = adjust(shots, mesh, config=config, rebuild=False)
            for row in product.tracks:
                correction = adjustment.corrections.get(row.track)
                if correction is None or not np.isfinite(correction.sigma).any():
                    uncorrected += 1  # too few shots met the model: not measured, nothing stored
                    continue
                row.rotation_x_rad, row.rotation_y_rad, row.rotation_z_rad = map(float, correction.rotation_rad)
                row.translation_x_km, row.translation_y_km, row.translation_z_km = map(
                    float, correction.translation_km)
                row.about_x_km, row.about_y_km, row.about_z_km = map(float, correction.about_km)
                row.correction_sigma = [float(s) if np.isfinite(s) else None for s in correction.sigma]
                row.adjusted_at = utcnow()
                corrected += 1
                largest = max(largest, correction.change_km(None))
        if not corrected + uncorrected:
            return None
        session.flush()
        figures = lidar_statistics(session, data_dir=data_dir, mesh=mesh, version=version)
    report = LidarAdjustment(version=version, tracks=corrected, uncorrected=uncorrected, largest_km=largest,
                             rms_km=None if figures is None else figures["rms_km"],
                             seconds=time.perf_counter() - clock)
    log.info("%s", report.summary())
    return report


def products_of(session: Session, downlink_id: int) -> list[int]:
    """The ids of a downlink's accepted lidar products."""
    return list(session.scalars(select(LidarProduct.id).where(LidarProduct.downlink_id == downlink_id,
                                                              LidarProduct.status == Acceptance.ACCEPTED)))
