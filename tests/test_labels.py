"""Resolving what labels name against the kernels (pwm.io.labels): the rules ingest and the
downlink reader share, on the real OSIRIS-REx and Hayabusa2 frames and instrument kernels."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pwm.io.labels import (
    exposure_times,
    frame_of,
    instrument_code,
    instrument_named,
    known_instruments,
    name_variants,
    observer_code,
    target_frame,
)
from pwm.io.pds4 import ArrayLayout, ImageProduct, ProductError
from pwm.io.spice_kernels import BUNDLED_DIR, kernel_pool
from pwm.simulate.missions import MISSIONS

PRODUCT = ImageProduct(
    lid="urn:test:x", vid="1.0", title="t", start_utc="2018-10-01T00:00:00.000Z", stop_utc="2018-10-01T00:00:00.004Z",
    mission=None, host_name=None, instrument_name=None, target_name=None, target_type=None, exposure_s=0.004,
    first_line=0, first_sample=0, data_path=Path("x.fits"), file_size=None, md5=None, lines=1, samples=1,
    data=np.zeros((1, 1)), fits_header=None, label_path=Path("x.xml"),
    layout=ArrayLayout(">i2", 0, 1.0, 0.0, ()))


def label(**fields) -> ImageProduct:
    return dataclasses.replace(PRODUCT, **fields)


@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    """The bundled OSIRIS-REx and Hayabusa2 kernels together, with the Ryugu constants and frame
    the simulator writes."""
    written = MISSIONS["hayabusa2"].write_kernels(tmp_path_factory.mktemp("kernels"))
    names = dict.fromkeys([*MISSIONS["osiris-rex"].kernels, *MISSIONS["hayabusa2"].kernels])
    with kernel_pool([BUNDLED_DIR / n for n in names] + written):
        yield


def test_name_variants_cover_how_labels_write_names():
    assert name_variants("(101955) Bennu") == ["(101955) Bennu", "(101955) BENNU", "(101955)_BENNU", "BENNU",
                                               "101955 BENNU"]
    assert "ONC_T" in name_variants(" onc-t ") and "ONC-T" in name_variants("onc-t")
    assert name_variants("Hayabusa 2") == ["Hayabusa 2", "HAYABUSA 2", "HAYABUSA_2"]


@pytest.mark.parametrize(("instrument", "host", "fits", "expected"), [
    ("ORX_OCAMS_MAPCAM", "OSIRIS-REx", None, -64361),  # the kernel's own name
    ("MapCam", "OSIRIS-REx", None, -64361),  # the one instrument of the host whose name ends in _MAPCAM
    ("ONC-T", "HAYABUSA2", None, -37100),  # the host's name as a prefix
    ("onc-w1", "Hayabusa2", None, -37110),  # any case
    (None, "HAYABUSA2", "ONC-W2", -37120),  # the FITS header's INSTRUME where the label names none
    ("TIR", "Hayabusa2", None, None),  # the kernels call it HAYABUSA2_TIR-S: no rule reaches it
    ("AMICA", "HAYABUSA2", None, None),  # another mission's camera
])
def test_instrument_names_resolve_in_their_spellings(pool, instrument, host, fits, expected):
    header = None if fits is None else {"INSTRUME": fits}
    product = label(instrument_name=instrument, host_name=host, fits_header=header)
    assert instrument_code(product, observer_code(host)) == expected


def test_an_instrument_of_another_spacecraft_is_not_the_hosts(pool):
    assert observer_code("OSIRIS-REx") == -64 and observer_code("Hayabusa2") == -37
    assert instrument_code(label(instrument_name="ORX_OCAMS_MAPCAM"), -37) is None
    assert observer_code(None) is None and observer_code("  ") is None and observer_code("PWM-NO-SUCH") is None


def test_targets_resolve_to_their_body_fixed_frame(pool):
    assert target_frame("(101955) Bennu") == (2101955, "IAU_BENNU")
    assert target_frame("(162173) Ryugu") == (2162173, "RYUGU_FIXED")
    assert target_frame("1999JU3") == (2162173, "RYUGU_FIXED")  # the FK's other name for Ryugu
    # SPICE knows Mathilde by name, but no kernel here gives it a frame
    assert target_frame("(253) Mathilde") == (2000253, None) and frame_of(2000253) is None
    assert target_frame("PWM no such body") == (None, None) and target_frame(None) == (None, None)


def test_instruments_given_by_a_person_resolve_or_list_what_the_kernels_define(pool):
    assert instrument_named("-37100") == -37100
    assert instrument_named("hayabusa2_onc-t") == -37100
    assert instrument_named("ORX_OCAMS_MAPCAM") == -64361
    defined = dict(known_instruments())
    expected = {-37100: "HAYABUSA2_ONC-T", -37110: "HAYABUSA2_ONC-W1", -64361: "ORX_OCAMS_MAPCAM"}
    assert expected.items() <= defined.items()
    with pytest.raises(ValueError, match=r"AMICA.*HAYABUSA2_ONC-T \(-37100\)"):
        instrument_named("AMICA")
    with pytest.raises(ValueError, match="not a NAIF instrument"):
        instrument_named("RYUGU")  # a body, not an instrument


@pytest.mark.parametrize(("start", "stop", "why"), [
    ("2018-13-01T00:00:00Z", "2018-13-01T00:00:01Z", "not a PDS4 UTC date_time"),
    ("2018-10-01T00:00:00+02:00", "2018-10-01T00:00:01+02:00", "not UTC"),
    ("2018-10-01T00:00:01Z", "2018-10-01T00:00:00Z", "precedes"),
])
def test_bad_exposure_times_are_bad_time(start, stop, why):
    with pytest.raises(ProductError, match=why) as caught:
        exposure_times(label(start_utc=start, stop_utc=stop))
    assert caught.value.code == "bad_time"
    start_dt, stop_dt = exposure_times(label(start_utc="2018-274T00:00:00.000Z", stop_utc="2018-10-01T00:00:01Z"))
    assert (stop_dt - start_dt).total_seconds() == 1.0
