"""Fusion into versions: nothing changed publishes nothing; concurrent fusions build one on the
other under the publication lock; a parent without sums (an imported model) starts a new grid
from every current revision; a version's lineage names the downlinks of the refinements it
carries, whichever fusion took them up; a version's statistics say whether it is one closed
surface and what it encloses, and its exports are closed or say why not (a DSK must be)."""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import trimesh
from sqlalchemy import func, select

from pwm.config import RefinementConfig
from pwm.evaluate.closure import closure, mass_properties
from pwm.io.meshio import read_shape_model, write_ply
from pwm.mesh import Mesh
from service.conductor import ingest_and_plan
from service.console.documents import make_mesh_document, unpack
from service.db import session_scope
from service.exports import ExportError, ExportFormat, make_export, plan_export
from service.jobs import claim_job, finish_job, refine_key
from service.publish import first_version_with, fuse_and_publish
from service.refinement import refine_catalog_maplet
from service.rows import Downlink, JobKind, ModelKind, ModelVersion
from service.versions import get_version, import_model, publish_version, version_mesh


def test_fusions_publish_changes_once(tiny_sim, catalog, tmp_path):
    data = tmp_path / "data"
    plan = ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=data,
                           config=RefinementConfig(nodes=40, tile_radius_km=0.0003))
    assert fuse_and_publish(catalog, data_dir=data) is None  # no revision yet
    [work] = plan.work
    revision = refine_catalog_maplet(catalog, data_dir=data, maplet_id=work.maplet_id,
                                     input_hash=work.input_hash)
    with ThreadPoolExecutor(2) as pool:
        published = list(pool.map(lambda _: fuse_and_publish(
            catalog, data_dir=data, downlink_ids=[plan.downlink_id]), range(2)))
    assert sorted(published, key=str) == [2, None]
    with catalog() as session:
        assert session.scalar(select(func.count()).select_from(ModelVersion)) == 2
        v2 = get_version(session, 2)
        assert [r.id for r in v2.maplet_revisions] == [revision]
        assert [d.id for d in v2.downlinks] == [plan.downlink_id]
        assert v2.statistics["maplets_changed"] == v2.statistics["maplets_added"] == 1
        assert not v2.statistics["incremental"] and "grid" in v2.artifacts
        start, fused = version_mesh(data, get_version(session, 1)), version_mesh(data, v2)
    assert fused.albedo is not None and len(fused.faces) > len(start.faces)
    # publication only publishes; the console's 3D document is made after it, so that its
    # first view reads it
    assert not list((data / "exports").glob("*.pwmc"))
    make_mesh_document(catalog, data_dir=data, version=2)
    [document] = (data / "exports").glob("*.pwmc")
    header, _ = unpack(document.read_bytes())
    assert (header["version"], header["parent"], header["faces"]) == (2, 1, len(fused.faces))
    assert header["colours"]["change"]["max"] is not None

    # An imported model becomes the parent: the next fusion starts over on it.
    write_ply(tmp_path / "other.ply", start)
    with session_scope(catalog) as session:
        assert import_model(session, data_dir=data, path=tmp_path / "other.ply").version == 3
    assert fuse_and_publish(catalog, data_dir=data) == 4
    with catalog() as session:
        v4 = get_version(session, 4)
        assert v4.kind is ModelKind.REFINED and v4.parent is not None and v4.parent.version == 3
        assert v4.statistics["base_version"] == 3 and not v4.statistics["incremental"]
        assert v4.statistics["maplets_fused"] == 1 and v4.statistics["maplets_changed"] == 1
        assert v4.downlinks == []


def test_a_version_names_every_downlink_whose_refinements_it_carries(tiny_sim, catalog,
                                                                     tmp_path):
    data = tmp_path / "data"
    plan = ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=data,
                           config=RefinementConfig(nodes=40, tile_radius_km=0.0003))
    [work] = plan.work
    with session_scope(catalog) as session:
        later = Downlink(name="later", path="/incoming/later")
        session.add(later)
        session.flush()
        later_id = later.id
        job = claim_job(session, kind=JobKind.REFINE, grace_s=60.0,
                        key=refine_key(plan.downlink_id, work.maplet_id, work.input_hash),
                        downlink_id=plan.downlink_id, maplet_id=work.maplet_id)
        assert job is not None
    refine_catalog_maplet(catalog, data_dir=data, maplet_id=work.maplet_id,
                          input_hash=work.input_hash)
    with session_scope(catalog) as session:
        finish_job(session, job, message="refined")
    # A later downlink's fusion runs before this downlink's and takes its refinement up.
    assert fuse_and_publish(catalog, data_dir=data, downlink_ids=[later_id]) == 2
    with catalog() as session:
        assert sorted(d.id for d in get_version(session, 2).downlinks) == sorted(
            [plan.downlink_id, later_id])
        assert first_version_with(session, downlink_id=plan.downlink_id) == 2
    # This downlink's own fusion then finds nothing left to publish.
    assert fuse_and_publish(catalog, data_dir=data, downlink_ids=[plan.downlink_id]) is None


