"""Weighing a simulated downlink's catalogued images against a shape model (service.conductor
.weigh) tiles the site and fills the image-maplet coverage rows with the geometry the simulator
planned."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree
from sqlalchemy import delete, func, select, update

from pwm.config import RefinementConfig
from pwm.footprints import places, seen_samples
from pwm.io.meshio import read_mesh
from pwm.raytrace import RayTracer
from pwm.simulate.truth import load as load_truth
from pwm.tiling import level_of, tile
from service.conductor import weigh
from service.coverage import update_coverage
from service.ingest import ingest_directory
from service.queries import count_maplets, list_maplets, maplet_coverage
from service.rows import Coverage, CoverageRole, Image, ImageGeometry, Maplet
from service.views import catalog_views


def _nadir(plan: dict) -> bool:
    """A planned nadir view: its emission at the site is zero up to the rounding of the pose
    through the kernels (about 1e-6 deg)."""
    return plan["site_emission_deg"] < 1e-3


def _rows(session) -> list[tuple]:
    """Every coverage row's values, by image and maplet."""
    return sorted((c.image_id, c.maplet_id, c.visible_fraction, c.shadowed_fraction,
                   c.incidence_deg, c.emission_deg, c.phase_deg, c.sun_azimuth_deg, c.camera_azimuth_deg,
                   c.resolution_m_per_px, c.weight, c.role)
                  for c in session.scalars(select(Coverage)))


def _maplets(session) -> list[tuple]:
    return list(session.execute(select(Maplet.id, Maplet.name, Maplet.region_weight)
                                .order_by(Maplet.id)))


def test_weighing_a_downlink_fills_the_coverage_of_the_site(tiny_sim, catalog):
    shape = read_mesh(tiny_sim / "downlink" / "start_model.obj")
    ingest_directory(catalog, tiny_sim / "downlink", shape=shape)
    report = weigh(catalog, shape)
    manifest = json.loads((tiny_sim / "truth" / "manifest.json").read_text())
    site = manifest["scenario"]
    plans = {im["label"].split("/")[-1]: im for im in manifest["images"]}
    assert report.maplets_added > 1
    with catalog() as session:
        near = list_maplets(session, lat_deg=site["site_lat_deg"], lon_deg=site["site_lon_deg"],
                            radius_km=site["site_size_km"] / 2)
        assert len(near) > 1 and all(m.image_count > 0 for m in near)
        centre = near[0]
        assert centre.distance_km == 0.0
        assert centre.gsd_m == pytest.approx(manifest["gsd_m"], rel=0.05)
        summary = maplet_coverage(session, name=centre.name)
        assert summary.image_count == manifest["image_count"]
        assert 0 < summary.region_weight <= 1 and summary.used_count >= 3
        rows = session.execute(select(Coverage, Image.label_path).join(Image)
                               .where(Coverage.maplet_id == centre.id)).all()
        planned = [(row, plans[path.split("/")[-1]]) for row, path in rows]
        # The maplet's normal (regional, of the start model) is off the site's by the emission
        # of a nadir image, which bounds how far any incidence may differ from the plan's.
        tilt = min(row.emission_deg for row, plan in planned if _nadir(plan))
        assert tilt < 10.0
        normal = np.asarray(session.get(Maplet, centre.id).rotation)[2]
        for row, plan in planned:
            assert abs(row.incidence_deg - plan["site_incidence_deg"]) <= tilt + 0.1
            assert abs(row.phase_deg - plan["site_phase_deg"]) < 0.1  # no normal in it
            g = row.image.geometry
            sun = np.array([g.sun_x, g.sun_y, g.sun_z])
            assert np.degrees(np.arccos(normal @ sun / np.linalg.norm(sun))) == pytest.approx(
                row.incidence_deg, abs=1e-6)
            # Azimuths from local north towards east: a tilted normal turns them by a few tilts.
            turn = (row.sun_azimuth_deg - plan["site_sun_azimuth_deg"] + 180.0) % 360.0 - 180.0
            assert abs(turn) < 3 * tilt
            assert row.resolution_m_per_px == pytest.approx(plan["site_gsd_m"], rel=0.01)
            assert row.visible_fraction > 0.9
        [(nadir, plan)] = [(row, plan) for row, plan in planned if row.role is CoverageRole.NADIR]
        assert _nadir(plan) and summary.views[CoverageRole.NADIR] == (
            nadir.image.lidvid)
        incidences = [plan["site_incidence_deg"] for row, plan in planned if row.weight > 0]
        assert np.allclose(summary.incidence_deg, (min(incidences), max(incidences)),
                           atol=tilt + 0.1)
        before, maplets = _rows(session), _maplets(session)

    ingest_directory(catalog, tiny_sim / "downlink", shape=shape)
    again = weigh(catalog, shape)
    assert again.maplets_added == again.rows_added == 0
    assert again.rows_updated == again.rows_deleted == 0
    with catalog() as session:
        assert _rows(session) == before and _maplets(session) == maplets
        # An image taken up later gets the same rows as if it had come with the others.
        dropped = session.execute(delete(Coverage).where(
            Coverage.image_id == rows[0][0].image_id)).rowcount
        added = update_coverage(session, shape)
        session.commit()
        assert dropped > 0 and added.rows_added == dropped and added.rows_updated == 0
        assert _rows(session) == before and _maplets(session) == maplets


