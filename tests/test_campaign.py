"""A campaign: one truth asteroid with landforms everywhere, its survey and two sites in time order,
and the whole-body evaluation that judges a global model."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pwm.camera import Camera, Pose
from pwm.evaluate.images import ncc
from pwm.evaluate.profiles import boulder_height_ratio
from pwm.evaluate.report import evaluate
from pwm.frames import latlon_to_unit
from pwm.io.meshio import read_obj, write_ply
from pwm.io.pds4 import read_image_product
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.render import render
from pwm.simulate.campaign import start_model
from pwm.simulate.landforms import Clearing, apply_landforms, sample_landforms
from pwm.simulate.missions import MISSIONS, SHAPES_DIR
from pwm.simulate.scenarios import CAMPAIGNS
from pwm.simulate.terrain import Boulder, Crater
from pwm.simulate.truth import SiteSpec, build_base, build_truth, load as load_truth, stitch_sites
from service.cli import app


def sphere(radius_km: float, subdivisions: int) -> Mesh:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius_km)
    return Mesh(s.vertices, s.faces, np.full(len(s.vertices), 0.05))


def test_landforms_are_placed_apart_clear_of_sites_and_shape_the_surface():
    body = sphere(0.25, 6)  # 40k vertices, 4 m edges
    clearing = Clearing(centre_km=0.25 * latlon_to_unit(10.0, 40.0), radius_km=0.06)
    forms = sample_landforms(body, np.random.default_rng(3), n_craters=5, n_boulders=12, n_steep=4,
                             crater_diameter_km=(0.03, 0.06), boulder_diameter_km=(0.015, 0.03),
                             clearings=[clearing])
    boulders = [f for f in forms if isinstance(f.shape, Boulder)]
    craters = [f for f in forms if isinstance(f.shape, Crater)]
    assert len(boulders) == 12 and len(craters) == 5
    assert sum(b.shape.steep for b in boulders) == 4
    for f in forms:
        assert np.linalg.norm(np.array(f.origin_km) - clearing.centre_km) >= clearing.radius_km + f.reach_km - 1e-12
    for i, a in enumerate(boulders):
        for b in boulders[i + 1:]:
            assert np.linalg.norm(np.subtract(a.origin_km, b.origin_km)) >= a.reach_km + b.reach_km
    shaped = apply_landforms(body, forms)
    moved = np.linalg.norm(shaped.vertices, axis=1) - 0.25
    untouched = np.ones(len(body.vertices), bool)
    for f in forms:
        untouched &= np.linalg.norm(body.vertices - f.origin_km, axis=1) > 1.5 * f.reach_km
    assert np.abs(moved[untouched]).max() < 1e-12
    # a boulder lifts the vertex nearest its centre by about its height; a crater sinks its centre
    for f in boulders + craters:
        k = int(np.argmin(np.linalg.norm(body.vertices - f.origin_km, axis=1)))
        if isinstance(f.shape, Boulder) and not any(np.linalg.norm(np.subtract(c.origin_km, f.origin_km)) < c.reach_km
                                                     for c in craters):
            assert moved[k] == pytest.approx(f.shape.height_km, rel=0.25)
        if isinstance(f.shape, Crater) and not any(np.linalg.norm(np.subtract(o.origin_km, f.origin_km)) < o.reach_km
                                                    + f.reach_km for o in forms if o is not f):
            assert moved[k] < -0.5 * f.shape.depth_km
    assert np.any(shaped.albedo != body.albedo)  # boulders differ in albedo from their ground


def test_a_body_can_be_too_crowded():
    with pytest.raises(ValueError, match="too crowded"):
        sample_landforms(sphere(0.05, 3), np.random.default_rng(0), n_craters=0, n_boulders=40, n_steep=0,
                         crater_diameter_km=(0.01, 0.02), boulder_diameter_km=(0.04, 0.05))


def test_two_sites_are_one_surface_and_the_first_is_what_a_lone_site_draws():
    base = read_obj(SHAPES_DIR / MISSIONS["osiris-rex"].shape)
    site_a = SiteSpec(lat_deg=10.0, lon_deg=40.0, size_km=0.01, resolution_km=5e-4, n_craters=1, n_boulders=3,
                      steep_boulders=1)
    site_b = SiteSpec(lat_deg=-30.0, lon_deg=200.0, size_km=0.01, resolution_km=5e-4, n_craters=1, n_boulders=3,
                      steep_boulders=1)
    body = build_base(base, base_edge_km=0.008, seed=4)
    stitched = stitch_sites(body, [site_a, site_b], seed=4)
    a, b = stitched.truth(0), stitched.truth(1)
    lone = build_truth(base=base, site_lat_deg=10.0, site_lon_deg=40.0, site_size_km=0.01, resolution_km=5e-4,
                       seed=4, base_edge_km=0.008, n_craters=1, n_boulders=3, steep_boulders=1)
    np.testing.assert_array_equal(a.height_km, lone.height_km)
    assert a.boulders == lone.boulders
    assert b.boulders != a.boulders  # the second site draws its own
    # the same surface, each with its own site last
    assert len(a.mesh.faces) == len(b.mesh.faces)
    np.testing.assert_allclose(a.mesh.face_areas().sum(), b.mesh.face_areas().sum(), rtol=1e-12)
    np.testing.assert_array_equal(np.sort(a.mesh.vertices, axis=0), np.sort(b.mesh.vertices, axis=0))
    np.testing.assert_allclose(b.site_frame.origin / np.linalg.norm(b.site_frame.origin),
                               latlon_to_unit(-30.0, 200.0), atol=1e-9)
    site_b_nodes = b.mesh.vertices[b.n_base_vertices:]
    assert len(site_b_nodes) == b.height_km.size


@pytest.fixture(scope="module")
def campaign(campaign_tiny_sim) -> Path:
    """`pwm simulate OUT --scenario campaign-tiny` (the session's, which the workers' tests share)."""
    return campaign_tiny_sim


def test_a_campaign_is_its_downlinks_in_time_order_over_one_truth(campaign):
    summary = json.loads((campaign / "truth" / "campaign.json").read_text())
    spec = CAMPAIGNS["campaign-tiny"]
    names = [e["name"] for e in summary["downlinks"]]
    assert names == sorted(p.name for p in (campaign / "downlinks").iterdir())
    assert [e["scope"] for e in summary["downlinks"]] == ["global", "site", "site"]
    previous_end = -np.inf
    for entry, scenario in zip(summary["downlinks"], spec.downlinks, strict=True):
        downlink = campaign / entry["downlink"]
        assert (downlink / "manifest.json").exists()  # written last: a complete downlink
        # --with-start-model: the survey comes with a start model, a site with none of its own
        assert (downlink / "start_model.obj").exists() == (entry["scope"] == "global")
        manifest = json.loads((campaign / entry["truth"] / "manifest.json").read_text())
        assert manifest["scenario"]["name"] == scenario.name
        # the sites' pixels integrate over their footprint, as a detector's do; the survey's need not
        assert (manifest["scenario"]["supersample"] > 1) == (entry["scope"] == "site")
        times = sorted(image["et"] for image in manifest["images"])
        assert times[0] > previous_end  # each downlink after the last
        previous_end = times[-1]
        label = downlink / manifest["images"][0]["label"]
        assert read_image_product(label).data.shape == (scenario.subframe_px, scenario.subframe_px)

    survey, site_a, site_b = (load_truth(campaign / e["truth"]) for e in summary["downlinks"])
    # one body: the landforms are the same everywhere, and each site truth is the whole surface
    assert survey.landforms == site_a.landforms == site_b.landforms
    assert sum(isinstance(f.shape, Boulder) for f in survey.landforms) == spec.boulders
    assert len(site_a.mesh.faces) == len(site_b.mesh.faces)
    np.testing.assert_allclose(site_a.mesh.face_areas().sum(), site_b.mesh.face_areas().sum(), rtol=1e-9)
    # the survey's truth holds the sites thinned to the body's own spacing
    assert survey.resolution_km <= spec.survey.base_edge_km
    assert len(survey.mesh.faces) < len(site_a.mesh.faces) / 4
    centre_b = site_b.site_frame.origin
    assert np.linalg.norm(centre_b / np.linalg.norm(centre_b) - latlon_to_unit(-30.0, 200.0)) < 1e-9
    for form in survey.landforms:  # nothing lands on a site
        for site in (site_a, site_b):
            assert np.linalg.norm(np.subtract(form.origin_km, site.site_frame.origin)) > form.reach_km



def test_a_site_is_judged_on_views_imaged_as_its_camera_images(campaign):
    # the held-out views integrate 2 x 2 rays per pixel: the truth imaged the same way matches
    # them; imaged one ray per pixel it would not (0.98 NCC, 0.96 SSIM), which a model was judged on
    site_dir = campaign / "truth" / "2-campaign-tiny-site-a"
    perfect = evaluate(site_dir / "mesh.ply", truth_dir=site_dir)
    assert perfect["views"] and all(v["ncc"] > 0.9999 and v["ssim"] > 0.9999 for v in perfect["views"])
    manifest = json.loads((site_dir / "manifest.json").read_text())
    view = np.load(site_dir / manifest["validation"][0]["file"])
    camera = Camera(**{k: manifest["camera"][k] for k in ("width", "height", "fx", "fy", "cx", "cy")})
    one_ray = render(RayTracer(load_truth(site_dir).mesh), camera=camera,
                     pose=Pose(position=view["position"], rotation=view["rotation"]), sun_direction=view["sun"])
    mask = view["in_site"] & view["hit"] & ~view["shadow"] & one_ray.hit & ~one_ray.shadow
    assert ncc(view["reflectance"].astype(float), one_ray.reflectance, mask) < 0.995

def test_global_scope_judges_the_whole_body(campaign, tmp_path):
    survey_dir = campaign / "truth" / "1-campaign-tiny-survey"
    truth = load_truth(survey_dir)
    write_ply(tmp_path / "truth.ply", truth.mesh)
    perfect = evaluate(tmp_path / "truth.ply", truth_dir=survey_dir, plots_dir=tmp_path / "plots")
    assert perfect["scope"] == "global"
    assert perfect["rms_gsd"] < 0.01 and perfect["completeness"] == 1.0
    assert perfect["ncc"] > 0.99
    assert perfect["boulder_height_ratio_min"] == pytest.approx(1.0, abs=0.02)
    assert len(perfect["boulders"]) == min(10, CAMPAIGNS["campaign-tiny"].boulders)
    for png in ("coverage.png", "vertex_error.png"):
        assert (tmp_path / "plots" / png).stat().st_size > 1000

    # the smooth body the survey could start from has no boulders, and misses none of the surface
    base = read_obj(SHAPES_DIR / MISSIONS["osiris-rex"].shape)
    smooth = start_model(truth, scenario=CAMPAIGNS["campaign-tiny"].survey, base=base, seed=2)
    write_ply(tmp_path / "smooth.ply", smooth)
    judged = evaluate(tmp_path / "smooth.ply", truth_dir=survey_dir)
    assert judged["rms_gsd"] > 0.1
    assert judged["boulder_height_ratio_median"] < 0.3

    # half the body missing is seen by the coverage, not by the distances from the model
    keep = smooth.vertices[smooth.faces].mean(axis=1)[:, 2] > 0
    half = Mesh(smooth.vertices, smooth.faces[keep])
    write_ply(tmp_path / "half.ply", half)
    holed = evaluate(tmp_path / "half.ply", truth_dir=survey_dir)
    assert holed["completeness"] < 0.6
    assert holed["rms_gsd"] < 2 * judged["rms_gsd"]


def test_a_scope_needs_the_truth_it_judges(campaign, tmp_path):
    # (a site truth judged at its own scope, the default there: tests/test_simulate.py)
    site_dir = campaign / "truth" / "2-campaign-tiny-site-a"
    write_ply(tmp_path / "site.ply", load_truth(site_dir).mesh)
    result = CliRunner().invoke(app, ["evaluate", str(tmp_path / "site.ply"), "--truth", str(site_dir),
                                      "--scope", "global"])
    assert result.exit_code == 2
    assert "survey downlink's truth" in result.output
    result = CliRunner().invoke(app, ["evaluate", str(tmp_path / "site.ply"), "--truth",
                                      str(campaign / "truth" / "1-campaign-tiny-survey"), "--scope", "site"])
    assert result.exit_code == 2
    assert "a site downlink's truth" in result.output


def test_a_quadric_ground_measures_a_boulder_on_a_curved_body():
    axis = np.linspace(-0.045, 0.045, 181)
    x, y = np.meshgrid(axis, axis)
    ground = -(x**2 + y**2) / (2 * 0.25)  # a 250 m body's curvature: 4 m down at 45 m
    boulder = np.where(np.hypot(x, y) < 0.015, 0.005, 0.0)
    flat = boulder_height_ratio(axis, axis, ground + boulder, ground, centres_km=np.zeros((1, 2)),
                                diameters_km=np.array([0.03]))[0]
    curved = boulder_height_ratio(axis, axis, ground + boulder, ground, centres_km=np.zeros((1, 2)),
                                  diameters_km=np.array([0.03]), curved=True)[0]
    assert flat > 0.3  # the ring's median lies below the foot, and a missing boulder looks half there
    assert abs(curved) < 1e-6
