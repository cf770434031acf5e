"""Hostile PDS4 products (issue 44): labels that misdescribe their FITS array, FITS headers too
large to read, arrays of inf or NaN, complex types, special constants a type cannot hold,
duplicate elements; and leap seconds, which PDS4 allows."""

from __future__ import annotations

import hashlib
import re
import tracemalloc
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
import spiceypy as sp
from astropy.io import fits

from pwm.io.labels import exposure_et, exposure_times, parse_utc
from pwm.io.pds4 import MISSING_DN, ProductError, read_image_label, read_image_product, write_image_product
from pwm.io.spice_kernels import kernel_pool

SCALE, OFFSET = 2.0e-5, 0.1
META = dict(lid="urn:nasa:pds:orex.ocams:data_raw:hostile", vid="1.0",
            start_utc="2019-03-03T10:59:40.279Z", stop_utc="2019-03-03T10:59:40.289Z",
            mission="OSIRIS-REx", host_name="OSIRIS-REx", instrument_name="MapCam",
            target_name="(101955) Bennu", title="hostile", exposure_s=0.01)
LINES, SAMPLES = 40, 60
HEADER = 2880  # the written product's header: one FITS block


@pytest.fixture
def dn() -> np.ndarray:
    values = np.random.default_rng(3).integers(100, 30000, size=(LINES, SAMPLES)).astype(np.int16)
    values[2, 3] = MISSING_DN
    return values


@pytest.fixture
def product(tmp_path: Path, dn: np.ndarray) -> tuple[Path, Path]:
    return write_image_product(directory=tmp_path, basename="hostile", dn=dn, scaling_factor=SCALE,
                               value_offset=OFFSET, **META)


def _edit(label: Path, old: str, new: str) -> None:
    text = label.read_text()
    assert old in text, old
    label.write_text(text.replace(old, new, 1))


def _sub(label: Path, pattern: str, new: str) -> None:
    text, count = re.subn(pattern, new, label.read_text(), count=1)
    assert count == 1, pattern
    label.write_text(text)


def _replace_data(label: Path, data_file: Path, raw: bytes, *, header_bytes: int | None = None) -> None:
    """Write `raw` as the data file, with the label's size and md5 (and, given, the FITS header's
    length and the array's offset after it) following, so that only what a test means differs."""
    data_file.write_bytes(raw)
    _sub(label, r'<file_size unit="byte">\d+<', f'<file_size unit="byte">{len(raw)}<')
    _sub(label, r"<md5_checksum>\w+<", f"<md5_checksum>{hashlib.md5(raw).hexdigest()}<")
    if header_bytes is not None:
        _sub(label, r'<object_length unit="byte">\d+<', f'<object_length unit="byte">{header_bytes}<')
        _sub(label, r'(<Array_2D_Image>\s*<offset unit="byte">)\d+<', rf"\g<1>{header_bytes}<")


def _fits(data: np.ndarray, **cards) -> tuple[bytes, int]:
    """A primary HDU of `data` (stored big-endian as given, cards written as given) and its
    header's length."""
    bitpix = (-8 if data.dtype.kind == "f" else 8) * data.dtype.itemsize
    header = fits.Header([("SIMPLE", True), ("BITPIX", bitpix), ("NAXIS", 2),
                          ("NAXIS1", data.shape[1]), ("NAXIS2", data.shape[0])])
    for key, value in cards.items():
        header[key] = value
    text = header.tostring().encode("ascii")
    body = data.astype(data.dtype.newbyteorder(">")).tobytes()
    return text + body + b"\0" * (-len(body) % 2880), len(text)


def _float_product(label: Path, data_file: Path, data: np.ndarray) -> None:
    """The product made a float32 image of `data`, with no scaling in label or header."""
    raw, header_bytes = _fits(data.astype(np.float32))
    _replace_data(label, data_file, raw, header_bytes=header_bytes)
    _edit(label, "SignedMSB2", "IEEE754MSBSingle")
    _sub(label, r"<scaling_factor>[^<]*</scaling_factor>", "")
    _sub(label, r"<value_offset>[^<]*</value_offset>", "")
    _sub(label, r"(?s)<Special_Constants>.*</Special_Constants>", "")


def _rejected(label: Path, code: str, match: str | None = None) -> ProductError:
    with pytest.raises(ProductError, match=match) as caught:
        read_image_product(label)
    assert caught.value.code == code, caught.value
    return caught.value


