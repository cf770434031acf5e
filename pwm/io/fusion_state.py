"""What incremental fusion keeps between model versions, as numpy .npz files: a refined maplet
(frame, spacing, heights, albedo, region weight, 1-sigma heights), the sums of a fusion, level by level
(pwm.levels.LevelGrids of pwm.fusion.VoxelGrid and pwm.volume.DistanceGrid), and how its surface
was composed (pwm.levels.Composition), and the sums of a fusion in blocks, a file per block
(`BlockFiles`, pwm.blocks).

Arrays are stored exactly (float64, int64), so a maplet read back subtracts from a grid exactly
what it added. Lengths in km, body-fixed frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pwm.blocks import BlockedSums, maplet_blocks
from pwm.frames import LocalFrame
from pwm.fusion import VoxelGrid
from pwm.levels import BATCH, Composition, LevelGrids
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh
from pwm.parallel import map_processes
from pwm.tiling import level_of
from pwm.volume import DistanceGrid
from pwm.voxels import pack, unpack

_KINDS: dict[str, type[VoxelGrid] | type[DistanceGrid]] = {"points": VoxelGrid, "distances": DistanceGrid}


def write_maplet(path: str | Path, maplet: MapletGrid) -> None:
    """Save a maplet's state (its meta is not kept)."""
    arrays = {"name": np.array(maplet.name), "origin_km": maplet.frame.origin,
              "rotation": maplet.frame.rotation, "spacing_km": np.array(maplet.spacing_km),
              "heights_km": maplet.heights, "weight": np.array(maplet.weight)}
    if maplet.albedo is not None:
        arrays["albedo"] = maplet.albedo
    if maplet.sigma is not None:
        arrays["sigma_km"] = maplet.sigma
    with open(path, "wb") as stream:
        np.savez(stream, **arrays)  # type: ignore[arg-type]  # numpy's stub checks **arrays against allow_pickle


def read_maplet(path: str | Path) -> MapletGrid:
    """A maplet saved by `write_maplet`."""
    with np.load(path, allow_pickle=False) as data:
        return MapletGrid(name=str(data["name"]),
                          frame=LocalFrame(origin=data["origin_km"], rotation=data["rotation"]),
                          spacing_km=float(data["spacing_km"]), heights=data["heights_km"],
                          albedo=data["albedo"] if "albedo" in data else None,
                          weight=float(data["weight"]), sigma=data["sigma_km"] if "sigma_km" in data else None)


def write_levels(path: str | Path, fusion: LevelGrids) -> None:
    """Save the sums of each level of a fusion (pwm.levels.LevelGrids): per level its kind
    ("points" for a VoxelGrid, "distances" for a DistanceGrid), voxel size, taper, keys, sums and
    counts, named with the level as a prefix."""
    arrays: dict[str, np.ndarray] = {"levels": np.array(sorted(fusion.grids), dtype=np.int64),
                                     "taper_fraction": np.array(fusion.taper_fraction)}
    for level, grid in fusion.grids.items():
        arrays |= {f"L{level}_{name}": value for name, value in _grid_arrays(grid).items()}
    with open(path, "wb") as stream:
        np.savez(stream, **arrays)  # type: ignore[arg-type]  # as in write_maplet


def read_levels(path: str | Path) -> LevelGrids:
    """The sums saved by `write_levels`; a file of one grid (as versions made before levels were
    kept hold) is that grid at its level."""
    with np.load(path, allow_pickle=False) as data:
        if "levels" not in data:
            grid = _grid(data, "")
            return LevelGrids(taper_fraction=grid.taper_fraction, grids={int(level_of(grid.voxel_km)): grid})
        return LevelGrids(taper_fraction=float(data["taper_fraction"]),
                          grids={int(level): _grid(data, f"L{int(level)}_") for level in data["levels"]})


def write_composition(path: str | Path, composition: Composition) -> None:
    """Save a composition: the surface below the laid levels, its digest, and the origins of
    the composed surface's vertices and faces."""
    below = composition.below
    arrays = {"vertices_km": below.vertices, "faces": below.faces, "digest": np.array(composition.digest),
              "vertex_origin": composition.vertex_origin, "face_origin": composition.face_origin,
              "below_region": composition.below_region}
    if below.albedo is not None:
        arrays["albedo"] = below.albedo
    with open(path, "wb") as stream:
        np.savez(stream, **arrays)  # type: ignore[arg-type]  # as in write_maplet


