"""PDS4 image products: a FITS data file (primary header + 2-D array) with its XML label.

Written as OSIRIS-REx OCAMS products are (Product_Observational, Header + Array_2D_Image in one
FITS file); read back, with the data file checked against its label before its array is read.
Arrays are [line, sample]; physical value = dn * scaling_factor + value_offset.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np
from astropy.io import fits
from pds4_tools.reader.data_types import pds_to_numpy_type

PDS_NS = "http://pds.nasa.gov/pds4/pds/v1"
IMG_NS = "http://pds.nasa.gov/pds4/img/v1"
XSI_NS = "http://www.w3.org/2001/XMLSchema-instance"
INFORMATION_MODEL = "1.14.0.0"  # schema files 1E00
_SCHEMAS = {PDS_NS: "https://pds.nasa.gov/pds4/pds/v1/PDS4_PDS_1E00",
            IMG_NS: "https://pds.nasa.gov/pds4/img/v1/PDS4_IMG_1E00_1800"}
MISSING_DN = -32768  # stored value of saturated/missing pixels (FITS BLANK, PDS4 missing_constant)
_FITS_STRUCTURAL = {"SIMPLE", "BITPIX", "NAXIS", "NAXIS1", "NAXIS2", "EXTEND", "BSCALE", "BZERO",
                    "BLANK", "END"}
_NS = {"pds": PDS_NS, "img": IMG_NS}
_SECONDS = {"s": 1.0, "ms": 1e-3, "microseconds": 1e-6, "ns": 1e-9, "min": 60.0}  # PDS4 time units
# Bounds on what one product may make the reader do, before it reads: the label's size (the
# XML parser holds it whole, several times over) and the array's pixel count
# (4096 x 4096, sixteen times OCAMS, ONC, AMICA or LORRI; read_array holds about 8 bytes
# a pixel of int16 data at its peak, bench/RESULTS.md). service.settings.Settings
# overrides both.
MAX_LABEL_BYTES = 4 * 1024**2
MAX_PIXELS = 4096 * 4096
# A FITS header's length is known only at its END card, which a hostile file may put a gigabyte
# in: it is read a 2880-byte block at a time up to this bound (364 blocks, 13,000 cards; mission
# headers take 2 to 10 blocks). service.settings.Settings overrides it.
MAX_FITS_HEADER_BYTES = 1024**2
FITS_BLOCK = 2880
_FITS_CARD = 80
_FITS_END = b"END".ljust(_FITS_CARD)
_FITS_SIGNATURE = b"SIMPLE  ="
# The array each FITS BITPIX stores: big-endian, signed integers except bytes (FITS standard 4.0
# table 8); an unsigned 16-bit FITS image is a signed one with BZERO 32768.
_FITS_DTYPES: dict[int, np.dtype] = {
    8: np.dtype("u1"), 16: np.dtype(">i2"), 32: np.dtype(">i4"), 64: np.dtype(">i8"),
    -32: np.dtype(">f4"), -64: np.dtype(">f8")}


class ProductError(ValueError):
    """A label or data file that cannot be ingested; `code` is short and machine-friendly."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class ImageLabel:
    """One PDS4 2-D image's label, checked against its data file but with the array not read:
    file_size (bytes) and md5 are as the label declares them (None where it does not) and agree
    with the data file; the array fits in it, and agrees with the FITS header's BITPIX and
    axes; its scaling is finite and non-zero."""

    lid: str
    vid: str
    title: str
    start_utc: str
    stop_utc: str
    mission: str | None
    host_name: str | None
    instrument_name: str | None
    target_name: str | None
    target_type: str | None
    exposure_s: float | None
    first_line: int  # zero-based detector position of the array (img:Subframe), 0 for full frames
    first_sample: int
    data_path: Path
    file_size: int | None
    md5: str | None
    lines: int
    samples: int
    fits_header: dict[str, Any] | None
    label_path: Path
    layout: ArrayLayout


@dataclass(frozen=True)
class ArrayLayout:
    """Where and how the array lies in the data file: numpy dtype (with byte order), byte
    offset, the scaling to physical values and the stored values that flag a pixel (the
    label's Special_Constants, each a value of the array's type)."""

    dtype: str
    offset: int
    scaling_factor: float
    value_offset: float
    special_constants: tuple[float, ...]


@dataclass(frozen=True)
class ImageProduct(ImageLabel):
    """One PDS4 2-D image: its label and the scaled array (float64 [line, sample], NaN where the
    label's special constants flag a pixel)."""

    data: np.ndarray


def _digest(path: Path, algorithm: str) -> str:
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, algorithm).hexdigest()


