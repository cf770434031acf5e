"""PDS4 laser altimeter products: a label with a Table_Binary or Table_Character of shots, read
into pwm.lidar.shots.Shots through the loaded SPICE kernels; the writer of pwm's own plain
layout (the simulator's); a directory's lidar products read through its one meta-kernel
without the catalog (`read_lidar_directory`); and the catalog's shots file (`write_shots`, `read_shots`: a
product's placed shots and their tracks as one compressed NumPy archive).

Which fields hold a shot's time, range, validity, intensity and direction is a `Layout`, one per
known record layout (LAYOUTS: pwm's plain one and OSIRIS-REx OLA's Level 2 science record),
recognised by its field names. A shot's direction is either a unit vector in the instrument
frame given per shot, or the boresight of the instrument's FOV in its IK (+Z where the IK gives
none, as the OLA and Hayabusa LIDAR frame kernels define it); the instrument's frame may move
(a scan mirror whose articulation a CK gives, as ORX_OLA_ART): SPICE turns it into the body
frame at the shot's time.

Geometry: the spacecraft's position is geometric (no aberration correction) and the frame is
taken at the shot's time, as pwm.io.spice_geometry.camera_pose does for images: a lidar's km
ranges take microseconds of light time, in which a small body turns by far less than a mm.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import spiceypy as sp
from pds4_tools.reader.data_types import pds_to_numpy_type

from pwm.io.labels import body_name, find_labels, target_frame
from pwm.io.pds4 import (
    INFORMATION_MODEL,
    MAX_LABEL_BYTES,
    ProductError,
    check_data_file,
    checksum_md5,
    label_text,
    utc_iso,
)
from pwm.io.spice_geometry import FOV_ROOM, spacecraft_of
from pwm.io.spice_kernels import kernel_pool
from pwm.lidar.shots import Invalid, Shots

MAX_SHOTS = 2_000_000  # shots one product may hold, by default
MAX_RECORD_BYTES = 65_536  # a record longer than this is no lidar shot
MAX_FIELDS = 1_000  # fields a record may declare
# Range limits and the range's 1 sigma where the IK states none (INS<id>_PWM_RANGE_LIMITS km,
# INS<id>_PWM_RANGE_SIGMA km): no small-body lidar ranges past a few hundred km (NEAR's NLR
# reached 327 km), and decimetres is the order of their single-shot precision.
DEFAULT_RANGE_LIMITS_KM = (0.0, 500.0)
RANGE_LIMITS_KEYWORD, RANGE_SIGMA_KEYWORD = "PWM_RANGE_LIMITS", "PWM_RANGE_SIGMA"  # INS<id>_... in an IK
DEFAULT_RANGE_SIGMA_KM = 1.0e-4
_NS = {"pds": "http://pds.nasa.gov/pds4/pds/v1"}


@dataclass(frozen=True)
class Layout:
    """A known record layout: the fields (by name) of a shot's time (TDB s past J2000), range
    (in units of range_scale_km), validity flag (the values that mean a usable return), intensity
    and unit direction in the instrument frame (None where the layout has none), and where the
    record does not name its instrument frame: a field choosing it by value (`frames`)."""

    name: str
    time: str
    range: str
    range_scale_km: float
    flag: str | None = None
    valid_flags: tuple[int, ...] = (0,)
    intensity: str | None = None
    direction: tuple[str, str, str] | None = None
    frame_field: str | None = None
    frames: dict[int, str] = field(default_factory=dict)

    def required(self) -> list[str]:
        return [self.time, self.range, *(f for f in (self.flag, self.frame_field) if f is not None)]


LAYOUTS: dict[str, Layout] = {
    # pwm's own (the simulator's): the instrument is the label's; flag 0 a return, 2 none
    "pwm": Layout(name="pwm", time="et", range="range_km", range_scale_km=1.0, flag="flag",
                  intensity="intensity", direction=("direction_x", "direction_y", "direction_z")),
    # OSIRIS-REx OLA Level 2 science data (OLA SIS): ephemeris time; range in mm; flag_status 0 a
    # valid return, 1 valid with overflow, 2 no return, 3 a missing sample; laser_selection 0
    # the high-energy transmitter, 1 the low-energy one, whose frames the scan mirror's CK turns
    "ola-l2": Layout(name="ola-l2", time="et", range="range", range_scale_km=1e-6, flag="flag_status",
                     valid_flags=(0, 1), intensity="intensity", frame_field="laser_selection",
                     frames={0: "ORX_OLA_HIGH", 1: "ORX_OLA_LOW"}),
}


# the plain layout's record, written big-endian (PDS4 MSB types): (field, PDS4 type, numpy type, unit)
_PLAIN = LAYOUTS["pwm"]
_PLAIN_FIELDS = [(_PLAIN.time, "IEEE754MSBDouble", ">f8", "s"), (_PLAIN.range, "IEEE754MSBDouble", ">f8", "km"),
                 (str(_PLAIN.flag), "UnsignedByte", "u1", None)]
_PLAIN_INTENSITY = (str(_PLAIN.intensity), "IEEE754MSBSingle", ">f4", None)
_PLAIN_DIRECTION = [(name, "IEEE754MSBDouble", ">f8", None) for name in _PLAIN.direction or ()]


@dataclass(frozen=True)
class LidarTable:
    """A lidar product's shots as its table gives them, before any geometry. et: TDB s;
    range_km; flagged: the product's own flag says no usable return; intensity or None;
    direction: (N, 3) unit vectors in the instrument frame, or None (the boresight); frames: the
    instrument frame of each shot (names; `frame_index` indexes them); target: the name the
    label's Target_Identification gives, None where it gives none."""

    lid: str
    layout: str
    instrument: str | None
    target: str | None
    et: np.ndarray
    range_km: np.ndarray
    flagged: np.ndarray
    intensity: np.ndarray | None
    direction: np.ndarray | None
    frames: tuple[str, ...]
    frame_index: np.ndarray
    label_path: Path


