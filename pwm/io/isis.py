"""ISIS3 cubes with attached SPICE (after `spiceinit ... attach=true`) as pwm images.

A cube holds its own geometry: the label's NaifKeywords (focal length, pixel pitch, focal-plane
map, distortion) and binary Tables of J2000 records (InstrumentPointing, InstrumentPosition,
BodyRotation, SunPosition). `read_cube` reads the label and tables only (bounded, no pixels) and
gives the pinhole camera of the whole detector, the window the cube holds, the pose at
mid-exposure (body-fixed, km) and the Sun direction; `read_cube_pixels` reads the core and
resamples it onto that ideal pinhole grid, the lens distortion removed, ISIS special pixels NaN.

Distortion: the model is chosen by the keywords, as ISIS's OsirisRexDistortionMap reads them:
INS<ik>_OD_K_<filter> (else INS<ik>_OD_K), five coefficients of dr/r = k0 + k1 r + ... + k4 r^4
(r in mm) about INS<ik>_OD_CENTER[_<filter>]; no distortion keywords, no distortion; any other
distortion keyword is refused (code unsupported). Pose tables must be lists of records (what
spiceinit attach=true writes); polynomial caches and constant-frame rotations are refused.

Axes: pwm's camera frame is the instrument's NAIF frame itself (+Z boresight); pwm's pixel grid
is laid along the frame's +X (samples) and +Y (lines), so the ISIS detector's samples and lines
map onto it through the focal-plane map (INS<ik>_TRANSX/TRANSY): for OSIRIS-REx MapCam, focal
plane X runs along ISIS lines, so pwm's image is the cube transposed. ISIS pixel centres are
1-based (the first at 1.0); pwm's are zero-based.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pvl
import spiceypy as sp
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation, Slerp

from pwm.camera import Camera, Pose
from pwm.io.pds4 import ProductError

CUBE_SUFFIX = ".cub"
# ISIS special pixels (ISIS SpecialPixel.h): 32-bit float NULL, LRS, LIS, HIS, HRS are the five
# most negative floats; the integer types reserve their ends of the range.
_SPECIAL_REAL_BITS = np.array([0xFF7FFFFB, 0xFF7FFFFC, 0xFF7FFFFD, 0xFF7FFFFE, 0xFF7FFFFF], np.uint32)
_PIXEL_TYPES: dict[str, tuple[str, tuple[int, ...]]] = {
    "UnsignedByte": ("u1", (0, 255)),
    "SignedWord": ("i2", (-32768, -32767, -32766, -32765, -32764)),
    "UnsignedWord": ("u2", (0, 1, 2, 65534, 65535)),
    "Real": ("f4", ()),
}
_FIELD_TYPES = {"Double": "f8", "Real": "f4", "Integer": "i4", "Text": "S"}
_GEOMETRY_TABLES = ("InstrumentPointing", "InstrumentPosition", "BodyRotation", "SunPosition")
_TIME_TOLERANCE_S = 1e-3  # a single cached record stands for mid-exposure within this


@dataclass(frozen=True)
class _Core:
    """Where and how the cube's pixels are stored."""

    start: int  # zero-based byte offset
    samples: int
    lines: int
    dtype: np.dtype
    specials: tuple[int, ...]
    base: float
    multiplier: float
    tile: tuple[int, int] | None  # (tile samples, tile lines); None: band sequential


@dataclass(frozen=True)
class _FocalPlane:
    """The cube's detector in pwm's grid: ISIS 1-based (sample, line) of the cube's first pixel
    on the detector, which ISIS axis lies along pwm's samples, and each pwm axis's sign and
    detector size; the OCAMS-form radial distortion (k0..k4 on r in mm about centre_mm), if any."""

    first: tuple[float, float]
    swapped: bool  # pwm samples run along ISIS lines
    signs: tuple[int, int]
    extent: tuple[int, int]  # detector size along pwm (samples, lines)
    origin: tuple[float, float]  # zero-based pwm (sample, line) of the focal-plane origin
    pitch_mm: float
    distortion: tuple[np.ndarray, np.ndarray] | None  # (k, centre_mm)


