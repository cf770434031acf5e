"""The lidar stage on the catalog (service.lidar, service.conductor.adjust_lidar, issue 46.3): a
downlink that brings lidar to a catalog with a model and publishes nothing has its tracks
strip-adjusted to the current version, each correction and sigma stored, and its residuals on
that version measured with them; a downlink without lidar adjusts nothing. And a catalog with no
model, given lidar alone, takes its first version from the spots (service.lidar.start_from_lidar)
through `pwm run`; given images and lidar, the start whose measurements sample the body more
finely (service.lidar.finer_start; the whole run: tests/service/test_start_from_images.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select

from pwm.config import RefinementConfig
from pwm.evaluate.closure import closure
from pwm.geometry import Ellipsoid
from pwm.io.lidar import read_shots
from pwm.io.meshio import write_ply
from pwm.knowledge import IndependentErrors
from pwm.lidar.model import lidar_residuals, model_from_spots, usable
from pwm.lidar.shots import Shots
from pwm.mesh import Mesh
from pwm.simulate.windows import window_downlink
from service.artifacts import artifact_path
from service.cli.science import _lidar_shots, _strip_adjusted_spots
from service.conductor import adjust_lidar
from service.ingest import ingest_directory
from service.lidar import finer_start
from service.rows import Downlink, LidarProduct, ModelKind
from service.run import run_directory
from service.versions import get_version, import_model, version_mesh

SHIFT_KM = np.array([0.005, -0.002, 0.0])  # the model lies 5 m off in x, 2 m in y


def test_a_downlink_of_lidar_alone_is_strip_adjusted_to_the_current_version(
        open_catalog_at, sqlite_url: str, global_tiny_sim: Path, tmp_path: Path) -> None:
    catalog, data = open_catalog_at(sqlite_url), tmp_path / "data"
    kernels_only = tmp_path / "kernels-only"
    shutil.copytree(global_tiny_sim / "downlink" / "kernels", kernels_only / "kernels")
    lidar_only = tmp_path / "lidar-only"
    for part in ("kernels", "lidar"):
        shutil.copytree(global_tiny_sim / "downlink" / part, lidar_only / part)
    ingest_directory(catalog, kernels_only, data_dir=data)
    ingest_directory(catalog, lidar_only, data_dir=data)
    with catalog() as session:
        product = session.scalars(select(LidarProduct)).one()
        shots, _ = read_shots(artifact_path(data, product.shots_artifact))
        ids = {d.name: d.id for d in session.scalars(select(Downlink))}
    # the current model: the spots' own, moved off them by SHIFT_KM (a model the images placed wrong)
    model = model_from_spots(shots)
    write_ply(tmp_path / "model.ply", Mesh(model.vertices + SHIFT_KM, model.faces))
    with catalog.begin() as session:
        version = import_model(session, data_dir=data, path=tmp_path / "model.ply", kind=ModelKind.START).version
    assert adjust_lidar(catalog, data_dir=data, downlink_id=ids["kernels-only"], published=None,
                        current=version) is None
    report = adjust_lidar(catalog, data_dir=data, downlink_id=ids["lidar-only"], published=None, current=version)
    assert report is not None and report.version == version and report.uncorrected == 0
    with catalog() as session:
        tracks = session.scalars(select(LidarProduct)).one().tracks
        assert report.tracks == len(tracks) > 1
        for t in tracks:
            rotation = np.array([t.rotation_x_rad, t.rotation_y_rad, t.rotation_z_rad])
            translation = np.array([t.translation_x_km, t.translation_y_km, t.translation_z_km])
            sigma = np.array(t.correction_sigma, dtype=float)
            # each track follows the model: the shift recovered to within a metre, a turn of at most 2 mrad
            assert np.linalg.norm(translation - SHIFT_KM) < 0.001 and np.linalg.norm(rotation) < 2e-3, t.track
            assert (sigma > 0).all() and (sigma[3:] < 0.001).all()
            assert t.residual_version == version and abs(t.residual_mean_km) < 0.5e-3 and t.residual_rms_km < 1e-3
        assert report.largest_km > 0.004 and report.rms_km < 1e-3


def test_a_catalog_with_no_model_takes_its_first_from_the_lidar(
        open_catalog_at, sqlite_url: str, global_tiny_sim: Path, tmp_path: Path) -> None:
    catalog, data = open_catalog_at(sqlite_url), tmp_path / "data"
    lidar_only = tmp_path / "lidar-only"
    for part in ("kernels", "lidar"):
        shutil.copytree(global_tiny_sim / "downlink" / part, lidar_only / part)
    run = run_directory(catalog, lidar_only, data_dir=data)
    assert (run.plan.base_version, run.versions, run.plan.work) == (1, [], [])
    truth = np.load(global_tiny_sim / "truth" / "lidar_spots.npz")
    with catalog() as session:
        first = get_version(session, 1)
        assert first.kind is ModelKind.LIDAR
        assert session.scalars(select(Downlink.model_note)).one().startswith("version 1 (lidar) made from the lidar")
        assert first.statistics["tracks_corrected"] == first.statistics["tracks"] > 1
        model = version_mesh(data, first)
        assert closure(model).closed
        # the true spots within a tenth of the survey's 4 m GSD of it (measured 0.40 m RMS), the adjusted ones too
        returned = truth["returned"]
        true_spots = Shots(frame="IAU_BENNU", et=truth["et"][returned], origin_km=truth["origin_km"][returned],
                           direction=truth["direction"][returned], range_km=truth["true_range_km"][returned],
                           sigma_km=np.full(int(returned.sum()), 1e-4),
                           invalid=np.zeros(int(returned.sum()), dtype=np.int8))
        against_truth = lidar_residuals(true_spots, model)
        assert abs(against_truth.mean_km) < 0.0005 and against_truth.rms_km < 0.0008, against_truth.rms_km
        assert first.statistics["lidar"]["rms_km"] < 0.0008


def test_the_start_whose_measurements_sample_the_body_more_finely_is_chosen() -> None:
    body = Ellipsoid(radii=(0.25, 0.25, 0.25)).mesh()
    area_m2 = body.face_areas().sum() * 1e6  # about 0.79 km2
    # 1,000 spots every 28 m against 100 stereo points every 89 m: the lidar's
    choice = finer_start(images=body, points=100, lidar=body, spots=1000)
    assert choice["chosen"] == "lidar"
    assert choice["lidar_spacing_m"] == pytest.approx(np.sqrt(area_m2 / 1000))
    assert choice["images_spacing_m"] == pytest.approx(np.sqrt(area_m2 / 100))
    assert "1000 spots every 28.0 m, 100 stereo points every 88.6 m" in choice["why"]
    # a lidar that ranged a few dozen times leaves the images' start
    assert finer_start(images=body, points=100, lidar=body, spots=40)["chosen"] == "images"
    # a start with no measurement at all is never the finer one (and its spacing is not a number to store)
    nothing = finer_start(images=body, points=0, lidar=body, spots=40)
    assert (nothing["chosen"], nothing["images_spacing_m"]) == ("lidar", None)


def test_images_then_lidar_then_images_through_pwm_run(
        open_catalog_at, sqlite_url: str, global_tiny_sim: Path, tmp_path: Path) -> None:
    """The sequence a mission gives, in one process (the same through the Celery workers:
    tests/workers/test_lidar_operations.py): every version published once the lidar is
    catalogued carries its residuals, and the tracks follow the latest version."""
    catalog, data = open_catalog_at(sqlite_url), tmp_path / "data"
    # the survey's places, 16-node maplets within 100 m, one pass a run (a pass's version is checked as
    # any other's); its exact poses known to a centimetre and a microradian
    config = RefinementConfig(nodes=16, tile_radius_km=0.1, passes=1,
                              knowledge=IndependentErrors(position_m=0.01, pointing_rad=1e-6))
    source = global_tiny_sim / "downlink"
    images = tmp_path / "images"
    for part in ("images", "kernels"):
        shutil.copytree(source / part, images / part)
    first = run_directory(catalog, images, data_dir=data, config=config, workers=2)
    assert first.plan.base_version == 1 and first.versions and first.lidar is None
    lidar_only = tmp_path / "lidar"
    for part in ("lidar", "kernels"):
        shutil.copytree(source / part, lidar_only / part)
    second = run_directory(catalog, lidar_only, data_dir=data, config=config)
    assert second.versions == [] and second.lidar is not None and second.lidar.version == first.versions[-1]
    again = tmp_path / "again"
    window_downlink(source, again, size_px=128, first_px=(96, 96), count=4, tag="again")
    third = run_directory(catalog, again, data_dir=data, config=config, workers=2)
    assert third.versions and third.lidar is not None and third.lidar.version == third.versions[-1]
    with catalog() as session:
        for number in first.versions:  # made before the catalog had lidar
            assert "lidar" not in get_version(session, number).statistics
        for number in third.versions:
            figures = get_version(session, number).statistics["lidar"]
            # the survey's 4 m GSD model: within 3 GSD of the spots, which cross one another
            assert figures["measured"] > 1000 and figures["rms_km"] < 0.012 and figures["crossovers"] > 0
        tracks = session.scalars(select(LidarProduct)).one().tracks
        assert len(tracks) > 1 and {t.residual_version for t in tracks} == {third.versions[-1]}

def test_pwm_refine_places_the_lidar_spots_on_its_start_model(global_tiny_sim: Path, tmp_path: Path) -> None:
    """`pwm refine --lidar`: the tracks strip-adjusted to the start model as the catalog's lidar
    stage adjusts them, their spots moved with them, each with its sigma."""
    lidar_only = tmp_path / "lidar-only"
    for part in ("kernels", "lidar"):
        shutil.copytree(global_tiny_sim / "downlink" / part, lidar_only / part)
    shots, _, products = _lidar_shots(lidar_only)
    model = model_from_spots(shots)
    spots = _strip_adjusted_spots(lidar_only, Mesh(model.vertices + SHIFT_KM, model.faces))
    given = shots.spots_km()[usable(shots)]
    assert products == 1 and len(spots.sigma_km) > 0.9 * len(given)
    assert np.isfinite(spots.sigma_km).all() and (spots.sigma_km > 0).all()
    # the spots follow the model: the shift recovered to within a metre
    assert np.linalg.norm(spots.body_km.mean(axis=0) - given.mean(axis=0) - SHIFT_KM) < 0.001
