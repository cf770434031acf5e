"""PDS4 image products: write/read round trip, corrupted products, real archive products."""

import hashlib
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pds4_tools
import pytest
from astropy.io import fits

from pwm.io.pds4 import (
    MISSING_DN,
    PDS_NS,
    ProductError,
    checksum_md5,
    file_sha256,
    read_image_product,
    write_image_product,
)

SCALE, OFFSET = 2.0e-5, 0.1
META = dict(lid="urn:nasa:pds:orex.ocams:data_raw:20190303t105940s279_map_panl0", vid="2.0",
            start_utc="2019-03-03T10:59:40.279", stop_utc="2019-03-03T10:59:40.289Z",
            mission="OSIRIS-REx", host_name="OSIRIS-REx", instrument_name="MapCam <PAN & test>",
            target_name="(101955) Bennu", title="MapCam image of Bennu", exposure_s=0.0051)


@pytest.fixture
def truth() -> tuple[np.ndarray, np.ndarray]:
    """A physical image (reflectance-like, non-square to catch transposes) and its DN."""
    rng = np.random.default_rng(7)
    phys = rng.uniform(0.02, 0.7, size=(40, 60))
    dn = np.round((phys - OFFSET) / SCALE).astype(np.int16)
    dn[5, 7] = dn[39, 0] = MISSING_DN
    return phys, dn


@pytest.fixture
def product(tmp_path: Path, truth) -> tuple[Path, Path]:
    return write_image_product(directory=tmp_path, basename="20190303T105940S279_map_panL0",
                               dn=truth[1], scaling_factor=SCALE, value_offset=OFFSET,
                               extra_fits_header={"FILTER": ("PAN", "MapCam filter")}, **META)


def test_round_trip(product, truth):
    label, data_file = product
    phys, dn = truth
    image = read_image_product(label)
    missing = dn == MISSING_DN
    assert image.data.dtype == np.float64 and image.data.shape == (40, 60)
    assert (image.lines, image.samples) == (40, 60)
    np.testing.assert_array_equal(np.isnan(image.data), missing)
    assert np.max(np.abs(image.data[~missing] - phys[~missing])) <= SCALE / 2 * (1 + 1e-9)
    for key in ("lid", "vid", "title", "mission", "host_name", "instrument_name", "target_name"):
        assert getattr(image, key) == META[key], key
    assert (image.start_utc, image.stop_utc) == ("2019-03-03T10:59:40.279Z",
                                                 "2019-03-03T10:59:40.289Z")
    assert image.target_type == "Asteroid" and image.exposure_s == pytest.approx(0.0051)
    raw = data_file.read_bytes()
    assert image.data_path == data_file and image.file_size == len(raw)
    assert image.md5 == hashlib.md5(raw).hexdigest() == checksum_md5(data_file)
    assert image.fits_header["INSTRUME"] == META["instrument_name"]
    assert image.fits_header["FILTER"] == "PAN" and image.fits_header["BITPIX"] == 16
    assert image.fits_header["DATE-OBS"] == "2019-03-03T10:59:40.279"

    # The array sits big-endian right after the header the label declares.
    root = ET.parse(label).getroot()
    ns = {"pds": PDS_NS}
    assert root.tag == f"{{{PDS_NS}}}Product_Observational"
    header_len = int(root.find(".//pds:Header/pds:object_length", ns).text)
    assert header_len % 2880 == 0
    assert raw[header_len:header_len + dn.nbytes] == dn.astype(">i2").tobytes()
    text = label.read_text()
    assert "<?xml-model" in text and "PDS4_PDS_1E00.xsd" in text and "&amp;" in text

    structures = pds4_tools.read(str(label), quiet=True, no_scale=True)
    assert [s.type for s in structures] == ["Header", "Array_2D_Image"]
    np.testing.assert_array_equal(structures[1].data, dn)

    # A FITS reader applying BSCALE/BZERO/BLANK agrees (astropy scales to float32).
    with fits.open(data_file) as hdul:
        assert hdul[0].header["BITPIX"] == 16
        np.testing.assert_allclose(hdul[0].data, image.data, rtol=1e-6, equal_nan=True)


def test_write_refuses_bad_input(tmp_path, product, truth):
    base = dict(directory=tmp_path, scaling_factor=SCALE, value_offset=OFFSET, **META)
    with pytest.raises(FileExistsError):
        write_image_product(basename="20190303T105940S279_map_panL0", dn=truth[1], **base)
    with pytest.raises(ValueError, match="int16"):
        write_image_product(basename="float", dn=truth[0], **base)
    with pytest.raises(ValueError, match="structural"):
        write_image_product(basename="naxis", dn=truth[1], extra_fits_header={"naxis1": 3}, **base)
    with pytest.raises(ValueError, match="UTC"):
        write_image_product(basename="tz", dn=truth[1],
                            **(base | {"start_utc": "2019-03-03T10:00+02:00"}))


def _edit_label(label: Path, old: str, new: str) -> None:
    text = label.read_text()
    assert old in text
    label.write_text(text.replace(old, new, 1))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-100])


def _flip_byte(path: Path) -> None:
    raw = bytearray(path.read_bytes())
    raw[4000] ^= 0x01  # inside the array, after the 2880-byte header
    path.write_bytes(bytes(raw))


