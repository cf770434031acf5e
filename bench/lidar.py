"""Lidar in the catalog at size (issue 46.4): the ingest of one product of many shots, and how
fast a catalog of many shots finds the maplets a new track crosses.

1. Ingest: global-tiny's simulated downlink (its kernels and its lidar product, `pwm simulate`)
   with its lidar product's shots repeated into one product of --shots shots (the same times,
   ranges and directions: every one placed through the kernels as any), ingested into a new
   SQLite catalog (service.ingest.ingest_directory) in a process of its own: wall time, the
   peak of numpy's and Python's memory during it (tracemalloc) and that process's peak resident
   memory during it (its imports' included).
2. Planning a track: a catalog of --catalog-shots shots in tracks of --track-shots (their rows
   only, as ingest writes them; the shots themselves are in files no query reads) and
   --maplets maplets over a 250 m body; then one new track's maplets found
   (service.queries.maplets_crossed), timed over --repeat queries.

    .venv/bin/python bench/lidar.py [--shots 100000] [--catalog-shots 10000000] [--track-shots 200]
                                    [--maplets 20000] [--repeat 20]
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import shutil
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
from sqlalchemy import insert, select

from pwm.frames import latlon_to_unit
from pwm.io.lidar import read_lidar_table, write_lidar_product
from pwm.simulate.campaign import simulate
from pwm.simulate.scenarios import get_scenario
from service.db import make_engine, make_sessionmaker, upgrade
from service.ingest import ingest_directory
from service.queries import maplets_crossed
from service.rows import Acceptance, LidarProduct, LidarTrack, Maplet
from service.settings import IngestLimits

RADIUS_KM = 0.25  # a Bennu-sized body
TRACK_HALF_ANGLE_RAD = 0.03  # a profile's spots about its centre, as seen from the body's centre


def simulate_global_tiny(out: Path) -> Path:
    simulate(out, scenario=get_scenario("global-tiny"), seed=2)
    return out


def bench_ingest(sim: Path, work: Path, shots: int) -> dict:
    table = read_lidar_table(next((sim / "downlink" / "lidar").glob("*.xml")))
    repeat = int(np.ceil(shots / len(table.et)))
    pick = np.tile(np.arange(len(table.et)), repeat)[:shots]
    downlink = work / "downlink"
    shutil.copytree(sim / "downlink" / "kernels", downlink / "kernels")
    assert table.direction is not None
    write_lidar_product(directory=downlink / "lidar", basename="many", lid="urn:nasa:pds:bench:many",
                        et=table.et[pick], range_km=table.range_km[pick], flag=np.where(table.flagged[pick], 2, 0),
                        direction=table.direction[pick], start_utc="2019-03-04T00:00:00",
                        stop_utc="2019-03-09T00:00:00", mission="OSIRIS-REx", host_name="OSIRIS-REX",
                        instrument_name="PWM_LIDAR", target_name="Bennu", title="bench")
    url = f"sqlite:///{work / 'catalog.sqlite'}"
    upgrade(url)
    engine = make_engine(url)
    _reset_peak_rss()
    tracemalloc.start()
    clock = time.perf_counter()
    report = ingest_directory(make_sessionmaker(engine), downlink, data_dir=work / "data",
                              limits=IngestLimits(max_lidar_shots=max(shots, 1)))
    seconds = time.perf_counter() - clock
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    engine.dispose()
    assert report.lidar.accepted == 1, report.summary()
    return {"shots": report.lidar_shots, "valid": report.lidar_valid_shots, "seconds": seconds,
            "traced_peak_mib": peak / 2**20, "rss_mib": _peak_rss_mib()}


def _reset_peak_rss() -> None:
    """Start this process's peak resident memory afresh (Linux: clear_refs 5 resets VmHWM)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass  # elsewhere the peak since the process began is all there is