@dataclass(frozen=True)
class LidarProduct:
    """A lidar product read through the kernels: its table and its shots (body-fixed, km)."""

    table: LidarTable
    shots: Shots


def read_lidar_product(label: Path, *, target: str, body_frame: str, root: Path | None = None,
                       max_label_bytes: int = MAX_LABEL_BYTES, max_shots: int = MAX_SHOTS,
                       range_limits_km: tuple[float, float] | None = None) -> LidarProduct:
    """Read a lidar product and place its shots with the loaded kernels (pwm.io.spice_kernels
    .kernel_pool): origins relative to `target` and directions in `body_frame`. Range limits:
    these, else the instrument IK's, else DEFAULT_RANGE_LIMITS_KM. ProductError for a product
    that cannot be read (see read_lidar_table); shots that cannot be used are kept, marked."""
    table = read_lidar_table(label, root=root, max_label_bytes=max_label_bytes, max_shots=max_shots)
    return LidarProduct(table=table, shots=place_shots(table, target=target, body_frame=body_frame,
                                                       range_limits_km=range_limits_km))


def read_lidar_directory(directory: Path, *, max_shots: int = MAX_SHOTS
                         ) -> tuple[list[LidarProduct], list[tuple[Path, str]]]:
    """The lidar products under `directory` (labels `is_lidar_label` takes), each read and its
    shots placed through the directory's one meta-kernel (*.tm) in the body-fixed frame of the
    target its label names; and those that could not be, with why. ValueError for a directory
    without exactly one meta-kernel or without lidar labels."""
    directory = Path(directory)
    metakernels = sorted(directory.rglob("*.tm"))
    if len(metakernels) != 1:
        raise ValueError(f"{directory}: expected one meta-kernel (*.tm), found {len(metakernels)}")
    labels = []
    for label in find_labels(directory):
        try:
            if label.suffix.lower() == ".xml" and label.stat().st_size <= MAX_LABEL_BYTES \
                    and is_lidar_label(ET.fromstring(label.read_bytes())):
                labels.append(label)
        except (ET.ParseError, OSError):
            continue
    if not labels:
        raise ValueError(f"{directory} holds no lidar product (a PDS4 table of shots in a known layout)")
    products, skipped = [], []
    with kernel_pool(metakernels):
        for label in labels:
            try:
                table = read_lidar_table(label, root=directory, max_shots=max_shots)
                target, frame = target_frame(table.target)
                if target is None or frame is None:
                    raise ProductError("unknown_target", f"the kernels give target {table.target!r} no body-fixed "
                                       "frame")
                products.append(LidarProduct(table=table, shots=place_shots(table, target=body_name(target),
                                                                            body_frame=frame)))
            except (ProductError, OSError, sp.stypes.SpiceyError) as exc:
                skipped.append((label, str(exc)))
    return products, skipped