def test_the_unedited_product_reads(product, dn):
    label, _ = product
    image = read_image_product(label)
    assert np.isnan(image.data[2, 3]) and image.data[0, 0] == pytest.approx(dn[0, 0] * SCALE + OFFSET)


# -- a label that misdescribes its FITS array ------------------------------------------------

def test_little_endian_label_over_a_big_endian_fits_array(product):
    """Every pixel byte-swapped, and the old reader believed it."""
    label, _ = product
    _edit(label, "SignedMSB2", "SignedLSB2")
    _rejected(label, "fits_mismatch", "big-endian")


def test_unsigned_label_over_a_signed_fits_array(product):
    label, _ = product
    _edit(label, "SignedMSB2", "UnsignedMSB2")
    # -32768 is no UnsignedMSB2 value: without the constant, the type itself is refused
    _rejected(label, "bad_special_constant", "UnsignedMSB2")
    _sub(label, r"(?s)<Special_Constants>.*</Special_Constants>", "")
    _rejected(label, "fits_mismatch", "BITPIX 16")


def test_bitpix_that_disagrees_with_the_data_type(product):
    label, data_file = product
    raw = data_file.read_bytes()
    bitpix = b"BITPIX  =                   16"
    assert raw.count(bitpix) == 1
    # a label saying SignedMSB2 over what the header says are bytes (refused before issue 44)
    _replace_data(label, data_file, raw.replace(bitpix, b"BITPIX  =                    8"))
    _rejected(label, "bad_dimensions", r"BITPIX 8 \(label: 16\)")


@pytest.mark.parametrize("offset", [1440, HEADER - 2, HEADER + 2], ids=["in_header", "two_before", "two_past"])
def test_array_offset_other_than_the_headers_end(product, offset):
    """Header text read as pixels, or the image shifted by one pixel."""
    label, _ = product
    _edit(label, f'<offset unit="byte">{HEADER}<', f'<offset unit="byte">{offset}<')
    _rejected(label, "fits_mismatch", f"ends at byte {HEADER}")


def test_header_length_that_disagrees_with_the_fits_header(product):
    label, _ = product
    _edit(label, f'<object_length unit="byte">{HEADER}<', f'<object_length unit="byte">{2 * HEADER}<')
    _rejected(label, "fits_mismatch", "object_length")


@pytest.mark.parametrize("old, new, what", [
    (f"<scaling_factor>{SCALE!r}<", "<scaling_factor>3e-05<", "BSCALE"),
    (f"<value_offset>{OFFSET!r}<", "<value_offset>0.2<", "BZERO"),
    (f"<value_offset>{OFFSET!r}</value_offset>", "", "BZERO"),  # the label's default of 0
])
def test_scaling_that_disagrees_with_bscale_bzero(product, old, new, what):
    label, _ = product
    _edit(label, old, new)
    _rejected(label, "fits_mismatch", what)


def test_blank_the_label_does_not_flag(product):
    """FITS BLANK pixels would be read as -32768 DN of signal."""
    label, _ = product
    _sub(label, r"(?s)<Special_Constants>.*</Special_Constants>", "")
    _rejected(label, "fits_mismatch", "BLANK")


def test_fits_file_without_a_declared_header_is_still_checked(product):
    """A label that omits the Header cannot hide the FITS header it sits behind."""
    label, _ = product
    _sub(label, r"(?s)<Header>.*</Header>", "")
    read_image_product(label)  # consistent: the primary header, found by its signature
    _edit(label, f'<offset unit="byte">{HEADER}<', f'<offset unit="byte">{HEADER + 2}<')
    _rejected(label, "fits_mismatch")


# -- arrays of inf and NaN, complex types, special constants ---------------------------------

def test_float_image_with_some_nan_reads_nan_as_missing(product):
    """FITS marks undefined floating-point pixels NaN: a calibrated product may hold them."""
    label, data_file = product
    data = np.linspace(0.0, 1.0, LINES * SAMPLES).reshape(LINES, SAMPLES)
    data[:20] = np.nan
    _float_product(label, data_file, data)
    image = read_image_product(label)
    np.testing.assert_array_equal(np.isnan(image.data), np.isnan(data))
    np.testing.assert_allclose(image.data[20:], data[20:], rtol=1e-7)


@pytest.mark.parametrize("fill, code", [
    (np.inf, "non_finite"), (-np.inf, "non_finite"), (np.nan, "no_valid_pixels")],
    ids=["all_inf", "all_minus_inf", "all_nan"])
