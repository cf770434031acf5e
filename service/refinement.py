"""Refinement driven by the catalog: which maplets need refining, and the refinement of one.

A maplet's input is the set of images its coverage rows weigh above zero (the refinement's own
rules, service.coverage), each with its pose correction, plus the refinement settings
(pwm.config.RefinementConfig.digest), the maplet's grid and the pass. Its input hash names that
input: a maplet whose current revision was made from other images is stale. Refining a maplet
stores a new revision, keyed by the input hash and recording the configuration's digest, so the
same input is never solved twice; the maplet's current revision moves to it while the hash is
still one of the maplet's inputs.

A changed configuration alone re-refines only when the operator asks (refine_on_config_change:
PWM_REFINE_ON_CONFIG_CHANGE, `pwm refine-catalog --because-config-changed`): otherwise a
revision made from the maplet's current images under the configuration it records is up to date
(`stale_maplets`), and `pwm downlinks` counts those maplets for the operator
(service.downlinks.other_configurations).

Passes, as `pwm refine` makes them: a maplet is refined from the same images config.passes
times, and up to config.max_passes while its last pass still changed it (RefinementConfig.
another_pass, on the revision's "changed_spacings"), each later pass against the model that fused
the pass before (pass p + 1 is due once the latest version holds the maplet's pass-p revision).
A new input starts again at pass 1.

The refinement itself is pwm.pipeline.refine_maplet, on the maplet's nodes at the heights of
the current model (the latest version), with visibility against that model.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Callable, Collection
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from pwm.config import DEFAULTS, RefinementConfig
from pwm.io.fusion_state import read_maplet, write_maplet
from pwm.maplets import MapletGrid, solution_change
from pwm.pipeline import refine_maplet
from pwm.raytrace import RayTracer
from pwm.tiling import sample_surface
from service.artifacts import artifact_mesh, artifact_path, scratch_file, store_artifact
from service.db import session_scope
from service.rows import (
    Coverage,
    GeometryStatus,
    Image,
    ImageStatus,
    Maplet,
    MapletRevision,
    model_version_maplet_revisions,
)
from service.versions import latest_version
from service.views import catalog_views

log = logging.getLogger(__name__)

_INSERT_ATTEMPTS = 5


@dataclass(frozen=True)
class MapletWork:
    """A maplet due for refinement: its id and name, the hash of its input now (of the pass
    due), how many images that input holds, and the pass (1 for a new input)."""

    maplet_id: int
    name: str
    input_hash: str
    images: int
    pass_number: int = 1


@dataclass(frozen=True)
class _Input:
    """A maplet's images (ids, and keys as input_hash takes them), its grid (nodes per side,
    side in km) and the input hash of each pass (pass 1 first) under one configuration."""

    image_ids: tuple[int, ...]
    image_keys: tuple[str, ...]
    grid: tuple[int, float]
    hashes: tuple[str, ...]

    def pass_of(self, input_hash: str | None) -> int | None:
        """The pass of this input that `input_hash` names, or None when it names another input."""
        return self.hashes.index(input_hash) + 1 if input_hash in self.hashes else None

    def under(self, digest: str) -> _Input:
        """The same images and grid under the configuration whose digest is `digest`, as many
        passes."""
        return replace(self, hashes=_pass_hashes(self.image_keys, self.grid, digest, len(self.hashes)))


def input_hash(image_keys: Collection[str], *, digest: str, nodes_per_side: int, size_km: float,
               pass_number: int = 1) -> str:
    """sha256 naming a refinement's input: the images' keys (sha256 of the product, with its
    pose correction), the refinement settings (`digest`, pwm.config.RefinementConfig.digest),
    the maplet's grid (nodes per side, side in km) and, after the first, the pass."""
    payload: dict[str, object] = {"images": sorted(image_keys), "config": digest,
                                  "nodes_per_side": nodes_per_side, "size_km": repr(float(size_km))}
    if pass_number > 1:
        payload["pass"] = pass_number
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _pass_hashes(image_keys: Collection[str], grid: tuple[int, float], digest: str, passes: int
                 ) -> tuple[str, ...]:
    return tuple(input_hash(image_keys, digest=digest, nodes_per_side=grid[0], size_km=grid[1],
                            pass_number=p) for p in range(1, passes + 1))


