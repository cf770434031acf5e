"""Size and time of a SPICE DSK of an uneven plate model and of even ones, and dskxv's time on
each: what the spatial index sizing of pwm/io/dsk.py costs.

    .venv/bin/python bench/dsk_index.py

Meshes: `uneven` is the Bennu radar model decimated to 60 plates with one plate subdivided 6
times (a dense site on a coarse body, as tests/test_exports.py builds it); `even-4000` is Bennu
subdivided once and decimated to 4000 plates; `even-172k` is Bennu subdivided 3 times.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import spiceypy as sp
import trimesh

from pwm.decimate import decimate
from pwm.io.dsk import write_dsk
from pwm.io.meshio import read_obj
from pwm.io.spice_kernels import bundled_kernels, kernel_pool
from pwm.mesh import Mesh

BENNU_OBJ = Path(__file__).resolve().parents[1] / "pwm" / "data" / "shapes" / "bennu_radar_nolan2013_sbgat.obj"
BENNU = 2101955
RAYS = 1000


def dense_site(mesh: Mesh, times: int) -> Mesh:
    """`mesh` with its first plate subdivided `times` times."""
    corners = mesh.vertices[mesh.faces[0]]
    centre = corners.mean(axis=0)
    reach = np.linalg.norm(corners - centre, axis=1).max()
    vertices, faces = mesh.vertices, mesh.faces
    for _ in range(times):
        inside = np.linalg.norm(vertices[faces].mean(axis=1) - centre, axis=1) < reach
        vertices, faces = trimesh.remesh.subdivide(vertices, faces, face_index=np.flatnonzero(inside))
    return Mesh(vertices, faces)


def subdivided(mesh: Mesh, times: int) -> Mesh:
    vertices, faces = mesh.vertices, mesh.faces
    for _ in range(times):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    return Mesh(vertices, faces)


def main() -> None:
    bennu = read_obj(BENNU_OBJ)
    meshes = {"uneven": dense_site(decimate(bennu, 60), 6),
              "even-4000": decimate(subdivided(bennu, 1), 4000),
              "even-172k": subdivided(bennu, 3)}
    rng = np.random.default_rng(1)
    origins = rng.normal(size=(RAYS, 3))
    origins /= np.linalg.norm(origins, axis=1, keepdims=True)
    directions = rng.uniform(-0.1, 0.1, size=(RAYS, 3)) - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    print("| mesh | plates | write s | MB | dskxv ms per 1000 rays |\n|---|---|---|---|---|")
    for name, mesh in meshes.items():
        with tempfile.TemporaryDirectory() as scratch:
            path = Path(scratch) / f"{name}.bds"
            with kernel_pool(bundled_kernels().values()):
                began = time.perf_counter()
                write_dsk(path, mesh, body=BENNU, frame="IAU_BENNU", comment=name)
                written = time.perf_counter() - began
            with kernel_pool([*bundled_kernels().values(), path]):
                began = time.perf_counter()
                sp.dskxv(False, "BENNU", [], 0.0, "IAU_BENNU", origins, directions)
                traced = time.perf_counter() - began
            print(f"| {name} | {len(mesh.faces)} | {written:.2f} | {path.stat().st_size / 1e6:.2f} "
                  f"| {traced * 1e3:.0f} |")


if __name__ == "__main__":
    main()
