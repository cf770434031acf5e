"""`pwm ingest`'s engine on real SQLite and PostgreSQL: kernels and PDS4 products into the
catalog, the geometry of each image, bad inputs, idempotence, and real archive data."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import tracemalloc
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
import spiceypy as sp
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from pwm.camera import look_at
from pwm.io.meshio import read_obj
from pwm.io.pds4 import write_image_product
from pwm.io.spice_kernels import CkSegment, SpkSegment, bundled_kernels, kernel_pool, write_ck, write_spk
from service.db import make_engine, make_sessionmaker, upgrade
from service.ingest import ingest_directory
from service.rows import (
    Acceptance,
    Downlink,
    DownlinkFile,
    DownlinkStatus,
    Image,
    ImageGeometry,
    ImageStatus,
    Instrument,
    Kernel,
    KernelCoverage,
    KernelKind,
)
from service.settings import IngestLimits

BENNU, SC, MAPCAM, SC_BUS = 2101955, -64, -64361, -64000
RANGE_KM = 2.0  # from Bennu's centre
START_UTC = "2019-03-03T10:00:00"
SPK_SPAN_S = 3600.0
CK_WINDOWS_S = [(0.0, 600.0), (1800.0, 2400.0)]  # attitude only here; the SPK covers the hour
GOOD_OFFSETS_S = [120.0, 240.0, 1860.0]
WINDOW = (600, 300, 16, 24)  # first line, first sample, lines, samples of the test products
REAL_MAPCAM_UTC = "2019-03-03T10:59:40.279"
BUNDLED_SHAPE = Path(__file__).resolve().parents[2] / "pwm" / "data" / "shapes" / "bennu_radar_nolan2013_sbgat.obj"
EXPOSURE_S = 0.01


def _sc_states(t: np.ndarray) -> np.ndarray:
    """Spacecraft (n, 6) in IAU_BENNU: RANGE_KM away, sweeping in longitude and latitude."""
    w_lon, w_lat = 3e-4, 1e-4  # rad/s
    lon, lat = 0.3 + w_lon * t, 0.2 + w_lat * t
    pos = RANGE_KM * np.stack([np.cos(lon) * np.cos(lat), np.sin(lon) * np.cos(lat),
                               np.sin(lat)], axis=1)
    vel = RANGE_KM * np.stack([
        -np.sin(lon) * np.cos(lat) * w_lon - np.cos(lon) * np.sin(lat) * w_lat,
        np.cos(lon) * np.cos(lat) * w_lon - np.sin(lon) * np.sin(lat) * w_lat,
        np.cos(lat) * w_lat], axis=1)
    return np.hstack([pos, vel])


@pytest.fixture(scope="module")
def kernels(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A consistent MapCam kernel set: bundled LSK/FK/IK/SCLK/PCK, SPKs of the spacecraft wrt
    Bennu (one hour), Bennu wrt the Sun and the Sun wrt the SSB, a spacecraft CK in two windows
    and the MapCam structure CK; the camera looks at Bennu's centre."""
    out = tmp_path_factory.mktemp("kernels")
    with kernel_pool(bundled_kernels().values()):
        et0 = sp.utc2et(START_UTC)
        epochs = et0 + np.arange(0.0, SPK_SPAN_S + 1, 60.0)
        bf = _sc_states(epochs - et0)
        sc_j2000 = np.array([sp.sxform("IAU_BENNU", "J2000", et) @ s for et, s in zip(epochs, bf, strict=True)])
        write_spk(out / "orx_sc.bsp", segments=[SpkSegment(SC, BENNU, epochs, sc_j2000)])
        sun_epochs = et0 + np.arange(-600.0, SPK_SPAN_S + 601, 600.0)
        direction = np.array([1.0, 0.3, 0.1]) / np.linalg.norm([1.0, 0.3, 0.1])
        velocity = 28.0 * np.array([-0.3, 1.0, 0.0]) / np.linalg.norm([-0.3, 1.0, 0.0])
        helio = np.hstack([1.8e8 * direction + np.outer(sun_epochs - et0, velocity),
                           np.tile(velocity, (len(sun_epochs), 1))])
        write_spk(out / "bennu_sun.bsp", segments=[
            SpkSegment(BENNU, 10, sun_epochs, helio),
            SpkSegment(10, 0, sun_epochs, np.zeros((len(sun_epochs), 6)))])
        struct = sp.eul2m(np.pi / 2, 0.01, -0.02, 3, 2, 1)  # ORX_SPACECRAFT -> MapCam
        ck_epochs = np.concatenate([et0 + np.arange(a, b + 1, 60.0) for a, b in CK_WINDOWS_S])
        ck_bf = _sc_states(ck_epochs - et0)
        attitude = np.array([
            struct.T @ look_at(s[:3], np.zeros(3), np.array([0.0, 0, 1])).rotation
            @ sp.pxform("J2000", "IAU_BENNU", et) for s, et in zip(ck_bf, ck_epochs, strict=True)])
        write_ck(out / "orx_sc.bc", segments=[CkSegment(
            SC_BUS, SC, ck_epochs, attitude, np.zeros((len(ck_epochs), 3)),
            [et0 + a for a, _ in CK_WINDOWS_S])])
        write_ck(out / "orx_struct_mapcam.bc", segments=[CkSegment(
            MAPCAM, SC, sun_epochs[[0, -1]], np.array([struct, struct]), np.zeros((2, 3)),
            [sun_epochs[0]], reference="ORX_SPACECRAFT")])
    files = [*bundled_kernels().values(),
             *(out / n for n in ("bennu_sun.bsp", "orx_sc.bsp", "orx_sc.bc",
                                 "orx_struct_mapcam.bc"))]
    return dict(files=files, et0=et0)


def _utc(et: float) -> str:
    return sp.et2utc(et, "ISOC", 3) + "Z"


def _product(directory: Path, name: str, mid_et: float, *,
             window: tuple[int, int, int, int] = WINDOW, **meta: str) -> tuple[Path, Path]:
    """A MapCam product of a detector window (first line, first sample, lines, samples) whose
    exposure is centred on `mid_et` (LSK loaded)."""
    directory.mkdir(parents=True, exist_ok=True)
    first_line, first_sample, lines, samples = window
    dn = np.random.default_rng(len(name)).integers(0, 4000, (lines, samples))
    fields = dict(mission="OSIRIS-REx", host_name="OSIRIS-REX",
                  instrument_name="ORX_OCAMS_MAPCAM", target_name="(101955) Bennu") | meta
    return write_image_product(
        directory=directory, basename=name, dn=dn.astype(np.int16), scaling_factor=1e-4,
        value_offset=0.0, lid=f"urn:nasa:pds:pwm_test:data_calibrated:{name}", title=name,
        start_utc=_utc(mid_et - EXPOSURE_S / 2), stop_utc=_utc(mid_et + EXPOSURE_S / 2),
        exposure_s=EXPOSURE_S, subframe=(first_line, first_sample), **fields)