@dataclass(frozen=True)
class Cube:
    """A cube's label and geometry, its pixels not read. camera: ideal pinhole of the window the
    cube holds; detector: of the whole detector; window: (first_line, first_sample, lines,
    samples) of it, zero-based in pwm's grid. pose: at mid-exposure (`et`, ET s), body-fixed
    (`body_frame`, of NAIF body `target_id`) km; sun: unit vector to the Sun, body-fixed.
    radii_km: the target's ellipsoid (BODY<id>_RADII). instrument_id: the NAIF frame code
    (NaifFrameCode), instrument_name: the label's InstrumentId. key: its identity (`cube_key`)."""

    path: Path
    key: str
    target_name: str
    target_id: int
    body_frame: str
    radii_km: np.ndarray
    instrument_id: int
    instrument_name: str
    start_utc: datetime
    stop_utc: datetime
    et: float
    exposure_s: float
    detector: Camera
    window: tuple[int, int, int, int]
    pose: Pose
    sun: np.ndarray
    _core: _Core
    _focal: _FocalPlane

    @property
    def camera(self) -> Camera:
        first_line, first_sample, lines, samples = self.window
        return self.detector.subframe(first_sample=first_sample, first_line=first_line, samples=samples, lines=lines)


def is_cube(path: Path) -> bool:
    return path.suffix.lower() == CUBE_SUFFIX


def cube_key(path: str | Path, *, max_label_bytes: int) -> str:
    """A cube's identity from its label alone (whatever its core and tables): the label's
    ProductId (Archive or Instrument group), else the sha256 of the label's bytes; ProductError
    (bad_label) for a label that cannot be read."""
    return _key(*_label(Path(path), max_label_bytes))


def _key(raw: bytes, label: Any) -> str:
    cube = label["IsisCube"]
    product_id = cube.get("Archive", {}).get("ProductId") or cube.get("Instrument", {}).get("ProductId")
    return str(product_id) if product_id else hashlib.sha256(raw).hexdigest()


