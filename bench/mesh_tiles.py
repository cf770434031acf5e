"""Benchmark a version's mesh too big for one file (issue 50, item 3): stored in tiles
(service.versions.store_mesh, pwm.mesh_tiles) against stored whole as PLY and OBJ, read back
whole (service.artifacts.artifact_mesh), one tile read and written as PLY (what an export of a
tile does), and the memory each step peaks at. Prints one table.

    .venv/bin/python bench/mesh_tiles.py [--subdivide 6] [--tile-faces 4000000]

The mesh: the bundled Bennu radar shape subdivided `--subdivide` times (4x the faces each time),
with albedo and a 1-sigma height per vertex. Each step runs in a process of its own, so that its
peak resident memory is its own.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pwm.io.meshio import read_mesh, write_ply  # noqa: E402
from pwm.mesh import Mesh  # noqa: E402
from service.artifacts import artifact_mesh, artifact_path, artifact_tile, tile_index  # noqa: E402
from service.versions import store_mesh  # noqa: E402

BENNU = Path(__file__).resolve().parents[1] / "pwm" / "data" / "shapes" / "bennu_radar_nolan2013_sbgat.obj"


def _mesh(subdivide: int) -> Mesh:
    start = read_mesh(BENNU)
    vertices, faces = start.vertices, start.faces
    for _ in range(subdivide):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    return Mesh(vertices, faces, albedo=0.044 + 0.01 * np.sin(vertices[:, 0] / 0.05),
                sigma=1e-5 * (3 + np.cos(vertices[:, 1] / 0.05)))


def _peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def _store(data_dir: str, subdivide: int, tile_faces: int) -> tuple[dict, float, float, int]:
    mesh = _mesh(subdivide)
    clock = time.perf_counter()
    records = store_mesh(Path(data_dir), mesh, tile_faces=tile_faces)
    return records, time.perf_counter() - clock, _peak_gib(), len(mesh.faces)


def _read(data_dir: str, record: dict, subdivide: int) -> tuple[float, float, bool]:
    clock = time.perf_counter()
    back = artifact_mesh(Path(data_dir), record)
    seconds = time.perf_counter() - clock
    mesh = _mesh(subdivide)
    same = bool(np.array_equal(back.vertices, mesh.vertices) and np.array_equal(back.faces, mesh.faces)
                and np.array_equal(back.albedo, mesh.albedo))
    return seconds, _peak_gib(), same


def _one_tile(data_dir: str, record: dict) -> tuple[float, float, int]:
    clock = time.perf_counter()
    entry = tile_index(Path(data_dir), record).tiles[0]
    tile = artifact_tile(Path(data_dir), entry.file)
    out = Path(data_dir) / "tile.ply"
    write_ply(out, tile.mesh)
    return time.perf_counter() - clock, _peak_gib(), out.stat().st_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--subdivide", type=int, default=6)
    parser.add_argument("--tile-faces", type=int, default=4_000_000)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as data_dir, ProcessPoolExecutor(1, max_tasks_per_child=1) as pool:
        def run(function, *arguments):
            return pool.submit(function, *arguments).result()

        whole, whole_s, whole_gib, faces = run(_store, data_dir, args.subdivide, 10**12)
        tiled, tiled_s, tiled_gib, _ = run(_store, data_dir, args.subdivide, args.tile_faces)
        index = tile_index(Path(data_dir), tiled["tiles"])
        read_whole_s, read_whole_gib, _ = run(_read, data_dir, whole["ply"], args.subdivide)
        join_s, join_gib, same = run(_read, data_dir, tiled["tiles"], args.subdivide)
        tile_s, tile_gib, tile_bytes = run(_one_tile, data_dir, tiled["tiles"])
        tiles_bytes = sum(artifact_path(Path(data_dir), t.file).stat().st_size for t in index.tiles)
        ply_bytes = artifact_path(Path(data_dir), whole["ply"]).stat().st_size
        obj_bytes = artifact_path(Path(data_dir), whole["obj"]).stat().st_size
    print(f"{faces:,} faces; tiles of at most {args.tile_faces:,}: {len(index.tiles)} tiles, "
          f"{min(t.faces for t in index.tiles):,}-{max(t.faces for t in index.tiles):,} faces each; "
          f"joined back the same mesh: {same}\n")
    print("| step | s | peak GiB | bytes stored |")
    print("|---|---|---|---|")
    print(f"| store whole (PLY + OBJ) | {whole_s:.1f} | {whole_gib:.2f} | {ply_bytes + obj_bytes:,} "
          f"(PLY {ply_bytes:,}) |")
    print(f"| store in tiles | {tiled_s:.1f} | {tiled_gib:.2f} | {tiles_bytes:,} |")
    print(f"| read whole PLY | {read_whole_s:.1f} | {read_whole_gib:.2f} | |")
    print(f"| read tiles, joined | {join_s:.1f} | {join_gib:.2f} | |")
    print(f"| one tile to PLY (export) | {tile_s:.1f} | {tile_gib:.2f} | {tile_bytes:,} |")


if __name__ == "__main__":
    main()
