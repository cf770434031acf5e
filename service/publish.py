"""Incremental fusion of the maplets' current revisions into a new model version.

The parent is the latest version. Its "grid" artifact holds the fusion sums of each level of
maplets (pwm.levels.LevelGrids) of the revisions in its lineage; the maplets whose current
revision differs from the parent's have their old revision subtracted and their new one added,
and the rest of the sums are left as they are. A parent without a grid (a start, imported or
photogrammetric model) starts an empty one. The base is the nearest version up the lineage
without a grid, the model that the refinements started from: the coarsest level is one closed
surface that the base closes where its lattice is affordable over the whole body (pwm.volume),
else laid onto the base (pwm.volume.grid_for chooses); each finer level is laid onto the surface
below it (pwm.levels), so a closed base gives a closed model (a base of a body and patches beside
it is sealed first, pwm.levels.sealed). The parent's "composition" artifact says how its
surface was made: while the closed levels' sums and the base are the same, that surface is not
made again, and the laid levels' regions that no changed maplet touches keep the parent's faces.
A closed level whose lattice spans more than a block is fused in blocks (pwm.blocks), whose
files the version keeps (service.fusion_blocks): the next fusion over the same base makes again
only the blocks about the maplets that changed.

All of it runs under the publication lock (service.versions.publication_lock), taken before the
parent is read, so two fusions never build on the same parent. Publication only publishes: what
is made from a version for its readers (the console's documents, exports) is made by their own
modules, after publication or on request.

Each version is checked against the catalog's lidar (`lidar_statistics`): a uniform sample of
its usable shots (PWM_LIDAR_RESIDUAL_SHOTS), each track's strip correction applied where it was
adjusted, gives the version's statistics "lidar" (pwm.lidar.model.residual_summary) and each
track's residuals on it.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session, selectinload, sessionmaker

import pwm
from pwm.blocks import FILES, mesh_in_blocks
from pwm.config import BLOCKS, DEFAULTS, FusionBlocks, RefinementConfig
from pwm.io.fusion_state import BlockFiles, read_composition, read_levels, write_composition, write_levels
from pwm.levels import LevelGrids
from pwm.lidar.config import LIDAR, LidarConfig
from pwm.lidar.model import disagreement, residual_summary, sample_shots, spot_normals, usable
from pwm.lidar.shots import Shots
from pwm.lidar.tracks import NO_TRACK, crossovers
from pwm.mesh import Mesh
from pwm.tiling import level_of
from pwm.uncertainty import sigma_summary, vertex_sigma
from pwm.volume import DistanceGrid
from service.artifacts import artifact_path
from service.db import session_scope
from service.fusion_blocks import Layout, carry_blocks, keep_blocks, working_folder
from service.jobs import refined_downlinks
from service.lidar_shots import adjusted_shots, usable_lidar_products
from service.refinement import load_revision_maplet
from service.rows import (
    Downlink,
    Maplet,
    MapletRevision,
    ModelKind,
    ModelVersion,
    model_version_downlinks,
)
from service.settings import get_settings
from service.versions import latest_version, publication_lock, publish_version, version_mesh

log = logging.getLogger(__name__)


def fuse_and_publish(sessions: sessionmaker[Session], *, data_dir: Path, downlink_ids: Sequence[int] = (),
                     config: RefinementConfig = DEFAULTS, blocks: FusionBlocks = BLOCKS) -> int | None:
    """Fuse the maplets' current revisions into the latest version and publish the result as a
    new version (kind refined); its number, or None when no maplet's current revision differs
    from the latest version's (nothing is published then).

    config.overlap: the maplets' overlap, over which fusion tapers their weights. blocks: how a
    closed level too large for one block is fused in blocks (pwm.blocks); a smaller one is fused
    whole, as before.
    Lineage: the parent, the maplet revisions fused, the parent's downlinks plus downlink_ids
    and the downlinks whose refine jobs made the revisions changed (service.jobs
    .refined_downlinks).
    Statistics: maplets changed, added, replaced and fused in all, images used, whether the
    parent's sums were reused, the base version, the coarsest level's surface ("closed" or
    "laid"), voxels, each level's surface, voxel size and voxels, how the surface was
    composed (regions laid and carried over, whether the closed levels' surface was made again),
    the 1-sigma heights (`pwm.uncertainty.sigma_summary`; each vertex's in the mesh, from every
    current maplet's, pwm.uncertainty.vertex_sigma), the block files kept with it and how many
    of them were written rather than carried from the parent ("blocks", where it was fused in
    blocks), and seconds; with the mesh's own
    (service.versions.mesh_statistics: size, closure checks and mass properties).
    """
    clock = time.perf_counter()
    with session_scope(sessions) as session:
        publication_lock(session)
        parent = latest_version(session)
        if parent is None:
            raise LookupError("the catalog has no model version to fuse into")
        used = {r.maplet_id: r for r in parent.maplet_revisions}
        current = _current_revisions(session)
        changed = [r for m, r in current.items() if m not in used or used[m].id != r.id]
        gone = [r for m, r in used.items() if m not in current]
        if not changed and not gone:
            log.info("fusion: no maplet changed since version %d; nothing published",
                     parent.version)
            return None
        previous = None
        if "grid" in parent.artifacts:
            fusion = read_levels(artifact_path(data_dir, parent.artifacts["grid"], verify=True))
            if "composition" in parent.artifacts:
                previous = (version_mesh(data_dir, parent), read_composition(
                    artifact_path(data_dir, parent.artifacts["composition"], verify=True)))
            for old in [used[r.maplet_id] for r in changed if r.maplet_id in used] + gone:
                fusion.subtract(load_revision_maplet(data_dir, old))
            added = changed
        else:
            added = list(current.values())
            fusion = LevelGrids(taper_fraction=config.overlap)
        base = _base(parent)
        base_mesh = version_mesh(data_dir, base)
        # coarsest level first, which makes it the level fused over the base (pwm.levels); a
        # batch at a time from disk: a whole body's maplets need not fit in memory together
        level = {maplet_id: k for maplet_id, k in session.execute(select(Maplet.id, Maplet.level))}
        added = sorted(added, key=lambda r: (-level[r.maplet_id], r.maplet_id))
        fusion.add_all((load_revision_maplet(data_dir, r) for r in added), base=base_mesh)
        layout = _layout(fusion, base, blocks)
        with working_folder(data_dir) as folder:
            carried = {} if layout is None else carry_blocks(data_dir, parent, layout=layout,
                                                             into=folder / f"L{layout.level}")
            # a closed level whose lattice spans more than a block is fused in blocks, each level
            # in its own folder
            mesh, composition, laid = fusion.compose(base_mesh, previous=previous,
                                                     close=partial(_close, folder=folder, blocks=blocks))
            manifest, kept = (None, None) if layout is None else keep_blocks(
                data_dir, folder / f"L{layout.level}", carried, layout=layout, manifest=folder / "blocks.json")
            sigma = vertex_sigma(mesh.vertices, (load_revision_maplet(data_dir, r) for r in current.values()),
                                 taper_fraction=config.overlap)
            mesh = dataclasses.replace(mesh, sigma=sigma)
            # in the working folder, which the next fusion clears if this one is killed
            scratch = {"grid": folder / "grid.npz", "composition": folder / "composition.npz"}
            if manifest is not None:
                scratch["blocks"] = manifest
            write_levels(scratch["grid"], fusion)
            write_composition(scratch["composition"], composition)
            downlinks = {d.id: d for d in parent.downlinks}
            # Every downlink whose refinements this version carries, besides those asked for: a
            # fusion may take up revisions whose own downlink's fusion has not run yet.
            for downlink_id in sorted(set(downlink_ids) | refined_downlinks(session, changed)):
                if downlink_id not in downlinks:
                    downlinks[downlink_id] = session.get_one(Downlink, downlink_id)
            images = {name for r in current.values() for name in r.statistics.get("images", [])}
            levels = fusion.describe()
            statistics = {
                "maplets_changed": len(changed), "maplets_added": sum(r.maplet_id not in used
                                                                      for r in changed),
                "maplets_replaced": sum(r.maplet_id in used for r in changed),
                "maplets_removed": len(gone), "maplets_fused": len(current), "images": len(images),
                "incremental": "grid" in parent.artifacts, "base_version": base.version,
                "surface": next(iter(levels.values()))["surface"], "voxels": fusion.voxels, "levels": levels,
                "composition": {"regions_laid": laid.regions_laid, "regions_carried": laid.regions_carried,
                                "closed_levels_made": laid.below_made},
                "height_sigma": sigma_summary(sigma), "fusion_seconds": time.perf_counter() - clock}
            if kept is not None and kept["files"]:
                statistics["blocks"] = kept
            lidar = lidar_statistics(session, data_dir=data_dir, mesh=mesh, version=parent.version + 1)
            if lidar is not None:
                statistics["lidar"] = lidar
            version = publish_version(session, data_dir=data_dir, mesh=mesh, kind=ModelKind.REFINED,
                                      parent=parent, statistics=statistics,
                                      extra_artifacts=scratch,
                                      maplet_revisions=current.values(),
                                      downlinks=downlinks.values())
            log.info("fusion: version %d from version %d, %d of %d maplets changed (%.1f s)",
                     version.version, parent.version, len(changed), len(current),
                     time.perf_counter() - clock)
            return version.version


def lidar_statistics(session: Session, *, data_dir: Path, mesh: Mesh, version: int,
                     at_most: int | None = None, config: LidarConfig = LIDAR) -> dict | None:
    """The lidar statistics of `mesh`, about to be published as `version`: at most `at_most`
    (default PWM_LIDAR_RESIDUAL_SHOTS) of the catalog's usable shots, sampled uniformly over
    its accepted lidar products, each track's correction applied where adjusted, measured
    against the mesh (pwm.lidar.model.residual_summary; tracks by their catalog id), and the
    crossovers between the tracks (`_crossovers`: in all, and per track their count and height
    RMS), and how far each track disagrees with the mesh in its own sigmas
    (pwm.lidar.model.disagreement), those beyond config.disagree_sigmas listed as disagreeing
    rather than averaged in silently; each track's figures stored on its row with the version.
    None where the catalog has no usable shot (or none is to be checked)."""
    at_most = get_settings().lidar_residual_shots if at_most is None else at_most
    products = usable_lidar_products(session)
    total = sum(p.valid_shots for p in products)
    if not total or not at_most:
        return None
    parts, ids, rows = [], [], {}
    for product in products:
        if product.shots_artifact is None:  # none, by the query
            continue
        shots, track = adjusted_shots(session, data_dir, product)
        mine = {t.track: t for t in product.tracks}
        pick = sample_shots(usable(shots), round(at_most * product.valid_shots / total), seed=product.id)
        parts.append(shots.take(pick))
        ids.append(np.array([mine[t].id if t in mine else NO_TRACK for t in track[pick]], dtype=np.int64))
        rows.update({row.id: row for row in mine.values()})
    sample = Shots.joined(parts)
    track_ids = np.concatenate(ids)
    summary = residual_summary(sample, mesh, track_ids)
    crossing = _crossovers(sample, track_ids)
    flagged = []
    for key, figures in summary["tracks"].items():
        row = rows[int(key)]
        row.residual_mean_km, row.residual_rms_km = figures["mean_km"], figures["rms_km"]
        row.residual_p95_km, row.residual_version = figures["p95_km"], version
        figures["crossovers"], figures["crossover_rms_km"] = crossing.get(int(key), (0, None))
        correction = row.strip_correction()
        figures["disagreement_sigmas"] = disagreement(figures, None if correction is None
                                                      else correction.placement_km)
        if (figures["disagreement_sigmas"] or 0.0) > config.disagree_sigmas:
            flagged.append(row.id)
    for row in rows.values():  # a track with no measured spot may still cross others
        row.crossovers, row.crossover_rms_km = crossing.get(row.id, (0, None))
    return summary | {"products": len(products), "usable_shots": total,
                      "crossovers": sum(n for n, _ in crossing.values()) // 2,
                      "disagree_sigmas": config.disagree_sigmas, "disagreeing_tracks": sorted(flagged)}


def _crossovers(shots: Shots, track: np.ndarray) -> dict[int, tuple[int, float | None]]:
    """Per track (by id): how many crossovers with other tracks its spots make
    (pwm.lidar.tracks.crossovers, corrections applied, the normals from the spots themselves:
    the tracks' agreement, whatever the model) and the RMS of their height differences (km)."""
    spots = shots.spots_km()
    if len(spots) < 3:
        return {}
    found = crossovers(spots, track, spot_normals(spots, shots.origin_km))
    ends = np.concatenate([track[found.first], track[found.second]])
    heights = np.concatenate([found.height_km, found.height_km])
    return {int(t): (int((ends == t).sum()), float(np.sqrt(np.mean(heights[ends == t] ** 2))))
            for t in np.unique(ends)}


def first_version_with(session: Session, *, downlink_id: int) -> int | None:
    """The first version whose lineage names the downlink, or None."""
    return session.scalar(select(func.min(ModelVersion.version)).join(
        model_version_downlinks, model_version_downlinks.c.model_version_id == ModelVersion.id)
        .where(model_version_downlinks.c.downlink_id == downlink_id))


def _layout(fusion: LevelGrids, base: ModelVersion, blocks: FusionBlocks) -> Layout | None:
    """The layout of the blocks kept with the version (service.fusion_blocks): those of the
    coarsest level, where it is closed over the base (a finer closed level closes over a
    surface that changes, so its blocks are made afresh each time); None where it is not."""
    held = fusion.held
    if not held or not isinstance(fusion.grids[held[0]], DistanceGrid):
        return None
    return Layout(base_version=base.version, level=held[0], voxel_km=fusion.grids[held[0]].voxel_km,
                  cells=blocks.cells, margin=blocks.margin, code=pwm.__version__, files=FILES)


def _close(grid: DistanceGrid, below: Mesh, *, folder: Path, blocks: FusionBlocks) -> Mesh:
    """A closed level's surface over the one below, in blocks kept in the level's own folder
    (pwm.blocks.mesh_in_blocks)."""
    store = BlockFiles(folder / f"L{int(level_of(grid.voxel_km))}")
    return mesh_in_blocks(grid, below, store=store, blocks=blocks)


def _current_revisions(session: Session) -> dict[int, MapletRevision]:
    """Each maplet's current revision, by maplet id."""
    rows = session.scalars(select(Maplet).where(Maplet.current_revision_id.is_not(None))
                           .options(selectinload(Maplet.current_revision)).order_by(Maplet.id))
    return {m.id: m.current_revision for m in rows if m.current_revision is not None}  # all, by the query


def _base(version: ModelVersion) -> ModelVersion:
    """The nearest version up the lineage (this one included) that has no fusion sums."""
    while "grid" in version.artifacts and version.parent is not None:
        version = version.parent
    return version