def read_cube(path: str | Path, *, max_label_bytes: int, max_pixels: int) -> Cube:
    """The cube's label, camera and geometry (see `Cube`); ProductError with a code and reason
    for a cube pwm cannot use: bad_label, no_attached_spice, unsupported, bad_dimensions,
    truncated."""
    path = Path(path)
    size = path.stat().st_size
    raw, label = _label(path, max_label_bytes)
    cube = label["IsisCube"]
    try:
        instrument, naif = cube["Instrument"], label["NaifKeywords"]
    except LookupError as exc:
        code = "no_attached_spice" if "NaifKeywords" in str(exc) else "bad_label"
        raise ProductError(code, f"{path.name}: no {exc} in the label (NaifKeywords and the tables come from "
                           "spiceinit attach=true)") from exc
    tables = {t.get("Name"): t for t in label.getall("Table")}
    missing = [n for n in _GEOMETRY_TABLES if n not in tables]
    if missing:
        raise ProductError("no_attached_spice", f"{path.name}: no attached {', '.join(missing)} table: run "
                           "ISIS spiceinit with attach=true (pwm reads a cube's pose from the cube only)")
    core = _core(cube, size, max_pixels)
    try:
        ik = int(cube["Kernels"]["NaifFrameCode"])
        exposure_s = _seconds(instrument["ExposureDuration"])
        start = instrument["StartTime"]
        if not isinstance(start, datetime):
            raise ValueError(f"StartTime {start!r} is not a time")
        target_id, frame_code = int(naif["BODY_CODE"]), int(naif["BODY_FRAME_CODE"])
        radii = np.asarray(naif[f"BODY{target_id}_RADII"], float)
        if radii.shape != (3,) or not np.all(np.isfinite(radii) & (radii > 0)):
            raise ValueError(f"BODY{target_id}_RADII {radii.tolist()} are not three radii")
        records = {n: _table(path, tables[n], size, max_label_bytes) for n in _GEOMETRY_TABLES}
        focal = _focal_plane(naif, ik, cube, core, str(cube.get("BandBin", {}).get("FilterName", "")))
        focal_length_px = float(naif[f"INS{ik}_FOCAL_LENGTH"]) / focal.pitch_mm
    except (LookupError, TypeError, ValueError) as exc:
        if isinstance(exc, ProductError):
            raise
        raise ProductError("bad_label", f"{path.name}: {type(exc).__name__}: {exc}") from exc
    et = _mid_exposure(records)
    to_camera = _rotation(path, tables["InstrumentPointing"], records["InstrumentPointing"], et)
    to_body = _rotation(path, tables["BodyRotation"], records["BodyRotation"], et)
    position = to_body @ _position(path, tables["InstrumentPosition"], records["InstrumentPosition"], et)
    sun = to_body @ _position(path, tables["SunPosition"], records["SunPosition"], et)
    if not (np.isfinite(et) and np.all(np.isfinite(position)) and np.all(np.isfinite(sun))
            and np.linalg.norm(sun) > 0 and np.linalg.norm(position) > 0):
        raise ProductError("bad_label", f"{path.name}: its tables give no finite position, Sun and time "
                           f"(ET {et}, camera {position.tolist()} km, Sun {sun.tolist()} km)")
    (width, height), (cx, cy) = focal.extent, focal.origin
    detector = Camera(width=width, height=height, fx=focal_length_px, fy=focal_length_px, cx=cx, cy=cy)
    with sp.no_found_check():
        frame = sp.frmnam(frame_code) or str(frame_code)
    return Cube(path=path, key=_key(raw, label), target_name=str(instrument.get("TargetName", "")),
                target_id=target_id, body_frame=frame, radii_km=radii, instrument_id=ik,
                instrument_name=str(instrument.get("InstrumentId", ik)), start_utc=start,
                stop_utc=start + timedelta(seconds=exposure_s), et=et, exposure_s=exposure_s, detector=detector,
                window=_window(focal, core), pose=Pose(position=position, rotation=to_camera @ to_body.T),
                sun=sun / np.linalg.norm(sun), _core=core, _focal=focal)


def read_cube_pixels(cube: Cube) -> np.ndarray:
    """The cube's pixels on `cube.camera`'s ideal pinhole grid [line, sample], float64, NaN where
    ISIS marks a pixel special or the distorted grid falls off the cube (bilinear resampling;
    a missing neighbour makes the pixel missing)."""
    data = _read_core(cube.path, cube._core)
    valid = np.isfinite(data)
    first_line, first_sample, lines, samples = cube.window
    v, u = np.mgrid[first_line:first_line + lines, first_sample:first_sample + samples].astype(float)
    rows, cols = _cube_indices(cube._focal, u, v)
    coords = np.stack([rows, cols])
    out = map_coordinates(np.where(valid, data, 0.0), coords, order=1, mode="constant", cval=0.0)
    weight = map_coordinates(valid.astype(float), coords, order=1, mode="constant", cval=0.0)
    return np.where(weight > 1.0 - 1e-9, out, np.nan)


def _label(path: Path, max_label_bytes: int) -> tuple[bytes, Any]:
    """The label's bytes (up to the NUL padding that ends it) and the label parsed."""
    with open(path, "rb") as fh:
        head = fh.read(max_label_bytes + 1)
    end = head.find(b"\0")
    if end < 0 and len(head) > max_label_bytes:
        raise ProductError("bad_label", f"{path.name}: label longer than {max_label_bytes} bytes (PWM_MAX_LABEL_BYTES)")
    head = head if end < 0 else head[:end]
    if not head.lstrip().startswith(b"Object = IsisCube"):
        raise ProductError("bad_label", f"{path.name}: not an ISIS3 cube (its label does not open an IsisCube)")
    try:
        label = pvl.loads(head.decode("utf-8", "replace"), grammar=pvl.grammar.ISISGrammar())
        label["IsisCube"].get("Instrument")  # an IsisCube object, not a keyword
    except (pvl.exceptions.ParseError, LookupError, TypeError, ValueError, AttributeError) as exc:
        raise ProductError("bad_label", f"{path.name}: not an ISIS cube label pwm can read "
                           f"({type(exc).__name__}: {exc})") from exc
    return head, label