@pytest.fixture
def downlink(tmp_path: Path, kernels: dict) -> Path:
    """A downlink directory: the kernel set and three good products inside the CK windows."""
    root = tmp_path / "downlink"
    (root / "kernels").mkdir(parents=True)
    for f in kernels["files"]:
        shutil.copy(f, root / "kernels" / f.name)
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        for k, offset in enumerate(GOOD_OFFSETS_S):
            _product(root / "images", f"good{k}", kernels["et0"] + offset)
    return root


def _images(catalog: sessionmaker[Session]) -> dict[str, Image]:
    """Images by label file stem, geometry and instrument loaded."""
    with catalog() as session:
        rows = session.scalars(select(Image)).all()
        for row in rows:
            _ = row.geometry, row.instrument
        return {Path(row.label_path).stem: row for row in rows}


def _snapshot(catalog: sessionmaker[Session]) -> dict:
    with catalog() as session:
        def rows(query):
            return sorted(tuple(r) for r in session.execute(query))
        return dict(
            images=rows(select(Image.lidvid, Image.sha256, Image.status, Image.rejection_code,
                               Image.rejection_reason, Image.geometry_status,
                               Image.geometry_unavailable_reason, Image.instrument_id)),
            geometry=rows(select(ImageGeometry.image_id, ImageGeometry.range_km,
                                 ImageGeometry.phase_deg, ImageGeometry.computed_at)),
            kernels=rows(select(Kernel.sha256, Kernel.kind, Kernel.status,
                                Kernel.rejection_reason)),
            coverage=session.scalar(select(func.count()).select_from(KernelCoverage)),
            instruments=rows(select(Instrument.naif_id, Instrument.fx_px)),
            downlinks=rows(select(Downlink.name, Downlink.status)))


def _assert_good_images_accepted(images: dict[str, Image]) -> None:
    for k in range(len(GOOD_OFFSETS_S)):
        image = images[f"good{k}"]
        assert (image.status, image.geometry_status) == ("accepted", "computed"), (
            image.rejection_reason)
        assert image.geometry is not None and image.instrument.naif_id == MAPCAM


# ---------------------------------------------------------------------------------------------
# A good downlink, and running it twice


def test_downlink_is_catalogued_with_geometry_and_rerun_changes_nothing(
    catalog: sessionmaker[Session], downlink: Path, kernels: dict
) -> None:
    report = ingest_directory(catalog, downlink)
    assert (report.images.accepted, report.images.rejected, report.failed) == (3, 0, 0)
    assert (report.kernels.accepted, report.kernels.rejected) == (len(kernels["files"]), 0)
    assert "3 accepted" in report.summary() and "0 failed" in report.summary()

    with catalog() as session:
        kinds = dict(session.execute(select(Kernel.path, Kernel.kind)).all())
        assert {Path(p).name: k for p, k in kinds.items()} == {
            "naif0012.tls": "lsk", "orx_sclkscet_00065.tsc": "sclk", "bennu_v16.tpc": "pck",
            "orx_v14.tf": "fk", "orx_ocams_v07.ti": "ik", "bennu_sun.bsp": "spk",
            "orx_sc.bsp": "spk", "orx_sc.bc": "ck", "orx_struct_mapcam.bc": "ck"}
        coverage = session.execute(
            select(KernelCoverage.naif_id, KernelCoverage.start_et, KernelCoverage.stop_et,
                   KernelCoverage.start_utc).join(Kernel).where(Kernel.kind == KernelKind.CK)
            .order_by(KernelCoverage.start_et)).all()
        instrument = session.scalars(select(Instrument)).one()
        assert session.scalars(select(Downlink)).one().status == DownlinkStatus.INGESTED
    et0 = kernels["et0"]
    bus = [(start, stop) for naif_id, start, stop, _ in coverage if naif_id == SC_BUS]
    assert np.allclose(bus, [(et0 + a, et0 + b) for a, b in CK_WINDOWS_S], atol=1e-3)
    assert min(c[3] for c in coverage).isoformat().startswith("2019-03-03T09:50:00")
    assert (instrument.width_px, instrument.height_px, instrument.cx_px) == (1024, 1024, 511.5)
    assert instrument.fx_px == pytest.approx(125.20 / 8.5e-3, rel=1e-12)
    assert instrument.focal_length_source == "FOCAL_LENGTH/PIXEL_SIZE"
    assert instrument.frame_name == "ORX_OCAMS_MAPCAM" and instrument.spacecraft_id == SC

    images = _images(catalog)
    _assert_good_images_accepted(images)
    with kernel_pool(kernels["files"]):
        radii = sp.bodvrd("BENNU", "RADII", 3)[1]
        for k, offset in enumerate(GOOD_OFFSETS_S):
            image, et = images[f"good{k}"], et0 + offset
            g = image.geometry
            assert image.start_et == pytest.approx(et - EXPOSURE_S / 2, abs=1e-6)
            position = _sc_states(np.array([offset]))[0, :3]
            camera = np.array([g.camera_x_km, g.camera_y_km, g.camera_z_km])
            assert np.abs(camera - position).max() < 1e-8
            assert g.range_km == pytest.approx(RANGE_KM, abs=1e-9)
            # Aimed at the centre: the boresight meets the ellipsoid straight below the camera.
            point = sp.surfpt(np.zeros(3), position, *radii)
            assert g.intercept_range_km == pytest.approx(RANGE_KM - np.linalg.norm(point), abs=1e-6)
            _, lon, lat = sp.reclat(position)
            assert g.intercept_lat_deg == pytest.approx(np.degrees(lat), abs=1e-6)
            assert g.intercept_lon_deg == pytest.approx(np.degrees(lon) % 360, abs=1e-6)
            sun = sp.spkpos("SUN", et, "IAU_BENNU", "LT+S", "BENNU")[0]
            assert np.allclose([g.sun_x, g.sun_y, g.sun_z], sun / np.linalg.norm(sun), atol=1e-9)
            assert g.phase_deg == pytest.approx(np.degrees(sp.vsep(position, sun)), abs=1e-6)
            normal = sp.surfnm(*radii, point)
            assert g.incidence_deg == pytest.approx(np.degrees(sp.vsep(normal, sun)), abs=1e-6)
            assert g.emission_deg == pytest.approx(np.degrees(sp.vsep(normal, position)), abs=1e-6)
            assert g.pixel_scale_m == pytest.approx(g.intercept_range_km * 1e3 / instrument.fx_px)
            rotation = np.array(g.camera_rotation)
            # stored in the image frame: rows are the IK's sample and line directions, then boresight
            axes = np.vstack([sp.gdpool("INS-64361_SPOC_FITS_NAXIS1", 0, 3),
                              sp.gdpool("INS-64361_SPOC_FITS_NAXIS2", 0, 3), [0, 0, 1]])
            assert np.allclose(rotation, axes @ sp.pxform("IAU_BENNU", "ORX_OCAMS_MAPCAM", et), atol=1e-9)
            corners = [_corner_point(et, d) for d in _mapcam_corner_rays(instrument, WINDOW)]
            assert all(c is not None for c in corners)
            _assert_footprint(g.footprint, corners)

    before = _snapshot(catalog)
    again = ingest_directory(catalog, downlink)
    assert (again.images.accepted, again.images.rejected, again.images.unchanged) == (0, 0, 3)
    assert (again.kernels.accepted, again.kernels.unchanged, again.failed) == (0, 9, 0)
    assert _snapshot(catalog) == before


