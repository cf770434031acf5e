"""The catalog's lidar shots as they are placed now, which every stage that reads them shares:
the usable products, their shots placed with the spacecraft's trajectory as the images of their
time corrected it (`placed_shots`), with each track's strip correction too (`adjusted_shots`),
and the spots of the tracks a strip adjustment placed (`catalog_spots`). The shots stay as
ingest stored them (the artifact store's shots file); these readings follow every later
correction. Lengths in km, body-fixed frame.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Sequence
from pathlib import Path

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from pwm.io.lidar import read_shots
from pwm.lidar.model import usable
from pwm.lidar.shots import Shots
from pwm.lidar.strips import apply_corrections
from pwm.trajectory import ARC_GAP_S, along_arcs
from service.artifacts import artifact_path
from service.rows import Acceptance, Image, ImageStatus, LidarProduct


def usable_lidar_products(session: Session, product_ids: Collection[int] | None = None) -> Sequence[LidarProduct]:
    """The accepted lidar products (of product_ids, or all) with valid shots stored, by id."""
    query = select(LidarProduct).where(LidarProduct.status == Acceptance.ACCEPTED, LidarProduct.valid_shots > 0,
                                       LidarProduct.shots_artifact.is_not(None))
    if product_ids is not None:
        query = query.where(LidarProduct.id.in_(list(product_ids)))
    return session.scalars(query.order_by(LidarProduct.id)).all()


def placed_shots(session: Session, data_dir: Path, product: LidarProduct) -> tuple[Shots, np.ndarray]:
    """A lidar product's shots placed with the spacecraft's corrected trajectory, and each shot's
    track number: as ingest stored them (through the kernels), each origin moved by the position
    corrections the catalog's images of that time carry (their stored pose corrections,
    interpolated in time within the images' navigation arcs, pwm.trajectory.along_arcs), since
    the spacecraft that carries the lidar is the one the images' positions were corrected for.
    Only the position: a camera's pointing correction holds its own misalignment, which the
    lidar does not share. Read again whenever the images' poses change, the spots follow."""
    if product.shots_artifact is None:
        raise ValueError(f"lidar product {product.id} has no shots stored")
    shots, track = read_shots(artifact_path(data_dir, product.shots_artifact, verify=True))
    if not len(shots) or product.start_et is None or product.stop_et is None:
        return shots, track
    images = session.execute(select(Image.start_et, Image.stop_et, Image.pose_dx_km, Image.pose_dy_km,
                                    Image.pose_dz_km).where(
        Image.status == ImageStatus.ACCEPTED, Image.pose_corrected_at.is_not(None),
        Image.start_et.is_not(None), Image.stop_et.is_not(None),
        Image.start_et <= product.stop_et + ARC_GAP_S, Image.stop_et >= product.start_et - ARC_GAP_S)).all()
    if not images:
        return shots, track
    # start, stop (none null, by the query) and the position correction (a component not set is 0)
    table = np.array([[start, stop, dx or 0.0, dy or 0.0, dz or 0.0] for start, stop, dx, dy, dz in images], float)
    shift = along_arcs(shots.et, table[:, :2].mean(axis=1), table[:, 2:])
    return dataclasses.replace(shots, origin_km=shots.origin_km + shift), track


def adjusted_shots(session: Session, data_dir: Path, product: LidarProduct) -> tuple[Shots, np.ndarray]:
    """A lidar product's shots placed (`placed_shots`), each track's stored strip correction
    applied (service.rows.LidarTrack.strip_correction), and each shot's track number."""
    shots, track = placed_shots(session, data_dir, product)
    return apply_corrections(shots, track, {row.track: c for row in product.tracks
                                            if (c := row.strip_correction()) is not None}), track


def catalog_spots(session: Session, *, data_dir: Path) -> np.ndarray | None:
    """The usable spots (km, body-fixed) of the catalogued tracks that a strip adjustment placed
    (their stored corrections applied): the surface the lidar measured, which the images'
    adjustment ties its points to (service.spg, pwm.spg.ties). None where there is none."""
    parts = []
    for product in usable_lidar_products(session):
        shots, track = adjusted_shots(session, data_dir, product)
        placed = np.isin(track, [row.track for row in product.tracks if row.strip_correction() is not None])
        parts.append(shots.spots_km()[usable(shots) & placed])
    spots = np.concatenate(parts) if parts else np.zeros((0, 3))
    return spots if len(spots) else None