def _core(cube: Any, size: int, max_pixels: int) -> _Core:
    try:
        core, dims, pixels = cube["Core"], cube["Core"]["Dimensions"], cube["Core"]["Pixels"]
        samples, lines, bands = int(dims["Samples"]), int(dims["Lines"]), int(dims["Bands"])
        kind, order, fmt = str(pixels["Type"]), str(pixels["ByteOrder"]), str(core["Format"])
        start = int(core["StartByte"]) - 1
        tile = (int(core["TileSamples"]), int(core["TileLines"])) if fmt == "Tile" else None
        base, multiplier = float(pixels["Base"]), float(pixels["Multiplier"])
    except (LookupError, TypeError, ValueError) as exc:
        raise ProductError("bad_label", f"cube core: {type(exc).__name__}: {exc}") from exc
    if kind not in _PIXEL_TYPES or order not in ("Lsb", "Msb") or fmt not in ("Tile", "BandSequential"):
        raise ProductError("unsupported", f"cube core of {kind} pixels, {order} byte order, {fmt} storage: pwm reads "
                           f"{', '.join(_PIXEL_TYPES)} pixels, Lsb or Msb, Tile or BandSequential")
    if bands != 1:
        raise ProductError("unsupported", f"a cube of {bands} bands: pwm takes single-band images (cubeit/explode)")
    if min(samples, lines, *(tile or (1, 1))) < 1 or start < 0 or samples * lines > max_pixels:
        raise ProductError("bad_dimensions", f"cube core {samples} x {lines} from byte {start + 1} (tiles {tile}): "
                           f"empty, or more than {max_pixels} pixels (PWM_MAX_PIXELS)")
    code, specials = _PIXEL_TYPES[kind]
    dtype = np.dtype(("<" if order == "Lsb" else ">") + code)
    stored = _stored_shape(samples, lines, tile)
    if stored[0] * stored[1] > max_pixels or start + stored[0] * stored[1] * dtype.itemsize > size:
        raise ProductError("truncated", f"cube core of {stored[0] * stored[1]} stored {kind} pixels from byte "
                           f"{start + 1} does not fit the {size}-byte file")
    return _Core(start=start, samples=samples, lines=lines, dtype=dtype, specials=specials, base=base,
                 multiplier=multiplier, tile=tile)