def test_a_survey_is_tiled_wherever_its_images_see_enough_and_nowhere_else(global_tiny_sim, catalog):
    """Issue 15.2: no disc about a mean intercept; the places that at least min_images images
    see usably, over the whole body, at the images' pixel scale."""
    truth = load_truth(global_tiny_sim / "truth").mesh
    config = RefinementConfig(nodes=16)
    ingest_directory(catalog, global_tiny_sim / "downlink", shape=truth)
    report = weigh(catalog, truth, config=config)
    with catalog() as session:
        views = list(catalog_views(session).values())
        maplets = session.execute(select(Maplet.origin_x_km, Maplet.origin_y_km, Maplet.origin_z_km,
                                         Maplet.size_km, Maplet.gsd_m)).all()
    assert report.maplets_added == len(maplets) > 0
    seen = seen_samples(RayTracer(truth), views, rules=config.rules, min_images=config.min_images)
    origins = np.array([m[:3] for m in maplets])
    # the survey's places lie round the body, far apart (Bennu's radius is 0.25 km): not one disc
    assert len(places(seen, nodes=16, spacing_gsd=1.0)) > 1
    assert max(np.linalg.norm(origins - o, axis=1).max() for o in origins) > 0.3
    # every seen sample lies under a maplet, and every maplet over seen ground
    size = maplets[0][3]
    assert cKDTree(origins).query(seen.points)[0].max() <= np.sqrt(0.5) * size
    assert cKDTree(seen.points).query(origins)[0].max() <= size
    # at the pixel scale of the images that see it (4 m; none coarser than twice the finest)
    gsd = np.array([m[4] for m in maplets])
    assert np.allclose(gsd, np.median(seen.pixel_km) * 1e3, rtol=0.25)
    # and a good part of the body is seen too little to be tiled (which makes the above a test)
    far = cKDTree(seen.points).query(truth.vertices)[0] > size
    assert far.mean() > 0.15


def test_coverage_makes_views_only_of_the_images_that_may_see_the_new_ones_place(tiny_sim, catalog, caplog):
    """Issue 16.4: the work of a downlink's coverage grows with the images about its place, not
    with the catalog: images looking elsewhere are never made views, and no view needs its label."""
    shape = read_mesh(tiny_sim / "downlink" / "start_model.obj")
    ingest_directory(catalog, tiny_sim / "downlink", shape=shape)
    weigh(catalog, shape)
    with catalog() as session:
        images = session.scalars(select(Image).order_by(Image.id)).all()
        assert all(image.window() == (image.window()[0], image.window()[1], 320, 320) for image in images)
        g = images[0].geometry
        axis = np.array([g.cone_axis_x, g.cone_axis_y, g.cone_axis_z])
        assert axis @ np.asarray(g.camera_rotation)[2] > 0.999  # about the boresight
        assert 0 < g.cone_half_angle_rad < 0.1
        before = _rows(session)
    with catalog.begin() as session:
        # far-side images whose labels are gone: making a view of one would fail
        template = session.get_one(Image, images[0].id)
        for k in range(40):
            twin = Image(lidvid=f"urn:nasa:pds:far:side{k}::1.0", lid=f"urn:nasa:pds:far:side{k}", vid="1.0",
                         label_path="/nonexistent/label.xml", data_path="/nonexistent/data.img", sha256="0" * 64,
                         size_bytes=1, instrument_id=template.instrument_id, target=template.target,
                         start_utc=template.start_utc, stop_utc=template.stop_utc, start_et=template.start_et,
                         stop_et=template.stop_et, status=template.status, geometry_status=template.geometry_status,
                         coverage_computed_at=template.coverage_computed_at)
            position = -np.array([g.camera_x_km, g.camera_y_km, g.camera_z_km])
            twin.geometry = ImageGeometry(
                camera_x_km=position[0], camera_y_km=position[1], camera_z_km=position[2],
                camera_rotation=(-np.asarray(g.camera_rotation)).tolist(), sun_x=g.sun_x, sun_y=g.sun_y,
                sun_z=g.sun_z, range_km=g.range_km, cone_axis_x=-axis[0], cone_axis_y=-axis[1],
                cone_axis_z=-axis[2], cone_half_angle_rad=g.cone_half_angle_rad, body_frame=g.body_frame,
                abcorr=g.abcorr)
            session.add(twin)
    # the site's images weighed again, as after a pose correction, with the far side catalogued
    with catalog.begin() as session:
        session.execute(delete(Coverage))
        caplog.set_level("INFO", logger="service.coverage")
        report = update_coverage(session, shape, image_ids=[image.id for image in images])
    assert report.maplets_weighed > 0
    assert f"{len(images)} of {len(images) + 40} images made views" in caplog.text
    with catalog() as session:
        assert _rows(session) == before


