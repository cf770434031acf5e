"""Where a model's error lies: by wavelength band (pwm.evaluate.bands) and by class
(pwm.evaluate.classes), and through pwm evaluate."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from pwm.evaluate.bands import band_names, band_rms, split
from pwm.evaluate.classes import MapletFootprint, edge_mask, error_by_class, rim_mask, shadow_share
from pwm.frames import LocalFrame
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.simulate.terrain import Crater
from service.cli import app

SPACING_KM = 5e-5  # 5 cm
BOUNDARIES_KM = (1e-3, 5e-3, 20e-3)
AXIS = np.arange(1600) * SPACING_KM  # 80 m


@pytest.mark.parametrize("wavelength_m, band", [(0.3, 0), (2.2, 1), (10.0, 2), (60.0, 3)])
def test_a_wave_lands_in_its_band(wavelength_m, band):
    x, y = np.meshgrid(AXIS, AXIS)
    error = 0.1 * np.sin(2 * np.pi * (x + 0.3 * y) / (wavelength_m * 1e-3))
    rms = list(band_rms(error, spacing_km=SPACING_KM, boundaries_km=BOUNDARIES_KM).values())
    # most of the wave in its own band (Gaussian filters part the bands gradually)
    assert rms[band] > 0.75 * 0.1 / np.sqrt(2)
    assert max(r for k, r in enumerate(rms) if k != band) < 0.35 * rms[band]


def test_the_bands_add_up_to_the_error_with_its_gaps():
    rng = np.random.default_rng(0)
    error = rng.normal(size=(300, 400))
    error[100:150, 50:300] = np.nan
    bands = split(error, spacing_km=SPACING_KM, boundaries_km=BOUNDARIES_KM)
    np.testing.assert_allclose(sum(bands), error, atol=1e-12)
    assert all(np.isnan(b[120, 100]) for b in bands)
    assert band_names(BOUNDARIES_KM) == ["<1 m", "1-5 m", "5-20 m", ">20 m"]


def test_rims_and_edges():
    x, y = np.meshgrid(AXIS[:200], AXIS[:100])
    crater = Crater(x_km=0.005, y_km=0.0025, diameter_km=0.004, depth_km=0.0008, rim_height_km=0.0001)
    rims = rim_mask(AXIS[:200], AXIS[:100], [crater])
    r = np.hypot(x - 0.005, y - 0.0025)
    assert rims[np.abs(r - 0.002) < 0.0001].all() and not rims[np.abs(r - 0.002) > 0.0004].any()
    # two maplets 4 m wide overlapping by 1 m along x: the edge strips of both, inside either
    frames = [LocalFrame(origin=np.array([cx, 0.0, 0.0]), rotation=np.eye(3)) for cx in (0.0, 0.003)]
    footprints = [MapletFootprint(frame=f, half_km=0.002) for f in frames]
    points = np.array([[-0.00195, 0, 0], [-0.0015, 0, 0], [0.00105, 0, 0], [0.0018, 0, 0], [0.00491, 0, 0],
                       [0.0, 0.00195, 0], [0.009, 0, 0]])
    assert edge_mask(points, footprints, band_km=1e-4).tolist() == [True, False, True, False, True, True, False]


def test_shadow_share_behind_a_wall():
    """A 1 m wall across a plane: with the Sun 30 deg above the horizon behind it, points less than
    1/tan(30) = 1.73 m in front are in shadow; with the Sun overhead, none are."""
    # 20 m across, so that the rays' lift off the surface (a thousandth of an edge) stays 2 cm
    wall_top = np.array([[0.0, -0.01, 0.001], [0.0, 0.01, 0.001]])
    vertices = np.vstack([0.01 * np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]),
                          [[0, -0.01, 0], [0, 0.01, 0]], wall_top])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 7], [4, 7, 6]])
    tracer = RayTracer(Mesh(vertices.astype(float), faces))
    points = np.array([[0.001, 0.0, 0.0], [0.0015, 0.0, 0.0], [0.0025, 0.0, 0.0]])
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    low_sun = np.array([-np.cos(np.radians(30)), 0.0, np.sin(np.radians(30))])
    share = shadow_share(tracer, points, normals, np.array([low_sun, [0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(share, [0.5, 0.5, 0.0])


def test_error_by_class_counts_every_node_once_outside_classes():
    error = np.array([[1.0, -2.0, np.nan], [3.0, 0.5, -0.5]])
    walls = np.array([[True, True, True], [False, False, False]])
    shadow = np.array([[True, False, False], [True, False, False]])
    figures = error_by_class(error, {"walls": walls, "shadow": shadow})
    assert figures["walls"]["nodes"] == 2 and figures["walls"]["rms"] == pytest.approx(np.sqrt(2.5))
    assert figures["shadow"]["nodes"] == 2
    assert figures["elsewhere"]["nodes"] == 2 and figures["elsewhere"]["rms"] == pytest.approx(0.5)
    assert figures["walls"]["p95"] == pytest.approx(np.percentile([1.0, 2.0], 95))


def test_pwm_evaluate_reports_bands_and_classes_with_a_map(tiny_sim, tmp_path):
    truth = tiny_sim / "truth"
    frame = json.loads((truth / "manifest.json").read_text())
    assert frame["images"][0]["sun_direction"]
    from pwm.simulate.truth import load as load_truth

    site = load_truth(truth).site_frame
    maplets = {"maplets": [{"origin_km": site.origin.tolist(), "rotation": site.rotation.tolist(),
                            "half_km": 0.003}]}
    (tmp_path / "maplets.json").write_text(json.dumps(maplets))
    out = tmp_path / "start.json"
    result = CliRunner().invoke(app, ["evaluate", str(tiny_sim / "downlink" / "start_model.obj"), "--truth",
                                      str(truth), "--json", str(out), "--plots", str(tmp_path / "plots"),
                                      "--maplets", str(tmp_path / "maplets.json")])
    assert result.exit_code == 0, result.output
    figures = json.loads(out.read_text())
    assert list(figures["bands_rms_m"]) == ["<0.5 m", "0.5-2.5 m", "2.5-10 m", ">10 m"]
    # the start is the truth low-passed at 1.5 m: little of its error lies at long wavelengths
    bands = figures["bands_rms_m"]
    assert bands[">10 m"] < 0.25 * max(bands.values())
    classes = figures["classes_m"]
    assert set(classes) == {"walls", "rims", "maplet edges", "shadow", "elsewhere"}
    assert all(classes[name]["nodes"] > 0 for name in classes)
    # a low-passed start misses boulder walls, rims and shadowed relief most
    assert min(classes[name]["rms"] for name in ("walls", "rims", "shadow")) > 1.2 * classes["elsewhere"]["rms"]
    assert (tmp_path / "plots" / "error_classes.png").stat().st_size > 10_000
    assert "band <0.5 m" in result.output and "walls" in result.output
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    refused = CliRunner().invoke(app, ["evaluate", str(tiny_sim / "downlink" / "start_model.obj"), "--truth",
                                       str(truth), "--maplets", str(bad)])
    assert refused.exit_code == 2 and "maplets.json" in refused.output