def read_lidar_table(label: Path, *, root: Path | None = None, max_label_bytes: int = MAX_LABEL_BYTES,
                     max_shots: int = MAX_SHOTS) -> LidarTable:
    """Read and check a lidar product's label and table; no kernels needed.

    The label must be at most max_label_bytes, and it and its data file must resolve inside
    `root` (default: the label's directory); the table's records must fit in the data file (a
    table that claims more records than the file holds is refused, as is a file shorter or
    other than the label says), and be at most max_shots. ProductError with a code otherwise.
    """
    label = Path(label)
    within = (Path(root) if root is not None else label.parent).resolve()
    if not label.resolve().is_relative_to(within):
        raise ProductError("outside_downlink", f"{label.name} resolves outside {within}")
    if (size := label.stat().st_size) > max_label_bytes:
        raise ProductError("too_large", f"{label.name} is {size} bytes, more than the {max_label_bytes} "
                           "a label may have")
    try:
        root_element = ET.fromstring(label.read_bytes())
    except ET.ParseError as exc:
        raise ProductError("malformed_xml", f"{label.name} is not well-formed XML: {exc}") from exc
    lid = _text(root_element, "pds:Identification_Area/pds:logical_identifier") or label.stem
    instrument = None
    for component in root_element.iterfind(".//pds:Observing_System_Component", _NS):
        if _text(component, "pds:type") == "Instrument":
            instrument = _text(component, "pds:name")
    tables = [(area, table) for area in root_element.iterfind("pds:File_Area_Observational", _NS)
              for table in area if table.tag.rpartition("}")[2] in ("Table_Binary", "Table_Character")]
    if len(tables) != 1:
        raise ProductError("not_lidar", f"{label.name} has {len(tables)} tables of shots, not one")
    area, table = tables[0]
    file_name = _text(area, "pds:File/pds:file_name")
    if file_name is None or Path(file_name).name != file_name:
        raise ProductError("missing_element", f"{label.name}: no bare data file_name")
    data_path = label.parent / file_name
    check_data_file(data_path, within, _optional_int(area, "pds:File/pds:file_size"),
                _text(area, "pds:File/pds:md5_checksum"))
    binary = table.tag.endswith("Table_Binary")
    record = table.find("pds:Record_Binary" if binary else "pds:Record_Character", _NS)
    if record is None:
        raise ProductError("missing_element", f"{label.name}: the table has no record description")
    fields = _fields(record, binary)
    layout = _layout(fields, label.name)
    offset, records = _int(table, "pds:offset"), _int(table, "pds:records")
    length = _int(record, "pds:record_length")
    if records < 0 or offset < 0 or not 0 < length <= MAX_RECORD_BYTES:
        raise ProductError("bad_dimensions", f"{label.name}: {records} records of {length} bytes at {offset}")
    if records > max_shots:
        raise ProductError("too_many_shots", f"{label.name} holds {records} shots, more than the {max_shots} "
                           "a product may")
    if (end := offset + records * length) > (available := data_path.stat().st_size):
        raise ProductError("truncated", f"{records} records of {length} bytes at byte {offset} end at {end}, "
                           f"past the {available} bytes of {data_path.name}")
    for name, (start, width, _) in fields.items():
        if start < 0 or start + width > length:
            raise ProductError("bad_dimensions", f"field {name} lies outside the {length}-byte record")
    columns = _read_columns(data_path, offset=offset, records=records, length=length, binary=binary,
                            fields={n: fields[n] for n in _wanted(layout, fields)})
    et = columns[layout.time].astype(float)
    range_km = columns[layout.range].astype(float) * layout.range_scale_km
    flagged = (~np.isin(columns[layout.flag], layout.valid_flags) if layout.flag is not None
               else np.zeros(records, dtype=bool))
    intensity = (columns[layout.intensity].astype(float)
                 if layout.intensity is not None and layout.intensity in columns else None)
    direction = None
    if layout.direction is not None and all(name in columns for name in layout.direction):
        direction = np.column_stack([columns[name].astype(float) for name in layout.direction])
    if layout.frame_field is not None:
        chosen = columns[layout.frame_field]
        if not np.isin(chosen, list(layout.frames)).all():
            raise ProductError("bad_value", f"{label.name}: {layout.frame_field} takes values other than "
                               f"{sorted(layout.frames)}")
        codes = sorted(layout.frames)
        frames = tuple(layout.frames[c] for c in codes)
        frame_index = np.searchsorted(codes, chosen)
    else:
        if instrument is None:
            raise ProductError("missing_element", f"{label.name} names no instrument")
        frames, frame_index = (instrument,), np.zeros(records, dtype=np.int64)
    target = _text(root_element, "pds:Observation_Area/pds:Target_Identification/pds:name")
    return LidarTable(lid=lid, layout=layout.name, instrument=instrument, target=target, et=et, range_km=range_km,
                      flagged=flagged, intensity=intensity, direction=direction, frames=frames, frame_index=frame_index,
                      label_path=label)