def _mapcam_corner_rays(instrument: Instrument, window: tuple[int, int, int, int]
                        ) -> list[list[float]]:
    """MapCam-frame rays through the outer corners of a detector window, in the order first
    line first sample, first line last sample, last line last sample, last line first sample.
    orx_ocams_v07.ti: samples (NAXIS1) run along +Y, lines (NAXIS2) along +X."""
    first_line, first_sample, lines, samples = window
    l0, l1 = first_line - 0.5, first_line + lines - 0.5
    s0, s1 = first_sample - 0.5, first_sample + samples - 0.5
    return [[(line - instrument.cy_px) / instrument.fy_px,
             (sample - instrument.cx_px) / instrument.fx_px, 1.0]
            for sample, line in ((s0, l0), (s1, l0), (s1, l1), (s0, l1))]


def _corner_point(et: float, ray: list[float]) -> np.ndarray | None:
    """Where a MapCam-frame ray meets Bennu's ellipsoid (SPICE's sincpt), None if it misses."""
    with sp.no_found_check():
        point, _, _, found = sp.sincpt("ELLIPSOID", "BENNU", et, "IAU_BENNU", "NONE", str(SC),
                                       "ORX_OCAMS_MAPCAM", ray)
    return point if found else None


def _assert_footprint(footprint: list, corners: list[np.ndarray | None]) -> None:
    assert [c is None for c in footprint] == [c is None for c in corners]
    for corner, expected in zip(footprint, corners, strict=True):
        if expected is not None:
            _, lon, lat = sp.reclat(expected)
            assert corner == pytest.approx([np.degrees(lat), np.degrees(lon) % 360], abs=1e-6)


# ---------------------------------------------------------------------------------------------
# Bad input: each is rejected with a reason, the good products go through, a rerun is a no-op


def _ingest_with_bad_product(catalog: sessionmaker[Session], downlink: Path, name: str,
                             code: str, *, orphans: int = 0) -> Image:
    """orphans: data files no readable label names, reported as unknown files."""
    report = ingest_directory(catalog, downlink)
    assert (report.images.accepted, report.images.rejected, report.failed) == (3, 1, 1 + orphans)
    assert report.failures[0].code == code and name in report.failures[0].path
    assert [f.code for f in report.failures[1:]] == ["unknown_type"] * orphans
    assert "1 rejected" in report.summary() and f"{1 + orphans} failed" in report.summary()
    images = _images(catalog)
    _assert_good_images_accepted(images)
    bad = images[name]
    assert (bad.status, bad.rejection_code) == (ImageStatus.REJECTED, code)
    assert bad.rejection_reason == report.failures[0].reason and bad.geometry is None
    before = _snapshot(catalog)
    again = ingest_directory(catalog, downlink)
    assert (again.images.unchanged, again.failed) == (4, 0)
    assert _snapshot(catalog) == before
    return bad


def _bad_product(downlink: Path, kernels: dict) -> tuple[Path, Path]:
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        return _product(downlink / "images", "bad", kernels["et0"] + 180.0)


def test_malformed_xml_is_rejected(catalog, downlink, kernels) -> None:
    label, _ = _bad_product(downlink, kernels)
    label.write_text(label.read_text()[:700])
    bad = _ingest_with_bad_product(catalog, downlink, "bad", "malformed_xml", orphans=1)
    assert "not well-formed" in bad.rejection_reason and bad.lid.startswith("unidentified:")


def test_missing_data_file_is_rejected(catalog, downlink, kernels) -> None:
    label, data = _bad_product(downlink, kernels)
    data.unlink()
    bad = _ingest_with_bad_product(catalog, downlink, "bad", "missing_file")
    assert "not found" in bad.rejection_reason and bad.lid.endswith(":bad")


def test_truncated_data_file_is_rejected(catalog, downlink, kernels) -> None:
    label, data = _bad_product(downlink, kernels)
    data.write_bytes(data.read_bytes()[:-500])
    bad = _ingest_with_bad_product(catalog, downlink, "bad", "size_mismatch")
    assert "truncated" in bad.rejection_reason


def test_checksum_mismatch_is_rejected(catalog, downlink, kernels) -> None:
    label, data = _bad_product(downlink, kernels)
    raw = bytearray(data.read_bytes())
    raw[3000] ^= 0x01  # inside the array, after the 2880-byte FITS header
    data.write_bytes(bytes(raw))
    bad = _ingest_with_bad_product(catalog, downlink, "bad", "md5_mismatch")
    assert "md5" in bad.rejection_reason


def test_real_non_image_products_are_rejected(catalog, downlink, shared_data) -> None:
    for folder in ("orex_tagcams_stowcam", "sbn_litcomp_comets"):
        shutil.copytree(shared_data / "pds4" / folder, downlink / folder)
    report = ingest_directory(catalog, downlink)
    assert (report.images.accepted, report.images.rejected, report.failed) == (3, 2, 2)
    assert {f.code for f in report.failures} == {"not_image"}
    images = _images(catalog)
    _assert_good_images_accepted(images)
    jpeg, table = images["20170303t022534s621_sto_l0.b"], images["colors"]
    assert jpeg.lid == "urn:nasa:pds:orex.tagcams:miscellaneous:20170303t022534s621_sto_l0.jpg"
    assert "Product_Ancillary" in jpeg.rejection_reason and "Encoded_Image" in jpeg.rejection_reason
    assert "Table_Character" in table.rejection_reason
    assert all(i.status == "rejected" and i.rejection_code == "not_image" for i in (jpeg, table))


@pytest.mark.parametrize("field, value, code", [
    ("instrument_name", "NoSuchCam", "unknown_instrument"),
    ("target_name", "(99999) Nowhere", "unknown_target"),
], ids=["instrument", "target"])
def test_unknown_instrument_or_target_is_rejected(catalog, downlink, kernels, field, value,
                                                  code) -> None:
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        _product(downlink / "images", "bad", kernels["et0"] + 180.0, **{field: value})
    bad = _ingest_with_bad_product(catalog, downlink, "bad", code)
    assert value in bad.rejection_reason


