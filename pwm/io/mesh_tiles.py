"""A mesh in tiles (pwm.mesh_tiles) on disk.

A tile is a numpy .npz file: its faces' and vertices' indices in the whole mesh, its vertices
(km, body-fixed, float64), its faces over them, and albedo and 1-sigma heights (km) where it has
them, stored exactly, so that the tiles joined give the very mesh that was cut. The tiles'
index is a JSON file: the whole mesh's vertex and face counts and per tile its key, counts,
bounding box (km) and the record of its file (whatever the store that keeps the files records).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pwm.mesh import Mesh
from pwm.mesh_tiles import MeshTile


def write_tile(path: str | Path, tile: MeshTile) -> None:
    """Save a tile."""
    # indices in the narrowest integers that hold them: a tile's own always fit 32 bits
    arrays = {"face_ids": _narrow(tile.faces), "vertex_ids": _narrow(tile.vertices),
              "vertices_km": tile.mesh.vertices, "faces": tile.mesh.faces.astype(np.uint32)}
    if tile.mesh.albedo is not None:
        arrays["albedo"] = tile.mesh.albedo
    if tile.mesh.sigma is not None:
        arrays["sigma_km"] = tile.mesh.sigma
    with open(path, "wb") as stream:
        np.savez(stream, **arrays)  # type: ignore[arg-type]  # numpy's stub checks **arrays against allow_pickle


def _narrow(ids: np.ndarray) -> np.ndarray:
    return ids.astype(np.uint32) if not ids.size or ids.max() < 2**32 else ids


def read_tile(path: str | Path) -> MeshTile:
    """A tile saved by `write_tile`. ValueError where its arrays do not agree with each other."""
    with np.load(path, allow_pickle=False) as data:
        vertices, faces = data["vertices_km"], data["faces"].astype(np.int64)
        face_ids, vertex_ids = data["face_ids"].astype(np.int64), data["vertex_ids"].astype(np.int64)
        if (face_ids.shape != (len(faces),) or vertex_ids.shape != (len(vertices),)
                or (faces.size and not (0 <= faces.min() and faces.max() < len(vertices)))
                or (face_ids.size and face_ids.min() < 0) or (vertex_ids.size and vertex_ids.min() < 0)):
            raise ValueError(f"{path}: a mesh tile whose indices do not agree with its arrays")
        mesh = Mesh(vertices=vertices, faces=faces, albedo=data["albedo"] if "albedo" in data else None,
                    sigma=data["sigma_km"] if "sigma_km" in data else None)
    return MeshTile(faces=face_ids, vertices=vertex_ids, mesh=mesh)


@dataclass(frozen=True)
class TileEntry:
    """One tile in the index: its key, face and vertex counts, bounding box (lowest and highest
    x, y, z, km) and its file's record."""

    key: str
    faces: int
    vertices: int
    box_km: tuple[list[float], list[float]]
    file: dict[str, Any]


@dataclass(frozen=True)
class TileIndex:
    """The tiles of one mesh of `vertices` vertices and `faces` faces."""

    vertices: int
    faces: int
    tiles: tuple[TileEntry, ...]

    def entry(self, key: str) -> TileEntry:
        """The tile of `key`; KeyError if there is none."""
        for tile in self.tiles:
            if tile.key == key:
                return tile
        raise KeyError(key)


# What `tile_key` gives: a request naming any other key names no tile.
TILE_KEY_PATTERN = r"^t[0-9]{5}$"


def tile_key(number: int) -> str:
    """The key of the tile of this number in its mesh's order."""
    if not 0 <= number < 100_000:
        raise ValueError(f"a mesh holds at most 100,000 tiles, not {number + 1}")
    return f"t{number:05d}"


def write_index(path: str | Path, index: TileIndex) -> None:
    """Save a tiles' index as JSON."""
    Path(path).write_text(json.dumps(asdict(index), sort_keys=True))


def read_index(path: str | Path) -> TileIndex:
    """A tiles' index saved by `write_index`. ValueError where it is not one."""
    try:
        data = json.loads(Path(path).read_text())
        tiles = tuple(TileEntry(key=str(t["key"]), faces=int(t["faces"]), vertices=int(t["vertices"]),
                                box_km=(list(map(float, t["box_km"][0])), list(map(float, t["box_km"][1]))),
                                file=dict(t["file"])) for t in data["tiles"])
        return TileIndex(vertices=int(data["vertices"]), faces=int(data["faces"]), tiles=tiles)
    except (KeyError, TypeError, IndexError, ValueError) as exc:
        raise ValueError(f"{path}: not an index of mesh tiles ({exc})") from exc
