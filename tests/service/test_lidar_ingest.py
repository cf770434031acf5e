"""Lidar products in the catalog (service.ingest, issue 46.1), on SQLite and PostgreSQL: the
global-tiny survey's product catalogued with its tracks and its shots in the artifact store,
unchanged when ingested again; the maplets a track may cross (service.queries.maplets_crossed);
and hostile products, each accepted or rejected with a code, a broken copy replaced by the whole
one, another content of a LIDVID refused as a conflict."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from pwm.frames import latlon_to_unit
from pwm.io.lidar import read_lidar_table, read_shots, write_lidar_product
from pwm.lidar.tracks import NO_TRACK
from service.artifacts import artifact_path
from service.ingest import ingest_directory
from service.queries import maplets_crossed
from service.rows import Acceptance, DownlinkFile, LidarProduct, LidarTrack, Maplet
from service.settings import IngestLimits

LIDAR_LABEL = Path("lidar") / "pwm_global-tiny_lidar.xml"


def _downlink(sim: Path, where: Path, *, lidar: bool = True) -> Path:
    """A downlink of the simulation's kernels (and its lidar product): no images."""
    shutil.copytree(sim / "downlink" / "kernels", where / "kernels")
    if lidar:
        shutil.copytree(sim / "downlink" / "lidar", where / "lidar")
    return where