def test_window_beyond_the_detector_is_rejected(sqlite_url, downlink, kernels) -> None:
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        _product(downlink / "images", "bad", kernels["et0"] + 180.0, window=(1020, 0, 16, 24))
    bad = _ingest_with_bad_product(sessions, downlink, "bad", "bad_dimensions")
    assert "exceeds the 1024x1024 detector" in bad.rejection_reason


@pytest.mark.parametrize("offset_s, missing", [
    (SPK_SPAN_S + 600.0, "SPK coverage of observer -64"),
    (1200.0, f"no CK data then for frames {SC_BUS}"),  # inside the SPK, between CK windows
], ids=["spk", "ck"])
def test_image_outside_kernel_coverage_is_rejected(catalog, downlink, kernels, offset_s,
                                                   missing) -> None:
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        _product(downlink / "images", "bad", kernels["et0"] + offset_s)
    bad = _ingest_with_bad_product(catalog, downlink, "bad", "outside_coverage")
    assert missing in bad.rejection_reason and bad.instrument_id is not None


def test_kernel_that_fails_to_load_is_rejected_with_spices_message(catalog, downlink) -> None:
    garbage = downlink / "kernels" / "garbage.bsp"
    garbage.write_bytes(np.random.default_rng(3).bytes(4096))
    report = ingest_directory(catalog, downlink)
    assert (report.kernels.accepted, report.kernels.rejected, report.failed) == (9, 1, 1)
    failure = report.failures[0]
    assert failure.path == str(garbage) and "INVALIDARCHTYPE" in failure.reason
    _assert_good_images_accepted(_images(catalog))
    with catalog() as session:
        row = session.scalars(select(Kernel).where(Kernel.status == Acceptance.REJECTED)).one()
    assert (row.kind, row.size_bytes) == (KernelKind.SPK, 4096)
    assert row.rejection_reason.startswith("SPICE(INVALIDARCHTYPE)")
    before = _snapshot(catalog)
    again = ingest_directory(catalog, downlink)
    assert (again.kernels.unchanged, again.kernels.rejected, again.images.unchanged) == (10, 0, 3)
    assert _snapshot(catalog) == before


def test_same_lidvid_twice(catalog, downlink, kernels, tmp_path) -> None:
    """Identical content delivered again is a no-op; other content under the same LIDVID is a
    conflict, and the first copy stays authoritative."""
    ingest_directory(catalog, downlink)
    original = _images(catalog)["good0"]
    second = tmp_path / "second"
    shutil.copytree(downlink / "images", second / "same")
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        _product(second / "changed", "good0", kernels["et0"] + 300.0)
    report = ingest_directory(catalog, second)
    assert (report.images.unchanged, report.images.rejected, report.images.accepted) == (3, 1, 0)
    assert report.failures[0].code == "conflict" and "changed" in report.failures[0].path
    with catalog() as session:
        copies = session.scalars(select(Image).where(Image.lid == original.lid)
                                 .order_by(Image.id)).all()
    assert [c.status for c in copies] == [ImageStatus.ACCEPTED, ImageStatus.CONFLICT]
    assert copies[0].lidvid == original.lidvid == f"{original.lid}::1.0"
    assert copies[0].sha256 == original.sha256 != copies[1].sha256
    assert copies[1].lidvid.startswith(original.lidvid + "#")
    assert original.sha256 in copies[1].rejection_reason
    before = _snapshot(catalog)
    again = ingest_directory(catalog, second)
    assert (again.images.unchanged, again.failed) == (4, 0)
    assert _snapshot(catalog) == before


# ---------------------------------------------------------------------------------------------
# Real data


def test_real_pds4_products_of_other_missions(catalog, tmp_path, shared_data) -> None:
    """No kernels for their observers: the two image arrays are accepted without geometry."""
    shutil.copytree(shared_data / "pds4", tmp_path / "pds4")
    report = ingest_directory(catalog, tmp_path / "pds4", downlink_name="archive-samples")
    counts = report.images
    assert (counts.accepted, counts.rejected, report.geometry_unavailable) == (2, 2, 2)
    images = _images(catalog)
    dart, tir = images["m221011.0013"], images["hyb2_tir_20180629_075501_l1"]
    for image in (dart, tir):
        assert (image.status, image.geometry_status) == ("accepted", "unavailable")
        assert image.geometry is None and image.geometry_unavailable_reason.startswith("no kernels")
    assert "'Magdalena Ridge Observatory (MRO)' is not a body" in dart.geometry_unavailable_reason
    assert "no SPK for observer 'Hayabusa2' (-37)" in tir.geometry_unavailable_reason
    assert tir.start_utc.isoformat() == "2018-06-29T07:54:59.949000+00:00"
    assert dart.target == "Sky" and dart.md5 is None  # the label's target: a calibration field
    assert {images[n].rejection_code for n in ("colors", "20170303t022534s621_sto_l0.b")} == {
        "not_image"}
    with catalog() as session:
        assert session.scalars(select(Downlink.name)).one() == "archive-samples"


def _real_mapcam_downlink(root: Path, shared_data: Path) -> Path:
    kernels = root / "kernels"
    shutil.copytree(shared_data / "spice" / "orex_mapcam_20190303", kernels)
    shutil.copy(shared_data / "spice" / "generic" / "naif0012.tls", kernels)
    with kernel_pool([kernels / "naif0012.tls"]):
        # As OCAMS labels name them: the camera and the spacecraft, not SPICE's names.
        _product(root / "images", "mapcam", sp.str2et(REAL_MAPCAM_UTC), host_name="OSIRIS-REx",
                 instrument_name="MapCam", window=(0, 0, 1024, 1024))
    return root