def test_a_later_downlink_is_weighed_into_the_stored_rows_as_weighing_all_again_would(tiny_sim, catalog):
    """Issue 16.4: a maplet's catalogued images bring their stored rows; only the new images are
    traced, and the weights, roles and w_PWM come out as those of weighing every image again."""
    shape = read_mesh(tiny_sim / "downlink" / "start_model.obj")
    ingest_directory(catalog, tiny_sim / "downlink", shape=shape)
    full = weigh(catalog, shape)
    with catalog() as session:
        before, maplets = _rows(session), _maplets(session)
        ids = sorted(session.scalars(select(Image.id)))
    later, earlier = ids[1::2], ids[0::2]
    with catalog.begin() as session:
        # the later half arrives after the earlier half was weighed; the earlier half's weights,
        # roles and w_PWM are those of a catalog without it, here scrambled to show that they
        # are weighed again from the stored geometry
        session.execute(delete(Coverage).where(Coverage.image_id.in_(later)))
        session.execute(update(Coverage).values(weight=0.5, role=None))
        session.execute(update(Maplet).values(region_weight=0.5))
        # a row weighed before its camera azimuth was kept: its image is traced again
        legacy = session.scalars(select(Coverage).where(Coverage.image_id == earlier[0])).first()
        legacy.camera_azimuth_deg = None
        session.execute(update(Image).where(Image.id.in_(later)).values(coverage_computed_at=None))
    with catalog.begin() as session:
        report = update_coverage(session, shape, image_ids=later)
    assert report.maplets_added == 0 and report.rows_deleted == 0
    assert report.maplets_weighed == full.maplets_weighed
    # the later half and the one legacy row traced, not the earlier half
    assert report.pairs_traced <= len(later) * report.maplets_weighed + 1
    assert report.pairs_traced < 0.6 * full.pairs_traced
    with catalog() as session:
        assert _rows(session) == before
        assert _maplets(session) == maplets


@pytest.mark.parametrize("coarser", [4.0, 1.5])
def test_finer_images_nest_maplets_of_their_level_under_coarser_ones(tiny_sim, catalog, coarser):
    """Issue 16.1: over maplets at least twice as coarse as a downlink's images (an earlier
    survey's), the downlink tiles its place again at its own level; the coarse maplets stay, are
    weighed too, and the levels are told apart by the queries. Over maplets less than twice as
    coarse it tiles nothing."""
    shape = read_mesh(tiny_sim / "downlink" / "start_model.obj")
    manifest = json.loads((tiny_sim / "truth" / "manifest.json").read_text())
    site = manifest["scenario"]
    gsd_km = manifest["gsd_m"] * 1e-3
    survey = tile(shape, spacing_km=coarser * gsd_km, nodes=40, centre_lat_deg=site["site_lat_deg"],
                  centre_lon_deg=site["site_lon_deg"], radius_km=site["site_size_km"])
    with catalog.begin() as session:
        session.add_all(Maplet.of(m) for m in survey)
    ingest_directory(catalog, tiny_sim / "downlink", shape=shape)
    report = weigh(catalog, shape)
    fine, coarse = int(level_of(gsd_km)), int(level_of(coarser * gsd_km))
    with catalog() as session:
        levels = dict(session.execute(select(Maplet.level, func.count()).group_by(Maplet.level)).all())
        assert levels[coarse] == len(survey)
        site_point = dict(lat_deg=site["site_lat_deg"], lon_deg=site["site_lon_deg"])
        if coarser < 2.0:
            assert report.maplets_added == 0 and levels == {coarse: len(survey)}
            return
        assert fine != coarse and report.maplets_added == levels[fine] > 0
        assert count_maplets(session, level=fine) == report.maplets_added
        here = list_maplets(session, **site_point)
        assert {m.level for m in here} == {fine, coarse}  # the site's maplet and the survey's above it
        [finest] = list_maplets(session, **site_point, level=fine)
        assert finest.gsd_m == pytest.approx(manifest["gsd_m"], rel=0.05) and finest.name.endswith(f"L{fine:+d}")
        # both levels weighed in the new images: the coarse maplets with the images no more than
        # twice as coarse as them, all of these
        weighed = dict(session.execute(select(Maplet.level, func.count(Coverage.id)).join(Coverage)
                                       .where(Coverage.weight > 0).group_by(Maplet.level)).all())
        assert weighed[fine] > 0 and weighed[coarse] > 0
