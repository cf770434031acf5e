"""Model versions: immutable shape models in the catalog, their files in the artifact store.

A version's files (artifacts) are stored content-addressed (service.artifacts.store_artifact).
`ModelVersion.artifacts` maps a role to a stored file's record; every version has "ply" (mesh
with per-vertex albedo when known) and "obj", or where its mesh has more faces than
PWM_MESH_TILE_FACES, "tiles" instead: the index of its tiles (pwm.mesh_tiles, each tile a
stored file of its own; `ModelVersion.mesh_artifact` names whichever holds the mesh); refined
versions add "grid" (the fusion sums that let the next version be fused incrementally) and
"composition" (how its surface was composed from them, pwm.levels.Composition, which lets the
next one carry over what did not change).

Publications are serialised by `publication_lock`, held to the end of the publishing
transaction: concurrent publications get consecutive numbers instead of failing on the unique
constraint, and a fusion that takes it before reading the latest version (service.publish) never
builds on a parent that another fusion is replacing.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import func, select, text
from sqlalchemy.orm import Session

from pwm.evaluate.closure import closure, mass_properties
from pwm.io.mesh_tiles import TileEntry, TileIndex, tile_key, write_index, write_tile
from pwm.io.meshio import read_shape_model, write_obj, write_ply
from pwm.io.pds4 import file_sha256
from pwm.levels import sealed
from pwm.mesh import Mesh
from pwm.mesh_tiles import split
from service.artifacts import artifact_mesh, scratch_file, store_artifact
from service.rows import Downlink, MapletRevision, ModelKind, ModelVersion
from service.settings import get_settings

# Arbitrary constant naming the PostgreSQL advisory lock that serialises publications.
_PUBLICATION_LOCK_ID = 0x70776D5F76657273


def store_mesh(data_dir: Path, mesh: Mesh, *, tile_faces: int) -> dict[str, dict[str, Any]]:
    """Write `mesh` (km, body-fixed) into the store: as PLY (with albedo) and OBJ, or where it
    has more than `tile_faces` faces as tiles of at most that many (pwm.mesh_tiles.split) and
    their index ("tiles")."""
    if len(mesh.faces) > tile_faces:
        return {"tiles": _store_tiles(data_dir, mesh, tile_faces=tile_faces)}
    records = {}
    for role, writer in (("ply", write_ply), ("obj", write_obj)):
        with scratch_file(data_dir, f".{role}") as scratch:
            writer(scratch, mesh)
            records[role] = store_artifact(data_dir, scratch)
    return records


def _store_tiles(data_dir: Path, mesh: Mesh, *, tile_faces: int) -> dict[str, Any]:
    entries = []
    for number, tile in enumerate(split(mesh, max_faces=tile_faces)):
        with scratch_file(data_dir, ".npz") as scratch:
            write_tile(scratch, tile)
            record = store_artifact(data_dir, scratch)
        entries.append(TileEntry(key=tile_key(number), faces=len(tile.faces), vertices=len(tile.vertices),
                                 box_km=tile.box_km(), file=record))
    with scratch_file(data_dir, ".json") as scratch:
        write_index(scratch, TileIndex(vertices=len(mesh.vertices), faces=len(mesh.faces), tiles=tuple(entries)))
        return store_artifact(data_dir, scratch)


def mesh_statistics(mesh: Mesh) -> dict[str, Any]:
    """Size of a mesh: vertex and face counts, area (km^2), signed volume (km^3), mean and
    extreme radius (km), mean edge (m); whether it is one closed surface ("closure": the checks
    of pwm.evaluate.closure, all but the self-intersections, which cost tens of seconds a million
    faces at every publication: a DSK export counts them), and for one that is, what it encloses
    ("mass": volume km^3, centre of figure km, inertia tensor about it per unit density km^5, area
    km^2; null otherwise)."""
    checks = closure(mesh, count_intersections=False)
    mass = mass_properties(mesh) if checks.closed else None
    radius = np.linalg.norm(mesh.vertices, axis=1)
    return {"vertices": len(mesh.vertices), "faces": len(mesh.faces),
            "area_km2": float(mesh.face_areas().sum()), "volume_km3": checks.volume_km3,
            "mean_radius_km": float(radius.mean()), "min_radius_km": float(radius.min()),
            "max_radius_km": float(radius.max()), "mean_edge_m": mesh.mean_edge_length() * 1e3,
            "closure": {"closed": checks.closed, **dataclasses.asdict(checks)},
            "mass": None if mass is None else {
                "volume_km3": mass.volume_km3, "centre_km": mass.centre_km.tolist(),
                "inertia_km5": mass.inertia_km5.tolist(), "area_km2": mass.area_km2}}


def publish_version(session: Session, *, data_dir: Path, mesh: Mesh, kind: ModelKind,
                    parent: ModelVersion | None = None, statistics: dict[str, Any] | None = None,
                    extra_artifacts: dict[str, Path] | None = None,
                    maplet_revisions: Iterable[MapletRevision] = (),
                    downlinks: Iterable[Downlink] = (), tile_faces: int | None = None) -> ModelVersion:
    """Store `mesh` and publish it as the next model version, in the caller's transaction.

    tile_faces: store it in tiles above this many faces (store_mesh; default
    PWM_MESH_TILE_FACES).
    extra_artifacts: role -> a file to move into the store with the mesh (e.g. "grid").
    statistics: figures to keep beside the mesh's own (mesh_statistics: its size, closure checks
    and mass properties, made here for every version, whatever its kind)."""
    artifacts = store_mesh(data_dir, mesh, tile_faces=get_settings().mesh_tile_faces if tile_faces is None
                           else tile_faces)
    for role, path in (extra_artifacts or {}).items():
        artifacts[role] = store_artifact(data_dir, path)
    publication_lock(session)
    number = (session.scalar(select(func.max(ModelVersion.version))) or 0) + 1
    version = ModelVersion(version=number, kind=kind, parent=parent, artifacts=artifacts,
                           statistics={**mesh_statistics(mesh), **(statistics or {})},
                           maplet_revisions=list(maplet_revisions), downlinks=list(downlinks))
    session.add(version)
    session.flush()
    return version


def import_model(session: Session, *, data_dir: Path, path: Path,
                 kind: ModelKind = ModelKind.IMPORTED) -> ModelVersion:
    """Publish a shape model file as a new version: any mesh format pwm exports, told by its
    content (pwm.io.meshio.read_shape_model; km, body-fixed). ValueError if it is none of them,
    saying why for the exports without faces (LAS, a site's terrain). A model of a body with
    holes and patches over them (as a site's start model comes) is published as one closed
    surface, its patches zipped into the holes (pwm.levels.sealed; statistics "sealed")."""
    given = read_shape_model(path)
    mesh = sealed(given)
    return publish_version(session, data_dir=data_dir, mesh=mesh, kind=kind,
                           statistics={"source": str(path.resolve()),
                                       "source_sha256": file_sha256(path), "sealed": mesh is not given})


def latest_version(session: Session, *, released_only: bool = False) -> ModelVersion | None:
    """The newest version (of those released, with `released_only`), or None."""
    query = select(ModelVersion).order_by(ModelVersion.version.desc()).limit(1)
    if released_only:
        query = query.where(ModelVersion.released.is_(True))
    return session.scalar(query)


def get_version(session: Session, ref: str | int) -> ModelVersion:
    """A version by number, by release tag, or `latest` (newest) / `released` (newest released).
    Raises LookupError when there is none."""
    if ref in ("latest", "released"):
        version = latest_version(session, released_only=ref == "released")
    elif isinstance(ref, int) or (str(ref).isascii() and str(ref).isdigit()):  # '²' is a digit too
        version = session.scalar(select(ModelVersion).filter_by(version=int(ref)))
    else:
        version = session.scalar(select(ModelVersion).filter_by(release_tag=str(ref)))
    if version is None:
        raise LookupError(f"no model version {ref!r}")
    return version


def version_mesh(data_dir: Path, version: ModelVersion) -> Mesh:
    """The mesh of `version` (km, body-fixed, albedo when published with it), checksum verified
    (a mesh stored in tiles: joined)."""
    return artifact_mesh(data_dir, version.mesh_artifact)


def publication_lock(session: Session) -> None:
    """Take the catalog's publication lock until the session's transaction ends (taking it again
    in the same transaction is harmless). Take it before reading what the publication builds on.

    PostgreSQL: a transaction-level advisory lock. SQLite: the database's write lock, which also
    holds back every other writer meanwhile."""
    if session.get_bind().dialect.name == "postgresql":
        session.execute(text("SELECT pg_advisory_xact_lock(:id)"), {"id": _PUBLICATION_LOCK_ID})
    else:
        # A write takes SQLite's database lock now rather than at the insert, so that two
        # publishers cannot both read the same maximum.
        session.execute(text("UPDATE model_versions SET id = id WHERE 0"))