def test_real_mapcam_geometry_matches_spice(catalog, tmp_path, shared_data) -> None:
    root = _real_mapcam_downlink(tmp_path / "orex", shared_data)
    report = ingest_directory(catalog, root)
    assert report.images.accepted == 1 and report.images.rejected == 0, report.failures
    # the archive's PDS3 (ISIS) label is no kernel or PDS4 label: recorded, with why
    assert [(Path(f.path).suffix, f.code) for f in report.failures] == [(".lbl", "unknown_type")]
    image = _images(catalog)["mapcam"]
    g = image.geometry
    assert (image.instrument.naif_id, g.body_frame) == (MAPCAM, "IAU_BENNU")
    with kernel_pool(sorted(p for p in (root / "kernels").iterdir() if p.suffix != ".lbl")):
        et = sp.str2et(REAL_MAPCAM_UTC)
        assert (image.start_et + image.stop_et) / 2 == pytest.approx(et, abs=1e-6)
        _, frame, boresight, _, _ = sp.getfov(MAPCAM, 4)
        point, _, to_point = sp.sincpt("ELLIPSOID", "BENNU", et, "IAU_BENNU", "NONE", str(SC),
                                       frame, boresight)
        _, _, phase, incidence, emission = sp.ilumin("ELLIPSOID", "BENNU", et, "IAU_BENNU",
                                                     "LT+S", str(SC), point)
        position = sp.spkpos(str(SC), et, "IAU_BENNU", "NONE", "BENNU")[0]
        _, lon, lat = sp.reclat(point)
        corners = [_corner_point(et, ray)
                   for ray in _mapcam_corner_rays(image.instrument, (0, 0, 1024, 1024))]
    assert g.range_km == pytest.approx(np.linalg.norm(position), abs=1e-3)  # 1 m
    assert g.intercept_range_km == pytest.approx(np.linalg.norm(to_point), abs=1e-3)
    assert 6.33 < g.intercept_range_km < 6.35  # PROVENANCE.md: 6.338 km to the ellipsoid
    for value, reference in ((g.phase_deg, phase), (g.incidence_deg, incidence),
                             (g.emission_deg, emission)):
        assert np.radians(value) == pytest.approx(reference, abs=1e-6)
    assert np.radians(g.intercept_lat_deg) == pytest.approx(lat, abs=1e-6)
    assert np.radians(g.intercept_lon_deg) == pytest.approx(lon % (2 * np.pi), abs=1e-6)
    _assert_footprint(g.footprint, corners)
    # Bennu fills the middle of the frame: two corners on it, two beyond the limb.
    assert sorted(c is None for c in corners) == [False, False, True, True]


def test_shape_model_intercept(sqlite_url: str, tmp_path: Path, shared_data: Path) -> None:
    """The boresight meets the radar shape model 23 m before the ellipsoid (PROVENANCE.md:
    6.361 km vs 6.338 km)."""
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    shape = read_obj(Path(__file__).resolve().parents[2] / "pwm" / "data" / "shapes"
                     / "bennu_radar_nolan2013_sbgat.obj")
    ingest_directory(sessions, _real_mapcam_downlink(tmp_path / "orex", shared_data), shape=shape)
    g = _images(sessions)["mapcam"].geometry
    assert g.intercept_range_km == pytest.approx(6.361, abs=6e-4)
    assert 0 < g.emission_deg < 90 and 0 < g.incidence_deg < 90
    assert g.range_km == pytest.approx(6.6, abs=0.1)


# ---------------------------------------------------------------------------------------------
# Kernels arriving separately, meta-kernels


def test_images_before_their_kernels_are_taken_up_later(sqlite_url, kernels, tmp_path) -> None:
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    images_dir, kernels_dir = tmp_path / "images", tmp_path / "kernels"
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        _product(images_dir, "early", kernels["et0"] + 120.0)
    first = ingest_directory(sessions, images_dir)
    assert (first.images.accepted, first.geometry_unavailable) == (1, 1)
    kernels_dir.mkdir()
    for f in kernels["files"]:
        shutil.copy(f, kernels_dir / f.name)
    ingest_directory(sessions, kernels_dir)
    again = ingest_directory(sessions, images_dir)
    assert (again.images.accepted, again.images.unchanged, again.geometry_unavailable) == (1, 0, 0)
    image = _images(sessions)["early"]
    assert image.geometry_status == "computed" and image.geometry_unavailable_reason is None
    assert image.geometry.range_km == pytest.approx(RANGE_KM, abs=1e-9)


def test_metakernels_register_the_kernels_they_name(sqlite_url, kernels, tmp_path, shared_data) -> None:
    """PATH_VALUES relative to the meta-kernel reach kernels elsewhere in the downlink; a
    meta-kernel naming missing files is rejected with the list; one naming files outside the
    downlink has those entries refused, with why, unless they are in the kernel library."""
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    archive = tmp_path / "archive"
    (archive / "lsk").mkdir(parents=True)
    (archive / "mk").mkdir()
    shutil.copy(bundled_kernels()["naif0012.tls"], archive / "lsk")
    (archive / "mk" / "set.tm").write_text(
        "KPL/MK\n\\begindata\n PATH_VALUES = ( '..' )\n PATH_SYMBOLS = ( 'K' )\n"
        " KERNELS_TO_LOAD = ( '$K/lsk/naif0012.tls' )\n\\begintext\n")
    shutil.copy(shared_data / "spice" / "mk" / "orx_2020_v05.tm", archive / "mk")
    report = ingest_directory(sessions, archive, limits=IngestLimits())
    with sessions() as session:
        rows = {Path(k.path).name: k for k in session.scalars(select(Kernel))}
    assert rows["set.tm"].status == "accepted" and rows["set.tm"].kind == "mk"
    assert rows["naif0012.tls"].path == str(archive / "lsk" / "naif0012.tls")
    assert rows["orx_2020_v05.tm"].status == "rejected"
    # It names 207 kernels; with PATH_VALUES '..' its LSK is the one in archive/lsk.
    reason = rows["orx_2020_v05.tm"].rejection_reason
    assert reason.startswith("206 kernels it names are missing: ")
    assert str(archive / "fk" / "orx_v14.tf") in reason and "naif0012" not in reason
    assert (report.kernels.accepted, report.kernels.rejected) == (2, 1)

    # another downlink's meta-kernel naming files outside it, by absolute path and by '..'
    other = tmp_path / "other"
    other.mkdir()
    shutil.copy(bundled_kernels()["bennu_v16.tpc"], tmp_path / "elsewhere.tpc")
    (other / "evil.tm").write_text(
        f"KPL/MK\n\\begindata\n KERNELS_TO_LOAD = ( '{tmp_path / 'elsewhere.tpc'}'\n"
        "  '../archive/lsk/naif0012.tls' )\n\\begintext\n")
    evil = ingest_directory(sessions, other, limits=IngestLimits())
    with sessions() as session:
        assert "elsewhere.tpc" not in {Path(k.path).name for k in session.scalars(select(Kernel))}
        refused = {f.path: (f.code, f.reason) for f in session.scalars(select(DownlinkFile))}
    assert set(refused) == {str(tmp_path / "elsewhere.tpc"), str(archive / "lsk" / "naif0012.tls")}
    code, reason = refused[str(tmp_path / "elsewhere.tpc")]
    assert code == "outside_downlink" and reason.startswith("named by evil.tm: ")
    assert f"outside {other}" in reason
    assert {(f.code, f.path) for f in evil.failures} == {("outside_downlink", p) for p in refused}
    again = ingest_directory(sessions, other, limits=IngestLimits())
    assert again.failed == 0 and again.kernels.unchanged == 3

    # a configured kernel library may be named from outside
    upgrade(f"sqlite:///{tmp_path / 'library.sqlite'}")
    library = make_sessionmaker(make_engine(f"sqlite:///{tmp_path / 'library.sqlite'}"))
    ingest_directory(library, other, limits=IngestLimits(kernel_library=archive / "lsk"))
    with library() as session:
        assert session.scalars(select(Kernel.status).where(
            Kernel.path == str(archive / "lsk" / "naif0012.tls"))).one() == "accepted"
        assert session.scalars(select(DownlinkFile.path)).all() == [str(tmp_path / "elsewhere.tpc")]


