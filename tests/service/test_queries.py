"""The catalog's maplet-indexed queries on real SQLite and PostgreSQL, over a small catalog
written by hand: maplets with real local frames on a 250 m sphere, images with geometry, and
coverage rows with roles. Also the `pwm images-near`, `pwm maplets` and `pwm coverage` commands."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from sqlalchemy import event, select
from sqlalchemy.orm import Session, sessionmaker
from typer.testing import CliRunner

from pwm.frames import LocalFrame, latlon_to_unit, local_frame, unit_to_latlon
from service.cli import app
from service.db import make_engine, make_sessionmaker, session_scope, upgrade
from service.queries import distance_to_square_km, images_covering, list_maplets, maplet_coverage, maplets_seen_by
from service.rows import Coverage, CoverageRole, Image, ImageGeometry, ImageStatus, Maplet, MapletRevision
from service.settings import get_settings

RADIUS_KM = 0.25
SIZE_KM = 0.02
HALF_KM = SIZE_KM / 2
T0 = datetime(2019, 3, 4, tzinfo=UTC)
NADIR, EAST, WEST, NORTH, SOUTH = CoverageRole
# A and B overlap across longitude 0; C's normal leans 25 deg east of the radial; D covers the
# north pole.
MAPLETS = {"A": (0.0, 1.5, 0.0), "B": (0.0, 358.5, 0.0), "C": (45.0, 90.0, 25.0),
           "D": (89.0, 200.0, 0.0)}


@dataclass(frozen=True)
class View:
    """A coverage row: image index, maplet, visible fraction, incidence, emission, Sun azimuth
    (deg), weight and role."""

    image: int
    maplet: str
    visible: float
    incidence: float
    emission: float
    sun_azimuth: float
    weight: float
    role: CoverageRole | None = None


VIEWS = [
    View(0, "A", 0.9, 30.0, 5.0, 350.0, 0.90, NADIR),
    View(1, "A", 0.8, 40.0, 30.0, 10.0, 0.70, EAST),
    View(2, "A", 0.7, 50.0, 32.0, 20.0, 0.50, WEST),
    View(3, "A", 0.8, 35.0, 28.0, 340.0, 0.60, NORTH),
    View(4, "A", 0.6, 45.0, 35.0, 0.0, 0.40, SOUTH),
    View(5, "A", 0.3, 85.0, 60.0, 180.0, 0.0),  # sees A, but with no weight
    View(6, "A", 0.0, 40.0, 20.0, 90.0, 0.80),  # occluded: does not see A
    View(0, "B", 0.9, 30.0, 6.0, 351.0, 0.20, NADIR),
    View(5, "B", 0.8, 40.0, 25.0, 5.0, 0.75, EAST),
    View(2, "C", 0.9, 45.0, 10.0, 120.0, 0.55, NADIR),
    View(3, "C", 0.5, 55.0, 38.0, 200.0, 0.30),
    View(4, "D", 0.9, 70.0, 10.0, 30.0, 0.35, NADIR),
]
N_IMAGES = 7


def _lidvid(k: int) -> str:
    return f"urn:nasa:pds:pwm_test:data_calibrated:img{k}::1.0"


def _frame(name: str) -> LocalFrame:
    lat, lon, lean_deg = MAPLETS[name]
    origin = RADIUS_KM * latlon_to_unit(lat, lon)
    radial = local_frame(origin, origin)
    lean = np.radians(lean_deg)
    east, _, up = radial.rotation
    return local_frame(origin, np.cos(lean) * up + np.sin(lean) * east)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _latlon(name: str, x_km: float, y_km: float) -> tuple[float, float]:
    """Latitude and longitude (deg) of the point (x, y) of a maplet's plane."""
    lat, lon = unit_to_latlon(_frame(name).to_body(np.array([x_km, y_km, 0.0])))
    return float(lat), float(lon)