@pytest.mark.parametrize("corrupt, code", [
    (lambda label, data: label.write_text(label.read_text()[:500]), "malformed_xml"),
    (lambda label, data: data.unlink(), "missing_file"),
    (lambda label, data: _truncate(data), "size_mismatch"),
    (lambda label, data: _flip_byte(data), "md5_mismatch"),
    # 4000 lines run past the end of the file; 41 still fit in the FITS padding but disagree
    # with the FITS header's NAXIS2.
    (lambda label, data: _edit_label(label, "<elements>40<", "<elements>4000<"), "truncated"),
    (lambda label, data: _edit_label(label, "<elements>40<", "<elements>41<"), "bad_dimensions"),
    (lambda label, data: _edit_label(label, ".fits</file_name>", "/../x.fits</file_name>"),
     "bad_file_name"),
], ids=["broken_xml", "missing_file", "truncated", "flipped_byte", "array_past_eof",
        "naxis_disagrees", "path_in_file_name"])
def test_corrupted_products_are_rejected(product, corrupt, code):
    label, data_file = product
    corrupt(label, data_file)
    with pytest.raises(ProductError) as err:
        read_image_product(label)
    assert err.value.code == code
    assert isinstance(err.value, ValueError) and str(err.value)


def test_md5_checked_before_array(product):
    """A flipped byte is caught by the checksum even though the array still parses."""
    label, data_file = product
    _flip_byte(data_file)
    assert pds4_tools.read(str(label), quiet=True)[1].data.shape == (40, 60)
    with pytest.raises(ProductError, match="md5"):
        read_image_product(label)


@pytest.fixture(scope="module")
def pds4_data(shared_data) -> Path:
    return shared_data / "pds4"


def test_real_dart_mro_image(pds4_data):
    image = read_image_product(pds4_data / "dart_teleobs_mro" / "m221011.0013.xml")
    assert image.data.shape == (image.lines, image.samples) == (512, 512)
    # PROVENANCE.md: min 1466, max 19620 (4 significant figures)
    assert np.nanmin(image.data) == 1466 and abs(np.nanmax(image.data) - 19620) < 5
    with fits.open(image.data_path) as hdul:  # BZERO 32768 applied independently by astropy
        np.testing.assert_array_equal(hdul[0].data, image.data)
    assert image.lid == "urn:nasa:pds:dart_teleobs:data_mroraw:m221011.0013"
    assert image.start_utc == "2022-10-11T08:49:36.32Z"
    assert (image.host_name, image.instrument_name) == ("Magdalena Ridge Observatory (MRO)",
                                                        "MRO2K")
    assert image.exposure_s == 15.0 and image.file_size is None and image.md5 is None
    assert image.fits_header["NAXIS1"] == 512
    assert file_sha256(image.data_path) == (
        "0c668158ac0dfe7aa4dc490f56c516e6d4c7d48bcbc25696f5bba6597a7af3aa")


def test_real_hayabusa2_tir_image(pds4_data):
    image = read_image_product(pds4_data / "hyb2_tir" / "hyb2_tir_20180629_075501_l1.xml")
    assert image.data.shape == (256, 384)
    # PROVENANCE.md: min 235.8, max 3231
    assert np.nanmin(image.data) == pytest.approx(235.8, abs=0.06)
    assert np.nanmax(image.data) == pytest.approx(3231, abs=0.5)
    with fits.open(image.data_path) as hdul:
        np.testing.assert_array_equal(hdul[0].data, image.data)
    assert (image.mission, image.host_name, image.instrument_name) == ("Hayabusa2", "Hayabusa2",
                                                                        "TIR")
    assert (image.target_name, image.target_type) == ("(162173) Ryugu", "Asteroid")
    assert image.file_size == 400320 == image.data_path.stat().st_size


@pytest.mark.parametrize("label, names", [
    ("orex_tagcams_stowcam/20170303t022534s621_sto_l0.b.xml",
     ("Product_Ancillary", "Encoded_Image")),
    ("sbn_litcomp_comets/colors.xml", ("Product_Observational", "Table_Character")),
])
def test_real_non_images_are_rejected(pds4_data, label, names):
    with pytest.raises(ProductError) as err:
        read_image_product(pds4_data / label)
    assert err.value.code == "not_image"
    assert all(name in str(err.value) for name in names)


def test_raw_array_without_fits_header_reads_with_scaling_and_special_constants(product, truth, tmp_path):
    """The same image as a headerless raw array file (as many archives ship them)."""
    label, data_file = product
    phys, dn = truth
    with fits.open(data_file) as hdul:
        fits_len = hdul[0].fileinfo()["datLoc"]
    raw_file = tmp_path / "raw_copy.img"
    raw_file.write_bytes(data_file.read_bytes()[fits_len:])
    ns = {"pds": PDS_NS}
    ET.register_namespace("", PDS_NS)
    tree = ET.parse(label)
    area = tree.getroot().find("pds:File_Area_Observational", ns)
    area.remove(area.find("pds:Header", ns))
    area.find("pds:File/pds:file_name", ns).text = raw_file.name
    area.find("pds:File/pds:file_size", ns).text = str(raw_file.stat().st_size)
    area.find("pds:File/pds:md5_checksum", ns).text = hashlib.md5(raw_file.read_bytes()).hexdigest()
    area.find("pds:Array_2D_Image/pds:offset", ns).text = "0"
    raw_label = tmp_path / "raw_copy.xml"
    tree.write(raw_label, xml_declaration=True, encoding="utf-8")
    image = read_image_product(raw_label)
    assert image.fits_header is None and image.data.shape == dn.shape
    missing = dn == MISSING_DN
    np.testing.assert_array_equal(np.isnan(image.data), missing)
    assert np.max(np.abs(image.data[~missing] - phys[~missing])) <= SCALE / 2 * (1 + 1e-9)
