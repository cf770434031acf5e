"""Real images: two OSIRIS-REx MapCam frames of Bennu as ISIS cubes with their SPICE attached
(shared data real/bennu_mapcam_isis, see its PROVENANCE.md), read by pwm.io.isis through the
downlink reader and the catalog's ingest.

The cubes' poses are checked against the Bennu radar shape model (Nolan et al. 2013, km,
body-fixed IAU_BENNU as the cubes' BodyRotation; shared data shapes/PROVENANCE.md): the body's
outline traced from the pose agrees with the lit body the pixels show, and stereo on the pair
lands on the model within its stated accuracy. Nolan et al. (2013, Icarus 226, 629-640) give the
model's mean diameter as 492 +/- 20 m: +/- 10 m in radius is the accuracy used here. The model's
facets are about 26 m (1348 vertices over 0.78 km^2), some 75 of these 0.34 m pixels: at this
range it gives the outline and the mean surface, not the boulders the images show.

What pwm assumes about real pixels is asserted here: I/F values (a dark body: albedo ~0.04),
ISIS special pixels missing (NaN), the cube's samples and lines laid on pwm's camera axes
(MapCam's focal-plane X runs along ISIS lines: pwm's image is the cube transposed).
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import spiceypy as sp
from scipy.spatial.transform import Rotation
from sqlalchemy import select
from sqlalchemy.orm import Session
from typer.testing import CliRunner

from pwm.camera import PoseCorrection
from pwm.io.downlink import DownlinkViews, read_downlink
from pwm.io.isis import Cube, read_cube, read_cube_pixels
from pwm.io.meshio import read_shape_model
from pwm.io.pds4 import MAX_LABEL_BYTES, MAX_PIXELS, ProductError
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.spg import stereo_photogrammetry
from pwm.spg.config import SPG_DEFAULTS
from pwm.spg.photogrammetry import ClosestPoint
from pwm.views import View
from service.catalog import open_catalog
from service.cli import app
from service.db import make_engine, upgrade
from service.ingest import ingest_directory
from service.rows import GeometryStatus, Image, ImageStatus
from service.settings import get_settings
from service.views import image_view

NAMES = ("20190509T174620S424_crop", "20190509T180552S020_crop")
RADAR_ACCURACY_KM = 0.010  # Nolan et al. 2013: mean diameter 492 +/- 20 m
MIN_OUTLINE_AGREEMENT = 0.95
LABEL_BYTES = 65536  # the real cubes' label area (Object = Label, Bytes)
FILE_BYTES = 1_124_548  # each real cube's size (PROVENANCE.md)


@pytest.fixture(scope="module")
def cube_dir(shared_data) -> Path:
    return shared_data / "real" / "bennu_mapcam_isis"


@pytest.fixture(scope="module")
def downlink(cube_dir) -> DownlinkViews:
    return read_downlink(cube_dir)


@pytest.fixture(scope="module")
def radar(shared_data) -> Mesh:
    return read_shape_model(shared_data / "shapes" / "bennu_radar_nolan2013_sbgat.obj")


def cube_of(path: Path) -> Cube:
    return read_cube(path, max_label_bytes=MAX_LABEL_BYTES, max_pixels=MAX_PIXELS)


def outline(view: View, tracer: RayTracer) -> np.ndarray:
    """True where the view's pixel rays hit the model."""
    dirs = view.pose.to_body_directions(view.camera.grid_directions())
    hits = tracer.intersect(np.broadcast_to(view.pose.position, dirs.shape).copy(), dirs)
    return hits.hit.reshape(view.camera.height, view.camera.width)


def lit(image: np.ndarray) -> np.ndarray:
    """Pixels above Otsu's threshold of the image's own histogram (missing pixels: False)."""
    values = image[np.isfinite(image)]
    counts, edges = np.histogram(values, 256)
    centres = 0.5 * (edges[:-1] + edges[1:])
    below, mass = np.cumsum(counts)[:-1], np.cumsum(counts * centres)[:-1]
    total, total_mass = counts.sum(), (counts * centres).sum()
    between = (total_mass * below - mass * total) ** 2 / (below * (total - below))
    return np.nan_to_num(image, nan=-np.inf) > centres[np.argmax(between)]