def _fill(session: Session) -> None:
    maplets = {}
    for name in MAPLETS:
        frame = _frame(name)
        lat, lon = unit_to_latlon(frame.origin)
        maplets[name] = Maplet(
            name=name, center_lat_deg=float(lat), center_lon_deg=float(lon),
            origin_x_km=frame.origin[0], origin_y_km=frame.origin[1], origin_z_km=frame.origin[2],
            rotation=frame.rotation.ravel().tolist(), size_km=SIZE_KM, gsd_m=0.05,
            nodes_per_side=401, region_weight=0.5 if name == "B" else 1.0)
    revisions = [MapletRevision(maplet=maplets["A"], revision=k, input_hash=str(k) * 64,
                                mode="photoclinometry", artifact_path=f"A/{k}.npz", sha256="f" * 64)
                 for k in (1, 2)]
    maplets["A"].current_revision = revisions[1]
    images = []
    for k in range(N_IMAGES):
        lid, vid = _lidvid(k).split("::")
        camera = 2.0 * latlon_to_unit(10.0 * k, 30.0 * k)
        images.append(Image(
            lidvid=_lidvid(k), lid=lid, vid=vid, label_path=f"img{k}.xml", data_path=f"img{k}.img",
            sha256=f"{k}" * 64, size_bytes=1024, status=ImageStatus.ACCEPTED,
            # later images first: time order is not weight order
            start_utc=T0 - timedelta(hours=k),
            geometry=ImageGeometry(
                camera_x_km=camera[0], camera_y_km=camera[1], camera_z_km=camera[2],
                camera_rotation=np.eye(3).tolist(), sun_x=1.0, sun_y=0.0, sun_z=0.0,
                range_km=2.0 + k, body_frame="IAU_BENNU", abcorr="LT+S")))
    session.add_all([*maplets.values(), *images])
    session.flush()
    session.add_all(Coverage(
        image=images[v.image], maplet=maplets[v.maplet], visible_fraction=v.visible,
        shadowed_fraction=0.1, incidence_deg=v.incidence, emission_deg=v.emission,
        phase_deg=v.incidence + v.emission, sun_azimuth_deg=v.sun_azimuth,
        resolution_m_per_px=0.04, weight=v.weight, role=v.role) for v in VIEWS)


@pytest.fixture
def catalog(db_url: str) -> Iterator[sessionmaker[Session]]:
    """Sessions on the small catalog above, on SQLite and on PostgreSQL."""
    upgrade(db_url)
    engine = make_engine(db_url)
    sessions = make_sessionmaker(engine)
    with session_scope(sessions) as session:
        _fill(session)
    yield sessions
    engine.dispose()


def _seen(maplets: set[str]) -> dict[int, View]:
    """The heaviest visible view of each image among the given maplets."""
    best: dict[int, View] = {}
    for v in VIEWS:
        if v.maplet in maplets and v.visible > 0 and (
                v.image not in best or v.weight > best[v.image].weight):
            best[v.image] = v
    return best


def test_images_covering_a_point_in_two_overlapping_maplets(
    catalog: sessionmaker[Session],
) -> None:
    expected = _seen({"A", "B"})
    with catalog() as session:
        by_weight = images_covering(session, lat_deg=0.0, lon_deg=0.0)
        by_time = images_covering(session, lat_deg=0.0, lon_deg=360.0, order="time")
        first_two = images_covering(session, lat_deg=0.0, lon_deg=0.0, limit=2)
        assert images_covering(session, lat_deg=-45.0, lon_deg=270.0) == []
        with pytest.raises(ValueError):
            images_covering(session, lat_deg=91.0, lon_deg=0.0)
        with pytest.raises(ValueError):
            images_covering(session, lat_deg=0.0, lon_deg=0.0, radius_km=-1.0)
    assert [h.lidvid for h in by_weight] == [
        _lidvid(k) for k in sorted(expected, key=lambda k: -expected[k].weight)]
    assert 6 not in expected and 5 in expected  # image 6 is occluded in A
    assert [h.lidvid for h in by_time] == [_lidvid(k) for k in sorted(expected, reverse=True)]
    assert first_two == by_weight[:2]
    for hit in by_weight:
        view = expected[[_lidvid(k) for k in range(N_IMAGES)].index(hit.lidvid)]
        assert (hit.maplet, hit.weight, hit.incidence_deg, hit.emission_deg, hit.role) == (
            view.maplet, view.weight, view.incidence, view.emission, view.role)
        assert hit.phase_deg == view.incidence + view.emission
        assert hit.range_km == 2.0 + view.image
        assert hit.start_utc == T0 - timedelta(hours=view.image)
    # image 5 sees both: its row of B (weight 0.75) beats its weightless row of A
    assert next(h for h in by_weight if h.lidvid == _lidvid(5)).maplet == "B"


