"""Refinement from the catalog: stale maplets by input hash, idempotent revisions (also when two
jobs refine the same input at once), pose corrections in the views and the hash, and a job whose
input changes while it runs leaves the current revision alone."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.spatial.transform import Rotation
from sqlalchemy import func, select

from pwm.config import RefinementConfig
from pwm.frames import LocalFrame
from pwm.maplets import MapletGrid
from pwm.photoclinometry import Solver
from pwm.tiling import sample_heights
from service.conductor import ingest_and_plan
from service.db import session_scope
from service.refinement import load_revision_maplet, refine_catalog_maplet, stale_maplets
from service.rows import Coverage, Image, Maplet, MapletRevision
from service.versions import get_version, version_mesh
from service.views import image_view

SITE = {"config": RefinementConfig(nodes=40, tile_radius_km=0.0003)}  # one maplet on the site's centre


def _correct_pose_of_an_input(catalog, maplet_id: int) -> int:
    """Give one image the maplet weighs in a pose correction; its id."""
    with session_scope(catalog) as session:
        image = session.scalars(select(Image).join(Coverage).where(
            Coverage.maplet_id == maplet_id, Coverage.weight > 0).order_by(Image.id)).first()
        image.pose_dx_km, image.pose_rz_rad = 1e-4, 2e-5
        return image.id


def test_revisions_are_keyed_by_input(tiny_sim, catalog, tmp_path):
    plan = ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=tmp_path, **SITE)
    [work] = plan.work
    with catalog() as session:
        assert stale_maplets(session) == plan.work
        assert stale_maplets(session, maplet_ids=[work.maplet_id + 1]) == []
        standard = stale_maplets(session, config=RefinementConfig(mode="standard"))
        looser = stale_maplets(session, config=RefinementConfig(solver=Solver(cost_tolerance=0.05)))
        retiled = stale_maplets(session, config=RefinementConfig(nodes=64))
    # the refinement's settings are part of the input, the tiling's are not (the grid is)
    assert standard[0].input_hash != work.input_hash
    assert looser[0].input_hash not in (work.input_hash, standard[0].input_hash)
    assert retiled == plan.work

    def refine() -> int:
        return refine_catalog_maplet(catalog, data_dir=tmp_path, maplet_id=work.maplet_id,
                                     input_hash=work.input_hash)

    with ThreadPoolExecutor(2) as pool:
        ids = list(pool.map(lambda _: refine(), range(2)))
    assert ids[0] == ids[1] == refine()
    with catalog() as session:
        assert session.scalar(select(func.count()).select_from(MapletRevision)) == 1
        revision = session.get(MapletRevision, ids[0])
        maplet = session.get(Maplet, work.maplet_id)
        assert maplet.current_revision_id == revision.id and revision.revision == 1
        assert revision.input_hash == work.input_hash and revision.mode == "pwm"
        assert revision.statistics["model_version"] == 1
        assert stale_maplets(session) == []
        start = version_mesh(tmp_path, get_version(session, 1))
        frame = LocalFrame(origin=np.array([maplet.origin_x_km, maplet.origin_y_km,
                                            maplet.origin_z_km]),
                           rotation=np.asarray(maplet.rotation).reshape(3, 3))
        refined = load_revision_maplet(tmp_path, revision)
    np.testing.assert_array_equal(refined.frame.origin, frame.origin)
    assert refined.albedo is not None
    before = sample_heights(start, MapletGrid(name="", frame=frame, spacing_km=refined.spacing_km,
                                              heights=refined.heights))
    change_m = (refined.heights - before) * 1e3
    assert 0.001 < np.sqrt(np.mean(change_m**2)) < 0.5  # moved, by centimetres, not metres

    image_id = _correct_pose_of_an_input(catalog, work.maplet_id)
    with catalog() as session:
        [moved] = stale_maplets(session)
        image = session.get(Image, image_id)
        view = image_view(image)
        g = image.geometry
    assert moved.maplet_id == work.maplet_id and moved.input_hash != work.input_hash
    np.testing.assert_allclose(view.pose.position - [g.camera_x_km, g.camera_y_km, g.camera_z_km],
                               [1e-4, 0.0, 0.0], atol=1e-12)
    turn = view.pose.rotation.T @ np.asarray(g.camera_rotation).reshape(3, 3)  # R(omega)
    np.testing.assert_allclose(Rotation.from_matrix(turn).as_rotvec(), [0.0, 0.0, 2e-5],
                               atol=1e-12)


def test_a_job_overtaken_by_new_input_leaves_the_current_revision(tiny_sim, catalog, tmp_path):
    plan = ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=tmp_path, **SITE)
    [work] = plan.work
    stages = []

    def meanwhile(fraction: float, message: str) -> None:
        stages.append(fraction)
        if message.startswith("refining"):  # the catalog changes while the job solves
            _correct_pose_of_an_input(catalog, work.maplet_id)

    first = refine_catalog_maplet(catalog, data_dir=tmp_path, maplet_id=work.maplet_id,
                                  input_hash=work.input_hash, progress=meanwhile)
    assert stages == sorted(stages) and stages[-1] == 1.0
    with catalog() as session:
        assert session.get(MapletRevision, first).input_hash == work.input_hash
        assert session.get(Maplet, work.maplet_id).current_revision_id is None
        [newer] = stale_maplets(session)
    second = refine_catalog_maplet(catalog, data_dir=tmp_path, maplet_id=work.maplet_id,
                                   input_hash=newer.input_hash)
    # A late duplicate of the first job finds its revision and moves nothing back.
    assert refine_catalog_maplet(catalog, data_dir=tmp_path, maplet_id=work.maplet_id,
                                 input_hash=work.input_hash) == first
    with catalog() as session:
        assert session.get(Maplet, work.maplet_id).current_revision_id == second
        assert session.get(MapletRevision, second).revision == 2
        assert stale_maplets(session) == []