def test_float_image_of_inf_or_nan_only(product, fill, code):
    label, data_file = product
    _float_product(label, data_file, np.full((LINES, SAMPLES), fill))
    _rejected(label, code)


def test_one_undeclared_inf_rejects_the_image(product):
    label, data_file = product
    data = np.ones((LINES, SAMPLES))
    data[7, 9] = np.inf
    _float_product(label, data_file, data)
    _rejected(label, "non_finite", "1 infinite")


def test_all_pixels_flagged_missing(product, dn):
    label, data_file = product
    raw = data_file.read_bytes()
    missing = np.full_like(dn, MISSING_DN).astype(">i2").tobytes()
    _replace_data(label, data_file, raw[:HEADER] + missing + raw[HEADER + len(missing):])
    _rejected(label, "no_valid_pixels")


def test_complex_array(product, tmp_path):
    """A plain binary (not FITS) array of complex values: its imaginary part would be dropped."""
    label, data_file = product
    values = (np.arange(LINES * SAMPLES) * (1 + 1j)).astype(">c8")
    _sub(label, r"(?s)<Header>.*</Header>", "")
    _replace_data(label, data_file, values.tobytes())
    _edit(label, f'<offset unit="byte">{HEADER}<', '<offset unit="byte">0<')
    _edit(label, "SignedMSB2", "ComplexMSB8")
    _rejected(label, "unsupported", "complex")


@pytest.mark.parametrize("constant", ["40000", "-40000", "1.5", "0x10000"])
def test_special_constant_the_data_type_cannot_hold(product, constant):
    label, _ = product
    _edit(label, "<missing_constant>", f"<saturated_constant>{constant}</saturated_constant><missing_constant>")
    _rejected(label, "bad_special_constant", "SignedMSB2")


def test_special_constants_of_a_float_array_are_matched_in_its_type(product):
    """-3.4028235E38 read as a double is not the float32 the array holds: matched in float32,
    it flags the pixel; the hexadecimal form is the value's bit pattern."""
    label, data_file = product
    data = np.ones((LINES, SAMPLES), dtype=np.float32)
    data[1, 1] = np.finfo(np.float32).min
    data[2, 2] = np.float32(-1e32)
    _float_product(label, data_file, data)
    bits = f"0x{np.float32(-1e32).view(np.uint32):08X}"
    _edit(label, "</Element_Array>", "</Element_Array><Special_Constants><saturated_constant>"
          f"{bits}</saturated_constant><missing_constant>-3.4028235E38</missing_constant>"
          "</Special_Constants>")
    image = read_image_product(label)
    assert np.isnan(image.data).sum() == 2 and np.isnan(image.data[1, 1]) and np.isnan(image.data[2, 2])


def test_plain_binary_array_still_reads(product, dn):
    label, data_file = product
    _sub(label, r"(?s)<Header>.*</Header>", "")
    _replace_data(label, data_file, dn.astype("<i2").tobytes())
    _edit(label, f'<offset unit="byte">{HEADER}<', '<offset unit="byte">0<')
    _edit(label, "SignedMSB2", "SignedLSB2")  # no FITS header: the label alone says the order
    image = read_image_product(label)
    assert image.fits_header is None
    assert image.data[0, 0] == pytest.approx(dn[0, 0] * SCALE + OFFSET) and np.isnan(image.data[2, 3])


# -- FITS header size -----------------------------------------------------------------------

def _long_header_product(label: Path, data_file: Path, dn: np.ndarray, comment_cards: int) -> int:
    """The product with `comment_cards` COMMENT cards in its FITS header; the header's length."""
    raw = data_file.read_bytes()
    cards = [raw[i:i + 80] for i in range(0, HEADER, 80)]
    end = cards.index(b"END".ljust(80))
    comments = b"COMMENT " + b"padding " * 9
    header = b"".join(cards[:end]) + comments * comment_cards + b"END".ljust(80)
    header += b" " * (-len(header) % 2880)
    _replace_data(label, data_file, header + raw[HEADER:], header_bytes=len(header))
    return len(header)