def test_a_lidar_product_is_catalogued_with_its_tracks_and_shots(catalog: sessionmaker[Session],
                                                                 global_tiny_sim: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    downlink = _downlink(global_tiny_sim, tmp_path / "lidar-only")
    report = ingest_directory(catalog, downlink, data_dir=data)
    assert (report.lidar.accepted, report.lidar.rejected, report.failed) == (1, 0, 0)
    assert "lidar products 1 accepted (4800 shots" in report.summary()
    truth = np.load(global_tiny_sim / "truth" / "lidar_spots.npz")
    with catalog() as session:
        product = session.scalars(select(LidarProduct)).one()
        assert (product.status, product.target, product.body_frame, product.shots) == (
            Acceptance.ACCEPTED, "Bennu", "IAU_BENNU", 4800)
        # every shot counted once: usable, or invalid with its reason (the simulator's dropouts are flagged)
        assert product.valid_shots + sum(product.invalid_shots.values()) == product.shots
        assert product.valid_shots == report.lidar_valid_shots == int(truth["returned"].sum())
        assert product.start_et <= product.stop_et and product.start_utc < product.stop_utc
        shots, track = read_shots(artifact_path(data, product.shots_artifact, verify=True))
        tracks = product.tracks
        assert sum(t.shots for t in tracks) == product.valid_shots == int((track != NO_TRACK).sum())
        # placed through exact kernels: each spot where the truth has it, to the range noise and footprint
        valid = shots.valid
        assert np.abs(shots.spots_km()[valid] - truth["spot_km"][valid]).max() < 0.002
        for row in tracks:
            spots = shots.spots_km()[track == row.track]
            unit = spots / np.linalg.norm(spots, axis=1)[:, None]
            axis = np.array([row.cone_axis_x, row.cone_axis_y, row.cone_axis_z])
            assert np.arccos(np.clip(unit @ axis, -1, 1)).max() <= row.cone_half_angle_rad + 1e-9
            assert (spots >= [row.min_x_km, row.min_y_km, row.min_z_km]).all()
            assert (spots <= [row.max_x_km, row.max_y_km, row.max_z_km]).all()
        ids = [(t.id, t.track) for t in tracks]
        # a ring of 1,000 maplets: the query finds exactly those whose square reaches into a track's cone
        row = min(tracks, key=lambda t: t.cone_half_angle_rad)
        _tile(session, radius_km=0.25, size_km=0.03, count=1000)
        axis = np.array([row.cone_axis_x, row.cone_axis_y, row.cone_axis_z])
        found = {c.maplet for c in maplets_crossed(session, track_id=row.id)}
        expected = {m.name for m in session.scalars(select(Maplet))
                    if np.degrees(np.arccos(np.clip(latlon_to_unit(m.center_lat_deg, m.center_lon_deg) @ axis,
                                                    -1, 1)))
                    <= np.degrees(row.cone_half_angle_rad + np.arcsin(m.size_km / np.sqrt(2) / 0.25))}
        assert found == expected and 0 < len(found) < 1000
        with pytest.raises(LookupError):
            maplets_crossed(session, track_id=10**9)
    again = ingest_directory(catalog, downlink, data_dir=data)
    assert (again.lidar.accepted, again.lidar.unchanged, again.failed) == (0, 1, 0)
    with catalog() as session:
        assert session.scalar(select(func.count()).select_from(LidarProduct)) == 1
        assert [(t.id, t.track) for t in session.scalars(select(LidarTrack).order_by(LidarTrack.track))] == ids


def _tile(session: Session, *, radius_km: float, size_km: float, count: int) -> None:
    """`count` flat maplets spread evenly over a sphere (a Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    lat = np.degrees(np.arcsin(1 - 2 * k / count))
    lon = np.degrees(np.pi * (1 + 5 ** 0.5) * k) % 360.0
    for n, (a, b) in enumerate(zip(lat, lon, strict=True)):
        x, y, z = radius_km * latlon_to_unit(a, b)
        session.add(Maplet(name=f"M{n:04d}", center_lat_deg=float(a), center_lon_deg=float(b), origin_x_km=x,
                           origin_y_km=y, origin_z_km=z, rotation=np.eye(3).tolist(), size_km=size_km, gsd_m=1.0,
                           nodes_per_side=31))
    session.flush()


def test_hostile_lidar_products_are_each_accepted_or_rejected_with_a_code(
        catalog: sessionmaker[Session], global_tiny_sim: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    table = read_lidar_table(global_tiny_sim / "downlink" / LIDAR_LABEL)
    downlink = _downlink(global_tiny_sim, tmp_path / "hostile", lidar=False)
    # 60 returns and 10 shots without one, in time order
    pick = np.sort(np.r_[np.flatnonzero(~table.flagged)[:60], np.flatnonzero(table.flagged)[:10]])
    flags = np.where(table.flagged[pick], 2, 0)
    et, range_km, flag = table.et[pick][:40], table.range_km[pick][:40].copy(), flags[:40]
    range_km[flag != 0] = 1.0  # the simulator's no-return ranges are NaN; these say flagged alone
    assert 0 < (flag != 0).sum() < 40

    def product(name: str, *, times: np.ndarray = et, ranges: np.ndarray = range_km, target: str = "Bennu",
                lid: str | None = None, where: Path = downlink / "lidar") -> Path:
        label, _ = write_lidar_product(
            directory=where, basename=name, lid=lid or f"urn:nasa:pds:test:{name}", et=times, range_km=ranges,
            flag=flags[:len(times)], start_utc="2019-03-04T00:00:00", stop_utc="2019-03-09T00:00:00",
            mission="OSIRIS-REx", host_name="OSIRIS-REX", instrument_name="PWM_LIDAR", target_name=target,
            title=name, direction=table.direction[pick][:len(times)])
        return label

    nan = range_km.copy()
    nan[::5] = np.nan
    product("nan", ranges=nan)
    product("late", times=et + 10 * 365 * 86400.0)  # ten years past the kernels
    product("stranger", target="Nowhere")
    product("many", times=table.et[pick][:60], ranges=np.ones(60))
    cut = product("cut").with_suffix(".dat")
    whole = cut.read_bytes()
    cut.write_bytes(whole[:-45])  # the last record not there yet
    report = ingest_directory(catalog, downlink, data_dir=data, limits=IngestLimits(max_lidar_shots=50))
    codes = {Path(f.path).stem: f.code for f in report.failures}
    assert codes == {"late": "outside_coverage", "stranger": "unknown_target", "many": "too_many_shots",
                     "cut": "size_mismatch"}
    with catalog() as session:
        rows = {r.lid.rpartition(":")[2]: r for r in session.scalars(select(LidarProduct))}
        assert set(rows) == {"nan", "late", "stranger", "many", "cut"} and all(r.shots_artifact is None
                                                                             for n, r in rows.items() if n != "nan")
        # NaN ranges kept, with why; the product's own flags too (first: a flagged shot's range means nothing)
        assert rows["nan"].invalid_shots == {"not_finite": int((np.isnan(nan) & (flag == 0)).sum()),
                                             "flagged": int((flag != 0).sum())}
        cut_id = rows["cut"].id
    # the whole copy arrives: it takes the broken one's row; the rest is as it was
    cut.write_bytes(whole)
    again = ingest_directory(catalog, downlink, data_dir=data, limits=IngestLimits(max_lidar_shots=50))
    # (late and stranger were judged again, for kernels may have come: the same verdict, unchanged)
    assert (again.lidar.accepted, again.lidar.unchanged, again.failed) == (1, 4, 0)
    with catalog() as session:
        healed = session.scalars(select(LidarProduct).filter_by(lid="urn:nasa:pds:test:cut")).one()
        assert (healed.id, healed.status, healed.valid_shots) == (cut_id, Acceptance.ACCEPTED, int((flag == 0).sum()))
    # another downlink offers the nan product's LIDVID with other content: not used, the first stays
    other = _downlink(global_tiny_sim, tmp_path / "other", lidar=False)
    product("impostor", lid="urn:nasa:pds:test:nan", ranges=range_km + 0.001, where=other / "lidar")
    third = ingest_directory(catalog, other, data_dir=data)
    assert [(Path(f.path).name, f.code) for f in third.failures] == [("impostor.xml", "conflict")]
    with catalog() as session:
        assert session.scalar(select(func.count()).select_from(LidarProduct)) == 5
        kept = session.scalars(select(LidarProduct).filter_by(lid="urn:nasa:pds:test:nan")).one()
        assert kept.label_path.endswith("nan.xml")
        assert {f.code for f in session.scalars(select(DownlinkFile))} == {"conflict"}