def checksum_md5(path: Path) -> str:
    """MD5 of a file as PDS4 md5_checksum gives it (lower-case hex), read in chunks."""
    return _digest(path, "md5")


def file_sha256(path: Path) -> str:
    """SHA-256 of a file (lower-case hex), read in chunks."""
    return _digest(path, "sha256")


def utc_iso(stamp: str) -> str:
    """ISO-8601 UTC time as PDS4 writes it, with a trailing Z."""
    parsed = datetime.fromisoformat(stamp)
    if parsed.utcoffset():  # None (naive, taken as UTC) and zero are both falsy
        raise ValueError(f"time {stamp!r} is not UTC")
    return stamp.removesuffix("Z").removesuffix("+00:00") + "Z"


def build_elements(parent: ET.Element, items: list[tuple]) -> None:
    """Add (tag, text or [children], optional unit) items under parent; ElementTree escapes."""
    for tag, content, *unit in items:
        element = ET.SubElement(parent, tag, {"unit": unit[0]} if unit else {})
        if isinstance(content, list):
            build_elements(element, content)
        else:
            element.text = str(content)


def label_text(body: list[tuple]) -> str:
    # Namespaces are written as plain attributes so the label keeps the usual prefixes
    # (default pds, img, xsi) without touching ElementTree's global prefix registry.
    root = ET.Element("Product_Observational", {
        "xmlns": PDS_NS, "xmlns:img": IMG_NS, "xmlns:xsi": XSI_NS,
        "xsi:schemaLocation": " ".join(f"{ns} {base}.xsd" for ns, base in _SCHEMAS.items())})
    build_elements(root, body)
    ET.indent(root, space="    ")
    models: list[ET.Element[Any]] = [
        ET.ProcessingInstruction("xml-model", f'href="{base}.sch" schematypens="http://purl.oclc.org/dsdl/schematron"')
        for base in _SCHEMAS.values()]
    return "\n".join(['<?xml version="1.0" encoding="UTF-8"?>',
                      *(ET.tostring(e, encoding="unicode") for e in [*models, root]), ""])


def _write_fits(path: Path, dn: np.ndarray, scaling_factor: float, value_offset: float,
                cards: dict[str, Any]) -> int:
    """Write the FITS file; return the primary header length in bytes."""
    hdu = fits.PrimaryHDU(data=dn.astype(">i2"))
    # Cards set after construction are written as given and the int16 array stays raw, so a
    # FITS reader applying BSCALE/BZERO/BLANK sees the values the PDS4 label describes.
    hdu.header["BSCALE"] = float(scaling_factor)
    hdu.header["BZERO"] = float(value_offset)
    hdu.header["BLANK"] = MISSING_DN
    for key, value in cards.items():
        hdu.header[key] = value
    hdu.writeto(path)
    with fits.open(path) as hdul:
        return int(hdul[0].fileinfo()["datLoc"])