def test_a_version_carries_its_closure_and_a_dsk_of_an_open_one_is_refused(sqlite_url, open_catalog_at,
                                                                          tmp_path, caplog):
    catalog, data = open_catalog_at(sqlite_url), tmp_path / "data"
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.25)
    unit = np.asarray(sphere.vertices) / 0.25
    vertices = np.asarray(sphere.vertices) * (1 + 0.05 * np.sin(5 * unit[:, [0]]))
    closed = Mesh(vertices, np.asarray(sphere.faces), 0.04 + 0.01 * unit[:, 2])
    holed = Mesh(closed.vertices, closed.faces[1:], closed.albedo)
    with session_scope(catalog) as session:
        for mesh in (closed, holed):
            publish_version(session, data_dir=data, mesh=mesh, kind=ModelKind.IMPORTED)
    tm = trimesh.Trimesh(closed.vertices, closed.faces, process=False)
    with catalog() as session:
        stats, open_stats = get_version(session, 1).statistics, get_version(session, 2).statistics
    # the statistics of publication: the checks, and what the closed one encloses, as trimesh has it
    assert stats["closure"]["closed"] and stats["closure"]["components"] == 1
    mass = stats["mass"]
    assert mass["volume_km3"] == pytest.approx(tm.volume, rel=5e-3) and mass["area_km2"] == pytest.approx(
        tm.area, rel=5e-3)
    np.testing.assert_allclose(mass["centre_km"], tm.center_mass, atol=1e-6)
    np.testing.assert_allclose(mass["inertia_km5"], tm.moment_inertia, rtol=5e-3, atol=1e-9)
    assert not open_stats["closure"]["closed"] and open_stats["closure"]["boundary_edges"] == 3
    assert open_stats["mass"] is None

    def export(version: int, fmt: ExportFormat, faces: int | None = None):
        with catalog() as session:
            plan = plan_export(session, data_dir=data, version=get_version(session, version), fmt=fmt,
                               faces=faces, body="499", frame="IAU_MARS")
        return make_export(plan, cache_bytes=10**9)

    # every export of the closed version is closed, decimated too, read back from its file
    for fmt in (ExportFormat.OBJ, ExportFormat.PLY, ExportFormat.ICQ, ExportFormat.DSK):
        for faces in (None, 1000):
            made = export(1, fmt, faces)
            again = read_shape_model(made.path)
            assert made.closure == "closed" and closure(again).closed, (fmt, faces)
            # an ICQ samples the surface at its grid's vertices (q = 9 at 1000 faces): inscribed, smaller
            within = 2.5e-2 if fmt is ExportFormat.ICQ and faces else 5e-3
            assert mass_properties(again).volume_km3 == pytest.approx(tm.volume, rel=within), (fmt, faces)
    # of the open one, a DSK is refused, saying why; the other formats are made, with a warning
    with pytest.raises(ExportError, match="a DSK must be one closed surface.*open: 3 boundary edges"):
        export(2, ExportFormat.DSK)
    with caplog.at_level(logging.WARNING, logger="service.exports"):
        made = export(2, ExportFormat.PLY)
    assert made.closure == "open: 3 boundary edges" and not closure(read_shape_model(made.path)).closed
    assert "pwm-v0002.ply of version 2 is not one closed surface (open: 3 boundary edges)" in caplog.text


def test_every_export_of_a_site_campaigns_versions_is_closed(tiny_sim, sqlite_url, open_catalog_at, tmp_path):
    """tiny's start model is its site's patch beside the body it was cut from; published sealed,
    and fused with the site's maplets laid into it, each version and every export of it is one
    closed surface, decimated too."""
    catalog, data = open_catalog_at(sqlite_url), tmp_path / "data"
    plan = ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=data,
                           config=RefinementConfig(nodes=40, tile_radius_km=0.0003))
    [work] = plan.work
    refine_catalog_maplet(catalog, data_dir=data, maplet_id=work.maplet_id, input_hash=work.input_hash)
    assert fuse_and_publish(catalog, data_dir=data) == 2
    with catalog() as session:
        start, fused = get_version(session, 1), get_version(session, 2)
        assert start.statistics["sealed"] and start.statistics["closure"]["closed"]
        assert fused.statistics["closure"]["closed"] and fused.statistics["levels"] == {
            "-4": {"surface": "laid", "voxel_m": pytest.approx(0.05, rel=1e-3), "voxels": fused.statistics["voxels"]}}
        volume = fused.statistics["mass"]["volume_km3"]
    # (an export's closure is its file's, read back; a DSK is made only of a closed surface)
    for fmt in (ExportFormat.OBJ, ExportFormat.PLY, ExportFormat.ICQ, ExportFormat.DSK):
        for faces in (None, 20000):
            with catalog() as session:
                export_plan = plan_export(session, data_dir=data, version=get_version(session, 2), fmt=fmt,
                                          faces=faces)
            made = make_export(export_plan, cache_bytes=10**9)
            assert made.closure == "closed", (fmt, faces, made.closure)
            enclosed = mass_properties(read_shape_model(made.path)).volume_km3
            assert enclosed == pytest.approx(volume, rel=5e-3), (fmt, faces)