def _peak_rss_mib() -> float:
    """This process's peak resident memory since `_reset_peak_rss` (MiB)."""
    try:
        status = Path("/proc/self/status").read_text()
        return next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmHWM:")) / 1024
    except (OSError, StopIteration, ValueError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def bench_planning(work: Path, *, catalog_shots: int, track_shots: int, maplets: int, repeat: int) -> dict:
    url = f"sqlite:///{work / 'planning.sqlite'}"
    upgrade(url)
    engine = make_engine(url)
    sessions = make_sessionmaker(engine)
    rng = np.random.default_rng(46)
    tracks = max(1, catalog_shots // track_shots)
    size_km = 2 * RADIUS_KM * np.sqrt(4 * np.pi / maplets)  # maplets overlapping about twice
    clock = time.perf_counter()
    with sessions.begin() as session:
        k = np.arange(maplets) + 0.5
        lat = np.degrees(np.arcsin(1 - 2 * k / maplets))
        lon = np.degrees(np.pi * (1 + 5 ** 0.5) * k) % 360.0
        origin = RADIUS_KM * np.array([latlon_to_unit(a, b) for a, b in zip(lat, lon, strict=True)])
        session.execute(insert(Maplet), [
            {"name": f"M{n:06d}", "center_lat_deg": float(a), "center_lon_deg": float(b), "origin_x_km": float(x),
             "origin_y_km": float(y), "origin_z_km": float(z), "rotation": np.eye(3).tolist(),
             "size_km": float(size_km), "gsd_m": 1.0, "level": 0, "nodes_per_side": 51}
            for n, (a, b, (x, y, z)) in enumerate(zip(lat, lon, origin, strict=True))])
        product = LidarProduct(lidvid="urn:nasa:pds:bench:tracks::1.0", lid="urn:nasa:pds:bench:tracks", vid="1.0",
                               label_path="-", data_path="-", sha256="0" * 64, size_bytes=0,
                               status=Acceptance.ACCEPTED, shots=tracks * track_shots,
                               valid_shots=tracks * track_shots, invalid_shots={})
        session.add(product)
        session.flush()
        axes = rng.normal(size=(tracks + 1, 3))
        axes /= np.linalg.norm(axes, axis=1)[:, None]
        rows = []
        for t, axis in enumerate(axes):
            low, high = RADIUS_KM * axis - 0.01, RADIUS_KM * axis + 0.01
            rows.append({"product_id": product.id, "track": t, "start_et": 60.0 * t, "stop_et": 60.0 * t + 50,
                         "shots": track_shots, "cone_axis_x": float(axis[0]), "cone_axis_y": float(axis[1]),
                         "cone_axis_z": float(axis[2]), "cone_half_angle_rad": TRACK_HALF_ANGLE_RAD,
                         "axis_lat_deg": float(np.degrees(np.arcsin(axis[2]))),
                         "axis_lon_deg": float(np.degrees(np.arctan2(axis[1], axis[0])) % 360.0),
                         "min_x_km": float(low[0]), "min_y_km": float(low[1]), "min_z_km": float(low[2]),
                         "max_x_km": float(high[0]), "max_y_km": float(high[1]), "max_z_km": float(high[2])})
        for start in range(0, len(rows), 10_000):
            session.execute(insert(LidarTrack), rows[start:start + 10_000])
    built = time.perf_counter() - clock
    with sessions() as session:
        newest = session.scalars(select(LidarTrack.id).order_by(LidarTrack.id.desc()).limit(1)).one()
        found = maplets_crossed(session, track_id=newest)  # warm: the first query reads the pages in
        times = []
        for _ in range(repeat):
            clock = time.perf_counter()
            found = maplets_crossed(session, track_id=newest)
            times.append(time.perf_counter() - clock)
    engine.dispose()
    return {"tracks": tracks + 1, "shots": (tracks + 1) * track_shots, "maplets": maplets, "built_s": built,
            "crossed": len(found), "median_s": float(np.median(times)), "max_s": float(np.max(times))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shots", type=int, default=100_000)
    parser.add_argument("--catalog-shots", type=int, default=10_000_000)
    parser.add_argument("--track-shots", type=int, default=200)
    parser.add_argument("--maplets", type=int, default=20_000)
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="pwm-bench-lidar-") as scratch:
        work = Path(scratch)
        sim = simulate_global_tiny(work / "sim")
        # a process of its own, so that its peak resident memory is the ingest's, not the simulation's
        pool = multiprocessing.get_context("spawn").Pool(1)
        ingest = pool.apply(bench_ingest, (sim, work / "ingest", args.shots))
        pool.close()
        pool.join()
        plan = bench_planning(work, catalog_shots=args.catalog_shots, track_shots=args.track_shots,
                              maplets=args.maplets, repeat=args.repeat)
    print(f"ingest: {ingest['shots']} shots ({ingest['valid']} valid) in one product: {ingest['seconds']:.1f} s, "
          f"traced peak {ingest['traced_peak_mib']:.0f} MiB, the ingest process's peak RSS {ingest['rss_mib']:.0f} MiB")
    print(f"planning: {plan['shots']} shots in {plan['tracks']} tracks, {plan['maplets']} maplets (catalog built in "
          f"{plan['built_s']:.1f} s): a new track crosses {plan['crossed']} maplets, found in "
          f"{plan['median_s'] * 1e3:.1f} ms median, {plan['max_s'] * 1e3:.1f} ms max over {args.repeat}")


if __name__ == "__main__":
    main()
