"""pwm.voxels: lattice keys, and the corners of a set of cells found in key space."""

from __future__ import annotations

import numpy as np
import pytest

from pwm.voxels import corners, pack, unpack


def test_the_corners_of_cells_are_each_cells_eight_once() -> None:
    rng = np.random.default_rng(4)
    cells = np.unique(pack(rng.integers(-40, 40, size=(3000, 3))))
    expected = np.unique(pack((unpack(cells)[:, None, :] + np.array(
        [[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])[None]).reshape(-1, 3)))
    np.testing.assert_array_equal(corners(cells), expected)
    assert len(corners(np.empty(0, dtype=np.int64))) == 0
    # a cell at the top of the keys' reach on any axis has corners beyond it
    for axis in range(3):
        top = np.zeros((1, 3), np.int64)
        top[0, axis] = (1 << 20) - 1
        with pytest.raises(ValueError, match="voxel_km too small"):
            corners(pack(top))
        top[0, axis] -= 1
        assert len(corners(pack(top))) == 8


def test_keys_round_trip_and_refuse_what_they_cannot_hold() -> None:
    index = np.array([[-5, 0, 7], [1_000_000, -1_000_000, 3]])
    np.testing.assert_array_equal(unpack(pack(index)), index)
    with pytest.raises(ValueError, match="voxel_km too small"):
        pack(np.array([[2_000_000, 0, 0]]))