def _inputs(session: Session, config: RefinementConfig, maplet_ids: Collection[int] | None
            ) -> dict[int, _Input]:
    """The input of each maplet (of maplet_ids, or all) that some image weighs into."""
    query = (select(Coverage.maplet_id, Image.id, Image.sha256, Image.pose_dx_km,
                    Image.pose_dy_km, Image.pose_dz_km, Image.pose_rx_rad, Image.pose_ry_rad,
                    Image.pose_rz_rad)
             .join(Image, Image.id == Coverage.image_id)
             .where(Coverage.weight > 0, Image.status == ImageStatus.ACCEPTED,
                    Image.geometry_status == GeometryStatus.COMPUTED)
             .order_by(Coverage.maplet_id, Image.id))
    if maplet_ids is not None:
        query = query.where(Coverage.maplet_id.in_(list(maplet_ids)))
    images: dict[int, list[tuple[int, str]]] = {}
    for maplet_id, image_id, sha256, *pose in session.execute(query):
        # A pose correction changes what the image says about the maplet.
        key = sha256 + (f"@{','.join(repr(v) for v in pose)}"
                        if any(v is not None for v in pose) else "")
        images.setdefault(maplet_id, []).append((image_id, key))
    grids = dict((i, (n, s)) for i, n, s in session.execute(
        select(Maplet.id, Maplet.nodes_per_side, Maplet.size_km).where(
            Maplet.id.in_(list(images)))))
    digest = config.digest()
    inputs = {}
    for m, rows in images.items():
        keys = tuple(k for _, k in rows)
        inputs[m] = _Input(tuple(i for i, _ in rows), keys, grids[m],
                           _pass_hashes(keys, grids[m], digest, config.most_passes))
    return inputs


def stale_maplets(session: Session, *, config: RefinementConfig = DEFAULTS,
                  maplet_ids: Collection[int] | None = None,
                  refine_on_config_change: bool = False) -> list[MapletWork]:
    """The maplets (of maplet_ids, or all) with at least config.min_images images that are due
    for refinement, by id: at pass 1 when their current revision is of another input, at pass
    p + 1 when it is the pass-p revision of their input and the latest version fused it. A
    revision not fused yet is awaited: its next pass starts from the model that holds it.

    A current revision made with another configuration (its config_digest) from the maplet's
    current images, at any of its passes, is up to date: a changed configuration
    alone re-refines only with refine_on_config_change (then such a maplet is due at pass 1).
    Revisions made before digests were recorded (config_digest None) are of another input once
    the configuration changed: due, once."""
    inputs = _inputs(session, config, maplet_ids)
    latest = latest_version(session)
    held = model_version_maplet_revisions.c
    digest = config.digest()
    # whether the latest version holds the current revision, for these maplets alone
    rows = session.execute(
        select(Maplet.id, Maplet.name, MapletRevision.input_hash, MapletRevision.config_digest,
               held.maplet_revision_id.is_not(None), MapletRevision.statistics["changed_spacings"].as_float())
        .outerjoin(MapletRevision, MapletRevision.id == Maplet.current_revision_id)
        .outerjoin(model_version_maplet_revisions,
                   (held.maplet_revision_id == MapletRevision.id)
                   & (held.model_version_id == (None if latest is None else latest.id)))
        .where(Maplet.id.in_(list(inputs))).order_by(Maplet.id))
    work = []
    for m, name, current, made_with, fused, changed in rows:
        if len(inputs[m].image_ids) < config.min_images:
            continue
        # up to date under the configuration it was made with: the operator chooses when to change
        if (made_with not in (None, digest) and not refine_on_config_change
                and inputs[m].under(made_with).pass_of(current) is not None):
            continue
        done = inputs[m].pass_of(current)
        if done is not None and not (fused and config.another_pass(done=done, changed_spacings=changed)):
            continue
        due = 1 if done is None else done + 1
        work.append(MapletWork(maplet_id=m, name=name, input_hash=inputs[m].hashes[due - 1],
                               images=len(inputs[m].image_ids), pass_number=due))
    return work