def test_point_tests_use_the_maplet_frame_and_the_radius(catalog: sessionmaker[Session]) -> None:
    """C leans 25 deg off the radial: points just in and just out of its square, along an edge
    and past a corner, where the radius turns the square into a rounded one."""
    c_images = {_lidvid(v.image) for v in VIEWS if v.maplet == "C"}
    with catalog() as session:
        def near(x: float, y: float, radius_km: float = 0.0) -> set[str]:
            lat, lon = _latlon("C", x * HALF_KM, y * HALF_KM)
            return {h.lidvid for h in images_covering(
                session, lat_deg=lat, lon_deg=lon, radius_km=radius_km * HALF_KM)}

        assert near(0.95, -0.95) == c_images
        assert near(-0.95, 0.95) == c_images
        assert near(1.05, 0.0) == set() and near(0.0, -1.05) == set()
        assert near(1.1, 0.0, radius_km=0.12) == c_images  # 0.10 from the edge
        assert near(1.1, 1.1, radius_km=0.12) == set()  # 0.14 from the corner
        assert near(1.1, 1.1, radius_km=0.16) == c_images
        # around the pole every longitude is near D's centre at latitude 89
        d_images = {_lidvid(v.image) for v in VIEWS if v.maplet == "D"}
        for lon in (0.0, 20.0, 200.0, 300.0):
            assert {h.lidvid for h in images_covering(
                session, lat_deg=89.8, lon_deg=lon)} == d_images
        listed = list_maplets(session, lat_deg=_latlon("C", 1.1 * HALF_KM, 0.0)[0],
                              lon_deg=_latlon("C", 1.1 * HALF_KM, 0.0)[1], radius_km=HALF_KM)
    assert [m.name for m in listed] == ["C"]
    assert listed[0].distance_km == pytest.approx(0.1 * HALF_KM, rel=1e-6)


def test_maplets_seen_by_an_image(catalog: sessionmaker[Session]) -> None:
    with catalog() as session:
        by_lidvid = maplets_seen_by(session, lidvid=_lidvid(3))
        image_id = session.scalar(select(Image.id).where(Image.lidvid == _lidvid(3)))
        by_id = maplets_seen_by(session, image_id=image_id)
        assert maplets_seen_by(session, lidvid=_lidvid(6)) == []  # occluded in its only maplet
        with pytest.raises(LookupError):
            maplets_seen_by(session, lidvid="urn:nasa:pds:pwm_test:data_calibrated:none::1.0")
        with pytest.raises(ValueError):
            maplets_seen_by(session, image_id=1, lidvid=_lidvid(0))
    assert by_lidvid == by_id
    assert [(m.maplet, m.weight, m.role) for m in by_lidvid] == [
        ("A", 0.60, NORTH), ("C", 0.30, None)]
    c = by_lidvid[1]
    assert (c.center_lat_deg, c.center_lon_deg) == pytest.approx((45.0, 90.0))
    assert (c.visible_fraction, c.incidence_deg, c.emission_deg) == (0.5, 55.0, 38.0)


def test_coverage_summary_of_a_full_and_of_a_partial_image_set(
    catalog: sessionmaker[Session],
) -> None:
    with catalog() as session:
        a = maplet_coverage(session, name="A")
        b = maplet_coverage(session, maplet_id=maplet_coverage(session, name="B").maplet_id)
        with pytest.raises(LookupError):
            maplet_coverage(session, name="Z")
    used = [v for v in VIEWS if v.maplet == "A" and v.visible > 0 and v.weight > 0]
    assert (a.image_count, a.used_count) == (6, 5)
    assert a.incidence_deg == (min(v.incidence for v in used), max(v.incidence for v in used))
    assert a.emission_deg == (min(v.emission for v in used), max(v.emission for v in used))
    # azimuths 340, 350, 0, 10, 20: 40 deg across 0/360, not 340
    assert a.sun_azimuth_spread_deg == pytest.approx(40.0)
    assert a.views == {v.role: _lidvid(v.image) for v in used}
    assert a.five_views and (a.region_weight, a.current_revision) == (1.0, 2)
    assert not b.five_views
    assert b.views == {NADIR: _lidvid(0), EAST: _lidvid(5), WEST: None, NORTH: None, SOUTH: None}
    assert (b.image_count, b.region_weight, b.current_revision) == (2, 0.5, None)
    assert b.sun_azimuth_spread_deg == pytest.approx(14.0)


