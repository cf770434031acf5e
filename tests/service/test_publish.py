"""Fusion into versions: nothing changed publishes nothing; concurrent fusions build one on the
other under the publication lock; a parent without sums (an imported model) starts a new grid
from every current revision; a version's lineage names the downlinks of the refinements it
carries, whichever fusion took them up."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

from sqlalchemy import func, select

from pwm.config import RefinementConfig
from pwm.io.meshio import write_ply
from service.conductor import ingest_and_plan
from service.console.documents import make_mesh_document, unpack
from service.db import session_scope
from service.jobs import claim_job, finish_job, refine_key
from service.publish import first_version_with, fuse_and_publish
from service.refinement import refine_catalog_maplet
from service.rows import Downlink, JobKind, ModelKind, ModelVersion
from service.versions import get_version, import_model, version_mesh


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
        assert v4.kind is ModelKind.REFINED and v4.parent.version == 3
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
