"""What incremental fusion keeps between model versions, as numpy .npz files: a refined maplet
(frame, spacing, heights, albedo, region weight) and the sums of a fusion (pwm.fusion.VoxelGrid
or pwm.volume.DistanceGrid).

Arrays are stored exactly (float64, int64), so a maplet read back subtracts from a grid exactly
what it added. Lengths in km, body-fixed frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pwm.frames import LocalFrame
from pwm.fusion import VoxelGrid
from pwm.maplets import MapletGrid
from pwm.volume import DistanceGrid

_KINDS: dict[str, type[VoxelGrid] | type[DistanceGrid]] = {"points": VoxelGrid, "distances": DistanceGrid}


def write_maplet(path: str | Path, maplet: MapletGrid) -> None:
    """Save a maplet's state (its meta is not kept)."""
    arrays = {"name": np.array(maplet.name), "origin_km": maplet.frame.origin,
              "rotation": maplet.frame.rotation, "spacing_km": np.array(maplet.spacing_km),
              "heights_km": maplet.heights, "weight": np.array(maplet.weight)}
    if maplet.albedo is not None:
        arrays["albedo"] = maplet.albedo
    with open(path, "wb") as stream:
        np.savez(stream, **arrays)  # type: ignore[arg-type]  # numpy's stub checks **arrays against allow_pickle


def read_maplet(path: str | Path) -> MapletGrid:
    """A maplet saved by `write_maplet`."""
    with np.load(path, allow_pickle=False) as data:
        return MapletGrid(name=str(data["name"]),
                          frame=LocalFrame(origin=data["origin_km"], rotation=data["rotation"]),
                          spacing_km=float(data["spacing_km"]), heights=data["heights_km"],
                          albedo=data["albedo"] if "albedo" in data else None,
                          weight=float(data["weight"]))


def write_grid(path: str | Path, grid: VoxelGrid | DistanceGrid) -> None:
    """Save a fusion's sums: a VoxelGrid's (kind "points") or a DistanceGrid's ("distances")."""
    kind = next(k for k, cls in _KINDS.items() if type(grid) is cls)
    with open(path, "wb") as stream:
        np.savez(stream, kind=np.array(kind), voxel_km=np.array(grid.voxel_km),
                 taper_fraction=np.array(grid.taper_fraction), keys=grid.keys, sums=grid.sums,
                 count=grid.count)


def read_grid(path: str | Path) -> VoxelGrid | DistanceGrid:
    """A fusion's sums saved by `write_grid` (those saved before kinds were written are points)."""
    with np.load(path, allow_pickle=False) as data:
        cls = _KINDS[str(data["kind"])] if "kind" in data else VoxelGrid
        return cls(voxel_km=float(data["voxel_km"]),
                         taper_fraction=float(data["taper_fraction"]), keys=data["keys"],
                         sums=data["sums"], count=data["count"])
