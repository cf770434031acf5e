"""The stopping rules against the accuracy they cost, on a simulated downlink: the solver's (a
maplet's iterations end once a step gains under `cost_tolerance` of the objective,
pwm.photoclinometry.Solver) and the number of passes (RefinementConfig.passes, which `pwm run`
and the workers follow too). Each variant refines the downlink's start model as `pwm refine`
does (pwm.pipeline.refine_region, the region `bench/accuracy.py` gives it) and is measured
against the truth (pwm.evaluate.report.evaluate). Prints a table.

    .venv/bin/python bench/stopping.py SIM [--variants 1e-2:2 1e-3:2 1e-2:3] [--out DIR] [--workers 2]

SIM: a simulation directory (downlink/ with start_model.obj, truth/). A variant is
COST_TOLERANCE:PASSES.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pwm.config import DEFAULTS  # noqa: E402
from pwm.evaluate.report import evaluate  # noqa: E402
from pwm.io.downlink import read_downlink  # noqa: E402
from pwm.io.meshio import read_mesh, write_ply  # noqa: E402
from pwm.pipeline import imaged_region, refine_region  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sim", type=Path)
    parser.add_argument("--variants", nargs="+", default=["1e-2:2", "1e-3:2", "1e-2:3"])
    parser.add_argument("--out", type=Path, default=Path("out/bench-stopping"))
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    manifest = json.loads((args.sim / "truth" / "manifest.json").read_text())
    views = read_downlink(args.sim / "downlink").views
    start = read_mesh(args.sim / "downlink" / "start_model.obj")
    region = imaged_region(views, start)
    region = dataclasses.replace(region, radius_km=1.3 * manifest["scenario"]["site_size_km"] / 2,
                                 spacing_km=DEFAULTS.spacing_gsd * region.spacing_km)
    print(f"{args.sim.name}: GSD {manifest['gsd_m']:.3f} m, {len(views)} images")
    print("| cost tolerance | passes | RMS GSD | median m | NCC | SSIM | steep | iterations (mean, max) | time s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for variant in args.variants:
        tolerance, passes = float(variant.split(":")[0]), int(variant.split(":")[1])
        config = dataclasses.replace(DEFAULTS, passes=passes,
                                     solver=dataclasses.replace(DEFAULTS.solver, cost_tolerance=tolerance))
        clock = time.perf_counter()
        model, results = refine_region(start, views, region, config=config, workers=args.workers)
        seconds = time.perf_counter() - clock
        path = args.out / args.sim.name / f"tol{tolerance:g}-passes{passes}" / "refined.ply"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_ply(path, model)
        figures = evaluate(path, truth_dir=args.sim / "truth")
        iterations = np.array([r.iterations for r in results])
        print(f"| {tolerance:g} | {passes} | {figures['rms_gsd']:.3f} | {figures['median_m']:.4f} | "
              f"{figures['ncc']:.3f} | {figures['ssim']:.3f} | "
              f"{figures['steep_boulder_height_ratio_median']:.2f} | {iterations.mean():.1f}, {iterations.max()} | "
              f"{seconds:.0f} |", flush=True)


if __name__ == "__main__":
    main()
