"""The lidar stage on the catalog (service.lidar, service.conductor.adjust_lidar, issue 46.3): a
downlink that brings lidar to a catalog with a model and publishes nothing has its tracks
strip-adjusted to the current version, each correction and sigma stored, and its residuals on
that version measured with them; a downlink without lidar adjusts nothing. And a catalog with no
model, given lidar alone, takes its first version from the spots (service.lidar.start_from_lidar)
through `pwm run`."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from sqlalchemy import select

from pwm.evaluate.closure import closure
from pwm.io.lidar import read_shots
from pwm.io.meshio import write_ply
from pwm.lidar.model import lidar_residuals, model_from_spots
from pwm.lidar.shots import Shots
from pwm.mesh import Mesh
from service.artifacts import artifact_path
from service.conductor import adjust_lidar
from service.ingest import ingest_directory
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