def _text(node: ET.Element, path: str) -> str | None:
    found = node.find(path, _NS)
    return None if found is None or found.text is None else found.text.strip()


def _int(node: ET.Element, path: str) -> int:
    value = _optional_int(node, path)
    if value is None:
        raise ProductError("missing_element", f"label lacks {path.replace('pds:', '')}")
    return value


def _optional_int(node: ET.Element, path: str) -> int | None:
    text = _text(node, path)
    if text is None:
        return None
    try:
        return int(text)
    except ValueError as exc:
        raise ProductError("bad_value", f"{path.replace('pds:', '')} = {text!r} is not an integer") from exc


def _fields(record: ET.Element, binary: bool) -> dict[str, tuple[int, int, str]]:
    """name -> (zero-based start byte, length, PDS4 data_type) of the record's own fields
    (fields inside groups are not read)."""
    kind = "pds:Field_Binary" if binary else "pds:Field_Character"
    elements = record.findall(kind, _NS)
    if len(elements) > MAX_FIELDS:
        raise ProductError("too_large", f"a record of {len(elements)} fields")
    fields = {}
    for element in elements:
        name = _text(element, "pds:name")
        data_type = _text(element, "pds:data_type")
        if name is None or data_type is None:
            raise ProductError("missing_element", "a field without name or data_type")
        if name in fields:
            raise ProductError("duplicate_element", f"field {name} appears twice")
        fields[name] = (_int(element, "pds:field_location") - 1, _int(element, "pds:field_length"), data_type)
    return fields


def is_lidar_label(root: ET.Element) -> bool:
    """Whether a parsed PDS4 label describes a table of shots in a known layout (LAYOUTS), by
    its fields' names alone: what read_lidar_table would take, whole or broken."""
    names = {(e.text or "").strip() for e in root.iterfind(
        "pds:File_Area_Observational/*/pds:Record_Binary/pds:Field_Binary/pds:name", _NS)}
    names |= {(e.text or "").strip() for e in root.iterfind(
        "pds:File_Area_Observational/*/pds:Record_Character/pds:Field_Character/pds:name", _NS)}
    return any(all(f in names for f in layout.required()) for layout in LAYOUTS.values())


def _layout(fields: dict[str, tuple[int, int, str]], name: str) -> Layout:
    for layout in LAYOUTS.values():
        if all(f in fields for f in layout.required()):
            return layout
    raise ProductError("unknown_layout", f"{name}: its fields ({', '.join(list(fields)[:12])}) match no known "
                       f"lidar layout ({', '.join(LAYOUTS)})")


def _wanted(layout: Layout, fields: dict) -> list[str]:
    names = [*layout.required(), layout.intensity, *(layout.direction or ())]
    return [n for n in names if n is not None and n in fields]


