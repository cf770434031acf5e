"""Benchmark the catalog: latency of the maplet-indexed queries (service.queries) on a
mission-sized catalog in PostgreSQL, the ingest rate of PDS4 products with SPICE geometry on
SQLite and PostgreSQL, and the ingest of a 30-image downlink with its coverage planning (tiling
and weighing against the shape) into the mission-sized catalog. Prints three tables.

    .venv/bin/python bench/catalog.py [--images 100000] [--maplets 5000] [--per-image 20]
                                      [--calls 500] [--products 300] [--explain]

The catalog: maplets from pwm.tiling on the bundled Bennu radar shape, images looking at random
maplets from 0.7-4.5 km with their geometry, and coverage rows for the maplets nearest each
image's aim point, bulk-loaded with COPY and analysed; every image already weighed. Each timed
call opens its own session, as an API request would. The downlink: `tiny`'s design with 30
images (pwm.simulate), over the catalog's start model. Targets: p95 < 50 ms per query, >= 50
products/s ingested, the 30-image downlink in < 10 s
(issue 50, at 50,000 maplets and 40,000 images: `--maplets 50000 --images 40000`).

The PostgreSQL server is the tests' throwaway cluster (the `postgres_server` fixture of
tests/conftest.py, run as a context manager), and the products and kernels are those of
tests/service/test_ingest.py, so the bench needs what the tests need (Debian's postgresql).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import psycopg
from scipy.spatial import cKDTree
from sqlalchemy import Engine, event
from sqlalchemy.orm import Session, sessionmaker

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pwm.camera import Camera  # noqa: E402
from pwm.config import DEFAULTS  # noqa: E402
from pwm.frames import latlon_to_unit, unit_to_latlon  # noqa: E402
from pwm.io.meshio import read_obj  # noqa: E402
from pwm.io.spice_kernels import bundled_kernels, kernel_pool  # noqa: E402
from pwm.maplets import MapletGrid  # noqa: E402
from pwm.simulate.campaign import simulate  # noqa: E402
from pwm.simulate.scenarios import get_scenario  # noqa: E402
from pwm.tiling import level_of, tile  # noqa: E402
from service.conductor import weigh  # noqa: E402
from service.db import make_engine, make_sessionmaker, upgrade  # noqa: E402
from service.ingest import ingest_directory  # noqa: E402
from service.queries import images_covering, list_maplets, maplet_coverage, maplets_seen_by  # noqa: E402
from service.versions import import_model  # noqa: E402
from tests import conftest as test_servers  # noqa: E402
from tests.service import test_ingest  # noqa: E402

BENNU_OBJ = REPO / "pwm" / "data" / "shapes" / "bennu_radar_nolan2013_sbgat.obj"
GSD_M = 0.05
IFOV_RAD = 8.5e-3 / 125.20  # MapCam pixel pitch over focal length
RANGE_KM = (0.7, 4.5)
MAX_EMISSION_DEG = 45.0
T0 = datetime(2019, 3, 4, tzinfo=UTC)
ET0 = 605_016_069.18  # T0 in ephemeris seconds past J2000
CAMPAIGN_S = 200 * 86400.0
ROTATION_S = 4.296 * 3600.0  # Bennu's sidereal rotation period
MAPCAM = Camera(width=1024, height=1024, fx=125.2 / 8.5e-3, fy=125.2 / 8.5e-3, cx=511.5, cy=511.5)
MAPCAM_ID = -64361
ROLE_AXES = {"east": (0, 1.0), "west": (0, -1.0), "north": (1, 1.0), "south": (1, -1.0),
             "nadir": (2, 1.0)}
NEAR_RADIUS_KM = 0.01


# ---------------------------------------------------------------------------------------------
# A synthetic catalog


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _acos_deg(cosines: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))


def _copy(connection: psycopg.Connection, table: str, columns: Sequence[str],
          rows: Iterable[Sequence[object]]) -> None:
    with connection.cursor() as cursor, cursor.copy(
            f"COPY {table} ({', '.join(columns)}) FROM STDIN") as copy:
        for row in rows:
            copy.write_row(row)


def _copy_numbers(connection: psycopg.Connection, table: str, columns: dict[str, np.ndarray],
                  chunk: int = 200_000) -> None:
    """COPY integer (int4) and float (float8) columns without NULLs in PostgreSQL's binary
    format, laid out by numpy: millions of rows without a Python loop over them."""
    fields: list[tuple[str, str]] = [("count", ">i2")]
    for k, values in enumerate(columns.values()):
        kind = ">i4" if values.dtype.kind in "iu" else ">f8"
        fields += [(f"size{k}", ">i4"), (f"value{k}", kind)]
    records = np.empty(len(next(iter(columns.values()))), dtype=fields)
    records["count"] = len(columns)
    for k, values in enumerate(columns.values()):
        records[f"size{k}"] = records.dtype[f"value{k}"].itemsize
        records[f"value{k}"] = values
    with connection.cursor() as cursor, cursor.copy(
            f"COPY {table} ({', '.join(columns)}) FROM STDIN (FORMAT BINARY)") as copy:
        copy.write(b"PGCOPY\n\xff\r\n\x00" + bytes(8))  # signature, flags, no extension
        for start in range(0, len(records), chunk):
            copy.write(records[start:start + chunk].tobytes())
        copy.write(b"\xff\xff")


def bennu_maplets(n: int) -> list[MapletGrid]:
    """About n maplets of 5 x 5 nodes tiling the Bennu radar shape. The side that n squares
    need, less the overlap, is corrected once for the maplets the tiler adds to close gaps."""
    mesh = read_obj(BENNU_OBJ)
    side_km = np.sqrt(mesh.face_areas().sum() / n) / (1.0 - DEFAULTS.overlap)
    maplets = tile(mesh, spacing_km=side_km / 4, nodes=5, overlap=DEFAULTS.overlap)
    side_km *= np.sqrt(len(maplets) / n)
    return tile(mesh, spacing_km=side_km / 4, nodes=5, overlap=DEFAULTS.overlap)


def load_catalog(connection: psycopg.Connection, *, n_images: int, n_maplets: int,
                 per_image: int, rng: np.random.Generator) -> dict[str, list[str]]:
    """Fill an empty migrated catalog; returns the maplet names and the image LIDVIDs."""
    # The ids below are consistent by construction: skip the per-row foreign key triggers, as
    # pg_restore does (the bench's cluster user is a superuser).
    connection.execute("SET session_replication_role = replica")
    maplets = bennu_maplets(n_maplets)
    origins = np.array([m.frame.origin for m in maplets])
    rotations = np.array([m.frame.rotation for m in maplets])
    size_km = (maplets[0].n - 1) * maplets[0].spacing_km
    names = [m.name for m in maplets]
    lat, lon = unit_to_latlon(origins)
    _copy(connection, "maplets",
          ["id", "name", "center_lat_deg", "center_lon_deg", "origin_x_km", "origin_y_km",
           "origin_z_km", "rotation", "size_km", "gsd_m", "level", "nodes_per_side", "region_weight"],
          ((k + 1, names[k], lat[k], lon[k], *origins[k].tolist(),
            json.dumps(rotations[k].ravel().tolist()), size_km, GSD_M, int(level_of(GSD_M * 1e-3)),
            int(round(size_km * 1e3 / GSD_M)) + 1, 1.0) for k in range(len(maplets))))

    # Images: each aims at a random maplet from within MAX_EMISSION_DEG of its normal; the Sun
    # turns with Bennu's rotation, its latitude within 10 deg of the equator.
    aim = rng.integers(0, len(maplets), n_images)
    normal = rotations[aim, 2]
    tilt = np.radians(MAX_EMISSION_DEG) * np.sqrt(rng.random(n_images))
    azimuth = rng.uniform(0.0, 2 * np.pi, n_images)
    across = (np.cos(azimuth)[:, None] * rotations[aim, 0]
              + np.sin(azimuth)[:, None] * rotations[aim, 1])
    view = _unit(np.cos(tilt)[:, None] * normal + np.sin(tilt)[:, None] * across)
    distance_km = rng.uniform(*RANGE_KM, n_images)
    camera = origins[aim] + distance_km[:, None] * view
    seconds = np.sort(rng.uniform(0.0, CAMPAIGN_S, n_images))
    sun = latlon_to_unit(rng.uniform(-10.0, 10.0, n_images), -360.0 * seconds / ROTATION_S)
    start = [T0 + timedelta(seconds=float(s)) for s in seconds]
    lidvids = [f"urn:nasa:pds:orex.ocams:data_calibrated:bench{k:06d}::1.0"
               for k in range(n_images)]
    _copy(connection, "instruments",
          ["id", "naif_id", "name", "spacecraft_id", "frame_name", "width_px", "height_px", "fx_px",
           "fy_px", "cx_px", "cy_px", "focal_length_source"],
          [(1, MAPCAM_ID, "ORX_OCAMS_MAPCAM", -64, "ORX_OCAMS_MAPCAM", MAPCAM.width, MAPCAM.height,
            MAPCAM.fx, MAPCAM.fx, MAPCAM.cx, MAPCAM.cy, "bench")])
    _copy(connection, "images",
          ["id", "lidvid", "lid", "vid", "label_path", "data_path", "sha256", "size_bytes",
           "status", "geometry_status", "target", "start_utc", "stop_utc", "start_et", "stop_et", "instrument_id",
           "window_first_line", "window_first_sample", "window_lines", "window_samples",
           "coverage_computed_at"],
          ((k + 1, lidvids[k], lidvids[k].removesuffix("::1.0"), "1.0", f"bench{k:06d}.xml",
            f"bench{k:06d}.img", f"{k:064x}", 2_113_536, "accepted", "computed", "BENNU",
            start[k], start[k] + timedelta(milliseconds=10), ET0 + seconds[k], ET0 + seconds[k] + 0.01, 1, 0, 0,
            MAPCAM.height, MAPCAM.width, T0)
           for k in range(n_images)))
    # pwm.camera.look_at with up = +Z, for all images at once
    boresight = -view
    x = _unit(np.cross(boresight, [0.0, 0.0, -1.0]))
    rotation = np.stack([x, np.cross(boresight, x), boresight], axis=1)
    phase = _acos_deg(np.einsum("ni,ni->n", sun, view))
    incidence = _acos_deg(np.einsum("ni,ni->n", sun, normal))
    emission = _acos_deg(np.einsum("ni,ni->n", view, normal))
    half_angle = float(np.arctan(np.hypot(MAPCAM.width, MAPCAM.height) / 2 / MAPCAM.fx))
    _copy(connection, "image_geometry",
          ["image_id", "camera_x_km", "camera_y_km", "camera_z_km", "camera_rotation", "sun_x",
           "sun_y", "sun_z", "range_km", "intercept_range_km", "pixel_scale_m", "phase_deg",
           "incidence_deg", "emission_deg", "intercept_lat_deg", "intercept_lon_deg",
           "cone_axis_x", "cone_axis_y", "cone_axis_z", "cone_half_angle_rad",
           "body_frame", "abcorr", "computed_at"],
          ((k + 1, *camera[k].tolist(), json.dumps(rotation[k].tolist()), *sun[k].tolist(),
            float(np.linalg.norm(camera[k])), distance_km[k], distance_km[k] * IFOV_RAD * 1e3,
            phase[k], incidence[k], emission[k], lat[aim[k]], lon[aim[k]], *boresight[k].tolist(),
            half_angle, "IAU_BENNU", "LT+S", T0) for k in range(n_images)))

    # Coverage: the maplets nearest each aim point, with their own angles.
    _, nearest = cKDTree(origins).query(origins[aim], k=per_image)
    image = np.repeat(np.arange(n_images), per_image)
    maplet = nearest.ravel()
    r = rotations[maplet]
    to_camera = camera[image] - origins[maplet]
    range_km = np.linalg.norm(to_camera, axis=1)
    v_local = np.einsum("nij,nj->ni", r, to_camera / range_km[:, None])
    s_local = np.einsum("nij,nj->ni", r, sun[image])
    incidence, emission = _acos_deg(s_local[:, 2]), _acos_deg(v_local[:, 2])
    visible = np.where(rng.random(len(image)) < 0.05, 0.0, rng.uniform(0.2, 1.0, len(image)))
    weight = np.where((incidence < 90.0) & (emission < 60.0),
                      visible * np.cos(np.radians(emission))
                      * np.exp(-(((incidence - 45.0) / 20.0) ** 2)), 0.0)
    _copy_numbers(connection, "coverage", {
        "id": np.arange(1, len(image) + 1), "image_id": image + 1, "maplet_id": maplet + 1,
        "visible_fraction": visible,
        "shadowed_fraction": np.clip((incidence - 60.0) / 30.0, 0.0, 1.0),
        "incidence_deg": incidence, "emission_deg": emission,
        "phase_deg": _acos_deg(np.einsum("ni,ni->n", v_local, s_local)),
        # from local north towards east, as pwm.weights measures it
        "sun_azimuth_deg": np.degrees(np.arctan2(s_local[:, 0], s_local[:, 1])) % 360.0,
        "camera_azimuth_deg": np.degrees(np.arctan2(v_local[:, 0], v_local[:, 1])) % 360.0,
        "resolution_m_per_px": range_km * IFOV_RAD * 1e3, "weight": weight})
    # Each role goes to the weighted image seen furthest along its axis (nadir, the last, along
    # z), one role per row.
    roles: dict[int, str] = {}
    for name, (axis, sign) in ROLE_AXES.items():
        score = np.where(weight > 0, sign * v_local[:, axis], -np.inf)
        ranked = np.lexsort((score, maplet))
        best = ranked[np.r_[np.flatnonzero(np.diff(maplet[ranked])), len(ranked) - 1]]
        roles |= dict.fromkeys((best[np.isfinite(score[best])] + 1).tolist(), name)
    connection.execute(
        "UPDATE coverage SET role = r.role FROM unnest(%s::int[], %s::text[]) AS r(id, role)"
        " WHERE coverage.id = r.id", [list(roles), list(roles.values())])
    # rows added later (the downlink's) take ids after those copied in
    for table in ("instruments", "images", "maplets", "coverage"):
        connection.execute(f"SELECT setval(pg_get_serial_sequence('{table}', 'id'), (SELECT max(id) FROM {table}))")
    connection.execute("VACUUM ANALYZE")
    return {"maplets": names, "lidvids": lidvids}


# ---------------------------------------------------------------------------------------------
# Query latency


def percentiles_ms(seconds: Sequence[float]) -> tuple[float, float, float]:
    return tuple(float(v) * 1e3 for v in np.percentile(seconds, [50, 95, 99]))


def time_calls(sessions: sessionmaker[Session], call: Callable, arguments: Iterable[dict]
               ) -> tuple[list[float], list[int]]:
    """Seconds and result sizes of `call(session, **kwargs)`, a fresh session each."""
    seconds, sizes = [], []
    for kwargs in arguments:
        clock = time.perf_counter()
        with sessions() as session:
            result = call(session, **kwargs)
        seconds.append(time.perf_counter() - clock)
        sizes.append(len(result) if isinstance(result, list) else result.image_count)
    return seconds, sizes


def query_workload(names: list[str], lidvids: list[str], calls: int,
                   rng: np.random.Generator) -> dict[str, tuple[Callable, list[dict]]]:
    """Random arguments for each query: surface points uniform over the sphere of directions,
    images and maplets uniform over the catalog."""
    lat = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, calls)))
    lon = rng.uniform(0.0, 360.0, calls)
    points = [dict(lat_deg=float(a), lon_deg=float(b)) for a, b in zip(lat, lon, strict=True)]
    return {
        "images_covering": (images_covering, points),
        "maplets_seen_by": (maplets_seen_by, [dict(lidvid=lidvids[k]) for k in
                                              rng.integers(0, len(lidvids), calls)]),
        "maplet_coverage": (maplet_coverage, [dict(name=names[k]) for k in
                                              rng.integers(0, len(names), calls)]),
        f"list_maplets {NEAR_RADIUS_KM * 1e3:g} m": (
            list_maplets, [p | dict(radius_km=NEAR_RADIUS_KM) for p in points]),
    }


def explain(engine: Engine, sessions: sessionmaker[Session],
            workload: dict[str, tuple[Callable, list[dict]]]) -> None:
    """EXPLAIN ANALYZE of every statement of one call of each query."""
    statements: list[tuple[str, object]] = []

    def record(_conn, _cursor, sql, params, _context, _many) -> None:
        statements.append((sql, params))

    for name, (call, arguments) in workload.items():
        statements.clear()
        event.listen(engine, "before_cursor_execute", record)
        with sessions() as session:
            call(session, **arguments[0])
        event.remove(engine, "before_cursor_execute", record)
        print(f"\n== {name} {arguments[0]}")
        with engine.connect() as connection:
            for sql, params in statements:
                print(" ".join(sql.split())[:160] + " ...")
                plan = connection.exec_driver_sql(f"EXPLAIN (ANALYZE, COSTS OFF) {sql}", params)
                for (line,) in plan:
                    print(f"    {line}")


# ---------------------------------------------------------------------------------------------
# Ingest rate


class _TempDirs:
    """The mktemp of pytest's tmp_path_factory, for the test fixture that writes the kernels."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def mktemp(self, name: str) -> Path:
        return Path(tempfile.mkdtemp(prefix=name, dir=self.root))


