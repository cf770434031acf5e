"""Pose knowledge in operations (issue 18.3): a downlink whose kernels state their pose knowledge
is adjusted on the current model before its maplets are refined, unasked; the corrections, the
sigmas and what was done are kept; a knowledge from the configuration serves kernels that
state none; and each image's registration search follows its sigma."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select
from sqlalchemy.orm import selectinload

import service.conductor
from pwm.camera import Camera, Pose, project
from pwm.config import RefinementConfig
from pwm.knowledge import IndependentErrors
from service.conductor import feed_back, ingest_and_plan
from service.rows import Downlink, Image, Maplet
from service.run import run_directory
from service.spg import fed_back
from service.views import catalog_views, image_pose, kernel_pose
from tests.service.test_spg_catalog import SITE


def _line_of_sight_px(sim: Path, poses: dict[str, Pose]) -> float:
    """RMS over the images of where the true boresight's ground point lands, px from where it belongs."""
    manifest = json.loads((sim / "truth" / "manifest.json").read_text())
    c = manifest["camera"]
    camera = Camera(width=c["width"], height=c["height"], fx=c["fx"], fy=c["fy"], cx=c["cx"], cy=c["cy"])
    errors = []
    for image in manifest["images"]:
        truth = Pose(np.array(image["position_km"]), np.array(image["rotation"]))
        ground = truth.position + truth.boresight * image["site_range_km"]
        pose = poses[Path(image["label"]).stem]
        errors.append(np.linalg.norm(project(ground, camera, pose) - project(ground, camera, truth)))
    return float(np.sqrt(np.mean(np.square(errors))))


def _poses(catalog) -> tuple[dict[str, Pose], dict[str, Pose]]:
    """Per image (label stem): its kernels' pose and its corrected pose."""
    with catalog() as session:
        images = session.scalars(select(Image).options(selectinload(Image.geometry))).all()
        return ({Path(i.label_path).stem: kernel_pose(i) for i in images},
                {Path(i.label_path).stem: image_pose(i) for i in images})


def test_stated_knowledge_is_adjusted_unasked(tiny_nav_sim, catalog, tmp_path):
    plan = ingest_and_plan(catalog, tiny_nav_sim / "downlink", data_dir=tmp_path, **SITE)
    with catalog() as session:
        report = session.get_one(Downlink, plan.downlink_id).pose_adjustment
        assert report["knowledge"] == "nav:3,1,50,20" and report["source"].startswith("stated in pwm_tiny_sc")
        assert report["note"] == "adjusted" and report["images"] == 6
        assert report["los_posterior_px"] < 0.5 * report["los_prior_px"]
        names = {u["name"] for u in report["unknowns"]}
        assert {"misalignment x", "drift z", "arc 0 along constant"} <= names
        images = session.scalars(select(Image)).all()
        assert all(i.pose_corrected_at is not None and i.pose_sigma["knowledge"] == "nav:3,1,50,20" for i in images)
        views = catalog_views(session)
        # each image's registration searches what is left of its line of sight after the adjustment
        for image in images:
            sigma = image.pose_sigma["posterior"]["los_px"] / np.sqrt(2)
            assert views[image.id].los_sigma_px == pytest.approx(sigma) and sigma > 0
        corrections = {i.id: i.pose_correction() for i in images}
    kernels, corrected = _poses(catalog)
    before, after = _line_of_sight_px(tiny_nav_sim, kernels), _line_of_sight_px(tiny_nav_sim, corrected)
    assert after < 0.7 * before, (before, after)

    # the same downlink again: its images were adjusted under that knowledge, nothing is redone
    ingest_and_plan(catalog, tiny_nav_sim / "downlink", data_dir=tmp_path, **SITE)
    with catalog() as session:
        assert {i.id: i.pose_correction() for i in session.scalars(select(Image))} == corrections


def test_configured_knowledge_serves_kernels_that_state_none(tiny_sim, catalog, tmp_path):
    config = dataclasses.replace(SITE["config"], knowledge=IndependentErrors(position_m=1.0, pointing_rad=1e-4))
    plan = ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=tmp_path, config=config)
    with catalog() as session:
        report = session.get_one(Downlink, plan.downlink_id).pose_adjustment
        assert report["knowledge"] == "1,0.0001" and report["source"] == "configured"
        assert report["note"] == "adjusted" and report["unknowns"] == []  # every image free: none shared