def refine_catalog_maplet(sessions: sessionmaker[Session], *, data_dir: Path, maplet_id: int,
                          input_hash: str, config: RefinementConfig = DEFAULTS,
                          progress: Callable[[float, str], None] | None = None) -> int:
    """Refine one maplet from the catalog; the id of its revision for `input_hash`.

    Idempotent: a revision already stored for (maplet, input_hash) is returned as it is. The
    maplet's current input is what gets refined, at the pass input_hash names; when input_hash
    names none of its passes (the catalog changed since the work was planned, and newer work is
    on its way), pass 1 of the current input is refined and stored under its hash, for that
    newer work to find. The current revision moves to the new one only if its hash is still one
    of the maplet's inputs when it is stored, and not to an earlier pass of the input it holds.
    The refined maplet is a content-addressed artifact (pwm.io.fusion_state.write_maplet).
    progress(fraction, message) is told how far it got.
    """
    say = progress or (lambda fraction, message: None)
    with sessions() as session:
        found = _revision_id(session, maplet_id, input_hash)
        if found is not None:
            return found
        row = session.get(Maplet, maplet_id)
        if row is None:
            raise LookupError(f"no maplet {maplet_id}")
        current = _inputs(session, config, [maplet_id]).get(maplet_id)
        if current is None or len(current.image_ids) < config.min_images:
            raise ValueError(f"maplet {row.name} has fewer than {config.min_images} usable images")
        pass_number = current.pass_of(input_hash)
        if pass_number is None:
            log.info("maplet %s: input changed since planned; refining its current input",
                     row.name)
            pass_number, input_hash = 1, current.hashes[0]
            found = _revision_id(session, maplet_id, input_hash)
            if found is not None:
                return found
        model = latest_version(session)
        if model is None:
            raise LookupError("the catalog has no model version to refine against")
        say(0.05, f"reading {len(current.image_ids)} images")
        views = catalog_views(session, image_ids=current.image_ids, pixels=True)
        ordered = [views[i] for i in current.image_ids if i in views]
        grid = row.grid()
        model_version, model_ply = model.version, model.mesh_artifact
        # the pass before, for how much this one changes the solution (the pass rule)
        previous = session.get(MapletRevision, row.current_revision_id) if row.current_revision_id else None
        before = (load_revision_maplet(data_dir, previous)
                  if previous is not None and pass_number > 1
                  and current.pass_of(previous.input_hash) == pass_number - 1 else None)
    say(0.2, f"refining (pass {pass_number}) against version {model_version}")
    tracer = _tracer(data_dir, model_ply["path"], model_ply["sha256"])
    grid.heights, grid.albedo = sample_surface(tracer, grid)
    result = refine_maplet(grid, ordered, tracer, config=config)
    changed = None if before is None else solution_change(before, result.maplet)
    if changed is not None and not math.isfinite(changed):
        changed = None  # no node over the pass before's grid (JSON has no infinity): not known
    say(0.9, "storing the revision")
    with scratch_file(data_dir, ".npz") as scratch:
        write_maplet(scratch, result.maplet)
        artifact = store_artifact(data_dir, scratch)
    statistics = {"images": result.images, "region_weight": result.region_weight,
                  "five_views": result.five_views, "dropped": result.dropped,
                  "iterations": result.iterations, "converged": result.converged,
                  "residual_rms": result.residual_rms, "seconds": result.seconds,
                  "model_version": model_version, "pass": pass_number,
                  # observations of the images' poses for the next adjustment (service.spg)
                  "registrations": {name: list(xy) for name, xy in result.registrations.items()},
                  "raised_m": result.raised_km * 1e3,
                  "height_change_rms_m": float(np.sqrt(np.mean(
                      (result.maplet.heights - grid.heights) ** 2)) * 1e3),
                  "changed_spacings": changed}
    revision_id = _store_revision(sessions, maplet_id=maplet_id, input_hash=input_hash,
                                  config=config, artifact=artifact, statistics=statistics)
    say(1.0, "done")
    log.debug("maplet %s: revision %d (pass %d) from %d images, %d iterations, changed by %s node spacings "
              "(%.1f s)", grid.name, revision_id, pass_number, len(result.images), result.iterations,
              "?" if changed is None else f"{changed:.2f}", result.seconds)
    return revision_id


def load_revision_maplet(data_dir: Path, revision: MapletRevision) -> MapletGrid:
    """The refined maplet a revision stored (checksum verified)."""
    return read_maplet(artifact_path(data_dir, {"path": revision.artifact_path,
                                                "sha256": revision.sha256}, verify=True))


@lru_cache(maxsize=1)
def _tracer(data_dir: Path, path: str, sha256: str) -> RayTracer:
    """The model's ray tracer, kept for the next maplet refined against the same model (a
    process refines many in a row, and a global model takes seconds to read and build)."""
    return RayTracer(artifact_mesh(data_dir, {"path": path, "sha256": sha256}))


def _revision_id(session: Session, maplet_id: int, input_hash: str) -> int | None:
    return session.scalar(select(MapletRevision.id).filter_by(maplet_id=maplet_id,
                                                             input_hash=input_hash))


def _store_revision(sessions: sessionmaker[Session], *, maplet_id: int, input_hash: str,
                    config: RefinementConfig, artifact: dict, statistics: dict) -> int:
    """Insert the revision (next number for its maplet) unless a concurrent job stored the same
    input first, and make it current if its hash is one of the maplet's inputs now and the
    current revision is not a later pass of that input; its id."""
    for _ in range(_INSERT_ATTEMPTS):
        try:
            with session_scope(sessions) as session:
                found = _revision_id(session, maplet_id, input_hash)
                if found is not None:
                    return found
                # Row lock (PostgreSQL): revisions of one maplet are numbered one at a time.
                maplet = session.scalars(select(Maplet).where(Maplet.id == maplet_id)
                                         .with_for_update()).one()
                number = (session.scalar(select(func.max(MapletRevision.revision))
                                         .where(MapletRevision.maplet_id == maplet_id)) or 0) + 1
                revision = MapletRevision(maplet_id=maplet_id, revision=number,
                                          input_hash=input_hash, mode=config.mode,
                                          config_digest=config.digest(),
                                          statistics=statistics, artifact_path=artifact["path"],
                                          sha256=artifact["sha256"])
                session.add(revision)
                session.flush()
                now = _inputs(session, config, [maplet_id]).get(maplet_id)
                made = None if now is None else now.pass_of(input_hash)
                held = None if now is None or maplet.current_revision is None else now.pass_of(
                    maplet.current_revision.input_hash)
                if made is not None and (held is None or held < made):
                    maplet.current_revision_id = revision.id
                return revision.id
        except IntegrityError:
            # A concurrent job stored this input (or took the number) first: look again.
            continue
    raise RuntimeError(f"could not store a revision of maplet {maplet_id} after "
                       f"{_INSERT_ATTEMPTS} attempts")
