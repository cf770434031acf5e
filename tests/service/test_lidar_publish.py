"""Every version checked against the lidar (service.publish.lidar_statistics, issue 46.2): the
catalogued spots' distances to a mesh, overall, per track and on a map, from a bounded sample,
each track's stored correction applied; none for a catalog without lidar. And `pwm evaluate
--lidar`, the same figures without the catalog."""

from __future__ import annotations

import json
import shutil
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select

from pwm.geometry import Ellipsoid
from pwm.io.lidar import read_shots
from pwm.io.meshio import write_ply
from service.artifacts import artifact_path
from service.cli import app
from service.cli.versions import lidar_lines
from service.ingest import ingest_directory
from service.lidar_shots import placed_shots
from service.publish import lidar_statistics
from service.rows import Image, LidarProduct, LidarTrack


def test_a_version_is_checked_against_the_catalogued_lidar(open_catalog_at, sqlite_url: str, global_tiny_sim: Path,
                                                           tmp_path: Path, pwm) -> None:
    catalog, data = open_catalog_at(sqlite_url), tmp_path / "data"
    # Bennu's PCK ellipsoid, a model tens of metres off the true surface (the truth's own mesh
    # is millions of faces: seconds to trace)
    truth = Ellipsoid(np.array([0.283065, 0.271215, 0.249720])).mesh()
    write_ply(tmp_path / "ellipsoid.ply", truth)
    with catalog() as session:
        assert lidar_statistics(session, data_dir=data, mesh=truth, version=1) is None  # no lidar, no figures
    downlink = tmp_path / "lidar-only"
    for part in ("kernels", "lidar"):
        shutil.copytree(global_tiny_sim / "downlink" / part, downlink / part)
    ingest_directory(catalog, downlink, data_dir=data)
    with catalog() as session:
        product = session.scalars(select(LidarProduct)).one()
        whole = lidar_statistics(session, data_dir=data, mesh=truth, version=7)
        assert whole is not None and whole["shots"] == product.valid_shots == whole["usable_shots"]
        # the ellipsoid is tens of metres off Bennu, within the reach (100 m) of a spot's intercept
        assert 0.005 < whole["rms_km"] < 0.05 and whole["rms_km"] < whole["p95_km"] < 0.1
        assert whole["missed"] < 0.05 * whole["shots"] and whole["measured"] + whole["missed"] == whole["shots"]
        tracks = {t.id: t for t in product.tracks}
        assert set(whole["tracks"]) == {str(i) for i in tracks}
        assert all(t.residual_version == 7 and t.residual_rms_km == whole["tracks"][str(i)]["rms_km"]
                   for i, t in tracks.items())
        # the tracks cross one another; each row holds its crossovers as the figures do
        assert whole["crossovers"] > 0
        assert all((t.crossovers, t.crossover_rms_km) == (whole["tracks"][str(i)]["crossovers"],
                                                          whole["tracks"][str(i)]["crossover_rms_km"])
                   for i, t in tracks.items())
        assert sum(t.crossovers for t in tracks.values()) == 2 * whole["crossovers"]
        # within the range noise where nothing is adjusted (measured 0.10-0.35 m per track)
        crossing = {i: t.crossover_rms_km for i, t in tracks.items()}
        assert all(rms is None or rms < 0.001 for rms in crossing.values())
        cells = [c for row in whole["map"]["rms_km"] for c in row]
        assert len(whole["map"]["rms_km"]) == 18 and len(whole["map"]["rms_km"][0]) == 36
        assert sum(c is not None for c in cells) > 100 and max(c for c in cells if c is not None) < 0.1
        # a sample is bounded and says what it sampled
        sample = lidar_statistics(session, data_dir=data, mesh=truth, version=7, at_most=500)
        assert sample is not None and sample["shots"] == 500 and sample["usable_shots"] == product.valid_shots
        assert sample["rms_km"] == pytest.approx(whole["rms_km"], rel=0.25)
        # a track adjusted 3 m outward: its spots stand 3 m off the truth, the others as they were
        moved = session.scalars(select(LidarTrack).order_by(LidarTrack.track)).first()
        spots = np.array([moved.cone_axis_x, moved.cone_axis_y, moved.cone_axis_z])
        moved.rotation_x_rad = moved.rotation_y_rad = moved.rotation_z_rad = 0.0
        moved.translation_x_km, moved.translation_y_km, moved.translation_z_km = (float(v) for v in 0.003 * spots)
        moved.about_x_km = moved.about_y_km = moved.about_z_km = 0.0
        moved.correction_sigma, moved.adjusted_at = [1e-6] * 6, datetime.now(UTC)
        adjusted = lidar_statistics(session, data_dir=data, mesh=truth, version=8)
        assert adjusted is not None
        # (outward along the cone's axis: the spots' normals lean off it, by up to the cone's half-angle)
        shift = adjusted["tracks"][str(moved.id)]["mean_km"] - whole["tracks"][str(moved.id)]["mean_km"]
        assert 0.001 < shift <= 0.003 + 1e-6
        residuals = ("shots", "mean_km", "rms_km", "p95_km")
        assert all([adjusted["tracks"][k][f] for f in residuals] == [v[f] for f in residuals]
                   for k, v in whole["tracks"].items() if k != str(moved.id))
        # and its crossovers with the others open by about those 3 m (the spots' normals lean off the axis)
        assert moved.crossovers and moved.crossover_rms_km > 0.001 > crossing[moved.id]
        # placed to a millimetre, it lies metres off this model: flagged, not averaged in; the
        # others are placed by nothing, so nothing says they disagree
        assert whole["disagreeing_tracks"] == [] and whole["disagree_sigmas"] == 3.0
        assert adjusted["disagreeing_tracks"] == [moved.id]
        assert adjusted["tracks"][str(moved.id)]["disagreement_sigmas"] > 10  # its spots scatter by metres here
        assert all(v["disagreement_sigmas"] is None for k, v in adjusted["tracks"].items() if k != str(moved.id))
        # placed only to 100 m, the same metres are within its sigmas
        moved.correction_sigma = [1e-6] * 3 + [0.1] * 3
        loose = lidar_statistics(session, data_dir=data, mesh=truth, version=9)
        assert loose is not None and loose["disagreeing_tracks"] == []
        assert loose["tracks"][str(moved.id)]["disagreement_sigmas"] < 1.0
        assert "DISAGREES" in "\n".join(lidar_lines(adjusted)) and "DISAGREES" not in "\n".join(lidar_lines(loose))
    # the same figures without the catalog
    out = tmp_path / "lidar.json"
    result = pwm.invoke(app, ["evaluate", str(tmp_path / "ellipsoid.ply"), "--lidar",
                              str(global_tiny_sim / "downlink"), "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "lidar: 1 products:\n4800 shots, " in result.output
    free = json.loads(out.read_text())["lidar"]
    assert free["measured"] == whole["measured"] and free["rms_km"] == pytest.approx(whole["rms_km"], rel=1e-9)


def test_the_spots_follow_the_corrected_trajectory(open_catalog_at, sqlite_url: str, global_tiny_sim: Path,
                                                  tmp_path: Path) -> None:
    """A lidar's spots are placed again whenever the images of their time are corrected
    (service.lidar_shots.placed_shots): each shot's origin moves by the images' position
    corrections, interpolated in time within their arcs; the pointing's are not the lidar's."""
    catalog, data = open_catalog_at(sqlite_url), tmp_path / "data"
    ingest_directory(catalog, global_tiny_sim / "downlink", data_dir=data)
    with catalog() as session:
        product = session.scalars(select(LidarProduct)).one()
        stored, _ = read_shots(artifact_path(data, product.shots_artifact, verify=True))
        as_stored, _ = placed_shots(session, data, product)  # no image corrected yet
        np.testing.assert_array_equal(as_stored.origin_km, stored.origin_km)
        images = session.scalars(select(Image).order_by(Image.start_et)).all()
        for k, image in enumerate(images):  # 1 m east to 1 m + k cm, and a turn the lidar must not take
            image.pose_dx_km, image.pose_dy_km, image.pose_dz_km = 1e-3 + 1e-5 * k, 0.0, 0.0
            image.pose_rx_rad, image.pose_ry_rad, image.pose_rz_rad = 1e-3, 0.0, 0.0
            image.pose_corrected_at = datetime.now(UTC)
        session.flush()
        placed, _ = placed_shots(session, data, product)
        moved = (placed.origin_km - stored.origin_km) * 1e3
        np.testing.assert_allclose(moved[:, 1:], 0.0, atol=1e-12)
        assert 1.0 - 1e-9 <= moved[:, 0].min() and moved[:, 0].max() <= 1.0 + 0.01 * (len(images) - 1) + 1e-9
        mid = np.array([(i.start_et + i.stop_et) / 2 for i in images])
        expected = np.interp(stored.et, mid, 1.0 + 0.01 * np.arange(len(images)))
        np.testing.assert_allclose(moved[:, 0], expected, atol=1e-9)
        np.testing.assert_array_equal(placed.direction, stored.direction)
