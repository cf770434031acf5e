"""The proving ground: a simulated downlink is real PDS4 and SPICE, and agrees with its truth."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pds4_tools
import pytest
import spiceypy as sp

from pwm.camera import Camera
from pwm.evaluate.report import evaluate
from pwm.io.pds4 import read_image_product
from pwm.io.spice_geometry import camera_pose
from pwm.io.spice_kernels import kernel_pool
from pwm.knowledge import IndependentErrors
from pwm.raytrace import RayTracer
from pwm.render import render
from pwm.simulate.campaign import simulate
from pwm.simulate.scenarios import get_scenario
from pwm.simulate.truth import load as load_truth


def manifest(out: Path) -> dict:
    return json.loads((out / "truth" / "manifest.json").read_text())


def metakernel(out: Path) -> Path:
    (mk,) = (out / "downlink" / "kernels" / "mk").glob("*.tm")
    return mk


def test_every_product_reads_with_pds4_tools_and_its_checksum_matches(tiny_sim):
    labels = sorted((tiny_sim / "downlink" / "images").glob("*.xml"))
    assert len(labels) == manifest(tiny_sim)["image_count"] == get_scenario("tiny").n_images
    for label in labels:
        structures = pds4_tools.read(str(label), lazy_load=False, quiet=True)
        image = structures[1] if len(structures) > 1 else structures[0]
        assert image.data.shape == (320, 320)
        product = read_image_product(label)  # raises on any size or md5 mismatch
        assert hashlib.md5(product.data_path.read_bytes()).hexdigest() == product.md5
        assert product.instrument_name == "ORX_OCAMS_MAPCAM" and product.target_name == "Bennu"
        assert (product.first_line, product.first_sample) == (352, 352)
        assert np.nanmax(product.data) > 0.5 * np.nanmax(product.data[product.data > 0])


def test_downlink_manifest_lists_every_file_with_its_checksum(tiny_sim):
    downlink = tiny_sim / "downlink"
    listed = json.loads((downlink / "manifest.json").read_text())["files"]
    on_disk = {p.relative_to(downlink).as_posix() for p in downlink.rglob("*") if p.is_file()} - {"manifest.json"}
    assert {f["path"] for f in listed} == on_disk
    for entry in listed:
        assert hashlib.sha256((downlink / entry["path"]).read_bytes()).hexdigest() == entry["sha256"]


def test_a_copied_downlinks_metakernel_loads_its_own_kernels(tiny_sim, tmp_path):
    """The meta-kernel names its kernels relative to itself (PATH_VALUES, which SPICE resolves
    from the working directory, as mission archives' meta-kernels do): run from its own folder,
    a copy of the downlink loads the copy's kernels, not the original's."""
    image = manifest(tiny_sim)["images"][0]
    copy = shutil.copytree(tiny_sim / "downlink", tmp_path / "copy")
    mk = copy / metakernel(tiny_sim).relative_to(tiny_sim / "downlink")
    code = (
        "import spiceypy as sp, sys\n"
        f"sp.furnsh({mk.name!r})\n"
        f"p, _ = sp.spkpos('-64', {image['et']!r}, 'IAU_BENNU', 'NONE', 'BENNU')\n"
        "print(*p)\n"
        "for k in range(sp.ktotal('ALL')):\n"
        "    print(sp.kdata(k, 'ALL')[0])\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=mk.parent, capture_output=True, text=True, check=True)
    first, *loaded = done.stdout.splitlines()
    np.testing.assert_allclose([float(v) for v in first.split()], image["position_km"], atol=1e-9)
    assert len(loaded) > 5
    assert all((mk.parent / path).resolve().is_relative_to(copy) for path in loaded), loaded


def test_geometry_matches_the_plan(tiny_sim):
    m = manifest(tiny_sim)
    sc = get_scenario("tiny")
    incidences = np.array([im["site_incidence_deg"] for im in m["images"]])
    emissions = np.array([im["site_emission_deg"] for im in m["images"]])
    assert incidences.min() > 20 and incidences.max() < 75
    assert np.sum(emissions < 1.0) == sc.n_nadir
    assert np.allclose(emissions[emissions > 1.0], 30.0, atol=0.5)
    # the Sun stands both east and west of the site across the set
    azimuths = np.array([im["site_sun_azimuth_deg"] for im in m["images"]])
    assert (azimuths < 180).any() and (azimuths >= 180).any()
    gsd = np.array([im["site_gsd_m"] for im in m["images"]])
    np.testing.assert_allclose(gsd, m["gsd_m"], rtol=1e-3)


def _project_with_kernels(point: np.ndarray, et: float, first_line: int, first_sample: int) -> np.ndarray:
    """Pixel of a body-fixed point from the kernel pool alone, with the IK's own units (mm, micron)
    and its image axes (samples along NAXIS1, lines along NAXIS2 of the instrument frame)."""
    position, _ = sp.spkpos("-64", et, "IAU_BENNU", "NONE", "BENNU")
    rotation = sp.pxform("IAU_BENNU", "ORX_OCAMS_MAPCAM", et)
    focal_px = sp.gdpool("INS-64361_FOCAL_LENGTH", 0, 1)[0] / (sp.gdpool("INS-64361_PIXEL_SIZE", 0, 1)[0] * 1e-3)
    cx, cy = sp.gdpool("INS-64361_CCD_CENTER", 0, 2)
    naxis1, naxis2 = sp.gdpool("INS-64361_SPOC_FITS_NAXIS1", 0, 3), sp.gdpool("INS-64361_SPOC_FITS_NAXIS2", 0, 3)
    p = rotation @ (point - position)
    return np.array([focal_px * (naxis1 @ p) / p[2] + cx - first_sample,
                     focal_px * (naxis2 @ p) / p[2] + cy - first_line])


def test_a_truth_point_lands_where_the_renderer_drew_a_marker(tiny_sim):
    truth = load_truth(tiny_sim / "truth")
    m = manifest(tiny_sim)
    # A spot where the rock field blends into the smooth base: on rough ground a round albedo
    # spot is not round in the image, and its centroid says nothing about the geometry.
    row = len(truth.y_km) // 2
    col = int(np.argmin(np.abs(truth.x_km - 0.83 * truth.x_km[-1])))
    assert truth.blend_weight()[row, col] < 0.5
    point = truth.site_frame.to_body(np.array([truth.x_km[col], truth.y_km[row], truth.height_km[row, col]]))

    sigma_km = 1.0 * m["gsd_m"] * 1e-3
    bump = np.exp(-0.5 * np.sum((truth.mesh.vertices - point) ** 2, axis=1) / sigma_km**2)
    tracer = RayTracer(truth.mesh)
    c = m["camera"]
    camera = Camera(width=c["width"], height=c["height"], fx=c["fx"], fy=c["fy"], cx=c["cx"], cy=c["cy"])
    checked = 0
    lines, samples = np.mgrid[0 : camera.height, 0 : camera.width]
    with kernel_pool([metakernel(tiny_sim)]):
        for image in m["images"]:
            pose = camera_pose(et=image["et"], instrument_id=-64361, target="BENNU", body_frame="IAU_BENNU")
            sun = np.array(image["sun_direction"])
            plain = render(tracer, camera=camera, pose=pose, sun_direction=sun)
            marked = render(tracer, camera=camera, pose=pose, sun_direction=sun, albedo=truth.mesh.albedo * (1 + bump))
            lit = plain.reflectance > 0
            signal = np.where(lit, marked.reflectance / np.where(lit, plain.reflectance, 1.0) - 1.0, 0.0)
            if signal.max() < 0.5:
                continue  # the spot is in shadow or hidden in this view
            expected = _project_with_kernels(point, image["et"], m["subframe"]["first_line"],
                                             m["subframe"]["first_sample"])
            near = np.hypot(samples - expected[0], lines - expected[1]) < 8.0
            w = signal * near
            drawn = np.array([np.sum(w * samples), np.sum(w * lines)]) / w.sum()
            assert np.linalg.norm(drawn - expected) < 0.1, (image["name"], drawn, expected)
            checked += 1
    assert checked == len(m["images"])


def test_truth_against_itself_is_perfect(tiny_sim, tmp_path):
    result = evaluate(tiny_sim / "truth" / "mesh.ply", truth_dir=tiny_sim / "truth", plots_dir=tmp_path)
    assert result["scope"] == "site"  # the default for a site downlink's truth
    assert result["rms_gsd"] < 0.01
    assert result["ncc"] > 0.99
    assert result["boulder_height_ratio_median"] == pytest.approx(1.0, abs=0.02)
    assert result["largest_boulder_height_ratio_min"] == pytest.approx(1.0, abs=0.02)
    assert result["tail"]["squared_error_share"] == 0.0
    assert all(c["rms"] < 0.01 * result["gsd_m"] for c in result["boulder_sizes_m"].values() if c["nodes"])
    assert (tmp_path / "height_error.png").stat().st_size > 1000


def test_start_model_is_worse_than_a_pixel(tiny_sim):
    result = evaluate(tiny_sim / "downlink" / "start_model.obj", truth_dir=tiny_sim / "truth")
    assert result["rms_gsd"] > 1.0
    tail = result["tail"]  # the few vertices of a 30 GSD low-pass far off (boulders' tops) carry more than their share
    assert tail["squared_error_share"] > 2 * tail["vertex_share"] > 0
    assert result["largest_boulder_height_ratio_min"] < 0.7
    assert "ncc" not in result  # the start model carries no albedo


def test_knowledge_errors_go_into_the_kernels_not_the_images(tmp_path):
    sc = get_scenario("tiny").model_copy(update={"n_nadir": 1, "n_azimuths": 2, "n_validation": 0, "subframe_px": 64})
    out = tmp_path / "sim"
    m = simulate(out, scenario=sc, seed=5, knowledge=IndependentErrors(position_m=1.0, pointing_rad=1e-4))
    assert m["image_count"] == sc.n_images == 3
    offsets, angles = [], []
    with kernel_pool([metakernel(out)]):
        for image in m["images"]:
            pose = camera_pose(et=image["et"], instrument_id=-64361, target="BENNU", body_frame="IAU_BENNU")
            offsets.append(np.linalg.norm(pose.position - image["position_km"]) * 1e3)
            delta = pose.rotation @ np.array(image["rotation"]).T
            angles.append(np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1)))
    # 3-D norms of 1-sigma-per-axis errors: between ~0.1 and ~4 sigma for any draw we would accept
    assert all(0.05 < o < 5.0 for o in offsets), offsets
    assert all(5e-6 < a < 5e-4 for a in angles), angles