def test_the_cubes_read_with_their_attached_geometry(downlink, cube_dir):
    assert [v.name for v in downlink.views] == list(NAMES) and downlink.skipped == []
    assert (downlink.target, downlink.target_id, downlink.body_frame) == ("Bennu", 2101955, "IAU_BENNU")
    assert downlink.instruments == {-64361: "MapCam"}
    for view in downlink.views:
        cube = cube_of(cube_dir / f"{view.name}.cub")
        # 125.2 mm over 8.5 micron pixels, the whole detector 1024 x 1024 about CCD_CENTER 511.5 (zero-based);
        # the crop is the detector's first 512 samples and lines
        assert cube.detector.fx == pytest.approx(125.2 / 0.0085) and cube.detector.cx == cube.detector.cy == 511.5
        assert (cube.detector.width, cube.detector.height, cube.window) == (1024, 1024, (0, 0, 512, 512))
        assert view.image.shape == (512, 512)
        # about 5.0 km from Bennu, looking at it; mid-exposure is StartTime + half the 11.3 ms exposure
        assert np.linalg.norm(view.pose.position) == pytest.approx(5.02, abs=0.01)
        assert view.pose.boresight @ -view.pose.position / np.linalg.norm(view.pose.position) > 0.999
        assert np.allclose(view.pose.rotation @ view.pose.rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(view.pose.rotation) == pytest.approx(1.0)
        assert np.linalg.norm(view.sun) == pytest.approx(1.0)
        assert cube.exposure_s == pytest.approx(0.011285275)
        assert (cube.stop_utc - cube.start_utc).total_seconds() == pytest.approx(cube.exposure_s, abs=1e-6)
        # I/F of a dark body; only the edge the undistortion pulls in from outside the crop is missing
        finite = view.image[np.isfinite(view.image)]
        assert 0.02 < np.median(finite) < 0.05 and finite.max() < 0.1
        missing = ~np.isfinite(view.image)
        assert missing[2:-4, 2:-4].sum() == 0 and missing.mean() < 0.01


def test_the_outline_traced_from_the_pose_is_the_lit_body(downlink, radar):
    tracer = RayTracer(radar)
    for view in downlink.views:
        predicted, observed = outline(view, tracer), lit(view.image)
        valid = np.isfinite(view.image)
        agreement = (predicted == observed)[valid].mean()
        assert agreement >= MIN_OUTLINE_AGREEMENT, (view.name, agreement)
        # the axes matter: the cube as stored (transposed) or mirrored agrees far worse
        for wrong in (predicted.T, predicted[::-1], predicted[:, ::-1]):
            assert (wrong == observed)[valid].mean() < agreement - 0.15


def test_stereo_on_the_pair_lands_on_the_radar_model(downlink, radar):
    # Bennu turns 27 degrees between the frames: their Suns (body-fixed) are 27 degrees apart,
    # past SPG's default 25
    config = dataclasses.replace(SPG_DEFAULTS, max_sun_deg=30.0)
    result = stereo_photogrammetry(downlink.views, radar, config=config)
    assert result.stats["points"] >= 15 and result.stats["residual_rms_px"] < 1.5
    distance = ClosestPoint(radar).query(result.points)[0]
    assert np.median(distance) < RADAR_ACCURACY_KM, np.median(distance)
    for view in downlink.views:
        correction = result.corrections[view.name]
        rng = float(np.linalg.norm(view.pose.position))
        shift_px = (np.linalg.norm(correction.rotation_rad) + np.linalg.norm(correction.position_km) / rng) \
            * view.camera.fx
        assert shift_px < 2.0, (view.name, shift_px)


def test_pwm_ingest_catalogues_both_cubes_with_their_geometry(cube_dir, downlink, tmp_path, monkeypatch):
    monkeypatch.setenv("PWM_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.delenv("PWM_DATABASE_URL", raising=False)
    get_settings.cache_clear()
    try:
        delivery = tmp_path / "delivery"  # copies: ingest refuses links out of the downlink
        delivery.mkdir()
        for name in NAMES:
            shutil.copyfile(cube_dir / f"{name}.cub", delivery / f"{name}.cub")
        result = CliRunner().invoke(app, ["ingest", str(delivery)])
        assert result.exit_code == 0, result.output
        again = CliRunner().invoke(app, ["ingest", str(delivery)])
        assert again.exit_code == 0 and "2 unchanged" in again.output, again.output
        by_name = {v.name: v for v in downlink.views}
        with open_catalog()() as session:
            images = session.scalars(select(Image).order_by(Image.label_path)).all()
            assert [Path(i.label_path).stem for i in images] == list(NAMES)
            for image in images:
                cube = cube_of(Path(image.label_path))
                assert image.status is ImageStatus.ACCEPTED and image.geometry_status is GeometryStatus.COMPUTED
                assert image.lidvid == f"isis:{cube.key}::1.0" and image.target == "Bennu"
                instrument, geometry = image.instrument, image.geometry
                assert instrument is not None and geometry is not None
                assert instrument.naif_id == -64361 and geometry.body_frame == "IAU_BENNU"
                assert geometry.pixel_scale_m == pytest.approx(0.34, abs=0.02)
                assert image.start_et is not None and image.stop_et is not None
                assert image.start_et < cube.et < image.stop_et
                view, read = image_view(image, pixels=True), by_name[Path(image.label_path).stem]
                assert view.camera == read.camera and np.array_equal(view.image, read.image, equal_nan=True)
                assert np.allclose(view.pose.position, read.pose.position, atol=1e-9)
                assert np.allclose(view.pose.rotation, read.pose.rotation, atol=1e-9)
    finally:
        get_settings.cache_clear()


def test_a_cube_cut_short_in_transfer_waits_for_its_whole_copy(cube_dir, tmp_path):
    """Keyed by its label, a cube cut short is the same product as its whole copy: rejected as
    truncated (a transfer code), then replaced in its row by the whole one on the next ingest."""
    url = f"sqlite:///{tmp_path / 'catalog.sqlite'}"
    upgrade(url)
    engine = make_engine(url)
    delivery = tmp_path / "delivery"
    delivery.mkdir()
    whole = (cube_dir / f"{NAMES[0]}.cub").read_bytes()
    (delivery / f"{NAMES[0]}.cub").write_bytes(whole[:600_000])
    first = ingest_directory(engine, delivery)
    assert [(f.code, Path(f.path).name) for f in first.failures] == [("truncated", f"{NAMES[0]}.cub")]
    (delivery / f"{NAMES[0]}.cub").write_bytes(whole)
    second = ingest_directory(engine, delivery)
    assert second.images.accepted == 1 and second.failures == []
    with Session(engine) as session:
        (image,) = session.scalars(select(Image)).all()
        assert image.status is ImageStatus.ACCEPTED and image.geometry_status is GeometryStatus.COMPUTED


# --- hostile and unusual cubes: the real cubes rewritten -----------------------------------


def rewritten(source: Path, dest: Path, replacements: dict[str, str], core: bytes | None = None,
              appended: bytes = b"") -> Path:
    """A copy of the cube with label text replaced (padded back to its label area), then bytes
    appended at the end of the file: a new core when given (the label's core StartByte moved
    there), and `appended` (its place for the label: FILE_BYTES + 1, after no core)."""
    raw = source.read_bytes()
    assert len(raw) == FILE_BYTES
    text = raw[:LABEL_BYTES].split(b"\0")[0].decode()
    if core is not None:
        replacements = {**replacements, "StartByte   = 65537": f"StartByte   = {len(raw) + 1}"}
    for old, new in replacements.items():
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    label = text.encode().ljust(LABEL_BYTES, b"\0")
    assert len(label) == LABEL_BYTES
    dest.write_bytes(label + raw[LABEL_BYTES:] + (core or b"") + appended)
    return dest


def tiles(array: np.ndarray, tile_lines: int, tile_samples: int) -> bytes:
    """The array stored as ISIS tiles: row by row of tiles, each [line, sample], padded."""
    lines, samples = array.shape
    padded = np.zeros((-(-lines // tile_lines) * tile_lines, -(-samples // tile_samples) * tile_samples), array.dtype)
    padded[:lines, :samples] = array
    return b"".join(padded[r:r + tile_lines, c:c + tile_samples].tobytes()
                    for r in range(0, padded.shape[0], tile_lines) for c in range(0, padded.shape[1], tile_samples))


@pytest.fixture(scope="module")
def original(cube_dir) -> tuple[Path, np.ndarray, np.ndarray]:
    """The first cube, its core as stored ([line, sample] float32) and its pixels as pwm reads them."""
    path = cube_dir / f"{NAMES[0]}.cub"
    core = np.frombuffer(path.read_bytes()[LABEL_BYTES:LABEL_BYTES + 512 * 512 * 4], "<f4").reshape(512, 512)
    return path, core, read_cube_pixels(cube_of(path))


def test_tiles_pixel_types_byte_orders_and_special_pixels(original, tmp_path):
    path, core, pixels = original
    # smaller tiles, padded at the edges: the same pixels
    tiled = rewritten(path, tmp_path / "tiled.cub", {"TileSamples = 512": "TileSamples = 200",
                                                     "TileLines   = 512": "TileLines   = 96"}, tiles(core, 96, 200))
    assert np.array_equal(read_cube_pixels(cube_of(tiled)), pixels, equal_nan=True)
    # band sequential, big-endian 16-bit integers with base and multiplier, and ISIS's special values
    multiplier = 4e-6
    words = np.round(core / multiplier).astype(">i2")
    specials = {(100, 300): -32768, (200, 50): -32767, (300, 400): -32766, (400, 10): -32765, (450, 450): -32764}
    for (line, sample), value in specials.items():
        words[line, sample] = value
    packed = rewritten(path, tmp_path / "words.cub", {
        "Format      = Tile\n    TileSamples = 512\n    TileLines   = 512": "Format      = BandSequential",
        "Type       = Real": "Type       = SignedWord", "ByteOrder  = Lsb\n      Base": "ByteOrder  = Msb\n      Base",
        "Multiplier = 1.0": f"Multiplier = {multiplier}"}, words.tobytes())
    read = read_cube_pixels(cube_of(packed))
    missing = np.isnan(read) & ~np.isnan(pixels)
    # pwm's image is the cube transposed: a special pixel at cube (line, sample) leaves pwm's
    # (line ~ sample, sample ~ line) missing, with the neighbours that interpolate from it
    for line, sample in specials:
        assert missing[sample - 2:sample + 3, line - 2:line + 3].any()
    assert missing.sum() <= 9 * len(specials)
    both = np.isfinite(read) & np.isfinite(pixels)
    assert np.abs(read - pixels)[both].max() <= multiplier
    # 32-bit float specials (NULL, LRS, LIS, HIS, HRS) are missing too
    floats = core.copy()
    bits = floats.view("<u4")
    for k, (line, sample) in enumerate(specials):
        bits[line, sample] = 0xFF7FFFFB + k
    special_floats = rewritten(path, tmp_path / "floats.cub", {}, floats.tobytes())
    assert (np.isnan(read_cube_pixels(cube_of(special_floats))) & ~np.isnan(pixels)).sum() == missing.sum()


def test_several_records_are_interpolated_to_mid_exposure(original, tmp_path):
    """Pointing slerped and position interpolated linearly between records about mid-exposure
    (the real cubes cache one record each: here two, placed symmetrically about it)."""
    path = original[0]
    cube = cube_of(path)
    raw = path.read_bytes()
    pointing = np.frombuffer(raw[1114112:1114176], "<f8").copy()  # Q0..Q3, AV1..AV3, ET
    position = np.frombuffer(raw[1114176:1114232], "<f8").copy()  # X, Y, Z, XV, YV, ZV, ET
    et, turned = pointing[7], sp.q2m(pointing[:4])
    records = []
    for sign in (-1.0, 1.0):
        quaternion = sp.m2q(Rotation.from_rotvec([0.0, 0.0, sign * 0.01]).as_matrix() @ turned)
        records.append(np.concatenate([quaternion, pointing[4:7], [et + sign * 2.0]]))
    moved = [np.concatenate([position[:3] + sign * np.array([0.5, -0.2, 0.1]), position[3:6], [et + sign * 2.0]])
             for sign in (-1.0, 1.0)]
    pointing_bytes = np.array(records, "<f8").tobytes()
    two = rewritten(path, tmp_path / "two.cub", {
        "StartByte           = 1114113\n  Bytes               = 64\n  Records             = 1":
        f"StartByte           = {FILE_BYTES + 1}\n  Bytes               = 128\n  Records             = 2",
        "StartByte            = 1114177\n  Bytes                = 56\n  Records              = 1":
        f"StartByte            = {FILE_BYTES + 129}\n  Bytes                = 112\n  Records              = 2"},
        appended=pointing_bytes + np.array(moved, "<f8").tobytes())
    interpolated = cube_of(two)
    assert interpolated.et == pytest.approx(cube.et, abs=1e-6)
    assert np.allclose(interpolated.pose.rotation, cube.pose.rotation, atol=1e-9)
    assert np.allclose(interpolated.pose.position, cube.pose.position, atol=1e-9)


@pytest.mark.parametrize(("replacements", "code", "limits"), [
    ({"Name                = InstrumentPointing": "Name                = SomethingElse"}, "no_attached_spice", {}),
    ({"Records             = 1\n  ByteOrder           = Lsb\n  TimeDependentFrames = (-64361":
      "Records             = 90000000\n  ByteOrder           = Lsb\n  TimeDependentFrames = (-64361"},
     "truncated", {}),
    ({"Samples = 512\n      Lines   = 512": "Samples = 512\n      Lines   = 51200000"}, "bad_dimensions", {}),
    ({"Type       = Real": "Type       = Double"}, "unsupported", {}),
    ({"Bands   = 1": "Bands   = 3"}, "unsupported", {}),
    ({"INS-64361_OD_K_B": "INS-64361_OD_RADIAL"}, "unsupported", {}),
    ({}, "bad_label", {"max_label_bytes": 4096}),
    ({}, "bad_dimensions", {"max_pixels": 512 * 511}),
])
def test_cubes_pwm_cannot_use_are_refused_with_a_reason(original, tmp_path, replacements, code, limits):
    path = rewritten(original[0], tmp_path / "hostile.cub", replacements)
    with pytest.raises(ProductError) as refused:
        read_cube(path, **{"max_label_bytes": MAX_LABEL_BYTES, "max_pixels": MAX_PIXELS, **limits})
    assert refused.value.code == code, str(refused.value)


def test_a_downlink_of_cubes_skips_a_cube_without_its_spice_and_applies_corrections(original, downlink, tmp_path):
    delivery = tmp_path / "delivery"
    delivery.mkdir()
    shutil.copyfile(original[0], delivery / f"{NAMES[0]}.cub")
    rewritten(original[0], delivery / "bare.cub", {"Name                = InstrumentPointing":
                                                   "Name                = SomethingElse"})
    correction = PoseCorrection(position_km=(0.001, 0.0, 0.0), rotation_rad=(0.0, 1e-4, 0.0))
    read = read_downlink(delivery, corrections={NAMES[0]: correction})
    assert [(Path(s.path).name, s.code) for s in read.skipped] == [("bare.cub", "no_attached_spice")]
    (view,) = read.views
    expected = correction.apply(downlink.views[0].pose)
    assert np.allclose(view.pose.position, expected.position) and np.allclose(view.pose.rotation, expected.rotation)


def test_a_cube_cut_short_is_refused(original, tmp_path):
    cut = tmp_path / "cut.cub"
    cut.write_bytes(original[0].read_bytes()[:600_000])
    with pytest.raises(ProductError, match="does not fit") as refused:
        cube_of(cut)
    assert refused.value.code == "truncated"
