"""Sparse sums over a regular lattice of the body frame, the store of both fusions.

A lattice cell (or lattice point) is named by its integer index (i, j, k) along the body axes,
packed into one int64 key; sums are kept sorted by key with a count of contributions per key, so
that one maplet's contribution can be added, and later subtracted exactly, without touching the
rest (pwm.fusion.VoxelGrid, pwm.volume.DistanceGrid). Lengths in km.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from itertools import islice
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pwm.maplets import MapletGrid

_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_KEY_MASK = (1 << _KEY_BITS) - 1
_BATCH = 64


def _beyond_reach() -> ValueError:
    return ValueError(f"points beyond {_KEY_OFFSET} voxels of the body centre: voxel_km too small")


def pack(index: np.ndarray) -> np.ndarray:
    """int64 keys of (N, 3) integer lattice indices; ValueError beyond the keys' reach."""
    idx = np.asarray(index, dtype=np.int64) + _KEY_OFFSET
    if idx.min(initial=0) < 0 or idx.max(initial=0) > _KEY_MASK:
        raise _beyond_reach()
    return (idx[:, 0] << 2 * _KEY_BITS) | (idx[:, 1] << _KEY_BITS) | idx[:, 2]


def corners(cells: np.ndarray) -> np.ndarray:
    """Sorted unique keys of the corners of the lattice cells whose lowest corners are the keys
    `cells` (sorted, unique): the cells grown by one step up along each axis in turn, each step a
    merge of two sorted runs (a stable sort merges them in linear time). ValueError, as `pack`'s,
    where a cell's upper corner lies beyond the keys' reach (one step up would leave its field)."""
    keys = np.asarray(cells, dtype=np.int64)
    if any(((keys >> shift) & _KEY_MASK).max(initial=0) >= _KEY_MASK for shift in (0, _KEY_BITS, 2 * _KEY_BITS)):
        raise _beyond_reach()
    for step in (1, 1 << _KEY_BITS, 1 << 2 * _KEY_BITS):
        merged = np.concatenate([keys, keys + step])
        merged.sort(kind="stable")
        keys = merged[np.concatenate([[True], merged[1:] != merged[:-1]])] if len(merged) else merged
    return keys


def find(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Index of each key in sorted_keys (sorted, unique), -1 where it is not there."""
    if not len(sorted_keys):
        return np.full(len(keys), -1, dtype=np.int64)
    pos = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return np.where(sorted_keys[pos] == keys, pos, -1)


def unpack(keys: np.ndarray) -> np.ndarray:
    """(N, 3) lattice indices of keys made by `pack`."""
    keys = np.asarray(keys, dtype=np.int64)
    return np.column_stack([keys >> 2 * _KEY_BITS, (keys >> _KEY_BITS) & _KEY_MASK, keys & _KEY_MASK]) - _KEY_OFFSET


@dataclass
class SparseSums:
    """Sums (N, columns) per lattice key (sorted, int64) with the number of contributions to each;
    a key goes when its count drops to 0. Subclasses say what a maplet contributes
    (`_contribution`)."""

    voxel_km: float
    keys: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    sums: np.ndarray = field(default_factory=lambda: np.empty((0, 0)))
    count: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))

    def add(self, maplet: MapletGrid, weight_sign: int = +1) -> None:
        """Add the maplet's contribution (weight_sign=-1: remove it, see `subtract`)."""
        self.merge(*self._contribution(maplet), sign=weight_sign, name=f"maplet {maplet.name}")

    def subtract(self, maplet: MapletGrid) -> None:
        """Remove a maplet added earlier: the same revision (heights, albedo, weight) must be given."""
        self.add(maplet, weight_sign=-1)

    def add_all(self, maplets: Iterable[MapletGrid]) -> None:
        """Add many maplets, merged into the sums a batch at a time (one insertion per batch)."""
        iterator = iter(maplets)
        while batch := list(islice(iterator, _BATCH)):
            parts = [self._contribution(m) for m in batch]
            keys, sums, count = sum_by_key(np.concatenate([p[0] for p in parts]),
                                           np.vstack([p[1] for p in parts]),
                                           np.concatenate([p[2] for p in parts]))
            self.merge(keys, sums, count, sign=+1, name="a batch of maplets")

    def _contribution(self, maplet: MapletGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A maplet's sorted unique keys, sums and counts."""
        raise NotImplementedError

    def merge(self, keys: np.ndarray, sums: np.ndarray, count: np.ndarray, *, sign: int, name: str) -> None:
        """Add (sign +1) or take away (sign -1) a contribution: sorted unique keys, their sums and
        counts. Taking away what was never added is a ValueError naming `name`."""
        if sign not in (1, -1):
            raise ValueError("sign must be +1 or -1")
        if not len(self.keys):
            self.sums = np.empty((0, sums.shape[1]))
        pos = np.searchsorted(self.keys, keys)
        found = pos < len(self.keys)
        found[found] = self.keys[pos[found]] == keys[found]
        if sign < 0 and not found.all():
            raise ValueError(f"{name} was not added in this revision")
        self.sums[pos[found]] += sign * sums[found]
        self.count[pos[found]] += sign * count[found]
        new = ~found
        self.keys = np.insert(self.keys, pos[new], keys[new])
        self.sums = np.insert(self.sums, pos[new], sums[new], axis=0)
        self.count = np.insert(self.count, pos[new], count[new])
        if (self.count < 0).any():
            raise ValueError(f"{name} was not added in this revision")
        live = self.count > 0
        if not live.all():
            self.keys, self.sums, self.count = self.keys[live], self.sums[live], self.count[live]


def sum_by_key(keys: np.ndarray, columns: np.ndarray,
               count: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sorted unique keys, the column sums (K, C) and the number of rows of each key (the sum of
    `count` when given)."""
    unique, inverse = np.unique(keys, return_inverse=True)
    sums = np.column_stack([np.bincount(inverse, weights=columns[:, c], minlength=len(unique))
                            for c in range(columns.shape[1])])
    counts = np.bincount(inverse, weights=count, minlength=len(unique))
    return unique, sums, counts.astype(np.int64) if count is not None else counts