def _stored_shape(samples: int, lines: int, tile: tuple[int, int] | None) -> tuple[int, int]:
    """(lines, samples) as stored: whole tiles, padded at the right and bottom edges."""
    if tile is None:
        return lines, samples
    return -(-lines // tile[1]) * tile[1], -(-samples // tile[0]) * tile[0]


def _read_core(path: Path, core: _Core) -> np.ndarray:
    """The core as float64 [line, sample] in ISIS order, NaN for special pixels."""
    lines, samples = _stored_shape(core.samples, core.lines, core.tile)
    with open(path, "rb") as fh:
        fh.seek(core.start)
        raw = np.fromfile(fh, dtype=core.dtype, count=lines * samples)
    if raw.size != lines * samples:
        raise ProductError("truncated", f"{path.name}: cube core cut short")
    if core.tile is not None:  # tiles row by row, each tile [line, sample]
        ts, tl = core.tile
        raw = raw.reshape(lines // tl, samples // ts, tl, ts).transpose(0, 2, 1, 3)
    raw = raw.reshape(lines, samples)[: core.lines, : core.samples]
    if core.dtype.kind == "f":
        special = np.isin(raw.view(core.dtype.str.replace("f", "u")), _SPECIAL_REAL_BITS)
        special |= ~np.isfinite(raw)
    else:
        special = np.isin(raw, core.specials)
    return np.where(special, np.nan, core.base + core.multiplier * raw.astype(float))


def _table(path: Path, table: Any, size: int, max_bytes: int) -> np.ndarray:
    """A Table's records as a numpy structured array, checked against the file before any read."""
    name = table.get("Name")
    try:
        order = "<" if str(table.get("ByteOrder", "Lsb")) == "Lsb" else ">"
        fields = [(str(f["Name"]), int(f["Size"]), _FIELD_TYPES[str(f["Type"])]) for f in table.getall("Field")]
        dtype = np.dtype([(n, f"S{k}") if t == "S" else (n, order + t, (k,) if k > 1 else ())
                          for n, k, t in fields])
        start, nbytes, records = int(table["StartByte"]) - 1, int(table["Bytes"]), int(table["Records"])
    except (LookupError, TypeError, ValueError) as exc:
        raise ProductError("bad_label", f"{path.name}: table {name}: {type(exc).__name__}: {exc}") from exc
    if records < 1 or nbytes != records * dtype.itemsize or start < 0 or start + nbytes > size or nbytes > max_bytes:
        raise ProductError("truncated", f"{path.name}: table {name} of {records} records of {dtype.itemsize} bytes "
                           f"(Bytes {nbytes}) from byte {start + 1} does not fit the {size}-byte file, or is "
                           f"more than {max_bytes} bytes")
    with open(path, "rb") as fh:
        fh.seek(start)
        return np.frombuffer(fh.read(nbytes), dtype=dtype)


def _mid_exposure(records: dict[str, np.ndarray]) -> float:
    """The ET the pose is taken at: spiceinit caches a framing camera's geometry at its centre
    time (ISIS: the clock start plus half the exposure), one record a table, so the pointing
    record's time; for a table of several records, the middle of their span."""
    times = records["InstrumentPointing"]["ET"]
    return float(times[0]) if times.size == 1 else float(0.5 * (times[0] + times[-1]))


def _check_times(path: Path, name: str, times: np.ndarray, et: float) -> None:
    if not (times.min() - _TIME_TOLERANCE_S <= et <= times.max() + _TIME_TOLERANCE_S) \
            or np.any(np.diff(times) <= 0):
        raise ProductError("bad_label", f"{path.name}: table {name} (ET {times.min():.3f}..{times.max():.3f}) "
                           f"does not cover mid-exposure {et:.3f} in increasing time order")


def _rotation(path: Path, table: Any, records: np.ndarray, et: float) -> np.ndarray:
    """J2000 -> the table's frame at `et` (SPICE quaternions, scalar first; slerp between
    records). Pointing cached as polynomials, or with a constant rotation, is refused."""
    name = table.get("Name")
    names = records.dtype.names or ()
    if "ConstantFrames" in table or not {"J2000Q0", "J2000Q1", "J2000Q2", "J2000Q3", "ET"} <= set(names):
        raise ProductError("unsupported", f"{path.name}: table {name} is not a list of J2000 quaternion records "
                           "without a constant rotation (polynomial caches are not supported: spiceinit "
                           "attach=true writes the records pwm reads)")
    times = records["ET"]
    _check_times(path, name, times, et)
    q = np.stack([records[f"J2000Q{i}"] for i in range(4)], axis=-1)
    if not np.all(np.abs(np.linalg.norm(q, axis=1) - 1.0) < 1e-6):
        raise ProductError("bad_label", f"{path.name}: table {name} holds quaternions that are not unit")
    # SPICE's quaternion convention (q2m: J2000 -> frame), not scipy's: through the matrices
    rotations = Rotation.from_matrix(np.array([sp.q2m(qi) for qi in q]))
    if times.size == 1:
        return np.asarray(rotations[0].as_matrix())
    return np.asarray(Slerp(times, rotations)([et])[0].as_matrix())


def _position(path: Path, table: Any, records: np.ndarray, et: float) -> np.ndarray:
    """The table's J2000 position (km, relative to the target) at `et`, linear between records."""
    name = table.get("Name")
    names = records.dtype.names or ()
    if not {"J2000X", "J2000Y", "J2000Z", "ET"} <= set(names):
        raise ProductError("unsupported", f"{path.name}: table {name} is not a list of J2000 position records "
                           "(polynomial caches are not supported)")
    times = records["ET"]
    _check_times(path, name, times, et)
    return np.array([np.interp(et, times, records[f"J2000{a}"]) for a in "XYZ"])


def _seconds(duration: Any) -> float:
    """ExposureDuration in s: ISIS writes milliseconds (<Millisec> or <ms>), else seconds."""
    value = float(getattr(duration, "value", duration))
    units = str(getattr(duration, "units", "")).lower()
    seconds = value / 1000.0 if units.startswith("m") else value
    if not np.isfinite(seconds) or not 0.0 <= seconds < 3600.0:
        raise ValueError(f"ExposureDuration {duration!r} is not a plausible exposure")
    return seconds


def _focal_plane(naif: Any, ik: int, cube: Any, core: _Core, band: str) -> _FocalPlane:
    """The focal-plane map (TRANSX/TRANSY: mm from ISIS detector sample and line about the
    detector origin CCD_CENTER + 1), the crop or scale of the cube (AlphaCube) and the
    distortion model the keywords name."""
    key = f"INS{ik}_"
    tx, ty = (np.asarray(naif[key + k], float) for k in ("TRANSX", "TRANSY"))
    origin = np.asarray(naif[key + "CCD_CENTER"], float) + 1.0  # ISIS: 1-based (sample, line)
    pitch = float(naif[key + "PIXEL_SIZE"]) / 1000.0  # microns
    # [x, y] = t0 + A @ [sample - s0, line - l0]; pwm's grid needs A a signed permutation of
    # the pixel pitch (square pixels, axes along the detector's)
    a = np.array([tx[1:3], ty[1:3]]) if tx.size == ty.size == 3 else np.zeros((2, 2))
    swapped = a[0, 0] == a[1, 1] == 0.0
    steps = np.array([a[0, 1], a[1, 0]]) if swapped else np.diag(a)
    aligned = swapped or a[0, 1] == a[1, 0] == 0.0
    if not aligned or not np.allclose(np.abs(steps), pitch, rtol=1e-6):
        raise ProductError("unsupported", f"{key}TRANSX {tx.tolist()} / TRANSY {ty.tolist()} are not square "
                           f"{pitch} mm pixels along the detector axes")
    alpha = cube.get("AlphaCube")
    full = (int(alpha["AlphaSamples"]), int(alpha["AlphaLines"])) if alpha else (core.samples, core.lines)
    # the cube's first pixel centre on the detector, 1-based (AlphaStarting* is its outer edge)
    first = ((float(alpha["AlphaStartingSample"]) + 0.5, float(alpha["AlphaStartingLine"]) + 0.5) if alpha
             else (1.0, 1.0))
    if alpha and (float(alpha["AlphaEndingSample"]) - float(alpha["AlphaStartingSample"]) != core.samples
                  or float(alpha["AlphaEndingLine"]) - float(alpha["AlphaStartingLine"]) != core.lines
                  or first[0] != round(first[0]) or first[1] != round(first[1])):
        raise ProductError("unsupported", "a cube scaled or cut off the pixel grid (AlphaCube): pwm takes whole "
                           "detector pixels only")
    signs = (int(np.sign(steps[0])), int(np.sign(steps[1])))
    axes = (1, 0) if swapped else (0, 1)  # the ISIS axis (0 sample, 1 line) along pwm sample, line
    extent = (full[axes[0]], full[axes[1]])
    offsets = (tx[0] / pitch, ty[0] / pitch)
    # where the focal-plane origin falls on pwm's zero-based grid, along each axis flipped or not
    pwm_origin = tuple(float((origin[axes[i]] - 1.0 if signs[i] > 0 else extent[i] - origin[axes[i]]) - offsets[i])
                       for i in range(2))
    return _FocalPlane(first=first, swapped=swapped, signs=signs, extent=extent,
                       origin=(pwm_origin[0], pwm_origin[1]), pitch_mm=pitch,
                       distortion=_distortion(naif, key, band, tx, ty, origin))


def _distortion(naif: Any, key: str, band: str, tx: np.ndarray, ty: np.ndarray, origin: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """The radial model the keywords give (ISIS OsirisRexDistortionMap's form, chosen by its
    keywords: OD_K[_<filter>] with five coefficients and OD_CENTER[_<filter>], the centre in
    detector pixels): distorted = x + (k0 + k1 r + ... + k4 r^4)(x - c), mm. None without
    distortion keywords; ProductError for a model pwm cannot apply."""
    suffixes = [f"_{band.strip().upper()}"] if band.strip() else []
    suffix = next((s for s in [*suffixes, ""] if key + "OD_K" + s in naif), None)
    others = sorted(k for k in naif.keys() if k.startswith(key) and re.search(r"_(OD|DISTORTION)", k[len(key) - 1:]))
    if suffix is None:
        if others:
            raise ProductError("unsupported", f"distortion keywords {', '.join(others)} name a model pwm cannot "
                               f"apply (it applies {key}OD_K with {key}OD_CENTER{suffixes[0] if suffixes else ''})")
        return None
    k = np.asarray(naif[key + "OD_K" + suffix], float).ravel()
    centre_key = key + "OD_CENTER" + suffix
    if k.size != 5 or centre_key not in naif:
        raise ProductError("unsupported", f"{key}OD_K{suffix} with {k.size} coefficients and "
                           f"{'a' if centre_key in naif else 'no'} {centre_key}: pwm applies the radial model "
                           "of five coefficients about a distortion centre only")
    centre = np.asarray(naif[centre_key], float) - origin  # detector (sample, line) about the origin
    # as ISIS, the centre goes through the focal-plane map without the offsets
    return k, np.array([tx[1] * centre[0] + tx[2] * centre[1], ty[1] * centre[0] + ty[2] * centre[1]])


def _window(focal: _FocalPlane, core: _Core) -> tuple[int, int, int, int]:
    """(first_line, first_sample, lines, samples) of the cube on pwm's detector grid."""
    axes = (1, 0) if focal.swapped else (0, 1)
    size = (core.samples, core.lines)
    first = []
    for i in range(2):
        start = focal.first[axes[i]] - 1.0  # zero-based along the ISIS axis
        first.append(int(start if focal.signs[i] > 0 else focal.extent[i] - start - size[axes[i]]))
    return first[1], first[0], size[axes[1]], size[axes[0]]


def _cube_indices(focal: _FocalPlane, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-based (row, column) in the cube of the ideal pinhole pixels (u sample, v line):
    the ideal focal-plane point distorted as the lens does, then back to ISIS pixels."""
    x, y = (u - focal.origin[0]) * focal.pitch_mm, (v - focal.origin[1]) * focal.pitch_mm
    if focal.distortion is not None:
        k, (x0, y0) = focal.distortion
        r = np.hypot(x - x0, y - y0)
        dr = k[0] + r * (k[1] + r * (k[2] + r * (k[3] + r * k[4])))
        x, y = x + dr * (x - x0), y + dr * (y - y0)
    grid_u, grid_v = x / focal.pitch_mm + focal.origin[0], y / focal.pitch_mm + focal.origin[1]
    along = []  # zero-based detector position along each pwm axis, back to the ISIS axis
    for i, g in enumerate((grid_u, grid_v)):
        along.append(g if focal.signs[i] > 0 else focal.extent[i] - 1.0 - g)
    sample, line = (along[1], along[0]) if focal.swapped else (along[0], along[1])
    return line - (focal.first[1] - 1.0), sample - (focal.first[0] - 1.0)
