"""The harder proving ground: `pwm simulate` with photometry the solver does not assume, sub-pixel
sampling, blur, smear, a flat field and a start model with smooth undulations (issue 21)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from pwm.evaluate.distance import ClosestPoint
from pwm.io.meshio import read_obj
from pwm.io.pds4 import read_image_product
from pwm.simulate.campaign import start_model
from pwm.simulate.missions import MISSIONS, SHAPES_DIR
from pwm.simulate.scenarios import SCENARIOS, Scenario
from pwm.simulate.truth import build_base, load as load_truth, low_pass, undulations
from service.cli import app

HARD = ["--photometry", "hapke", "--supersample", "2", "--psf-px", "0.6", "--smear-px", "0.8",
        "--flat-field", "0.01", "--start-error", "1.0,1,4"]


def test_undulations_have_their_rms_and_only_their_wavelengths(tiny_sim):
    truth = load_truth(tiny_sim / "truth")
    gsd_km = 5e-5
    field = undulations(truth, rms_km=gsd_km, shortest_km=1e-3, longest_km=4e-3, seed=1)
    weight = truth.blend_weight()
    assert field.shape == truth.height_km.shape
    assert np.sqrt(np.mean(field[weight >= 1] ** 2)) == pytest.approx(gsd_km, rel=1e-9)
    assert np.all(field[weight == 0] == 0)
    # inside the full-weight square the power lies in the band (the taper leaks a little)
    square = field[np.ix_(weight.max(axis=1) >= 1, weight.max(axis=0) >= 1)]
    power = np.abs(np.fft.rfft2(square)) ** 2
    k = np.hypot(np.fft.rfftfreq(square.shape[1], truth.resolution_km)[None, :],
                 np.fft.fftfreq(square.shape[0], truth.resolution_km)[:, None])
    in_band = (k >= 1 / 5e-3) & (k <= 1 / 0.8e-3)
    assert power[in_band].sum() / power.sum() > 0.95
    with pytest.raises(ValueError, match="shortest < longest"):
        undulations(truth, rms_km=gsd_km, shortest_km=4e-3, longest_km=1e-3, seed=1)
    # the start model carries them on top of the low-pass
    plain = low_pass(truth, wavelength_km=30 * gsd_km, spacing_km=10 * gsd_km)
    wavy = low_pass(truth, wavelength_km=30 * gsd_km, spacing_km=10 * gsd_km, error_km=field)
    moved = np.linalg.norm(wavy.vertices - plain.vertices, axis=1)
    assert 0.5 * gsd_km < np.sqrt(np.mean(moved[moved > 0] ** 2)) < 1.5 * gsd_km


def test_simulate_options_make_a_harder_downlink(tiny_sim, tmp_path):
    out = tmp_path / "hard"
    result = CliRunner().invoke(app, ["simulate", str(out), "--scenario", "tiny", "--seed", "3", *HARD,
                                      "--with-start-model"])
    assert result.exit_code == 0, result.output
    manifest = json.loads((out / "truth" / "manifest.json").read_text())
    scenario = manifest["scenario"]
    assert (scenario["photometry"], scenario["supersample"]) == ("hapke", 2)
    assert scenario["optics"] == {"psf_sigma_px": 0.6, "smear_px": 0.8, "smear_azimuth_deg": 30.0,
                                  "flat_field_rms": 0.01}
    assert manifest["start_model"]["undulation_rms_m"] == pytest.approx(0.05)
    # same truth and plan, other pixels: blurred (less pixel-to-pixel contrast) and otherwise lit
    plain_manifest = json.loads((tiny_sim / "truth" / "manifest.json").read_text())
    for hard_image, plain_image in zip(manifest["images"][:2], plain_manifest["images"][:2], strict=True):
        hard = read_image_product(out / "downlink" / hard_image["label"]).data
        plain = read_image_product(tiny_sim / "downlink" / plain_image["label"]).data
        assert hard.shape == plain.shape
        lit = (plain > 0) & (hard > 0)
        contrast = [np.abs(np.diff(image, axis=1))[lit[:, 1:]].mean() for image in (hard, plain)]
        assert contrast[0] < 0.9 * contrast[1]
    start = read_obj(out / "downlink" / "start_model.obj")
    plain_start = read_obj(tiny_sim / "downlink" / "start_model.obj")
    assert start.vertices.shape == plain_start.vertices.shape
    assert not np.allclose(start.vertices, plain_start.vertices, atol=1e-6)


@pytest.mark.parametrize("option, value, message", [
    ("--photometry", "lommel", "unknown photometry"), ("--start-error", "1,2", "RMS_GSD"),
    ("--start-error", "1,40,10", "shortest < longest"), ("--psf-px", "-1", "psf_sigma_px"),
    ("--supersample", "9", "supersample")])
def test_simulate_refuses_impossible_options(tmp_path, option, value, message):
    result = CliRunner().invoke(app, ["simulate", str(tmp_path / "x"), "--scenario", "tiny", option, value])
    assert result.exit_code == 2 and message in " ".join(re.sub("[│╭╮╰╯─]", " ", result.output).split()), result.output
    assert not (tmp_path / "x").exists()


def test_site_hard_departs_from_site_only_in_what_the_solver_does_not_assume():
    site, hard = SCENARIOS["site"].model_dump(), SCENARIOS["site-hard"].model_dump()
    differing = {k for k in site if site[k] != hard[k]}
    assert differing == {"name", "description", "photometry", "supersample", "optics", "start_error_rms_gsd"}
    assert Scenario.model_validate(hard).optics.perfect is False
    assert SCENARIOS["site"].optics.perfect and SCENARIOS["site-polar"].photometry == "mcewen"


def test_a_global_start_model_is_the_body_smoothed_not_the_truth(tiny_sim):
    """global-coarse's start scored 0.00 GSD: it was the truth's own base wherever the images
    look. Now it is the body rebuilt with its roughness low-passed at 30 GSD."""

    # global-coarse at a coarser base, so that the truth's body builds in a second
    scenario = Scenario.model_validate({**SCENARIOS["global-coarse"].model_dump(), "base_edge_km": 0.004,
                                        "global_roughness_km": 0.002, "gsd_km": 0.004})
    shape = read_obj(SHAPES_DIR / MISSIONS[scenario.mission].shape)
    truth_body = build_base(shape, base_edge_km=scenario.base_edge_km, seed=3,
                            global_roughness_km=scenario.global_roughness_km)
    start = start_model(load_truth(tiny_sim / "truth"), scenario=scenario, base=shape, seed=3)
    assert start.mean_edge_length() <= 10 * scenario.gsd_km
    # radial distance from the truth's body to the start, sampled at the truth's vertices
    distance, _, _ = ClosestPoint(start).query(truth_body.vertices[::50])
    rms_gsd = np.sqrt(np.mean(distance**2)) / scenario.gsd_km
    assert 0.05 < rms_gsd < 2.0, rms_gsd