def _read_columns(path: Path, *, offset: int, records: int, length: int, binary: bool,
                  fields: dict[str, tuple[int, int, str]]) -> dict[str, np.ndarray]:
    """The named fields of every record, as numbers (ProductError for a field that is not)."""
    # mapped, not read: only the wanted fields' bytes are copied out of a record however long
    raw = (np.memmap(path, dtype=np.uint8, mode="r", offset=offset, shape=(records, length)) if records
           else np.zeros((0, length), dtype=np.uint8))
    columns = {}
    for name, (start, width, data_type) in fields.items():
        chunk = np.array(raw[:, start:start + width])  # a copy: nothing keeps the file mapped
        # a binary table's numbers are binary, but it may hold numbers as text (ASCII_Real) too
        if binary and not data_type.startswith("ASCII"):
            try:
                dtype = np.dtype(pds_to_numpy_type(data_type))
            except (ValueError, TypeError) as exc:
                raise ProductError("unsupported", f"field {name}: unknown data_type {data_type!r}") from exc
            if dtype.kind not in "iuf" or dtype.itemsize != width:
                raise ProductError("unsupported", f"field {name}: {data_type} of {width} bytes is not a number")
            columns[name] = chunk.view(dtype).reshape(records)
            continue
        try:
            columns[name] = np.char.strip(chunk.view(f"S{width}").reshape(records)).astype(float)
        except ValueError as exc:
            raise ProductError("bad_value", f"field {name} ({data_type}) holds values that are not numbers") from exc
    return columns


def place_shots(table: LidarTable, *, target: str, body_frame: str,
                range_limits_km: tuple[float, float] | None = None) -> Shots:
    """The table's shots in `body_frame` relative to `target`, through the loaded kernels: each
    shot's origin (the spacecraft of its instrument) and direction at its time. Shots whose time
    the kernels do not cover are marked OUTSIDE_KERNELS (origin and direction NaN)."""
    n = len(table.et)
    origin = np.full((n, 3), np.nan)
    direction = np.full((n, 3), np.nan)
    sigma = np.empty(n)
    limits = np.empty((n, 2))
    outside = np.zeros(n, dtype=bool)
    finite_et = np.isfinite(table.et)
    for k, frame in enumerate(table.frames):
        instrument_id = _naif_id(frame)
        mine = table.frame_index == k
        lo_hi = range_limits_km if range_limits_km is not None else _ik(instrument_id, RANGE_LIMITS_KEYWORD, 2)
        limits[mine] = lo_hi if lo_hi is not None else DEFAULT_RANGE_LIMITS_KM
        sig = _ik(instrument_id, RANGE_SIGMA_KEYWORD, 1)
        sigma[mine] = sig[0] if sig is not None else DEFAULT_RANGE_SIGMA_KM
        frame_name, boresight = _frame_and_boresight(frame, instrument_id)
        spacecraft = str(spacecraft_of(instrument_id))
        for i in np.flatnonzero(mine & finite_et):
            et = float(table.et[i])
            try:
                origin[i] = sp.spkpos(spacecraft, et, body_frame, "NONE", target)[0]
                turn = sp.pxform(frame_name, body_frame, et)
            except sp.stypes.SpiceyError:
                outside[i] = True
                origin[i] = np.nan
                continue
            local = table.direction[i] if table.direction is not None else boresight
            direction[i] = turn @ local
    norm = np.linalg.norm(direction, axis=1)
    # a direction given per shot must be a unit vector to a part in a million
    bad_direction = ~np.isfinite(norm) | (np.abs(norm - 1.0) > 1e-6)
    direction = direction / np.where(norm > 0, norm, 1.0)[:, None]
    invalid = np.zeros(n, dtype=np.int8)
    shots = Shots(frame=body_frame, et=table.et, origin_km=origin, direction=direction, range_km=table.range_km,
                  sigma_km=sigma, invalid=invalid, intensity=table.intensity)
    shots = shots.marked(~finite_et, Invalid.NOT_FINITE)
    shots = shots.marked(table.flagged, Invalid.FLAGGED)
    shots = shots.marked(outside, Invalid.OUTSIDE_KERNELS)
    shots = shots.marked(~np.isfinite(table.range_km) | bad_direction, Invalid.NOT_FINITE)
    with np.errstate(invalid="ignore"):
        out_of_range = (table.range_km < limits[:, 0]) | (table.range_km > limits[:, 1])
    return shots.marked(out_of_range, Invalid.RANGE_LIMITS)


