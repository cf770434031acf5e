"""Benchmark the proving ground: time and peak memory of `pwm simulate` per scenario, and the
renderer's ray rate. Prints a table.

    .venv/bin/python bench/simulate.py [--scenarios tiny site site-polar global-coarse] [--out DIR]

Each scenario runs in its own process, so its peak memory (max RSS) is its own.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CHILD = """
import resource, sys, time
from pwm.simulate.campaign import simulate
from pwm.simulate.scenarios import get_scenario
start = time.perf_counter()
simulate(sys.argv[1], scenario=get_scenario(sys.argv[2]), seed=1, with_start_model=True)
print(time.perf_counter() - start, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def run_scenario(name: str, out: Path) -> dict:
    done = subprocess.run([sys.executable, "-c", CHILD, str(out / name), name], check=True, capture_output=True,
                          text=True)
    wall, peak_kib = done.stdout.split()[-2:]
    manifest = json.loads((out / name / "truth" / "manifest.json").read_text())
    return {"scenario": name, "images": manifest["image_count"], "gsd_m": manifest["gsd_m"], "wall_s": float(wall),
            "peak_gib": int(peak_kib) / 2**20}


def ray_rate(faces: int = 100_000, rays: int = 2_000_000) -> tuple[float, float, int]:
    """Rays per second of one core for first-hit and occlusion queries on a sphere of ~`faces` faces."""
    import trimesh

    from pwm.mesh import Mesh
    from pwm.raytrace import RayTracer

    sphere = trimesh.creation.icosphere(subdivisions=int(round(np.log(faces / 20) / np.log(4))))
    tracer = RayTracer(Mesh(sphere.vertices * 0.25, sphere.faces))
    rng = np.random.default_rng(0)
    origins = rng.normal(size=(rays, 3))
    origins *= 1.0 / np.linalg.norm(origins, axis=1, keepdims=True)
    directions = rng.normal(size=(rays, 3)) * 0.2 - origins
    t = time.perf_counter()
    tracer.intersect(origins, directions)
    hit_rate = rays / (time.perf_counter() - t)
    t = time.perf_counter()
    tracer.occluded(origins, directions)
    occ_rate = rays / (time.perf_counter() - t)
    return hit_rate, occ_rate, len(sphere.faces)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", nargs="+", default=["tiny", "site", "site-polar", "global-coarse"])
    parser.add_argument("--out", type=Path, default=None,
                        help="keep the simulations here (default: a temporary directory)")
    args = parser.parse_args()
    hit, occ, nfaces = ray_rate()
    print(f"renderer, one core, {nfaces} faces: first hit {hit / 1e6:.2f} M rays/s, occlusion {occ / 1e6:.2f} M rays/s")
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        rows = [run_scenario(name, out) for name in args.scenarios]
    print(f"{'scenario':<15}{'images':>8}{'GSD (m)':>10}{'time (s)':>11}{'peak (GiB)':>12}")
    for r in rows:
        print(f"{r['scenario']:<15}{r['images']:>8}{r['gsd_m']:>10.3f}{r['wall_s']:>11.1f}{r['peak_gib']:>12.2f}")


if __name__ == "__main__":
    main()
