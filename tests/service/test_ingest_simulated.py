"""A simulated downlink goes into the catalog with the geometry the simulator knows is true."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select

from pwm.simulate.campaign import simulate
from pwm.simulate.scenarios import get_scenario
from service.ingest import ingest_directory
from service.rows import Image, ImageStatus


def test_simulated_downlink_matches_the_truth_manifest(tiny_sim, catalog):
    report = ingest_directory(catalog, tiny_sim / "downlink")
    manifest = json.loads((tiny_sim / "truth" / "manifest.json").read_text())
    assert report.failed == 0 and report.images.accepted == manifest["image_count"]
    truth = {im["label"].split("/")[-1]: im for im in manifest["images"]}
    with catalog() as session:
        images = session.scalars(select(Image)).all()
        assert len(images) == manifest["image_count"]
        for image in images:
            assert image.status == ImageStatus.ACCEPTED
            true = truth[image.label_path.split("/")[-1]]
            g = image.geometry
            position = np.array([g.camera_x_km, g.camera_y_km, g.camera_z_km])
            assert np.linalg.norm(position - true["position_km"]) * 1e3 < 1e-3  # 1 mm
            delta = np.array(g.camera_rotation) @ np.array(true["rotation"]).T
            angle = np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1))
            assert angle < 1e-6
            assert np.allclose([g.sun_x, g.sun_y, g.sun_z], true["sun_direction"], atol=1e-6)


@pytest.fixture(scope="module")
def tiny_sim_seed4(tmp_path_factory) -> Path:
    """The tiny scenario with another seed than tiny_sim's: the same observation names, other
    products."""
    out = tmp_path_factory.mktemp("tiny-seed4") / "sim"
    simulate(out, scenario=get_scenario("tiny"), seed=4, with_start_model=True)
    return out


def test_simulations_of_different_seeds_ingest_side_by_side(tiny_sim, tiny_sim_seed4, catalog):
    other = tiny_sim_seed4
    first = ingest_directory(catalog, tiny_sim / "downlink")
    second = ingest_directory(catalog, other / "downlink")
    count = json.loads((other / "truth" / "manifest.json").read_text())["image_count"]
    assert (second.failed, second.images.accepted) == (0, count)
    assert first.images.accepted + second.images.accepted == 2 * count
    with catalog() as session:
        lidvids = session.scalars(select(Image.lidvid).where(
            Image.status == ImageStatus.ACCEPTED)).all()
    assert len(set(lidvids)) == 2 * count
    assert {lidvid.split(":")[3] for lidvid in lidvids} == {"pwm_sim_tiny_s3", "pwm_sim_tiny_s4"}