def test_list_maplets_pages_by_name_or_by_distance(catalog: sessionmaker[Session]) -> None:
    with catalog() as session:
        everything = list_maplets(session)
        page = list_maplets(session, limit=2, offset=1)
        at_zero = list_maplets(session, lat_deg=0.0, lon_deg=0.0)
        # B ends 2.2 deg (9.6 m) west of longitude 3
        narrow = list_maplets(session, lat_deg=0.0, lon_deg=3.0, radius_km=0.005)
        wide = list_maplets(session, lat_deg=0.0, lon_deg=3.0, radius_km=0.015)
        assert list_maplets(session, lat_deg=-45.0, lon_deg=270.0) == []
    assert [m.name for m in everything] == ["A", "B", "C", "D"]
    assert [m.name for m in page] == ["B", "C"]
    counts = {name: len({v.image for v in VIEWS if v.maplet == name and v.visible > 0})
              for name in MAPLETS}
    assert {m.name: m.image_count for m in everything} == counts
    assert [(m.name, m.distance_km) for m in at_zero] == [("A", 0.0), ("B", 0.0)]
    assert everything[0].current_revision == 2 and everything[0].distance_km is None
    assert [(m.name, m.distance_km) for m in narrow] == [("A", 0.0)]
    assert [m.name for m in wide] == ["A", "B"] and 0.005 < wide[1].distance_km < 0.015


def test_prefilter_keeps_every_maplet_near_a_point(db_url: str) -> None:
    """Maplets of mixed sizes and leans on a lumpy body: the maplets found for random points,
    poles and the 0/360 seam included, are those a test of every maplet finds."""
    rng = np.random.default_rng(7)
    lat = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, 300)))
    lon = rng.uniform(0.0, 360.0, 300)
    frames, sizes = [], rng.uniform(0.01, 0.08, 300)
    for a, b in zip(lat, lon, strict=True):
        origin = rng.uniform(0.2, 0.3) * latlon_to_unit(a, b)
        frames.append(local_frame(origin, _unit(origin) + rng.normal(0.0, 0.3, 3)))
    # The largest maplet, nearest the centre, turned 45 deg about its normal: its corners lie
    # north, south, east and west of its centre, where the bound is tightest.
    sizes[0] = 0.08
    radial = local_frame(0.2 * latlon_to_unit(lat[0], lon[0]), latlon_to_unit(lat[0], lon[0]))
    turn = np.array([[1.0, 1.0, 0.0], [-1.0, 1.0, 0.0], [0.0, 0.0, np.sqrt(2.0)]]) / np.sqrt(2.0)
    frames[0] = LocalFrame(origin=radial.origin, rotation=turn @ radial.rotation)
    corners = [unit_to_latlon(frames[0].to_body(0.0399 * np.array([x, y, 0.0])))
               for x, y in ((1, 1), (1, -1), (-1, 1), (-1, -1))]
    upgrade(db_url)
    engine = make_engine(db_url)
    sessions = make_sessionmaker(engine)
    with session_scope(sessions) as session:
        session.add_all(Maplet(
            name=f"M{k:03d}", center_lat_deg=lat[k], center_lon_deg=lon[k],
            origin_x_km=f.origin[0], origin_y_km=f.origin[1], origin_z_km=f.origin[2],
            rotation=f.rotation.tolist(), size_km=sizes[k], gsd_m=0.1, nodes_per_side=101)
            for k, f in enumerate(frames))
    anywhere = zip(np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, 40))), rng.uniform(-180, 360, 40), strict=True)
    points = [(90.0, 0.0), (-90.0, 123.0), (89.9, 10.0), (0.0, 0.0), (0.0, 359.99), (10.0, -0.5),
              *corners, *anywhere]
    with sessions() as session:
        for (a, b), radius_km in zip(points, rng.choice([0.0, 0.005, 0.03], len(points)), strict=True):
            found = {m.name for m in list_maplets(
                session, lat_deg=float(a), lon_deg=float(b), radius_km=float(radius_km))}
            every = {f"M{k:03d}" for k, f in enumerate(frames) if distance_to_square_km(
                f, latlon_to_unit(a, b), sizes[k] / 2) <= radius_km}
            assert found == every, (a, b, radius_km)
    engine.dispose()