def _naif_id(name: str) -> int:
    try:
        return int(sp.bodn2c(name))
    except sp.stypes.SpiceyError:
        raise ProductError("unknown_instrument", f"the kernels do not know the instrument {name!r}") from None


def _ik(instrument_id: int, keyword: str, count: int) -> tuple[float, ...] | None:
    variable = f"INS{instrument_id}_{keyword}"
    if not sp.expool(variable):
        return None
    values = np.atleast_1d(sp.gdpool(variable, 0, count)).astype(float)
    if len(values) != count or not np.isfinite(values).all():
        raise ProductError("bad_kernel", f"{variable} is not {count} finite numbers")
    return tuple(float(v) for v in values)


def _frame_and_boresight(name: str, instrument_id: int) -> tuple[str, np.ndarray]:
    """The instrument's frame and boresight: its IK's FOV where it has one, else the frame of
    that name with +Z."""
    try:
        _, frame, boresight, _, _ = sp.getfov(instrument_id, FOV_ROOM)
    except sp.stypes.SpiceyError:
        if sp.namfrm(name) == 0:
            raise ProductError("unknown_instrument", f"no FOV in the IK and no frame {name!r} in the kernels"
                               ) from None
        return name, np.array([0.0, 0.0, 1.0])
    boresight = np.asarray(boresight, dtype=float)
    return frame, boresight / np.linalg.norm(boresight)