def read_composition(path: str | Path) -> Composition:
    """A composition saved by `write_composition`."""
    with np.load(path, allow_pickle=False) as data:
        below = Mesh(data["vertices_km"], data["faces"], data["albedo"] if "albedo" in data else None)
        return Composition(below=below, digest=str(data["digest"]), vertex_origin=data["vertex_origin"],
                           face_origin=data["face_origin"], below_region=data["below_region"])


def _grid_arrays(grid: VoxelGrid | DistanceGrid) -> dict[str, np.ndarray]:
    kind = next(k for k, cls in _KINDS.items() if type(grid) is cls)
    return {"kind": np.array(kind), "voxel_km": np.array(grid.voxel_km),
            "taper_fraction": np.array(grid.taper_fraction), "keys": grid.keys, "sums": grid.sums, "count": grid.count}


def _grid(data: Any, prefix: str) -> VoxelGrid | DistanceGrid:
    """The grid whose arrays are named with `prefix` (those saved before kinds were written are points)."""
    cls = _KINDS[str(data[prefix + "kind"])] if prefix + "kind" in data else VoxelGrid
    return cls(voxel_km=float(data[prefix + "voxel_km"]), taper_fraction=float(data[prefix + "taper_fraction"]),
               keys=data[prefix + "keys"], sums=data[prefix + "sums"], count=data[prefix + "count"])


@dataclass(frozen=True)
class BlockFiles:
    """The blocks' files of pwm.blocks (a pwm.blocks.BlockStore), as one file per block and kind
    under `directory`: `<kind>/<i>_<j>_<k>.npz` for the block of index (i, j, k), holding its
    arrays (a grid's as `write_levels` holds a level's). A block's file is written only when its
    contents change, so the others stay as they were, byte for byte."""

    directory: Path

    def path(self, kind: str, block: int) -> Path:
        """The file of a block's sums of this kind."""
        i, j, k = (int(v) for v in unpack(np.array([block]))[0])
        return self.directory / kind / f"{i}_{j}_{k}.npz"

    def blocks(self, kind: str) -> list[int]:
        index = [[int(v) for v in p.stem.split("_")] for p in sorted((self.directory / kind).glob("*.npz"))]
        return sorted(int(b) for b in pack(np.array(index, dtype=np.int64).reshape(-1, 3)))

    def read(self, kind: str, block: int) -> DistanceGrid | None:
        arrays = self.read_arrays(kind, block)
        if arrays is None:
            return None
        grid = _grid(arrays, "")
        if not isinstance(grid, DistanceGrid):
            raise ValueError(f"{self.path(kind, block)} holds no signed distances")
        return grid

    def write(self, kind: str, block: int, grid: DistanceGrid) -> None:
        self.write_arrays(kind, block, _grid_arrays(grid) if len(grid.keys) else {})

    def read_arrays(self, kind: str, block: int) -> dict[str, np.ndarray] | None:
        path = self.path(kind, block)
        if not path.exists():
            return None
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}

    def write_arrays(self, kind: str, block: int, arrays: dict[str, np.ndarray]) -> None:
        path = self.path(kind, block)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not arrays:
            path.unlink(missing_ok=True)
            return
        scratch = path.with_suffix(".part")
        with open(scratch, "wb") as stream:
            np.savez(stream, **arrays)  # type: ignore[arg-type]  # as in write_maplet
        scratch.replace(path)

    def clear(self, kind: str) -> None:
        for path in (self.directory / kind).glob("*.npz"):
            path.unlink()


def build_blocks(store: BlockFiles, paths: Sequence[Path], *, voxel_km: float, taper_fraction: float, cells: int,
                 workers: int) -> dict[int, int]:
    """Each block's sums made on its own (on `workers` processes) from the maplet files
    (`write_maplet`) whose band reaches it, in their order, BATCH at a time: no process holds
    more than a block's sums and a batch. The maplets each block was made from, by block."""
    touching: dict[int, list[Path]] = {}
    for path in paths:
        for block in maplet_blocks(read_maplet(path), voxel_km=voxel_km, cells=cells):
            touching.setdefault(int(block), []).append(path)
    make = partial(_build_block, store, voxel_km=voxel_km, taper_fraction=taper_fraction, cells=cells)
    list(map_processes(make, sorted(touching.items()), workers=workers))
    return {block: len(found) for block, found in touching.items()}


def _build_block(store: BlockFiles, job: tuple[int, list[Path]], *, voxel_km: float, taper_fraction: float,
                 cells: int) -> None:
    block, paths = job
    sums = BlockedSums(store, voxel_km, taper_fraction, cells, only={block})
    for start in range(0, len(paths), BATCH):
        sums.add_batch(read_maplet(p) for p in paths[start:start + BATCH])
    sums.save()