# ---------------------------------------------------------------------------------------------
# Hostile input (issue 17): each product judged on its own, kernels kept to the downlink, reading
# bounded before it starts, symbolic links refused, and every file accounted for


def _edit(label: Path, old: str, new: str) -> None:
    text = label.read_text()
    assert old in text, old
    label.write_text(text.replace(old, new, 1))


def _edit_fits(label: Path, data: Path, card: str, value: str) -> None:
    """Rewrite one card of the FITS header of `data` and the label's md5 to match it."""
    raw = bytearray(data.read_bytes())
    start = raw.index(card.ljust(8).encode() + b"= ")
    raw[start + 10:start + 30] = value.rjust(20).encode()
    old_md5 = hashlib.md5(data.read_bytes()).hexdigest()
    data.write_bytes(bytes(raw))
    _edit(label, old_md5, hashlib.md5(bytes(raw)).hexdigest())


def _bad(downlink: Path, kernels: dict, name: str, **meta) -> tuple[Path, Path]:
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        return _product(downlink / "images", name, kernels["et0"] + 180.0, **meta)


def _hostile_labels(downlink: Path, kernels: dict) -> dict[str, str]:
    """Products whose checks used to raise out of ingest, by label stem: the expected code."""
    label, _ = _bad(downlink, kernels, "a_exposure")
    _edit(label, '<img:exposure_duration unit="s">0.01<', '<img:exposure_duration unit="s">fast<')
    for name, length in (("b_header_1e20", 10**20), ("c_header_4e15", 4 * 10**15)):
        label, _ = _bad(downlink, kernels, name)
        _edit(label, '<object_length unit="byte">2880<', f'<object_length unit="byte">{length}<')
    # two LIDs that join into one LIDVID: a::b + c and a + b::c
    base = "urn:nasa:pds:pwm_test:data_calibrated:joined"
    for name, lid, vid in (("d_join1", f"{base}::1", "0"), ("e_join2", base, "1::0")):
        label, _ = _bad(downlink, kernels, name)
        _edit(label, f"<logical_identifier>urn:nasa:pds:pwm_test:data_calibrated:{name}<",
              f"<logical_identifier>{lid}<")
        _edit(label, "<version_id>1.0<", f"<version_id>{vid}<")
    label, _ = _bad(downlink, kernels, "f_long_vid")
    _edit(label, "<version_id>1.0<", f"<version_id>{'1' * 40}.0<")  # past VARCHAR(32)
    return {"a_exposure": "bad_value", "b_header_1e20": "bad_header",
            "c_header_4e15": "bad_header", "d_join1": "bad_identifier",
            "e_join2": "bad_identifier", "f_long_vid": "bad_identifier"}


def test_one_bad_label_never_stops_the_downlink(catalog, downlink, kernels) -> None:
    expected = _hostile_labels(downlink, kernels)
    report = ingest_directory(catalog, downlink)
    assert (report.images.accepted, report.images.rejected) == (3, len(expected))
    assert {Path(f.path).stem: f.code for f in report.failures} == expected
    images = _images(catalog)
    _assert_good_images_accepted(images)
    for name, code in expected.items():
        assert (images[name].status, images[name].rejection_code) == ("rejected", code)
        assert images[name].rejection_reason
    assert "4000000000000000 bytes at byte 0 does not fit" in images["c_header_4e15"].rejection_reason
    assert images["d_join1"].lid.startswith("unidentified:")  # keyed by its label's sha256
    with catalog() as session:
        assert session.scalars(select(Downlink.status)).one() == DownlinkStatus.INGESTED
    before = _snapshot(catalog)
    again = ingest_directory(catalog, downlink)
    assert (again.images.unchanged, again.failed) == (3 + len(expected), 0)
    assert _snapshot(catalog) == before


def _radii_doubled(tmp_path: Path) -> Path:
    pck = tmp_path / "outside" / "bennu_big.tpc"
    pck.parent.mkdir()
    text = bundled_kernels()["bennu_v16.tpc"].read_text()
    with kernel_pool([bundled_kernels()["bennu_v16.tpc"]]):
        radii = sp.bodvrd("BENNU", "RADII", 3)[1]
    start = text.index("BODY2101955_RADII")
    end = text.index(")", start) + 1
    pck.write_text(text[:start] + "BODY2101955_RADII = ( "
                   + " ".join(f"{2 * r:.6f}" for r in radii) + " )" + text[end:])
    return pck


def test_kernels_of_a_later_downlink_never_change_catalogued_geometry(catalog, downlink, kernels,
                                                                      tmp_path) -> None:
    """A later downlink holding only a meta-kernel that names a PCK elsewhere (Bennu twice as
    large): the PCK is refused, and the images catalogued already keep their geometry."""
    ingest_directory(catalog, downlink)
    before = _snapshot(catalog)
    later = tmp_path / "later"
    later.mkdir()
    pck = _radii_doubled(tmp_path)
    (later / "later.tm").write_text("KPL/MK\n\\begindata\n KERNELS_TO_LOAD = ( "
                                    "'../outside/bennu_big.tpc' )\n\\begintext\n")
    report = ingest_directory(catalog, later)
    assert [(f.path, f.code) for f in report.failures] == [(str(pck), "outside_downlink")]
    after = _snapshot(catalog)
    assert after["geometry"] == before["geometry"] and after["images"] == before["images"]
    with catalog() as session:
        assert str(pck) not in set(session.scalars(select(Kernel.path)))
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        _product(downlink / "images", "good_later", kernels["et0"] + 300.0)
    ingest_directory(catalog, downlink)  # new images still use the downlink's own PCK
    image = _images(catalog)["good_later"]
    assert image.geometry.intercept_range_km == pytest.approx(
        _images(catalog)["good0"].geometry.intercept_range_km, rel=0.05)


