"""PDS4 lidar products (pwm.io.lidar): the plain layout written and read back, and hostile tables
refused with a code before anything large is read (OLA's layout: tests/test_lidar_simulate.py,
with the kernels its scan mirror needs)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from pwm.io.lidar import read_lidar_table, write_lidar_product
from pwm.io.pds4 import ProductError


def _product(directory: Path, n: int = 50, *, direction: bool = True) -> tuple[Path, dict]:
    rng = np.random.default_rng(5)
    d = rng.normal(size=(n, 3)) + [0.0, 0.0, 5.0]
    arrays = {"et": 6.0e8 + np.arange(n) * 0.1, "range_km": rng.uniform(0.5, 2.0, n),
              "flag": (np.arange(n) % 7 == 0).astype(int) * 2, "intensity": rng.uniform(0, 1, n),
              "direction": d / np.linalg.norm(d, axis=1, keepdims=True) if direction else None}
    label, _ = write_lidar_product(directory=directory, basename="shots", lid="urn:nasa:pds:test:shots",
                                   start_utc="2019-01-06T12:00:00", stop_utc="2019-01-06T12:00:05",
                                   mission="Test", host_name="TEST", instrument_name="PWM_LIDAR",
                                   target_name="Bennu", title="test shots", **arrays)
    return label, arrays


def test_the_plain_layout_round_trips(tmp_path: Path) -> None:
    label, arrays = _product(tmp_path)
    table = read_lidar_table(label)
    assert (table.layout, table.instrument, table.frames, table.lid) == ("pwm", "PWM_LIDAR", ("PWM_LIDAR",),
                                                                        "urn:nasa:pds:test:shots")
    np.testing.assert_array_equal(table.et, arrays["et"])
    np.testing.assert_array_equal(table.range_km, arrays["range_km"])
    np.testing.assert_array_equal(table.flagged, arrays["flag"] != 0)
    assert table.intensity is not None
    np.testing.assert_allclose(table.intensity, arrays["intensity"], rtol=1e-6)  # stored single precision
    np.testing.assert_array_equal(table.direction, arrays["direction"])
    # a profile's product has no directions: the reader takes the boresight
    profile, _ = _product(tmp_path / "profile", direction=False)
    assert read_lidar_table(profile).direction is None


def _relabel(label: Path, pattern: str, replacement: str) -> None:
    text, count = re.subn(pattern, replacement, label.read_text())
    assert count == 1
    label.write_text(text)


def test_hostile_tables_are_refused_with_a_reason(tmp_path: Path) -> None:
    label, _ = _product(tmp_path, n=40)
    data = tmp_path / "shots.dat"
    whole = data.read_bytes()
    # a truncated file: shorter than the label says
    data.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(ProductError) as err:
        read_lidar_table(label)
    assert err.value.code == "size_mismatch"
    # a table that claims more records than its file holds (no size or checksum to betray it)
    data.write_bytes(whole)
    _relabel(label, r"<file_size[^<]*</file_size>\s*<md5_checksum>[0-9a-f]+</md5_checksum>", "")
    _relabel(label, r"<records>40</records>", "<records>4000000000</records>")
    with pytest.raises(ProductError) as err:
        read_lidar_table(label, max_shots=10**10)
    assert err.value.code == "truncated"
    # more shots than a product may hold: refused before reading
    _relabel(label, r"<records>4000000000</records>", "<records>40</records>")
    assert len(read_lidar_table(label).et) == 40
    with pytest.raises(ProductError) as err:
        read_lidar_table(label, max_shots=39)
    assert err.value.code == "too_many_shots"
    # a field past the end of its record, an oversized label, and fields of no known layout
    _relabel(label, r"<field_location unit=\"byte\">9</field_location>",
             '<field_location unit="byte">999</field_location>')
    with pytest.raises(ProductError) as err:
        read_lidar_table(label)
    assert err.value.code == "bad_dimensions"
    with pytest.raises(ProductError) as err:
        read_lidar_table(label, max_label_bytes=100)
    assert err.value.code == "too_large"
    _relabel(label, r"<name>range_km</name>", "<name>altitude</name>")
    with pytest.raises(ProductError) as err:
        read_lidar_table(label)
    assert err.value.code == "unknown_layout"
