"""The refinement chain on a simulated downlink: maplets refined from the images get closer to
the truth than the start model, and their fusion is a valid model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pwm.config import DEFAULTS, RefinementConfig
from pwm.decimate import decimate
from pwm.io.downlink import read_downlink
from pwm.io.meshio import read_mesh
from pwm.maplets import Spots
from pwm.mesh import Mesh
from pwm.pipeline import fuse, imaged_region, refine_maplets, refine_region
from pwm.raytrace import RayTracer
from pwm.simulate.truth import load as load_truth
from pwm.tiling import sample_heights, tile


def test_refined_maplets_beat_the_start_and_fuse(tiny_sim):
    views = read_downlink(tiny_sim / "downlink").views
    start = read_mesh(tiny_sim / "downlink" / "start_model.obj")
    truth = load_truth(tiny_sim / "truth")
    region = imaged_region(views, start)
    assert abs(region.spacing_km - 5e-5) < 2e-6  # the tiny scenario's 5 cm GSD
    maplets = tile(start, spacing_km=region.spacing_km, nodes=48, overlap=0.25, centre_lat_deg=region.lat_deg,
                   centre_lon_deg=region.lon_deg, radius_km=0.0015)
    results = refine_maplets(maplets, views, start, workers=2)
    truth_tracer = RayTracer(truth.mesh)
    start_err, refined_err, start_offset, refined_offset = [], [], [], []
    for original, result in zip(maplets, results, strict=True):
        assert len(result.images) >= 3 and 0 < result.region_weight <= 1
        true_h = sample_heights(truth_tracer, original)
        # heights are compared after removing the mean: photometry does not see a common offset
        start_err.append(np.std(original.heights - true_h))
        refined_err.append(np.std(result.maplet.heights - true_h))
        # which the images' parallax places (the poses are exact here)
        start_offset.append(abs(np.mean(original.heights - true_h)))
        refined_offset.append(abs(np.mean(result.maplet.heights - true_h)))
    assert np.mean(refined_err) < 0.8 * np.mean(start_err), (start_err, refined_err)
    # each node's 1-sigma height: where it says more, the error is larger
    errors = np.concatenate([np.abs(r.maplet.heights - sample_heights(truth_tracer, m)
                                    - np.mean(r.maplet.heights - sample_heights(truth_tracer, m))).ravel()
                             for m, r in zip(maplets, results, strict=True)])
    sigmas = np.concatenate([r.maplet.sigma.ravel() for r in results])
    told = np.isfinite(sigmas)
    assert told.mean() > 0.9 and np.all(sigmas[told] >= DEFAULTS.uncertainty.floor_spacings * region.spacing_km)
    high = sigmas > np.quantile(sigmas[told], 0.9)
    low = sigmas < np.quantile(sigmas[told], 0.5)
    assert np.median(errors[high]) > 1.5 * np.median(errors[low])
    assert np.median(refined_offset) < np.median(start_offset) + 0.5 * region.spacing_km, (start_offset, refined_offset)

    model, grid = fuse([r.maplet for r in results], start, overlap=0.25)
    assert model.albedo is not None and len(model.faces) > len(start.faces)
    # the fused sigmas: over the maplets, within the range of theirs; none beyond them
    assert model.sigma is not None
    assert np.isnan(model.sigma).any() and np.nanmax(model.sigma) <= np.max(sigmas[told]) * (1 + 1e-9)
    # no holes over the refined region: rays down every maplet's nodes hit the fused model
    tracer = RayTracer(model)
    for m in maplets:
        nodes = m.nodes_body().reshape(-1, 3)[:: 7]
        hits = tracer.intersect(nodes + 0.01 * m.frame.normal, np.broadcast_to(-m.frame.normal, nodes.shape))
        assert hits.hit.all()


def test_a_maplet_nested_under_a_coarse_model_is_placed_by_its_images_parallax(tiny_sim):
    """A start four levels coarser than the maplets and 25 cm (5 GSD, several pixels of parallax)
    too high: the joint solution alone would keep that mean height; the sweep of rises and the
    offsets' parallax bring the maplets down to the truth."""
    views = read_downlink(tiny_sim / "downlink").views
    start = read_mesh(tiny_sim / "downlink" / "start_model.obj")
    coarse = decimate(start, len(start.faces) // 6)
    coarse = Mesh(coarse.vertices * (1 + 2.5e-4 / np.linalg.norm(coarse.vertices, axis=1, keepdims=True)), coarse.faces)
    truth_tracer = RayTracer(load_truth(tiny_sim / "truth").mesh)
    maplets = tile(coarse, spacing_km=5e-5, nodes=48, overlap=0.25, centre_lat_deg=10.0, centre_lon_deg=40.0,
                   radius_km=0.0015)
    results = refine_maplets(maplets, views, coarse, workers=2)
    before = [float(np.mean(m.heights - sample_heights(truth_tracer, m))) for m in maplets]
    after = [float(np.mean(r.maplet.heights - sample_heights(truth_tracer, m))) for m, r in
             zip(maplets, results, strict=True)]
    assert np.mean(before) > 1.2e-4  # the maplets start over 12 cm too high, on average
    # most are brought within a few centimetres (six images: a sweep may also pick a wrong rise,
    # and which ones does differ between hosts: 3 of 9 on one, by 32-65 cm, fewer on another,
    # 4 of 9 on a third, one of them by 10.1 cm)
    assert np.median(np.abs(after)) < 0.3 * np.median(np.abs(before)), (before, after)
    assert np.mean(np.abs(after) < 1e-4) >= 5 / 9, (before, after)


def test_a_maplet_over_lidar_spots_is_placed_on_them(tiny_sim):
    """The same start 25 cm too high, and the truth measured by lidar spots (every 16th node of the
    site's grid, 20 cm apart, 2 cm noise): the spots, found for each maplet in the worker
    processes, place every refined maplet within a few centimetres, most within one, which its
    images' parallax does only for most (the test before)."""
    views = read_downlink(tiny_sim / "downlink").views
    start = read_mesh(tiny_sim / "downlink" / "start_model.obj")
    coarse = decimate(start, len(start.faces) // 6)
    coarse = Mesh(coarse.vertices * (1 + 2.5e-4 / np.linalg.norm(coarse.vertices, axis=1, keepdims=True)), coarse.faces)
    truth = load_truth(tiny_sim / "truth")
    truth_tracer = RayTracer(truth.mesh)
    grid = truth.mesh.vertices[truth.n_base_vertices:].reshape(*truth.height_km.shape, 3)[::16, ::16].reshape(-1, 3)
    rng = np.random.default_rng(7)
    sigma_km = 2e-5
    measured = grid + rng.normal(0.0, sigma_km, (len(grid), 1)) * truth.site_frame.normal
    maplets = tile(coarse, spacing_km=5e-5, nodes=48, overlap=0.25, centre_lat_deg=10.0, centre_lon_deg=40.0,
                   radius_km=0.0015)
    results = refine_maplets(maplets, views, coarse, workers=2,
                             spots=Spots(body_km=measured, sigma_km=np.full(len(grid), sigma_km)))
    after = [float(np.mean(r.maplet.heights - sample_heights(truth_tracer, m))) for m, r in
             zip(maplets, results, strict=True)]
    before = [float(np.mean(m.heights - sample_heights(truth_tracer, m))) for m in maplets]
    refined = np.array([len(r.images) >= 3 for r in results])
    assert all(r.lidar_spots >= 100 for r in results)
    assert np.median(np.abs(after)) < 1.5e-5 and np.max(np.abs(np.array(after)[refined])) < 5e-5, after
    # a maplet too few images see keeps its start's shape, placed nearer its spots all the same
    # (its spots may cover only part of it: the site's grid ends under one); which maplets the
    # images see too little of differs between hosts, so every maplet is made one here
    unseen = refine_maplets(maplets, views, coarse, workers=2, config=dataclasses.replace(DEFAULTS, min_images=99),
                            spots=Spots(body_km=measured, sigma_km=np.full(len(grid), sigma_km)))
    placed = [float(np.mean(r.maplet.heights - sample_heights(truth_tracer, m))) for m, r in
              zip(maplets, unseen, strict=True)]
    assert all(r.iterations == 0 and r.maplet.sigma is None for r in unseen)
    assert np.all(np.abs(placed) < 0.6 * np.abs(before)), (before, placed)
    for m, r in zip(maplets, unseen, strict=True):  # the start's shape, moved by a plane
        moved = r.maplet.heights - m.heights
        assert max(np.abs(np.diff(moved, 2, axis=0)).max(), np.abs(np.diff(moved, 2, axis=1)).max()) < 1e-12


def test_a_second_pass_refines_the_first_pass_model(tiny_sim):
    views = read_downlink(tiny_sim / "downlink").views
    start = read_mesh(tiny_sim / "downlink" / "start_model.obj")
    truth_tracer = RayTracer(load_truth(tiny_sim / "truth").mesh)
    region = dataclasses.replace(imaged_region(views, start), radius_km=0.0015)
    with pytest.raises(ValueError, match="one pass"):
        refine_region(start, views, region, config=RefinementConfig(nodes=48, passes=0))
    first, _ = refine_region(start, views, region, config=RefinementConfig(nodes=48, passes=1), workers=2)
    told: list[tuple[str, int, int]] = []
    # two passes, and a third for the maplets that the second changed by more than half a node spacing
    config = RefinementConfig(nodes=48, passes=2, max_passes=3, settled_spacings=0.5)
    second, results = refine_region(start, views, region, config=config, workers=2,
                                    progress=lambda stage, done, total: told.append((stage, done, total)))
    assert second.albedo is not None
    # each pass's progress, from none to all of its maplets; one result per place, its last
    stages = {stage: total for stage, _, total in told}
    assert list(stages) == ["refine pass 1/3", "refine pass 2/3", "refine pass 3/3"]
    assert stages["refine pass 1/3"] == stages["refine pass 2/3"] == len(results) > stages["refine pass 3/3"] > 0
    assert told == [(stage, k, total) for stage, total in stages.items() for k in range(total + 1)]
    # on the second pass's maplets: its refined heights, the first pass's model and the start
    first_tracer, start_tracer = RayTracer(first), RayTracer(start)
    err = {"start": [], "first": [], "second": []}
    for result in results:
        m = result.maplet
        true_h = sample_heights(truth_tracer, m)
        err["start"].append(np.std(sample_heights(start_tracer, m) - true_h))
        err["first"].append(np.std(sample_heights(first_tracer, m) - true_h))
        err["second"].append(np.std(m.heights - true_h))
    mean = {k: float(np.mean(v)) for k, v in err.items()}
    assert mean["first"] < 0.8 * mean["start"] and mean["second"] < 1.05 * mean["first"], mean


def test_maplets_refined_in_processes_match_those_refined_here(tiny_sim):
    views = read_downlink(tiny_sim / "downlink").views
    start = read_mesh(tiny_sim / "downlink" / "start_model.obj")
    region = imaged_region(views, start)
    maplets = tile(start, spacing_km=region.spacing_km, nodes=24, overlap=0.25, centre_lat_deg=region.lat_deg,
                   centre_lon_deg=region.lon_deg, radius_km=0.0008)[:3]
    assert len(maplets) == 3
    here = refine_maplets(maplets, views, start, workers=1)
    spawned = refine_maplets(maplets, views, start, workers=2)
    assert [r.maplet.name for r in spawned] == [m.name for m in maplets]
    for a, b in zip(here, spawned, strict=True):
        assert a.images == b.images and a.iterations == b.iterations
        np.testing.assert_allclose(b.maplet.heights, a.maplet.heights, rtol=0, atol=1e-12)