def write_image_product(*, directory: Path, basename: str, dn: np.ndarray, scaling_factor: float,
                        value_offset: float, lid: str, vid: str = "1.0", start_utc: str,
                        stop_utc: str, mission: str, host_name: str, instrument_name: str,
                        target_name: str, target_type: str = "Asteroid", title: str,
                        exposure_s: float | None = None, subframe: tuple[int, int] | None = None,
                        extra_fits_header: dict | None = None) -> tuple[Path, Path]:
    """Write basename.fits (int16 big-endian [line, sample] with BSCALE/BZERO = the PDS4 scaling,
    BLANK = MISSING_DN) and its PDS4 label basename.xml. Times are UTC ISO-8601; exposure in s;
    subframe: zero-based (first_line, first_sample) of a detector window, written as img:Subframe
    (1-based, as PDS4 counts). extra_fits_header values may be (value, comment) pairs. Existing files are never
    overwritten. Returns (label_path, data_path)."""
    dn = np.asarray(dn)
    if dn.dtype != np.int16 or dn.ndim != 2:
        raise ValueError(f"dn must be a 2-D int16 array, got {dn.ndim}-D {dn.dtype}")
    if not np.isfinite(scaling_factor) or scaling_factor == 0 or not np.isfinite(value_offset):
        raise ValueError("scaling_factor must be finite and non-zero, value_offset finite")
    extra = dict(extra_fits_header or {})
    if clash := _FITS_STRUCTURAL & {k.upper() for k in extra}:
        raise ValueError(f"extra_fits_header may not set structural cards {sorted(clash)}")
    if Path(basename).name != basename:
        raise ValueError(f"basename {basename!r} must be a bare file name")
    start, stop = utc_iso(start_utc), utc_iso(stop_utc)
    label_path, data_path = (Path(directory) / f"{basename}.{ext}" for ext in ("xml", "fits"))
    for path in (label_path, data_path):
        if path.exists():
            raise FileExistsError(f"{path} exists; a product is written once")

    cards: dict[str, Any] = {"DATE-OBS": start[:-1], "DATE-END": stop[:-1], "TELESCOP": host_name,
                             "INSTRUME": instrument_name, "TARGET": target_name}
    lines, samples = dn.shape
    imaging: list[tuple[str, list[tuple]]] = []
    if exposure_s is not None:
        cards["EXPTIME"] = float(exposure_s)
        imaging.append(("img:Exposure", [("img:exposure_duration", repr(float(exposure_s)), "s")]))
    if subframe is not None:
        first_line, first_sample = (int(v) for v in subframe)
        if first_line < 0 or first_sample < 0:
            raise ValueError("subframe offsets are zero-based and non-negative")
        imaging.append(("img:Subframe", [("img:first_line", first_line + 1), ("img:first_sample", first_sample + 1),
                                         ("img:lines", lines), ("img:samples", samples)]))
    discipline = [("Discipline_Area", imaging)] if imaging else []
    header_bytes = _write_fits(data_path, dn, scaling_factor, value_offset, cards | extra)
    text = label_text([
        ("Identification_Area", [
            ("logical_identifier", lid), ("version_id", vid), ("title", title),
            ("information_model_version", INFORMATION_MODEL),
            ("product_class", "Product_Observational")]),
        ("Observation_Area", [
            ("Time_Coordinates", [("start_date_time", start), ("stop_date_time", stop)]),
            ("Investigation_Area", [("name", mission), ("type", "Mission")]),
            ("Observing_System", [
                ("Observing_System_Component", [("name", host_name), ("type", "Host")]),
                ("Observing_System_Component", [("name", instrument_name),
                                                ("type", "Instrument")])]),
            ("Target_Identification", [("name", target_name), ("type", target_type)]),
            *discipline]),
        ("File_Area_Observational", [
            ("File", [
                ("file_name", data_path.name),
                ("creation_date_time",
                 datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")),
                ("file_size", data_path.stat().st_size, "byte"),
                ("md5_checksum", checksum_md5(data_path))]),
            ("Header", [("offset", 0, "byte"), ("object_length", header_bytes, "byte"),
                        ("parsing_standard_id", "FITS 3.0")]),
            ("Array_2D_Image", [
                ("offset", header_bytes, "byte"), ("axes", 2),
                ("axis_index_order", "Last Index Fastest"),
                ("Element_Array", [("data_type", "SignedMSB2"),
                                   ("scaling_factor", repr(float(scaling_factor))),
                                   ("value_offset", repr(float(value_offset)))]),
                ("Axis_Array", [("axis_name", "Line"), ("elements", lines),
                                ("sequence_number", 1)]),
                ("Axis_Array", [("axis_name", "Sample"), ("elements", samples),
                                ("sequence_number", 2)]),
                ("Special_Constants", [("missing_constant", MISSING_DN)])])])])
    with open(label_path, "x", encoding="utf-8") as fh:
        fh.write(text)
    return label_path, data_path


def _one(node: ET.Element, path: str) -> ET.Element | None:
    """The element at `path`, None if none; ProductError (duplicate_element) if several: read
    first-wins, a second logical_identifier, start time or data_type would be ignored here and
    believed by another reader."""
    found = node.findall(path, _NS)
    if len(found) > 1:
        raise ProductError("duplicate_element", f"label has {len(found)} "
                           f"{path.replace('pds:', '').replace('.//', '')} elements")
    return found[0] if found else None


@overload
def _text(node: ET.Element, path: str, required: Literal[True] = True, *,
          repeatable: bool = False) -> str: ...
@overload
def _text(node: ET.Element, path: str, required: bool, *, repeatable: bool = False
          ) -> str | None: ...
def _text(node: ET.Element, path: str, required: bool = True, *, repeatable: bool = False
          ) -> str | None:
    """The element's text, stripped; `repeatable` for an element the schema lets repeat (a
    product's investigations and targets): the first is read."""
    found = node.find(path, _NS) if repeatable else _one(node, path)
    if found is None or found.text is None:
        if required:
            raise ProductError("missing_element", f"label lacks {path.replace('pds:', '')}")
        return None
    return found.text.strip()


@overload
def _int(node: ET.Element, path: str, required: Literal[True] = True) -> int: ...
@overload
def _int(node: ET.Element, path: str, required: bool) -> int | None: ...
def _int(node: ET.Element, path: str, required: bool = True) -> int | None:
    text = _text(node, path, required)
    try:
        return None if text is None else int(text)
    except ValueError as exc:
        raise ProductError("bad_value", f"{path} = {text!r} is not an integer") from exc


def _component(obs: ET.Element, kinds: tuple[str, ...]) -> str | None:
    for component in obs.iterfind("pds:Observing_System/pds:Observing_System_Component", _NS):
        if _text(component, "pds:type", False) in kinds:
            return _text(component, "pds:name", False)
    return None


def check_data_file(data_path: Path, root: Path, size: int | None, md5: str | None) -> None:
    """A product's data file as its label states it: there, inside `root` (no link out of the
    downlink), of the label's size and MD5 where the label gives them; ProductError otherwise."""
    if not data_path.is_file():
        raise ProductError("missing_file", f"data file {data_path} not found")
    if not data_path.resolve().is_relative_to(root):
        raise ProductError("outside_downlink", f"data file {data_path.name} resolves to "
                           f"{data_path.resolve()}, outside {root}")
    actual = data_path.stat().st_size
    if size is not None and actual != size:
        raise ProductError("size_mismatch", f"{data_path.name} is {actual} bytes, label says {size}"
                           + (" (truncated)" if actual < size else ""))
    if md5 is not None and checksum_md5(data_path) != md5.lower():
        raise ProductError("md5_mismatch", f"{data_path.name} md5 differs from the label's {md5}")


def _float(node: ET.Element, path: str) -> float | None:
    text = _text(node, path, False)
    try:
        return None if text is None else float(text)
    except ValueError as exc:
        raise ProductError("bad_value", f"{path.replace('pds:', '')} = {text!r} is not a number"
                           ) from exc


def _scaling(image: ET.Element) -> tuple[float, float]:
    """The array's scaling factor and value offset (1 and 0 where the label gives none). A
    scaling factor that is NaN, infinite or zero, or an offset that is not finite, would make
    every pixel NaN, infinite or one value."""
    scaling = _float(image, "pds:Element_Array/pds:scaling_factor")
    offset = _float(image, "pds:Element_Array/pds:value_offset")
    if scaling is not None and (not np.isfinite(scaling) or scaling == 0):
        raise ProductError("bad_value", f"scaling_factor {scaling} is not finite and non-zero")
    if offset is not None and not np.isfinite(offset):
        raise ProductError("bad_value", f"value_offset {offset} is not finite")
    return 1.0 if scaling is None else scaling, 0.0 if offset is None else offset


def _special_constants(image: ET.Element, dtype: np.dtype, data_type: str) -> tuple[float, ...]:
    """The stored values the label's Special_Constants flag (decimal, or 0x hexadecimal: the
    value of an integer, the bit pattern of a float), each checked to be a value of the array's
    type: one it cannot hold flags nothing, and says the label is not of this array."""
    found = _one(image, "pds:Special_Constants")
    values = []
    for element in [] if found is None else list(found):
        name, text = element.tag.rpartition("}")[2], (element.text or "").strip()
        if name.startswith("valid_"):  # a valid range, not a flagged value
            continue
        try:
            value = _constant(text, dtype)
        except (ValueError, OverflowError):
            raise ProductError("bad_special_constant", f"special constant {name} = {text!r} is "
                               f"not a {data_type} value") from None
        values.append(value)
    return tuple(values)


def _constant(text: str, dtype: np.dtype) -> float:
    """A special constant as a value of `dtype`; ValueError when it is none."""
    is_hex = text.lower().startswith("0x")
    if dtype.kind == "f" and is_hex:
        return float(np.array(int(text, 16), dtype=f">u{dtype.itemsize}").view(f">f{dtype.itemsize}"))
    value = float(int(text, 16)) if is_hex else float(text)
    if dtype.kind == "f":
        # -3.4028235E38, the usual float32 constant, is a double just past float32's range:
        # rounded to the type it is float32's lowest value, as the array stores it.
        with np.errstate(over="ignore"):
            rounded = dtype.type(value)
        if np.isfinite(value) and not np.isfinite(rounded):
            raise ValueError(text)
        return float(rounded)
    limits = np.iinfo(dtype)
    if not value.is_integer() or not limits.min <= value <= limits.max:
        raise ValueError(text)
    return value


def _fits_bitpix(dtype: np.dtype) -> int:
    """The FITS BITPIX of an array of `dtype`'s size and kind: bits, negative for floating
    point (_check_fits then checks its sign and byte order)."""
    return -8 * dtype.itemsize if dtype.kind == "f" else 8 * dtype.itemsize


def _check_array(area: ET.Element, data_path: Path, lines: int, samples: int, *, max_pixels: int,
                 max_fits_header_bytes: int) -> tuple[ArrayLayout, dict | None]:
    """Check the array's size and type, that it fits in the data file and agrees with the FITS
    header it follows, if any (_check_fits); return its layout and that header."""
    image = area.find("pds:Array_2D_Image", _NS)
    if image is None:
        raise ProductError("missing_element", f"{data_path.name}: the file area lacks Array_2D_Image")
    if lines < 1 or samples < 1:
        raise ProductError("bad_dimensions", f"label says {lines}x{samples}")
    if lines * samples > max_pixels:
        raise ProductError("too_large", f"{lines}x{samples} pixels is more than the "
                           f"{max_pixels} an image may have")
    data_type = _text(image, "pds:Element_Array/pds:data_type")
    dtype = pds_to_numpy_type(data_type)  # unknown names come back as a zero-length string type
    if dtype.kind == "c":  # read as real values, its imaginary part would be dropped
        raise ProductError("unsupported", f"array data_type {data_type} is complex, not an "
                           "image of real values")
    if dtype.kind not in "iuf":
        raise ProductError("unsupported", f"array data_type {data_type!r} is not binary numeric")
    if (order := _text(image, "pds:axis_index_order", False)) not in (None, "Last Index Fastest"):
        raise ProductError("unsupported", f"axis_index_order {order!r}")
    array_offset = _int(image, "pds:offset")
    if array_offset < 0:
        raise ProductError("bad_dimensions", f"array offset {array_offset} is negative")
    layout = ArrayLayout(dtype.str, array_offset, *_scaling(image),
                         _special_constants(image, dtype, data_type))
    file_size = data_path.stat().st_size
    end = array_offset + lines * samples * dtype.itemsize
    if end > file_size:
        # A file cut short in transfer, as far as can be told without the label's file_size.
        raise ProductError("truncated", f"{lines}x{samples} {data_type} array ends at byte "
                           f"{end}, past the end of {data_path.name} ({file_size} bytes)")
    located = _fits_header_at(area, data_path, array_offset)
    if located is None:
        return layout, None
    start, declared_length = located
    if declared_length is not None and (declared_length < 0 or start + declared_length > file_size):
        # refused unread: a declared length of 1e20 bytes would be a header never found
        raise ProductError("bad_header", f"Header of {declared_length} bytes at byte {start} "
                           f"does not fit in {data_path.name} ({file_size} bytes)")
    cards, length = _read_fits_header(data_path, start, max_fits_header_bytes)
    if declared_length is not None and declared_length != length:
        raise ProductError("fits_mismatch", f"the label's Header object_length {declared_length} "
                           f"is not the {length} bytes of the FITS header of {data_path.name}")
    _check_fits(cards, layout, data_type=data_type, lines=lines, samples=samples,
                data_start=start + length, name=data_path.name)
    return layout, {c.keyword: c.value for c in cards.cards
                    if c.keyword not in ("", "COMMENT", "HISTORY")}


def _fits_header_at(area: ET.Element, data_path: Path, array_offset: int
                    ) -> tuple[int, int | None] | None:
    """Where the FITS header the array follows starts, and the length the label declares for
    it: the label's last FITS Header before the array or, where it declares none, the primary
    header of a file that starts as FITS does (a label cannot hide it by leaving it out). None
    for a plain binary array. An array in an extension HDU needs its Header declared."""
    declared = [(_int(h, "pds:offset"), _int(h, "pds:object_length"))
                for h in area.findall("pds:Header", _NS)
                if "FITS" in (_text(h, "pds:parsing_standard_id", False) or "")]
    if before := [(offset, length) for offset, length in declared if offset <= array_offset]:
        return max(before)
    with open(data_path, "rb") as fh:
        return (0, None) if fh.read(len(_FITS_SIGNATURE)) == _FITS_SIGNATURE else None


def _read_fits_header(data_path: Path, offset: int, max_bytes: int) -> tuple[fits.Header, int]:
    """The FITS header at `offset` and its length, read a block at a time up to its END card:
    ProductError (too_large) rather than read past max_bytes, bad_header when it is no FITS
    header (no END before the end of the file, not ASCII, not block-aligned)."""
    if offset < 0 or offset % FITS_BLOCK:
        raise ProductError("bad_header", f"a FITS header starts on a {FITS_BLOCK}-byte block, "
                           f"not at byte {offset} of {data_path.name}")
    blocks: list[bytes] = []
    with open(data_path, "rb") as fh:
        fh.seek(offset)
        while not blocks or not _ends_header(blocks[-1]):
            if (len(blocks) + 1) * FITS_BLOCK > max_bytes:
                raise ProductError("too_large", f"the FITS header of {data_path.name} runs past "
                                   f"{len(blocks) * FITS_BLOCK} bytes with no END card, more "
                                   f"than the {max_bytes} a header may have")
            block = fh.read(FITS_BLOCK)
            if len(block) < FITS_BLOCK:
                raise ProductError("bad_header", f"the FITS header of {data_path.name} has no "
                                   "END card before the end of the file")
            blocks.append(block)
    raw = b"".join(blocks)
    try:
        return fits.Header.fromstring(raw.decode("ascii")), len(raw)
    except (UnicodeDecodeError, ValueError) as exc:
        raise ProductError("bad_header", f"FITS header of {data_path.name} unreadable") from exc


def _ends_header(block: bytes) -> bool:
    return any(block[i:i + _FITS_CARD] == _FITS_END for i in range(0, len(block), _FITS_CARD))


def _check_fits(cards: fits.Header, layout: ArrayLayout, *, data_type: str, lines: int,
                samples: int, data_start: int, name: str) -> None:
    """Check everything the FITS header says of its array against the label: a label that
    misdescribes it would have its pixels byte-swapped, shifted or scaled wrongly, or header
    text read as pixels."""
    first = cards.cards[0] if len(cards) else None
    if first is None or (first.keyword, first.value) not in (("SIMPLE", True), ("XTENSION", "IMAGE")):
        raise ProductError("bad_header", f"{name}: the Header is not a FITS primary or IMAGE "
                           "extension header")
    dtype = np.dtype(layout.dtype)
    declared = {"BITPIX": _fits_bitpix(dtype), "NAXIS": 2, "NAXIS1": samples, "NAXIS2": lines}
    found = {key: cards.get(key) for key in declared}
    if found != declared:
        differ = ", ".join(f"{k} {found[k]} (label: {v})" for k, v in declared.items()
                           if found[k] != v)
        raise ProductError("bad_dimensions", f"the FITS header of {name} disagrees with the "
                           f"label's {lines}x{samples} {data_type} array: {differ}")
    bitpix = declared["BITPIX"]
    if (stored := _FITS_DTYPES[bitpix]) != dtype:  # the same size, another sign or byte order
        endian = " (FITS arrays are big-endian)" if stored.newbyteorder("<") == dtype else ""
        raise ProductError("fits_mismatch", f"the FITS header of {name} says BITPIX {bitpix}, "
                           f"a big-endian {stored.name} array, not the label's {data_type}{endian}")
    if layout.offset != data_start:
        raise ProductError("fits_mismatch", f"the label puts the array of {name} at byte "
                           f"{layout.offset}, but its FITS header ends at byte {data_start}, "
                           "where the data starts")
    _check_fits_scaling(cards, layout, integer=bitpix > 0, name=name)


def _check_fits_scaling(cards: fits.Header, layout: ArrayLayout, *, integer: bool, name: str
                        ) -> None:
    """BSCALE and BZERO equal to the label's scaling (to a millionth of BSCALE, and a
    thousandth of a stored unit for BZERO: headers and labels print numbers to other
    precisions), and an integer array's BLANK among the label's special constants (else its
    pixels would be read as signal)."""
    bscale, bzero = (_card_number(cards, key, default, name) for key, default in
                     (("BSCALE", 1.0), ("BZERO", 0.0)))
    if not math.isclose(bscale, layout.scaling_factor, rel_tol=1e-6):
        raise ProductError("fits_mismatch", f"the FITS header of {name} says BSCALE {bscale}, "
                           f"the label scaling_factor {layout.scaling_factor}")
    if not math.isclose(bzero, layout.value_offset, rel_tol=1e-9,
                        abs_tol=1e-3 * abs(layout.scaling_factor)):
        raise ProductError("fits_mismatch", f"the FITS header of {name} says BZERO {bzero}, "
                           f"the label value_offset {layout.value_offset}")
    if integer and "BLANK" in cards:
        blank = _card_number(cards, "BLANK", 0, name)
        if blank not in layout.special_constants:
            raise ProductError("fits_mismatch", f"the FITS header of {name} says BLANK {blank}, "
                               "a value no special constant of the label flags")


def _card_number(cards: fits.Header, key: str, default: float, name: str) -> float:
    value = cards.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ProductError("bad_header", f"the FITS header of {name} has {key} = {value!r}, "
                           "not a finite number")
    return float(value)


def read_array(label: ImageLabel) -> ImageProduct:
    """The product of a checked label with its array read: physical values as float64, NaN
    where a special constant flags a pixel. Read straight from the data file at the layout the
    label was checked for (pds4_tools would parse the label again, in time that grows with the
    square of its size). ProductError for an array with no valid pixel or an infinite one
    (_check_finite)."""
    layout = label.layout
    count = label.lines * label.samples
    try:
        with open(label.data_path, "rb") as fh:
            fh.seek(layout.offset)
            stored = np.fromfile(fh, dtype=np.dtype(layout.dtype), count=count)
    except (OSError, ValueError) as exc:
        raise ProductError("unreadable", f"{label.data_path.name}: {exc}") from exc
    if stored.size != count:
        raise ProductError("bad_dimensions", f"{label.data_path.name} holds {stored.size} of the "
                           f"{count} values its label declares")
    stored = stored.reshape(label.lines, label.samples)
    data = stored.astype(np.float64)
    if (layout.scaling_factor, layout.value_offset) != (1.0, 0.0):
        data *= layout.scaling_factor
        data += layout.value_offset
    if layout.special_constants:
        # compared in the array's own type: a float32 constant is not the double it was read as
        constants = np.asarray(layout.special_constants).astype(stored.dtype)
        data[np.isin(stored, constants)] = np.nan
    _check_finite(data, label.data_path.name)
    fields = {f.name: getattr(label, f.name) for f in dataclasses.fields(ImageLabel)}
    return ImageProduct(**fields, data=data)


def _check_finite(data: np.ndarray, name: str) -> None:
    """NaN is how FITS marks a missing floating-point pixel, and a calibrated product may hold
    many (off the detector's valid area, or where a special constant flags them): kept, as long
    as one pixel is valid. No convention makes an infinite pixel missing, and a radiance or DN
    is never infinite: one there, stored or made by the scaling, says the array is not what the
    label describes (or holds a flag the label does not declare)."""
    finite = np.isfinite(data)
    if finite.all():
        return
    if infinite := int(np.isinf(data).sum()):
        raise ProductError("non_finite", f"{name}: {infinite} infinite pixel values that no "
                           "special constant flags")
    if not finite.any():
        raise ProductError("no_valid_pixels", f"{name}: every pixel is NaN or flagged by a "
                           "special constant; the image holds no data")


def read_image_product(label: Path, *, root: Path | None = None,
                       max_label_bytes: int = MAX_LABEL_BYTES, max_pixels: int = MAX_PIXELS,
                       max_fits_header_bytes: int = MAX_FITS_HEADER_BYTES) -> ImageProduct:
    """Read a Product_Observational with one Array_2D_Image: its label (read_image_label), then
    its array."""
    return read_array(read_image_label(label, root=root, max_label_bytes=max_label_bytes,
                                       max_pixels=max_pixels,
                                       max_fits_header_bytes=max_fits_header_bytes))


def read_image_label(label: Path, *, root: Path | None = None,
                     max_label_bytes: int = MAX_LABEL_BYTES, max_pixels: int = MAX_PIXELS,
                     max_fits_header_bytes: int = MAX_FITS_HEADER_BYTES) -> ImageLabel:
    """Read and check a Product_Observational with one Array_2D_Image without reading its array:
    the data file's size and md5 (where the label declares them), the array's extent, type and
    scaling, and all that a FITS header it follows says of it. Nothing is read past
    max_label_bytes of label or max_fits_header_bytes of FITS header, and an array of more than
    max_pixels is refused before it is read. Elements that say what the product is or where and
    how its array lies must each appear once. The label and its data file must resolve
    (symbolic links followed) inside `root` (default: the label's directory)."""
    label = Path(label)
    within = (Path(root) if root is not None else label.parent).resolve()
    if not label.resolve().is_relative_to(within):
        raise ProductError("outside_downlink", f"{label.name} resolves to {label.resolve()}, "
                           f"outside {within}")
    if (label_bytes := label.stat().st_size) > max_label_bytes:
        raise ProductError("too_large", f"{label.name} is {label_bytes} bytes, more than the "
                           f"{max_label_bytes} a label may have")
    try:
        # parsed from one buffer: fed in chunks, expat rescans a long token at every chunk
        root_element = ET.fromstring(label.read_bytes())
    except ET.ParseError as exc:
        raise ProductError("malformed_xml", f"{label.name} is not well-formed XML: {exc}") from exc
    return _image_label(label, root_element, within, max_pixels=max_pixels,
                        max_fits_header_bytes=max_fits_header_bytes)


def _image_label(label: Path, root: ET.Element, within: Path, *, max_pixels: int,
                 max_fits_header_bytes: int) -> ImageLabel:
    kind = root.tag.rpartition("}")[2]
    areas = [a for a in root if a.tag.rpartition("}")[2].startswith("File_Area")]
    objects = sorted({o.tag.rpartition("}")[2] for a in areas for o in a} - {"File"})
    images = [a for a in root.findall("pds:File_Area_Observational", _NS)
              if a.find("pds:Array_2D_Image", _NS) is not None]
    if kind != "Product_Observational" or not images:
        what = f"{kind} with {', '.join(objects) or 'no data objects'}"
        raise ProductError("not_image", f"{label.name} is a {what}, not a Product_Observational "
                           "with an Array_2D_Image")
    area = images[0]
    if len(images) > 1 or len(area.findall("pds:Array_2D_Image", _NS)) > 1:
        raise ProductError("unsupported", f"{label.name} holds more than one Array_2D_Image")
    numbered = [(_int(a, "pds:sequence_number"), a)
                for a in area.findall("pds:Array_2D_Image/pds:Axis_Array", _NS)]
    if len({n for n, _ in numbered}) < len(numbered):
        raise ProductError("duplicate_element", f"{label.name}: two Axis_Array elements share "
                           "a sequence_number")
    axes = [a for _, a in sorted(numbered, key=lambda pair: pair[0])]
    if [(_text(a, "pds:axis_name") or "").lower() for a in axes] != ["line", "sample"]:
        raise ProductError("unsupported", f"{label.name}: axes are not Line, Sample")
    if (declared := _int(area, "pds:Array_2D_Image/pds:axes", False)) not in (None, 2):
        raise ProductError("bad_dimensions", f"{label.name}: an Array_2D_Image of {declared} axes")
    lines, samples = (_int(a, "pds:elements") for a in axes)

    file_name = _text(area, "pds:File/pds:file_name")
    if Path(file_name).name != file_name:
        raise ProductError("bad_file_name", f"file_name {file_name!r} is not a bare file name")
    data_path = label.parent / file_name
    size = _int(area, "pds:File/pds:file_size", False)
    md5 = _text(area, "pds:File/pds:md5_checksum", False)
    check_data_file(data_path, within, size, md5)
    layout, fits_header = _check_array(area, data_path, lines, samples, max_pixels=max_pixels,
                                       max_fits_header_bytes=max_fits_header_bytes)

    obs = _one(root, "pds:Observation_Area")
    if obs is None:
        raise ProductError("missing_element", f"{label.name} lacks Observation_Area")
    return ImageLabel(
        lid=_text(root, "pds:Identification_Area/pds:logical_identifier"),
        vid=_text(root, "pds:Identification_Area/pds:version_id"),
        title=_text(root, "pds:Identification_Area/pds:title"),
        start_utc=_text(obs, "pds:Time_Coordinates/pds:start_date_time"),
        stop_utc=_text(obs, "pds:Time_Coordinates/pds:stop_date_time"),
        mission=_text(obs, "pds:Investigation_Area/pds:name", False, repeatable=True),
        # older labels (IM < 1.9) call the host "Spacecraft"
        host_name=_component(obs, ("Host", "Spacecraft")),
        instrument_name=_component(obs, ("Instrument",)),
        target_name=_text(obs, "pds:Target_Identification/pds:name", False, repeatable=True),
        target_type=_text(obs, "pds:Target_Identification/pds:type", False, repeatable=True),
        exposure_s=_exposure_s(obs),
        first_line=_subframe_start(obs, "first_line"), first_sample=_subframe_start(obs, "first_sample"),
        data_path=data_path, file_size=size, md5=md5,
        lines=lines, samples=samples, fits_header=fits_header, label_path=label, layout=layout)


def _exposure_s(obs: ET.Element) -> float | None:
    """img:exposure_duration in seconds, None without one; ProductError unless a finite,
    non-negative number in a PDS4 time unit."""
    exposure = _one(obs, ".//img:exposure_duration")
    if exposure is None:
        return None
    if (unit := exposure.get("unit")) is None or unit not in _SECONDS:
        raise ProductError("unsupported", f"exposure_duration unit {unit!r}")
    try:
        value = float(exposure.text or "")
    except ValueError:
        raise ProductError("bad_value", f"img:exposure_duration {exposure.text!r} is not a "
                           "number") from None
    if not np.isfinite(value) or value < 0:
        raise ProductError("bad_value", f"img:exposure_duration {value} is not a finite, "
                           "non-negative duration")
    return value * _SECONDS[unit]


def _subframe_start(obs: ET.Element, name: str) -> int:
    """Zero-based detector offset from img:Subframe (1-based there), 0 without one."""
    element = _one(obs, f".//img:Subframe/img:{name}")
    if element is None:
        return 0
    try:
        value = int(element.text or "")
    except ValueError:
        raise ProductError("bad_value", f"img:{name} {element.text!r} is not an integer") from None
    if value < 1:
        raise ProductError("bad_value", f"img:{name} {value} is not a 1-based line/sample number")
    return value - 1