def test_a_copied_simulated_downlink_catalogues_its_own_kernels(sqlite_url, tiny_sim, tmp_path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(tiny_sim / "downlink", copy)
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    report = ingest_directory(sessions, copy)
    assert report.failed == 0, report.failures
    with sessions() as session:
        paths = list(session.scalars(select(Kernel.path)))
    assert paths and all(Path(p).is_relative_to(copy) for p in paths)


def test_a_giant_metakernel_or_text_kernel_leaves_room_in_the_pool(sqlite_url, downlink) -> None:
    """A meta-kernel naming 200k kernels, and a PCK holding 20k strings (more than SPICE's pool
    holds), are rejected with why; the downlink's FK, IK and images are still accepted."""
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    with open(downlink / "kernels" / "giant.tm", "w") as fh:
        fh.write("KPL/MK\n\\begindata\nKERNELS_TO_LOAD = (\n")
        fh.writelines(f"'k{i}.bsp'\n" for i in range(200_000))
        fh.write(")\n\\begintext\n")
    with open(downlink / "kernels" / "aaa_full.tpc", "w") as fh:
        fh.write("KPL/PCK\n\\begindata\nFILLER = (\n")
        fh.writelines(f"'value{i}'\n" for i in range(20_000))
        fh.write(")\n\\begintext\n")
    report = ingest_directory(sessions, downlink)
    with sessions() as session:
        rows = {Path(k.path).name: k for k in session.scalars(select(Kernel))}
    assert rows["giant.tm"].status == "rejected"
    assert "more than the 5000 kernels a meta-kernel may name" in rows["giant.tm"].rejection_reason
    assert rows["aaa_full.tpc"].status == "rejected"
    assert "KERNELPOOLFULL" in rows["aaa_full.tpc"].rejection_reason
    assert all(rows[n].status == "accepted" for n in ("orx_v14.tf", "orx_ocams_v07.ti"))
    assert report.images.accepted == 3
    _assert_good_images_accepted(_images(sessions))


def test_label_reading_is_bounded_before_it_starts(sqlite_url, downlink, kernels) -> None:
    """A 16 MB label is refused unread; arrays larger than the detector, or than the pixel
    limit, are refused from the label's axes before any array is read."""
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    label, _ = _bad(downlink, kernels, "giant_label")
    _edit(label, "<Identification_Area>", "<Identification_Area><!--" + "x" * 16 * 1024**2 + "-->")
    label, _ = _bad(downlink, kernels, "huge_declared")
    for n in ("16", "24"):
        _edit(label, f"<elements>{n}<", "<elements>8000<")
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        _product(downlink / "images", "beyond_detector", kernels["et0"] + 200.0,
                 window=(0, 0, 1500, 1500))
    tracemalloc.start()
    clock = time.perf_counter()
    report = ingest_directory(sessions, downlink)
    elapsed = time.perf_counter() - clock
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    codes = {Path(f.path).name: f.code for f in report.failures}
    # the giant label, unread, names no data file: its data file is unknown
    assert codes == {"giant_label.xml": "too_large", "giant_label.fits": "unknown_type",
                     "huge_declared.xml": "too_large", "beyond_detector.xml": "bad_dimensions"}
    assert elapsed < 10 and peak < 16 * 1024**2  # the 1500x1500 array read would be 18 MB


def test_symbolic_links_out_of_the_downlink_are_refused(sqlite_url, downlink, kernels, tmp_path) -> None:
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    label, data = _bad(downlink, kernels, "to_passwd")
    data.unlink()
    data.symlink_to("/etc/passwd")
    outside = tmp_path / "outside"
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        elsewhere, _ = _product(outside, "elsewhere", kernels["et0"] + 200.0)
    (downlink / "images" / "linked.xml").symlink_to(elsewhere)
    (downlink / "kernels" / "linked.tpc").symlink_to(bundled_kernels()["bennu_v16.tpc"])
    report = ingest_directory(sessions, downlink)
    codes = {Path(f.path).name: f.code for f in report.failures}
    assert codes == {"to_passwd.xml": "outside_downlink", "to_passwd.fits": "outside_downlink",
                     "linked.xml": "outside_downlink", "linked.tpc": "outside_downlink"}
    images = _images(sessions)
    assert "to_passwd" in images and images["to_passwd"].geometry is None
    assert "elsewhere" not in images and report.images.accepted == 3
    with sessions() as session:
        files = {Path(f.path).name: f.reason for f in session.scalars(select(DownlinkFile))}
        assert all(not k.path.endswith("linked.tpc") for k in session.scalars(select(Kernel)))
    assert set(files) == {"linked.xml", "linked.tpc", "to_passwd.fits"}
    assert "outside" in files["linked.xml"]


def test_lenient_values_are_rejected(sqlite_url, downlink, kernels) -> None:
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    for name, value in (("scale_nan", "NaN"), ("scale_inf", "inf"), ("scale_zero", "0.0")):
        label, _ = _bad(downlink, kernels, name)
        _edit(label, "<scaling_factor>0.0001<", f"<scaling_factor>{value}<")
    label, data = _bad(downlink, kernels, "bitpix_lie")
    _edit_fits(label, data, "BITPIX", "32")
    label, data = _bad(downlink, kernels, "naxis_lie")
    _edit_fits(label, data, "NAXIS", "3")
    label, _ = _bad(downlink, kernels, "year_0019")
    text = label.read_text()
    label.write_text(text.replace("<start_date_time>2019", "<start_date_time>0019")
                     .replace("<stop_date_time>2019", "<stop_date_time>0019"))
    report = ingest_directory(sessions, downlink)
    codes = {Path(f.path).stem: f.code for f in report.failures}
    assert codes == {"scale_nan": "bad_value", "scale_inf": "bad_value", "scale_zero": "bad_value",
                     "bitpix_lie": "bad_dimensions", "naxis_lie": "bad_dimensions",
                     "year_0019": "bad_time"}
    reasons = {Path(f.path).stem: f.reason for f in report.failures}
    assert "BITPIX 32 (label: 16)" in reasons["bitpix_lie"] and "NAXIS 3" in reasons["naxis_lie"]
    assert "year 19" in reasons["year_0019"]


def test_every_file_is_accounted_for(catalog, downlink, kernels) -> None:
    """Files of no known type get a row with why; the downlink's rows account for every file."""
    (downlink / "README.txt").write_text("notes\n")
    (downlink / "empty.dat").write_bytes(b"")
    report = ingest_directory(catalog, downlink)
    assert {Path(f.path).name: f.code for f in report.failures} == {
        "README.txt": "unknown_type", "empty.dat": "unknown_type"}
    with catalog() as session:
        accounted = ({Path(p) for p in session.scalars(select(Kernel.path))}
                     | {Path(p) for p in session.scalars(select(Image.label_path))}
                     | {Path(p) for p in session.scalars(select(Image.data_path))}
                     | {Path(p) for p in session.scalars(select(DownlinkFile.path))})
    assert {p for p in downlink.rglob("*") if p.is_file()} <= accounted
    assert ingest_directory(catalog, downlink).failed == 0


def _ingest_command(directory: Path, url: str) -> subprocess.Popen:
    env = {**os.environ, "PWM_DATABASE_URL": url, "PYTHONPATH": str(Path(__file__).parents[2])}
    return subprocess.Popen([sys.executable, "-c", "from service.cli import app; app()", "ingest",
                             str(directory)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def test_two_concurrent_command_line_ingests_of_one_downlink(catalog, db_url, downlink) -> None:
    """Serialised: the second waits for the first, then finds everything catalogued."""
    runs = [_ingest_command(downlink, db_url) for _ in range(2)]
    results = [(run.wait(timeout=240), *run.communicate()) for run in runs]
    assert [code for code, _, _ in results] == [0, 0], results
    assert not any("Traceback" in err or "IntegrityError" in err for _, _, err in results)
    summaries = sorted(out for _, out, _ in results)
    assert "3 accepted" in summaries[0] + summaries[1] and "3 unchanged" in summaries[0] + summaries[1]
    with catalog() as session:
        downlink_row = session.scalars(select(Downlink)).one()
        assert (downlink_row.status, downlink_row.ingest_owner) == ("ingested", None)
        assert downlink_row.repeat_count == 1
    _assert_good_images_accepted(_images(catalog))


@pytest.mark.parametrize("owner, age_s", [(f"{socket.gethostname()}:999999999", 0.0),
                                          ("elsewhere:1", 7200.0)])
def test_a_killed_ingest_is_recovered(catalog, downlink, owner, age_s) -> None:
    """A downlink left ingesting by a process that is gone, or that stopped committing longer
    ago than the stale limit, is taken over and ingested."""
    ingest_directory(catalog, downlink)
    with catalog.begin() as session:
        row = session.scalars(select(Downlink)).one()
        row.status, row.ingest_owner = DownlinkStatus.INGESTING, owner
        row.ingest_heartbeat_at = datetime.now(UTC) - timedelta(seconds=age_s)
    clock = time.perf_counter()
    report = ingest_directory(catalog, downlink, limits=IngestLimits(stale_s=600.0))
    assert time.perf_counter() - clock < 30 and report.images.unchanged == 3
    with catalog() as session:
        assert session.scalars(select(Downlink.status)).one() == DownlinkStatus.INGESTED


def test_a_live_ingest_is_waited_for(sqlite_url, downlink) -> None:
    upgrade(sqlite_url)
    sessions = make_sessionmaker(make_engine(sqlite_url))
    ingest_directory(sessions, downlink)
    with sessions.begin() as session:
        row = session.scalars(select(Downlink)).one()
        row.status, row.ingest_owner = DownlinkStatus.INGESTING, "elsewhere:1"
        row.ingest_heartbeat_at = datetime.now(UTC)
    clock = time.perf_counter()
    ingest_directory(sessions, downlink, limits=IngestLimits(stale_s=3.0))
    assert time.perf_counter() - clock >= 2.5  # until the claim went stale


def test_a_repeated_delivery_is_counted_on_its_downlink(catalog, downlink, tmp_path) -> None:
    (downlink / "manifest.json").write_text('{"files": []}')
    ingest_directory(catalog, downlink)
    again = tmp_path / "again"
    shutil.copytree(downlink, again)
    report = ingest_directory(catalog, again)
    assert report.images.unchanged == 3 and report.downlink == "downlink"
    with catalog() as session:
        row = session.scalars(select(Downlink)).one()
        assert row.repeat_count == 1 and row.last_seen_at is not None


def test_downlinks_command_and_api_show_each_outcome(tmp_path, downlink, kernels, monkeypatch) -> None:
    """A downlink whose products all failed is marked rejected, by `pwm downlinks` as by the
    API's /downlinks."""
    from fastapi.testclient import TestClient
    from typer.testing import CliRunner

    from service.api import create_app
    from service.cli import app
    from service.settings import Settings, get_settings

    monkeypatch.setenv("PWM_DATA_DIR", str(tmp_path / "data"))
    get_settings.cache_clear()
    try:
        bad = tmp_path / "all-bad"
        label, _ = _bad(bad, kernels, "broken")
        label.write_text("<not-a-label")
        runner = CliRunner()
        for directory in (downlink, bad):
            runner.invoke(app, ["ingest", str(directory)])
        result = runner.invoke(app, ["downlinks", "--json"])
        assert result.exit_code == 0, result.output
        by_cli = {d["name"]: d for d in json.loads(result.output)}
        with TestClient(create_app(Settings())) as client:
            by_api = {d["name"]: d for d in client.get("/downlinks").json()["items"]}
    finally:
        get_settings.cache_clear()
    assert {n: d["outcome"] for n, d in by_cli.items()} == {"downlink": "accepted", "all-bad": "rejected"}
    for name, d in by_cli.items():
        assert {k: by_api[name][k] for k in ("outcome", "accepted", "rejected", "conflict", "kernels",
                                             "repeat_count", "status")} == {
            k: d[k] for k in ("outcome", "accepted", "rejected", "conflict", "kernels", "repeat_count",
                              "status")}
    assert (by_cli["all-bad"]["accepted"], by_cli["all-bad"]["rejected"]) == (0, 1)
    assert [f["code"] for f in by_cli["all-bad"]["unused_files"]] == ["unknown_type"]  # broken.fits
    table = runner.invoke(app, ["downlinks", "--files"]).output
    assert "rejected" in table and "unused" in table and "broken.fits" in table


def test_without_a_broker_an_ingest_runs_after_the_response(tmp_path, downlink, monkeypatch) -> None:
    """POST /ingests answers at once; the ingest (and what follows) runs in a background
    process, and its job is done afterwards."""
    from fastapi.testclient import TestClient

    from service.api import create_app
    from service.cli.background import BackgroundQueue
    from service.settings import Settings
    from workers.tasks import CeleryQueue

    data = tmp_path / "data"
    shutil.copytree(downlink, data / "incoming" / "dl")
    shutil.copy(BUNDLED_SHAPE, data / "incoming" / "dl" / "start_model.obj")
    monkeypatch.setenv("PWM_DATA_DIR", str(data))
    monkeypatch.setenv("PWM_API_TOKEN", "token-0123456789abcdef")
    monkeypatch.delenv("PWM_BROKER_URL", raising=False)
    queue = BackgroundQueue(CeleryQueue())
    try:
        with TestClient(create_app(Settings(), job_queue=queue)) as client:
            clock = time.perf_counter()
            response = client.post("/ingests", json={"path": "dl"},
                                   headers={"Authorization": "Bearer token-0123456789abcdef"})
            answered_s = time.perf_counter() - clock
            assert response.status_code == 202, response.text
            key = response.json()["key"]
            queued = {j["key"]: j["status"] for j in client.get("/jobs").json()["items"]}
            assert queued[key] in ("queued", "running")
            queue.close()
            jobs = {j["key"]: j for j in client.get("/jobs").json()["items"]}
    finally:
        queue.close()
    assert answered_s < 5.0
    assert jobs[key]["status"] == "done", jobs[key]
