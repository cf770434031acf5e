"""What incremental fusion keeps between model versions, as numpy .npz files: a refined maplet
(frame, spacing, heights, albedo, region weight) and the voxel sums of a pwm.fusion.VoxelGrid.

Arrays are stored exactly (float64, int64), so a maplet read back subtracts from a grid exactly
what it added. Lengths in km, body-fixed frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pwm.frames import LocalFrame
from pwm.fusion import VoxelGrid
from pwm.maplets import MapletGrid


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


def write_grid(path: str | Path, grid: VoxelGrid) -> None:
    """Save a voxel grid's sums."""
    with open(path, "wb") as stream:
        np.savez(stream, voxel_km=np.array(grid.voxel_km),
                 taper_fraction=np.array(grid.taper_fraction), keys=grid.keys, sums=grid.sums,
                 count=grid.count)


def read_grid(path: str | Path) -> VoxelGrid:
    """A voxel grid saved by `write_grid`."""
    with np.load(path, allow_pickle=False) as data:
        return VoxelGrid(voxel_km=float(data["voxel_km"]),
                         taper_fraction=float(data["taper_fraction"]), keys=data["keys"],
                         sums=data["sums"], count=data["count"])