def test_no_knowledge_no_adjustment(tiny_sim, catalog, tmp_path):
    plan = ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=tmp_path, **SITE)
    with catalog() as session:
        assert session.get_one(Downlink, plan.downlink_id).pose_adjustment is None
        assert all(i.pose_correction() is None and i.pose_sigma is None for i in session.scalars(select(Image)))
        assert all(v.los_sigma_px == 0.0 for v in catalog_views(session).values())


def test_knowledge_within_a_pixel_needs_no_adjustment(tiny_sim, catalog, tmp_path):
    config = dataclasses.replace(SITE["config"], knowledge=IndependentErrors(position_m=0.001, pointing_rad=1e-8))
    plan = ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=tmp_path, config=config)
    with catalog() as session:
        report = session.get_one(Downlink, plan.downlink_id).pose_adjustment
        assert report["note"] == "not adjusted: the knowledge keeps every line of sight within a pixel"
        images = session.scalars(select(Image)).all()
        assert all(i.pose_correction() is None for i in images)
        # what the knowledge allows is still what each image's registration searches
        assert all(0 < 3 * i.los_sigma_px() <= 1.0 for i in images)


def test_the_maplets_registrations_feed_back_into_the_adjustment(tiny_nav_sim, catalog, tmp_path, monkeypatch):
    """tiny's 3 m navigation errors are 60 px at its range: the first adjustment leaves them far
    beyond a pixel, so after the first fusion the maplets' registrations join the features in
    adjusting the poses again (service.spg.feed_back_registrations), once, and the maplets are
    refined again with the new poses."""
    weighings = []
    update_coverage = service.conductor.update_coverage

    def counted(*args, **kwargs):
        weighings.append(kwargs["image_ids"])
        return update_coverage(*args, **kwargs)

    monkeypatch.setattr(service.conductor, "update_coverage", counted)
    config = RefinementConfig(nodes=40, tile_radius_km=0.002, passes=1)
    report = run_directory(catalog, tiny_nav_sim / "downlink", data_dir=tmp_path, config=config, workers=2)
    assert len(report.versions) == 2  # the first fusion, and the one after the feedback
    assert len(weighings) == 2  # once after the first adjustment, once after the feedback
    with catalog() as session:
        adjustment = session.get_one(Downlink, report.plan.downlink_id).pose_adjustment
        feedback = adjustment["feedback"]
        assert feedback["note"] == "adjusted" and feedback["los_before_px"] == adjustment["los_posterior_px"]
        maplets = [m for m in session.scalars(select(Maplet)) if m.revisions]  # those with enough images
        first = [m for m in maplets if m.revisions[0].statistics["model_version"] == report.plan.base_version]
        # a landmark for each maplet of the first round; the new poses weigh in a few more
        assert feedback["landmarks"] == len(first) > 3 and feedback["observations"] >= 2 * feedback["landmarks"]
        assert len(maplets) >= len(first)
        for maplet in maplets:
            *earlier, again = (r.statistics for r in maplet.revisions)
            assert len(earlier) == (maplet in first)
            # each revision keeps where each image it used saw its landmark (observed pixels)
            assert set(again["registrations"]) <= set(again["images"]) and len(again["registrations"]) >= 2
            assert all(np.all(np.isfinite(xy)) for xy in again["registrations"].values())
            # refined again with the new poses, against the first fusion
            assert maplet.current_revision.statistics == again and again["model_version"] == report.versions[0]
        assert fed_back(session, report.plan.downlink_id)
    kernels, corrected = _poses(catalog)
    assert _line_of_sight_px(tiny_nav_sim, corrected) < 0.7 * _line_of_sight_px(tiny_nav_sim, kernels)
    # once per downlink: a second call changes nothing
    assert not feed_back(catalog, data_dir=tmp_path, downlink_id=report.plan.downlink_id,
                         version=report.versions[-1], config=config)