def write_downlinks(root: Path, n_products: int) -> tuple[Path, Path]:
    """A kernels-only downlink and one of n_products small MapCam products inside the CK
    windows (tests/service/test_ingest.py's kernel set and product writer)."""
    kernels = test_ingest.kernels.__wrapped__(_TempDirs(root))
    kernel_dir, product_dir = root / "kernels", root / "products"
    kernel_dir.mkdir()
    for path in kernels["files"]:
        shutil.copy(path, kernel_dir / path.name)
    spans = [(a + 1.0, b - 1.0) for a, b in test_ingest.CK_WINDOWS_S]
    per_window = -(-n_products // len(spans))
    offsets = np.concatenate([np.linspace(a, b, per_window) for a, b in spans])[:n_products]
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        for k, offset in enumerate(offsets):
            test_ingest._product(product_dir, f"bench{k:05d}", kernels["et0"] + offset)
    return kernel_dir, product_dir


def ingest_rate(url: str, kernel_dir: Path, product_dir: Path) -> tuple[int, float]:
    """Products accepted with geometry, and seconds, of ingesting product_dir into a catalog
    that holds kernel_dir's kernels already."""
    upgrade(url)
    engine = make_engine(url)
    try:
        ingest_directory(engine, kernel_dir)
        clock = time.perf_counter()
        report = ingest_directory(engine, product_dir)
        elapsed = time.perf_counter() - clock
    finally:
        engine.dispose()
    if report.failed or report.geometry_unavailable:
        raise RuntimeError(f"ingest went wrong: {report.summary()}")
    return report.images.accepted, elapsed


def downlink_into_catalog(url: str, root: Path) -> dict:
    """Seconds and figures of ingesting a simulated 30-image downlink, with its coverage planning
    against the catalog's start model, into the catalog at `url` (which gets that model first)."""
    scenario = get_scenario("tiny").model_copy(update={"name": "bench-30", "n_azimuths": 28, "n_validation": 0})
    simulate(root / "sim", scenario=scenario, seed=3, with_start_model=True)
    downlink = root / "sim" / "downlink"
    shape = read_obj(downlink / "start_model.obj")
    engine = make_engine(url)
    sessions = make_sessionmaker(engine)
    try:
        with sessions.begin() as session:
            import_model(session, data_dir=root / "data", path=downlink / "start_model.obj")
        clock = time.perf_counter()
        report = ingest_directory(sessions, downlink, shape=shape)
        coverage = weigh(sessions, shape)
        elapsed = time.perf_counter() - clock
    finally:
        engine.dispose()
    if report.failed or report.images.accepted != scenario.n_images:
        raise RuntimeError(f"ingest went wrong: {report.summary()}")
    return {"images": report.images.accepted, "seconds": elapsed, "tiled": coverage.maplets_added,
            "weighed": coverage.maplets_weighed, "traced": coverage.pairs_traced, "rows": coverage.rows_added}


# ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def postgres() -> Iterator[test_servers.PostgresServer]:
    # __wrapped__: the fixture's own generator function, which functools.wraps keeps.
    with contextlib.contextmanager(test_servers.postgres_server.__wrapped__)() as server:
        yield server


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=int, default=100_000)
    parser.add_argument("--maplets", type=int, default=5_000, help="about this many")
    parser.add_argument("--per-image", type=int, default=20, help="coverage rows per image")
    parser.add_argument("--calls", type=int, default=500, help="timed calls per query")
    parser.add_argument("--products", type=int, default=300, help="products ingested per database")
    parser.add_argument("--explain", action="store_true", help="print the query plans")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)

    with postgres() as server, tempfile.TemporaryDirectory() as tmp:
        with server.admin() as admin:
            for name in ("pwm_bench", "pwm_ingest"):
                admin.execute(f'CREATE DATABASE "{name}"')
        url = server.url("pwm_bench")
        upgrade(url)
        clock = time.perf_counter()
        with psycopg.connect(host=server.host, port=server.port, user=server.user,
                             dbname="pwm_bench", autocommit=True) as connection:
            catalog = load_catalog(connection, n_images=args.images, n_maplets=args.maplets,
                                   per_image=args.per_image, rng=rng)
            counts = {t: connection.execute(f"SELECT count(*) FROM {t}").fetchone()[0]
                      for t in ("maplets", "images", "image_geometry", "coverage")}
        load_s = time.perf_counter() - clock
        print(f"catalog loaded in {load_s:.1f} s: "
              + ", ".join(f"{n} {t}" for t, n in counts.items()))

        engine = make_engine(url)
        sessions = make_sessionmaker(engine)
        workload = query_workload(catalog["maplets"], catalog["lidvids"], args.calls, rng)
        if args.explain:
            explain(engine, sessions, workload)
        rows = []
        for name, (call, arguments) in workload.items():
            time_calls(sessions, call, arguments[:20])  # warm the caches and the pool
            seconds, sizes = time_calls(sessions, call, arguments)
            rows.append((name, *percentiles_ms(seconds), float(np.mean(sizes))))
        engine.dispose()
        downlink = downlink_into_catalog(url, Path(tmp))
        # Timings stretch when other work shares the cores: print the load beside them.
        print(f"\nPostgreSQL, {args.calls} random calls each (target p95 < 50 ms), "
              f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
        print(f"{'query':<22}{'p50 ms':>9}{'p95 ms':>9}{'p99 ms':>9}{'mean rows':>11}")
        for name, p50, p95, p99, size in rows:
            print(f"{name:<22}{p50:>9.2f}{p95:>9.2f}{p99:>9.2f}{size:>11.1f}")

        kernel_dir, product_dir = write_downlinks(Path(tmp), args.products)
        rates = [("SQLite", *ingest_rate(f"sqlite:///{Path(tmp) / 'ingest.sqlite'}",
                                         kernel_dir, product_dir)),
                 ("PostgreSQL", *ingest_rate(server.url("pwm_ingest"), kernel_dir, product_dir))]
    print("\nIngest, one process: labels, checksums and SPICE geometry (target >= 50 products/s),"
          f" load average {os.getloadavg()[0]:.1f}")
    print(f"{'database':<12}{'products':>10}{'seconds':>10}{'products/s':>12}")
    for name, products, seconds in rates:
        print(f"{name:<12}{products:>10}{seconds:>10.2f}{products / seconds:>12.1f}")
    print(f"\nA downlink into the catalog of {counts['images']} images and {counts['maplets']} maplets "
          "(PostgreSQL; ingest, tiling and weighing; target < 10 s)")
    print(f"{'images':>8}{'seconds':>10}{'maplets tiled':>15}{'weighed':>9}{'pairs traced':>14}{'rows added':>12}")
    print(f"{downlink['images']:>8}{downlink['seconds']:>10.2f}{downlink['tiled']:>15}{downlink['weighed']:>9}"
          f"{downlink['traced']:>14}{downlink['rows']:>12}")


if __name__ == "__main__":
    main()