def test_queries_read_through_the_indexes(sqlite_url: str) -> None:
    """On SQLite's planner, each statement but the maplet extent aggregate searches an index."""
    upgrade(sqlite_url)
    engine = make_engine(sqlite_url)
    sessions = make_sessionmaker(engine)
    with session_scope(sessions) as session:
        _fill(session)
    statements: list[tuple[str, tuple]] = []

    def record(_conn, _cursor, sql: str, params: tuple, _context, _many: bool) -> None:
        statements.append((sql, params))

    event.listen(engine, "before_cursor_execute", record)
    with sessions() as session:
        images_covering(session, lat_deg=0.0, lon_deg=0.0)
        maplets_seen_by(session, lidvid=_lidvid(3))
        maplet_coverage(session, name="A")
    event.remove(engine, "before_cursor_execute", record)
    with engine.connect() as connection:
        plans = {sql: " | ".join(row[-1] for row in connection.exec_driver_sql(
            f"EXPLAIN QUERY PLAN {sql}", params)) for sql, params in statements}
    engine.dispose()
    # scans of a statement's own subqueries are fine; scans of tables are not
    scans = {sql: plan for sql, plan in plans.items()
             if re.search(r"SCAN (maplets|coverage|images|image_geometry)\b", plan)}
    assert len(scans) == 1 and "min(" in next(iter(scans)).lower(), scans
    assert any("ix_maplets_center_lat_deg_center_lon_deg" in plan for plan in plans.values())
    assert any("ix_coverage_maplet_id" in plan for plan in plans.values())
    # SQLite names the index of the (image_id, maplet_id) unique constraint itself
    assert any("SEARCH coverage USING INDEX" in plan and "(image_id=?)" in plan
               for plan in plans.values())


def test_commands_print_the_queries(
    sqlite_url: str, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    upgrade(sqlite_url)
    engine = make_engine(sqlite_url)
    with session_scope(make_sessionmaker(engine)) as session:
        _fill(session)
    with make_sessionmaker(engine)() as session:
        summary = maplet_coverage(session, name="B")
    engine.dispose()
    monkeypatch.setenv("PWM_DATABASE_URL", sqlite_url)
    monkeypatch.setenv("PWM_DATA_DIR", str(tmp_path / "data"))
    get_settings.cache_clear()
    runner = CliRunner()
    try:
        near = runner.invoke(app, ["images-near", "--lat", "0", "--lon", "0"])
        listed = runner.invoke(app, ["maplets", "--lat", "0", "--lon", "0", "--json"])
        table = runner.invoke(app, ["coverage", "B"])
        as_json = runner.invoke(app, ["coverage", "B", "--json"])
        missing = runner.invoke(app, ["coverage", "Z"])
    finally:
        get_settings.cache_clear()
    assert near.exit_code == 0, near.output
    expected = _seen({"A", "B"})
    lines = [line for line in near.output.splitlines() if line.startswith("urn:")]
    assert [line.split()[0] for line in lines] == [
        _lidvid(k) for k in sorted(expected, key=lambda k: -expected[k].weight)]
    assert [m["name"] for m in json.loads(listed.output)] == ["A", "B"]
    assert table.exit_code == 0 and "west" in table.output and "missing" in table.output
    assert json.loads(as_json.output) == summary.model_dump(mode="json")
    assert missing.exit_code != 0 and "no maplet Z" in missing.output