def write_lidar_product(*, directory: Path, basename: str, lid: str, et: np.ndarray, range_km: np.ndarray,
                        flag: np.ndarray, start_utc: str, stop_utc: str, mission: str, host_name: str,
                        instrument_name: str, target_name: str, title: str, intensity: np.ndarray | None = None,
                        direction: np.ndarray | None = None, vid: str = "1.0") -> tuple[Path, Path]:
    """Write basename.dat (one big-endian record per shot in the plain layout: et TDB s, range_km,
    flag (0 a return, else none), then intensity and the unit direction in the instrument frame
    where given) and its PDS4 label basename.xml, naming instrument_name (its NAIF name: the
    reader finds its frame and IK by it). Existing files are never overwritten. Returns
    (label_path, data_path)."""
    n = len(et)
    columns = [np.asarray(et, float), np.asarray(range_km, float), np.asarray(flag, np.uint8)]
    spec = list(_PLAIN_FIELDS)
    if intensity is not None:
        spec.append(_PLAIN_INTENSITY)
        columns.append(np.asarray(intensity, float))
    if direction is not None:
        spec += _PLAIN_DIRECTION
        columns += list(np.asarray(direction, float).T)
    if any(c.shape != (n,) for c in columns):
        raise ValueError("every column needs one value per shot")
    if Path(basename).name != basename:
        raise ValueError(f"basename {basename!r} must be a bare file name")
    dtype = np.dtype([(name, np_type) for name, _, np_type, _ in spec])
    records = np.empty(n, dtype=dtype)
    for (name, *_), column in zip(spec, columns, strict=True):
        records[name] = column
    label_path, data_path = (Path(directory) / f"{basename}.{ext}" for ext in ("xml", "dat"))
    Path(directory).mkdir(parents=True, exist_ok=True)
    with open(data_path, "xb") as fh:
        fh.write(records.tobytes())
    fields, location = [], 1
    for k, (name, pds_type, np_type, unit) in enumerate(spec):
        fields.append(("Field_Binary", [("name", name), ("field_number", k + 1), ("field_location", location, "byte"),
                                        ("data_type", pds_type), ("field_length", np.dtype(np_type).itemsize, "byte"),
                                        *([("unit", unit)] if unit else [])]))
        location += np.dtype(np_type).itemsize
    text = label_text([
        ("Identification_Area", [("logical_identifier", lid), ("version_id", vid), ("title", title),
                                 ("information_model_version", INFORMATION_MODEL),
                                 ("product_class", "Product_Observational")]),
        ("Observation_Area", [
            ("Time_Coordinates", [("start_date_time", utc_iso(start_utc)), ("stop_date_time", utc_iso(stop_utc))]),
            ("Investigation_Area", [("name", mission), ("type", "Mission")]),
            ("Observing_System", [
                ("Observing_System_Component", [("name", host_name), ("type", "Host")]),
                ("Observing_System_Component", [("name", instrument_name), ("type", "Instrument")])]),
            ("Target_Identification", [("name", target_name), ("type", "Asteroid")])]),
        ("File_Area_Observational", [
            ("File", [("file_name", data_path.name),
                      ("creation_date_time", datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")),
                      ("file_size", data_path.stat().st_size, "byte"), ("md5_checksum", checksum_md5(data_path))]),
            ("Table_Binary", [("offset", 0, "byte"), ("records", n),
                              ("Record_Binary", [("fields", len(spec)), ("groups", 0),
                                                 ("record_length", dtype.itemsize, "byte"), *fields])])])])
    with open(label_path, "x", encoding="utf-8") as fh:
        fh.write(text)
    return label_path, data_path


# the arrays of a shots file: (name, dtype, per-shot shape); intensity is optional
_SHOTS_ARRAYS = (("et", "f8", ()), ("origin_km", "f8", (3,)), ("direction", "f8", (3,)), ("range_km", "f8", ()),
                 ("sigma_km", "f8", ()), ("invalid", "i1", ()), ("track", "i8", ()), ("spots_km", "f8", (3,)))


def write_shots(path: Path, shots: Shots, track: np.ndarray) -> None:
    """Write placed shots and each one's track (pwm.lidar.tracks.track_ids) to `path` as a
    compressed NumPy archive (.npz): times (TDB s), origins, directions, ranges, range sigmas,
    invalid reasons (pwm.lidar.shots.Invalid), tracks, the spots (origin + range * direction,
    km, the shots' body-fixed frame, kept so that a reader needs no arithmetic), the frame's
    name and the intensity where given."""
    track = np.asarray(track, dtype=np.int64)
    if track.shape != (len(shots),):
        raise ValueError(f"track has shape {track.shape}, expected ({len(shots)},)")
    arrays = {"et": shots.et, "origin_km": shots.origin_km, "direction": shots.direction, "range_km": shots.range_km,
              "sigma_km": shots.sigma_km, "invalid": shots.invalid, "track": track, "spots_km": shots.spots_km()}
    typed = {name: np.asarray(arrays[name], dtype=dtype) for name, dtype, _ in _SHOTS_ARRAYS}
    if shots.intensity is not None:
        typed["intensity"] = np.asarray(shots.intensity, dtype=float)
    typed["frame"] = np.array(shots.frame)
    with open(path, "wb") as fh:
        np.savez_compressed(fh, allow_pickle=False, **typed)


def read_shots(path: Path) -> tuple[Shots, np.ndarray]:
    """The shots and tracks `write_shots` wrote (ValueError for a file that is not one: no
    pickled objects are loaded, every array's type and length is checked)."""
    with np.load(path, allow_pickle=False) as archive:
        names = set(archive.files)
        missing = {name for name, _, _ in _SHOTS_ARRAYS} - names
        if missing or "frame" not in names:
            raise ValueError(f"{Path(path).name} is no shots file: it lacks {sorted(missing | ({'frame'} - names))}")
        n = len(archive["et"])
        arrays = {}
        for name, dtype, shape in _SHOTS_ARRAYS:
            value = archive[name]
            if value.dtype != np.dtype(dtype) or value.shape != (n, *shape):
                raise ValueError(f"{Path(path).name}: {name} is {value.dtype} {value.shape}, not {dtype} {(n, *shape)}")
            arrays[name] = value
        intensity = archive["intensity"] if "intensity" in names else None
        frame = str(archive["frame"])
    shots = Shots(frame=frame, et=arrays["et"], origin_km=arrays["origin_km"], direction=arrays["direction"],
                  range_km=arrays["range_km"], sigma_km=arrays["sigma_km"], invalid=arrays["invalid"],
                  intensity=intensity)
    return shots, arrays["track"]
