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
from pwm.lidar.strips import Correction, apply_corrections, corrected_spots
from pwm.maplets import Spots
from pwm.trajectory import ARC_GAP_S, along_arcs
from service.artifacts import artifact_path
from service.rows import Acceptance, Image, ImageStatus, LidarProduct, LidarTrack


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


def tracks_over(session: Session, maplets: Sequence[tuple[int, np.ndarray, float]]) -> dict[int, list[LidarTrack]]:
    """Per maplet (id, body-fixed origin km, side km), the strip-corrected tracks of the usable
    products whose cone of spots about the body's centre (service.rows.LidarTrack) reaches its
    square, by product and track: a superset of the tracks with spots over it, as
    service.queries.maplets_crossed finds them. Maplets no track reaches are left out."""
    tracks = [row for product in usable_lidar_products(session) for row in product.tracks
              if row.adjusted_at is not None]
    if not tracks or not maplets:
        return {}
    axes = np.array([[t.cone_axis_x, t.cone_axis_y, t.cone_axis_z] for t in tracks], float)
    half_angle = np.array([t.cone_half_angle_rad for t in tracks], float)
    origin = np.array([m[1] for m in maplets], float).reshape(-1, 3)
    distance = np.maximum(np.linalg.norm(origin, axis=1), 1e-300)
    reach = np.arcsin(np.clip(np.array([m[2] for m in maplets], float) / np.sqrt(2.0) / distance, 0.0, 1.0))
    angle = np.arccos(np.clip((origin / distance[:, None]) @ axes.T, -1.0, 1.0))
    within = angle <= half_angle[None, :] + reach[:, None]
    return {maplets[i][0]: [tracks[t] for t in np.flatnonzero(row)] for i, row in enumerate(within) if row.any()}


def track_key(track: LidarTrack) -> str:
    """A track's name in a maplet's input (service.refinement): its product's content and its
    number. Its strip correction is not in it: a later adjustment moves its spots within their
    sigma, and re-refining every maplet under a survey's rasters for that is not worth it."""
    return f"{track.product.sha256}:{track.track}"


def track_spots(session: Session, data_dir: Path, tracks: Sequence[LidarTrack]) -> Spots:
    """The usable spots of these strip-corrected tracks as placed now (`placed_shots`, their
    stored corrections applied), with their sigmas (pwm.lidar.strips.corrected_spots)."""
    wanted: dict[int, dict[int, Correction]] = {}
    for row in tracks:
        correction = row.strip_correction()
        if correction is not None:
            wanted.setdefault(row.product_id, {})[row.track] = correction
    spots, sigmas = [np.zeros((0, 3))], [np.zeros(0)]
    for product in usable_lidar_products(session, list(wanted)):
        shots, track = placed_shots(session, data_dir, product)
        own, sigma = corrected_spots(shots, track, wanted[product.id])
        spots.append(own)
        sigmas.append(sigma)
    return Spots(body_km=np.concatenate(spots), sigma_km=np.concatenate(sigmas))
