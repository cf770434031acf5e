"""A survey's start from nothing against the proving ground's truth: per simulated survey, the
first model as the catalog makes it with no model given (`start`: pwm.spg.stereo_photogrammetry
from the target's PCK ellipsoid, with the views' visual hull), the same without the hull
(`ellipsoid + stereo`, the start before the hull), and the visual hull by itself (`hull`): RMS
and median after ICP (GSD of the survey), coverage within 2 GSD, time and peak memory.

    .venv/bin/python bench/start.py SIM [SIM ...] [--out DIR]

Each SIM is a simulated survey (`pwm simulate OUT --scenario global-tiny`, a campaign's
downlinks/<survey>), holding downlink/ and truth/; only read. Each start runs in its own process so
that its peak memory is its own.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

STARTS = ("hull", "start", "ellipsoid + stereo")


def one(sim: Path, start: str, out: Path) -> dict:
    """Make the start `start` of the survey in `sim`, write it to `out`, and evaluate it."""
    from pwm.evaluate.report import evaluate
    from pwm.io.downlink import read_downlink
    from pwm.io.meshio import write_ply
    from pwm.io.spice_geometry import ellipsoid_of
    from pwm.io.spice_kernels import kernel_pool
    from pwm.spg.config import SPG_DEFAULTS
    from pwm.spg.hull import visual_hull
    from pwm.spg.photogrammetry import stereo_photogrammetry

    clock = time.perf_counter()
    read = read_downlink(sim / "downlink")
    with kernel_pool(sorted((sim / "downlink").rglob("*.tm"))):
        figure = ellipsoid_of(str(read.target_id)).mesh()
    config = SPG_DEFAULTS
    if start == "hull":
        radius = float(max(abs(figure.vertices).max(axis=0)))
        hull = visual_hull(read.views, bound_km=config.hull.bound_radii * radius, config=config.hull)
        if hull is None:
            raise RuntimeError(f"{sim}: no visual hull")
        mesh = hull.mesh
    else:
        if start == "ellipsoid + stereo":  # a hull no figure can hold: refused, as a failed carving is
            config = replace(config, hull=replace(config.hull, max_figure_volumes=1e-9))
        mesh = stereo_photogrammetry(read.views, figure, from_figure=True, config=config).mesh
    seconds = time.perf_counter() - clock
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{start.replace(' + ', '_')}.ply"
    write_ply(path, mesh)
    figures = evaluate(path, truth_dir=sim / "truth", scope="global")
    return {"seconds": seconds, "rms_gsd": figures["rms_gsd"], "median_gsd": figures["median_gsd"],
            "completeness": figures["completeness"], "faces": len(mesh.faces)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sims", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=Path("/tmp/pwm-bench-start"))
    parser.add_argument("--one", nargs=2, help=argparse.SUPPRESS)  # child: SIM START
    args = parser.parse_args()
    if args.one:
        sim, start = Path(args.one[0]), args.one[1]
        result = one(sim, start, args.out / sim.name)
        result["peak_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
        print("RESULT", json.dumps(result))
        return
    print("| survey | start | RMS (GSD) | median (GSD) | coverage (2 GSD) | faces | time (s) | peak (GiB) |")
    print("|---|---|---|---|---|---|---|---|")
    for sim in args.sims:
        for start in STARTS:
            done = subprocess.run([sys.executable, __file__, str(sim), "--out", str(args.out), "--one", str(sim),
                                   start], capture_output=True, text=True)
            line = next((x for x in done.stdout.splitlines() if x.startswith("RESULT ")), None)
            if line is None:
                print(f"| {sim.name} | {start} | failed: {done.stderr.strip().splitlines()[-1:]} |||||")
                continue
            r = json.loads(line.removeprefix("RESULT "))
            print(f"| {sim.name} | {start} | {r['rms_gsd']:.2f} | {r['median_gsd']:.2f} | {r['completeness']:.3f} "
                  f"| {r['faces']} | {r['seconds']:.0f} | {r['peak_gib']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
