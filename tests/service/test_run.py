"""`pwm run` in-process on a simulated downlink: a first downlink publishes a refined version on
top of the start model, and its second pass another on top of that, refined against it; the
same downlink again changes nothing; a second downlink that sees part of the site refines only
the maplets whose image set changed (both passes), and the new version's sums are those of a
fusion from scratch."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path

import numpy as np
import spiceypy as sp
from scipy.spatial import cKDTree
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker
from typer.testing import CliRunner

from pwm.config import RefinementConfig
from pwm.io.fusion_state import read_composition, read_levels
from pwm.io.meshio import read_mesh
from pwm.io.pds4 import MISSING_DN, read_image_product, write_image_product
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh, grid_faces
from pwm.raytrace import RayTracer
from pwm.tiling import level_of, tile
from service.artifacts import artifact_path
from service.cli import app
from service.console.documents import unpack
from service.db import session_scope
from service.exports import ExportFormat, ExportSurface, make_export, plan_export
from service.jobs import fuse_key, ingest_key
from service.publish import fuse_and_publish
from service.refinement import load_revision_maplet
from service.rows import Coverage, Job, JobKind, JobStatus, Maplet, MapletRevision, ModelKind
from service.run import run_directory
from service.settings import get_settings
from service.versions import get_version, version_mesh

# a few maplets about the site's centre: seconds; two passes, however far a maplet's second pass still
# moved it (the settling passes: tests/service/test_settling.py)
CONFIG = RefinementConfig(nodes=40, tile_radius_km=0.0008, max_passes=2)


def _second_downlink(sim: Path, out: Path) -> Path:
    """The last image again, cut down to the first half of its samples, under a LID of its own:
    a new image that sees only part of the site."""
    label = sim / "downlink" / "images" / "pwm_tiny_img005.xml"
    product = read_image_product(label)
    text = label.read_text()
    scale = float(re.search(r"<scaling_factor>(.*?)<", text)[1])
    offset = float(re.search(r"<value_offset>(.*?)<", text)[1])
    half = product.data[:, : product.samples // 2]
    dn = np.where(np.isnan(half), MISSING_DN, np.round((half - offset) / scale)).astype(np.int16)
    (out / "images").mkdir(parents=True)
    write_image_product(directory=out / "images", basename="pwm_tiny_img005_half", dn=dn,
                        scaling_factor=scale, value_offset=offset, lid=product.lid + "_half",
                        start_utc=product.start_utc, stop_utc=product.stop_utc,
                        mission=product.mission, host_name=product.host_name,
                        instrument_name=product.instrument_name,
                        target_name=product.target_name, title=product.title + " (half)",
                        exposure_s=product.exposure_s,
                        subframe=(product.first_line, product.first_sample))
    return out


def _inputs(session) -> dict[int, set[int]]:
    """The images each maplet weighs in, by maplet id."""
    inputs: dict[int, set[int]] = {}
    for maplet_id, image_id in session.execute(
            select(Coverage.maplet_id, Coverage.image_id).where(Coverage.weight > 0)):
        inputs.setdefault(maplet_id, set()).add(image_id)
    return inputs


def test_downlinks_publish_versions_incrementally(tiny_sim, catalog, db_url, tmp_path, monkeypatch):
    data = tmp_path / "data"
    first = shutil.copytree(tiny_sim / "downlink", tmp_path / "first")
    told: list[tuple[str, int, int]] = []
    run = run_directory(catalog, first, data_dir=data, config=CONFIG,
                        progress=lambda stage, done, total: told.append((stage, done, total)))
    assert (run.plan.base_version, run.versions) == (1, [2, 3]) and CONFIG.passes == 2
    assert len(run.plan.work) >= 2 and len(run.revisions) == 2 * len(run.plan.work)
    assert {w.pass_number for w in run.plan.work} == {1}
    # the progress of each pass's refinement, from 0 to every maplet, one call per maplet
    n = len(run.plan.work)
    assert told == [(f"refine round {r}", k, n) for r in (1, 2) for k in range(n + 1)]
    # each stage recorded as the job a worker would have run: the ingest, a refinement per
    # maplet and pass, a fusion per pass, all done, and listed by `pwm jobs list`
    _assert_jobs_of_the_run(catalog, downlink_id=run.plan.downlink_id, maplets=n, directory=first)
    monkeypatch.setenv("PWM_DATABASE_URL", db_url)
    monkeypatch.setenv("PWM_DATA_DIR", str(data))
    get_settings.cache_clear()
    try:
        listed = CliRunner().invoke(app, ["jobs", "list"])
    finally:
        get_settings.cache_clear()
    assert listed.exit_code == 0, listed.output
    header, *rows = listed.stdout.splitlines()
    assert header.split("\t")[:3] == ["id", "kind", "status"]
    assert sorted(row.split("\t")[1] for row in rows) == sorted(["ingest", "fuse", "fuse"] + ["refine"] * 2 * n)
    assert all(row.split("\t")[2] == "done" for row in rows)
    # the console's 3D document made for the run's last version, not for the pass it superseded
    documents = [unpack(path.read_bytes())[0] for path in (data / "exports").glob("*.pwmc")]
    assert [(d["version"], d["parent"]) for d in documents] == [(3, 2)]
    with catalog() as session:
        start, v2, v3 = (get_version(session, v) for v in (1, 2, 3))
        start_artifacts = dict(start.artifacts)
        assert start.kind is ModelKind.START and v2.kind is ModelKind.REFINED
        assert v2.parent.version == 1 and [d.name for d in v2.downlinks] == ["first"]
        assert sorted(r.id for r in v2.maplet_revisions) == sorted(run.revisions[:n])
        assert v2.statistics["maplets_changed"] == n
        assert v2.statistics["images"] == 6 and v2.statistics["base_version"] == 1
        # each version's 1-sigma heights, from its maplets' (the tiny site's 5 cm pixels: cm)
        sigma = v2.statistics["height_sigma"]
        assert 0 < sigma["vertex_share"] < 1 and 0.005 < sigma["median_m"] < sigma["p90_m"] < 0.5, sigma
        assert version_mesh(data, v2).sigma is not None
        # The second pass: the same maplets from the same images, against version 2.
        assert v3.parent.version == 2 and [d.name for d in v3.downlinks] == ["first"]
        assert sorted(r.id for r in v3.maplet_revisions) == sorted(run.revisions[n:])
        assert v3.statistics["maplets_replaced"] == n and v3.statistics["base_version"] == 1
        first_pass = {r.maplet_id: r for r in v2.maplet_revisions}
        for revision in v3.maplet_revisions:
            assert revision.statistics["pass"] == 2 and revision.statistics["model_version"] == 2
            assert first_pass[revision.maplet_id].statistics["pass"] == 1
            # offered the same images; the drop rules, weighed against version 2's shape, may
            # keep fewer (an image's shadowed share can cross its limit)
            offered = [set(r.statistics["images"]) | set(r.statistics["dropped"])
                       for r in (revision, first_pass[revision.maplet_id])]
            assert offered[0] == offered[1] and revision.statistics["images"]
        inputs = _inputs(session)
        maplets = set(session.scalars(select(Maplet.id)))
        assert len(run.plan.work) == sum(len(images) >= CONFIG.min_images for images in inputs.values())
    start_mesh, refined = version_mesh(data, start), version_mesh(data, v2)
    assert refined.albedo is not None and len(refined.faces) > len(start_mesh.faces)
    for revision in v3.maplet_revisions:
        change = (load_revision_maplet(data, revision).heights
                  - load_revision_maplet(data, first_pass[revision.maplet_id]).heights)
        assert 0.01 < np.sqrt(np.mean(change**2)) * 1e6 < 200  # mm, not metres: refined again

    again = run_directory(catalog, first, data_dir=data, config=CONFIG)
    assert again.plan.work == [] and again.versions == [] and again.version is None
    with catalog() as session:
        assert session.scalar(select(func.count()).select_from(MapletRevision)) == len(
            run.revisions)
        assert _inputs(session) == inputs
        # the ingest ran again: a second attempt at its job, and no other job
        jobs = session.scalars(select(Job)).all()
        assert len(jobs) == 3 + 2 * n
        assert [j.attempts for j in jobs if j.kind is JobKind.INGEST] == [2]

    second = _second_downlink(tiny_sim, tmp_path / "second")
    later = run_directory(catalog, second, data_dir=data, config=CONFIG)
    with catalog() as session:
        after = _inputs(session)
        changed = {m for m in after if after[m] != inputs.get(m) and len(after[m]) >= CONFIG.min_images}
        # some of the maplets tiled before (and any the new image's ground adds), not all
        assert 0 < len(changed & maplets) < len(maplets)
        assert {w.maplet_id for w in later.plan.work} == changed
        assert later.versions == [4, 5] and len(later.revisions) == 2 * len(changed)
        v5 = get_version(session, 5)
        assert v5.parent.version == 4 and v5.statistics["incremental"]
        assert sorted(d.name for d in v5.downlinks) == ["first", "second"]
        assert get_version(session, 4).statistics["maplets_changed"] == len(changed)
        assert v5.statistics["maplets_changed"] == len(changed)
        assert v5.statistics["maplets_fused"] == n + len(changed - set(
            w.maplet_id for w in run.plan.work))
        current = {m.id: m.current_revision for m in session.scalars(select(Maplet))
                   if m.current_revision is not None}
        assert {r.id for r in v5.maplet_revisions} == {r.id for r in current.values()}
        assert all(r.statistics["pass"] == 2 for r in current.values())
        # Unchanged maplets keep the revision version 3 used.
        kept = {r.maplet_id: r.id for r in v3.maplet_revisions if r.maplet_id not in changed}
        assert kept and all(current[m].id == r for m, r in kept.items())
        [incremental] = read_levels(artifact_path(data, v5.artifacts["grid"], verify=True)).grids.values()
        scratch = type(incremental)(voxel_km=incremental.voxel_km, taper_fraction=CONFIG.overlap)
        for revision in sorted(current.values(), key=lambda r: r.maplet_id):
            scratch.add(load_revision_maplet(data, revision))
        # Version 1 is as it was published, and still readable.
        assert get_version(session, 1).artifacts == start_artifacts
    np.testing.assert_array_equal(incremental.keys, scratch.keys)
    np.testing.assert_array_equal(incremental.count, scratch.count)
    np.testing.assert_allclose(incremental.sums, scratch.sums, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(version_mesh(data, start).vertices, start_mesh.vertices)


def _assert_jobs_of_the_run(catalog: sessionmaker[Session], *, downlink_id: int, maplets: int,
                            directory: Path) -> None:
    with catalog() as session:
        jobs = session.scalars(select(Job).order_by(Job.id)).all()
    # in the order the conductor ran them: ingest, then per pass the refinements and their fusion
    assert [j.kind for j in jobs] == [JobKind.INGEST] + ([JobKind.REFINE] * maplets + [JobKind.FUSE]) * 2
    assert all(j.status is JobStatus.DONE and j.attempts == 1 and j.downlink_id == downlink_id for j in jobs)
    assert jobs[0].key == ingest_key(directory)
    assert jobs[0].message is not None and f"{maplets} maplets to refine from version 1" in jobs[0].message
    assert [j.key for j in jobs if j.kind is JobKind.FUSE] == [fuse_key(downlink_id), fuse_key(downlink_id, 2)]
    assert [j.message for j in jobs if j.kind is JobKind.FUSE] == [
        f"published version 2; {maplets} maplets due for another pass", "published version 3"]
    refines = [j for j in jobs if j.kind is JobKind.REFINE]
    assert len({j.maplet_id for j in refines}) == maplets and len({j.key for j in refines}) == 2 * maplets
    assert all(j.started_at <= j.finished_at for j in jobs)


def test_a_site_level_under_a_survey_level_is_refined_and_laid_into_one_model(tiny_sim, sqlite_url, open_catalog_at,
                                                                             tmp_path):
    """Issue 16.1-16.2: over a survey's maplets four times as coarse, a downlink tiles its own
    level nested under them; both levels are refined from its images and fused, each place
    from the finest level that covers it."""
    catalog = open_catalog_at(sqlite_url)
    data = tmp_path / "data"
    gsd_km, survey = _survey_maplets(tiny_sim, catalog, coarser=4)
    config = dataclasses.replace(CONFIG, passes=1)
    run = run_directory(catalog, shutil.copytree(tiny_sim / "downlink", tmp_path / "first"), data_dir=data,
                        config=config)
    fine, coarse = str(int(level_of(gsd_km))), str(int(level_of(4 * gsd_km)))
    with catalog() as session:
        [version] = [get_version(session, v) for v in run.versions]
        levels = version.statistics["levels"]
        assert list(levels) == [coarse, fine] and levels[fine]["surface"] == "laid"
        refined = {m.level: [] for m in session.scalars(select(Maplet))}
        for revision in version.maplet_revisions:
            maplet = load_revision_maplet(data, revision)
            refined[int(level_of(maplet.spacing_km))].append(maplet)
        mesh = version_mesh(data, version)
    assert len(refined[int(coarse)]) == len(survey) and len(refined[int(fine)]) >= 2
    # Down the middle of the site's maplets: the model is the site level's surface, not the
    # survey level's, which differs from it there.
    tracer = RayTracer(mesh)
    below = [RayTracer(Mesh(s.nodes_body().reshape(-1, 3), grid_faces(s.n, s.n))) for s in refined[int(coarse)]]
    to_site, to_survey = [], []
    for m in refined[int(fine)]:
        middle = m.nodes_body()[10:-10, 10:-10].reshape(-1, 3)
        down = np.broadcast_to(-m.frame.normal, middle.shape)
        hits = tracer.intersect(middle - 20 * gsd_km * down, down)
        assert hits.hit.all()
        to_site.append(hits.t - 20 * gsd_km)
        survey_t = np.full(len(middle), np.inf)
        for t in below:
            h = t.intersect(middle - 20 * gsd_km * down, down)
            survey_t = np.where(h.hit & (h.t < survey_t), h.t, survey_t)
        to_survey.append(survey_t[np.isfinite(survey_t)] - 20 * gsd_km)
    to_site_km, to_survey_km = np.abs(np.concatenate(to_site)), np.abs(np.concatenate(to_survey))
    # measured: 0.06 GSD from the site level (where its maplets overlap, the model is their
    # blend), 0.97 GSD from the survey level's
    assert np.median(to_site_km) < 0.1 * gsd_km and np.median(to_site_km) < 0.2 * np.median(to_survey_km)

    # Issue 16.5: the whole model's DSK holds the body and the site region as segments that part
    # its surface; the global model is the survey level's surface alone, coarser
    with catalog() as session:
        exported = get_version(session, version.version)
        plans = [plan_export(session, data_dir=data, version=exported, fmt=fmt, surface=surface)
                 for fmt, surface in ((ExportFormat.DSK, ExportSurface.MODEL),
                                      (ExportFormat.PLY, ExportSurface.GLOBAL))]
        composition = read_composition(artifact_path(data, exported.artifacts["composition"]))
    dsk, global_ply = (make_export(plan, cache_bytes=10**9).path for plan in plans)
    plates = _segment_plates(dsk)
    assert len(plates) == 2 and sum(plates) == len(mesh.faces)
    survey_level = read_mesh(global_ply)
    assert len(survey_level.faces) < len(mesh.faces) and plans[1].filename.endswith("-global.ply")
    np.testing.assert_array_equal(survey_level.vertices, composition.below.vertices)

    # Issue 16.3: one site maplet withdrawn, the next fusion lays the site's region again onto
    # the survey level's surface, which it does not make again, and changes nothing outside it.
    withdrawn = refined[int(fine)][0]
    with session_scope(catalog) as session:
        session.scalars(select(Maplet).filter_by(name=withdrawn.name)).one().current_revision_id = None
    number = fuse_and_publish(catalog, data_dir=data)
    assert number is not None
    with catalog() as session:
        after = get_version(session, number)
        assert after.statistics["composition"] == {"regions_laid": 1, "regions_carried": 0,
                                                   "closed_levels_made": False}
        again = version_mesh(data, after)
    known = {tuple(v) for v in mesh.vertices}
    new = np.array([v for v in again.vertices if tuple(v) not in known])
    # what moved lies over the site's maplets, seen along the site's vertical (in 3D it can lie
    # far above their nodes, where the survey level runs up a boulder's flank that they smooth):
    # measured 3.7 voxels at most, the faces split about the site's border
    nodes = np.vstack([m.nodes_body().reshape(-1, 3) for m in refined[int(fine)]])
    centre = nodes.mean(axis=0)
    across = np.linalg.svd(nodes - centre, full_matrices=False)[2][:2].T
    site_ground = cKDTree((nodes - centre) @ across)
    assert len(new) and site_ground.query((new - centre) @ across)[0].max() < 8 * gsd_km


def test_close_images_leave_a_level_three_octaves_coarser_as_it_was(tiny_sim, sqlite_url, open_catalog_at,
                                                                    tmp_path):
    """Issue 16: over survey maplets eight times as coarse as its images, a downlink refines its
    own level only; its images are the finer maplets' (pwm.weights.Rules.min_resolution_ratio),
    so the survey level keeps its shape."""
    catalog = open_catalog_at(sqlite_url)
    gsd_km, _ = _survey_maplets(tiny_sim, catalog, coarser=8)
    run = run_directory(catalog, shutil.copytree(tiny_sim / "downlink", tmp_path / "first"), data_dir=tmp_path / "data",
                        config=dataclasses.replace(CONFIG, passes=1))
    coarse = int(level_of(8 * gsd_km))
    with catalog() as session:
        refined: dict[int, int] = {}
        for m in session.scalars(select(Maplet)):
            refined[m.level] = refined.get(m.level, 0) + (m.current_revision_id is not None)
        over_survey = session.scalars(select(Coverage).join(Maplet).where(Maplet.level == coarse)).all()
    assert run.versions and refined[coarse] == 0 and sum(refined.values()) >= 2
    assert over_survey and all(row.weight == 0 for row in over_survey)


def _survey_maplets(sim: Path, catalog: sessionmaker[Session], *, coarser: int) -> tuple[float, list[MapletGrid]]:
    """The site's GSD (km), and survey maplets `coarser` times as coarse about the site, tiled
    on its start model and catalogued."""
    manifest = json.loads((sim / "truth" / "manifest.json").read_text())
    site, gsd_km = manifest["scenario"], manifest["gsd_m"] * 1e-3
    survey = tile(read_mesh(sim / "downlink" / "start_model.obj"), spacing_km=coarser * gsd_km, nodes=CONFIG.nodes,
                  centre_lat_deg=site["site_lat_deg"], centre_lon_deg=site["site_lon_deg"],
                  radius_km=CONFIG.tile_radius_km)
    with catalog.begin() as session:
        session.add_all(Maplet.of(m) for m in survey)
    return gsd_km, survey


def _segment_plates(path: Path) -> list[int]:
    """The plates of each segment of a DSK file."""
    handle = sp.dasopr(str(path))
    plates, found = [], True
    try:
        descriptor = sp.dlabfs(handle)
        while found:
            plates.append(sp.dskz02(handle, descriptor)[1])
            with sp.no_found_check():
                descriptor, found = sp.dlafns(handle, descriptor)
    finally:
        sp.dascls(handle)
    return plates
