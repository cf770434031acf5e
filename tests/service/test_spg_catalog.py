"""Stereo photogrammetry on the catalog: a photogrammetric version on top of the latest, pose
corrections stored per image, the refined maplets made stale by them, and the next ingest
weighing the corrected images again."""

from __future__ import annotations

import numpy as np
from sqlalchemy import select
from typer.testing import CliRunner

from pwm.camera import PoseCorrection
from pwm.config import RefinementConfig
from service.cli import app
from service.conductor import ingest_and_plan
from service.refinement import refine_catalog_maplet, stale_maplets
from service.rows import Image, ImageGeometry, ModelKind
from service.settings import get_settings
from service.spg import _store_correction, photogrammetry_version
from service.versions import get_version, latest_version, version_mesh
from service.views import catalog_views, image_pose, kernel_pose

SITE = {"config": RefinementConfig(nodes=40, tile_radius_km=0.0003)}  # one maplet on the site's centre


def test_photogrammetric_version_corrects_poses_and_stales_maplets(tiny_sim, catalog, tmp_path):
    plan = ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=tmp_path, **SITE)
    assert plan.work
    for work in plan.work:
        refine_catalog_maplet(catalog, data_dir=tmp_path, maplet_id=work.maplet_id, input_hash=work.input_hash)
    with catalog() as session:
        assert stale_maplets(session) == []
        before = {i: v.pose for i, v in catalog_views(session).items()}

    number = photogrammetry_version(catalog, data_dir=tmp_path)

    with catalog() as session:
        version = get_version(session, number)
        assert version.kind is ModelKind.PHOTOGRAMMETRIC and latest_version(session).version == number
        assert version.parent.version == plan.base_version
        assert version.statistics["images"] == len(before) and version.statistics["points"] >= 30
        assert version.statistics["residual_rms_px"] < 1.5
        assert [d.name for d in version.downlinks] == [tiny_sim.joinpath("downlink").name]
        mesh = version_mesh(tmp_path, version)
        assert len(mesh.vertices) > 0
        images = session.scalars(select(Image).where(Image.id.in_(list(before)))).all()
        assert len(images) == len(before)
        moved_m = []
        for image in images:
            assert image.pose_corrected_at is not None and image.coverage_computed_at is None
            pose = image_pose(image)
            moved_m.append(np.linalg.norm(pose.position - before[image.id].position) * 1e3)
            # the correction is what makes the stored pose differ from SPICE's
            assert np.allclose(pose.position - kernel_pose(image).position,
                               [image.pose_dx_km, image.pose_dy_km, image.pose_dz_km])
        # navigation knowledge is 1 m: the adjustment moves cameras, within a few sigma
        assert 0.0 < max(moved_m) < 5.0
        stale = stale_maplets(session)
        assert {w.maplet_id for w in stale} == {w.maplet_id for w in plan.work}
        assert {w.input_hash for w in stale}.isdisjoint(w.input_hash for w in plan.work)

    # the next ingest weighs the corrected images again, against the photogrammetric model
    again = ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=tmp_path, **SITE)
    assert again.base_version == number
    assert {w.input_hash for w in again.work} == {w.input_hash for w in stale}
    with catalog() as session:
        assert None not in session.scalars(select(Image.coverage_computed_at).where(Image.id.in_(list(before)))).all()


def test_a_correction_composes_onto_the_stored_one():
    g = ImageGeometry(camera_x_km=1.2, camera_y_km=-0.3, camera_z_km=0.4,
                      camera_rotation=np.linalg.qr(np.random.default_rng(4).normal(size=(3, 3)))[0].ravel().tolist())
    image = Image(geometry=g, pose_dx_km=1e-3, pose_dy_km=None, pose_dz_km=-2e-3, pose_rx_rad=3e-4, pose_ry_rad=None,
                  pose_rz_rad=-1e-4)
    first = image_pose(image)
    new = PoseCorrection((5e-4, -5e-4, 0.0), (-2e-4, 1e-4, 4e-4))
    _store_correction(image, new)
    expected = new.apply(first)
    assert np.allclose(image_pose(image).position, expected.position, atol=1e-12)
    assert np.allclose(image_pose(image).rotation, expected.rotation, atol=1e-12)


def test_spg_catalog_command_needs_a_version(tmp_path, monkeypatch):
    monkeypatch.setenv("PWM_DATA_DIR", str(tmp_path))
    monkeypatch.delenv("PWM_DATABASE_URL", raising=False)
    get_settings.cache_clear()
    try:
        result = CliRunner().invoke(app, ["spg-catalog"])
    finally:
        get_settings.cache_clear()
    assert result.exit_code == 1
    assert "no model version" in result.output