def test_seventeen_megabyte_fits_header_refused_in_bounded_memory(product, dn):
    label, data_file = product
    length = _long_header_product(label, data_file, dn, 17 * 1024**2 // 80)
    assert length > 17 * 1024**2
    tracemalloc.start()
    try:
        with pytest.raises(ProductError, match="more than the 1048576") as caught:
            read_image_label(label)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert caught.value.code == "too_large"
    assert peak < 4 * 1024**2, f"{peak / 1024**2:.1f} MiB for a {length / 1024**2:.0f} MiB header"


def test_header_of_many_blocks_reads_within_its_bound(product, dn):
    label, data_file = product
    length = _long_header_product(label, data_file, dn, 200)  # six blocks
    image = read_image_product(label)
    assert length == 6 * 2880 and image.data[0, 0] == pytest.approx(dn[0, 0] * SCALE + OFFSET)
    with pytest.raises(ProductError, match="more than the 11520") as caught:
        read_image_label(label, max_fits_header_bytes=4 * 2880)
    assert caught.value.code == "too_large"


def test_fits_header_without_end(product, dn):
    label, data_file = product
    raw = data_file.read_bytes()
    _replace_data(label, data_file, raw[:HEADER].replace(b"END".ljust(80), b" " * 80))
    _sub(label, r'(<Array_2D_Image>\s*<offset unit="byte">)\d+<', r"\g<1>0<")
    _edit(label, "<elements>40<", "<elements>1<")
    _edit(label, "<elements>60<", "<elements>1<")
    _rejected(label, "bad_header", "END")


# -- duplicate elements ---------------------------------------------------------------------

@pytest.mark.parametrize("element", [
    "logical_identifier", "version_id", "start_date_time", "stop_date_time", "file_name",
    "data_type", "scaling_factor", "exposure_duration"])
def test_duplicate_element_is_rejected(product, element):
    """Read first-wins, a second value would be ignored by pwm and believed by another reader."""
    label, _ = product
    text = label.read_text()
    found = re.search(rf"(<(?:img:)?{element}\b[^>]*>)([^<]*)(</(?:img:)?{element}>)", text)
    assert found
    _edit(label, found[0], found[0] + found[1] + "1" + found[2] + found[3])
    _rejected(label, "duplicate_element", element)


def test_duplicate_axis_sequence_number(product):
    label, _ = product
    _edit(label, "<sequence_number>2<", "<sequence_number>1<")
    _rejected(label, "duplicate_element", "sequence_number")


def test_duplicate_array_offset(product):
    label, _ = product
    _edit(label, f'<offset unit="byte">{HEADER}</offset>',
          f'<offset unit="byte">{HEADER}</offset><offset unit="byte">1440</offset>')
    _rejected(label, "duplicate_element", "offset")


# -- leap seconds ---------------------------------------------------------------------------

def test_leap_second_is_the_first_instant_of_the_next_day():
    assert parse_utc("2016-12-31T23:59:60.500Z") == datetime(2017, 1, 1, tzinfo=UTC)
    assert parse_utc("2016-366T23:59:60.5") == datetime(2017, 1, 1, tzinfo=UTC)
    with pytest.raises(ProductError, match="not a PDS4 UTC") as caught:
        parse_utc("2016-12-31T12:00:60.5Z")  # only the day's last minute has a 61st second
    assert caught.value.code == "bad_time"


def test_product_starting_in_a_leap_second_is_accepted(product, shared_data):
    label, _ = product
    _edit(label, "2019-03-03T10:59:40.279Z</start", "2016-12-31T23:59:60.500Z</start")
    _edit(label, "2019-03-03T10:59:40.289Z</stop", "2017-01-01T00:00:00.100Z</stop")
    image = read_image_label(label)
    assert exposure_times(image) == (datetime(2017, 1, 1, tzinfo=UTC),
                                     datetime(2017, 1, 1, 0, 0, 0, 100000, tzinfo=UTC))
    with kernel_pool([shared_data / "spice" / "generic" / "naif0012.tls"]):
        start, stop = exposure_et(image)
        midnight = sp.str2et("2017-01-01T00:00:00")
    assert start == pytest.approx(midnight - 0.5, abs=1e-6)  # inside the leap second
    assert stop - start == pytest.approx(0.6, abs=1e-6)


def test_a_leap_second_the_leapseconds_kernel_does_not_have(product, shared_data):
    label, _ = product
    _edit(label, "2019-03-03T10:59:40.279Z</start", "2017-06-30T23:59:60.500Z</start")
    _edit(label, "2019-03-03T10:59:40.289Z</stop", "2017-07-01T00:00:00.800Z</stop")
    image = read_image_label(label)
    with kernel_pool([shared_data / "spice" / "generic" / "naif0012.tls"]), \
            pytest.raises(ProductError, match="has no leap second") as caught:
        exposure_et(image)
    assert caught.value.code == "bad_time"
