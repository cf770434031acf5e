"""A simulated downlink goes into the catalog with the geometry the simulator knows is true."""

from __future__ import annotations

import json

import numpy as np
from sqlalchemy import select

from service.ingest import ingest_directory
from service.models import Image, ImageStatus


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
