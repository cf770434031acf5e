"""The best a model sampled every few centimetres can score: the truth itself, averaged over and
sampled at a coarser grid, measured with `pwm evaluate` (RMS, NCC and SSIM of held-out views).

    .venv/bin/python bench/ceiling.py TRUTH_DIR [--grids 1:1 1:0.5 0.75:1 ...] [--out DIR]

Each grid is SPACING:AVERAGE in image GSDs: node spacing, and the side of the square the truth is
averaged over (a refinement estimates the image-blurred surface, about one GSD). This is the
ceiling that node spacing alone puts on a refined model's figures, whatever the solver does.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from pwm.evaluate.report import evaluate
from pwm.io.meshio import write_ply
from pwm.simulate.truth import load, sampled


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("truth", type=Path)
    parser.add_argument("--grids", nargs="+", default=["1:1", "0.75:1", "0.5:1", "0.5:0.5"])
    parser.add_argument("--out", type=Path, default=Path("out/bench-ceiling"))
    args = parser.parse_args()
    truth = load(args.truth)
    gsd_km = json.loads((args.truth / "manifest.json").read_text())["gsd_m"] * 1e-3
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"{args.truth}: GSD {gsd_km * 1e3:.3f} m, truth grid {truth.resolution_km * 1e3:.3f} m")
    print(f"{'spacing GSD':>12}{'average GSD':>12}{'RMS GSD':>9}{'NCC':>7}{'SSIM':>7}  per view (NCC/SSIM)")
    for grid in args.grids:
        spacing, average = (float(x) for x in grid.split(":"))
        path = args.out / f"truth_{spacing:g}_{average:g}.ply"
        write_ply(path, sampled(truth, spacing_km=spacing * gsd_km, average_km=average * gsd_km))
        r = evaluate(path, truth_dir=args.truth)
        views = " ".join(f"{v['ncc']:.3f}/{v['ssim']:.3f}" for v in r["views"])
        print(f"{spacing:>12.2f}{average:>12.2f}{r['rms_gsd']:>9.2f}{r['ncc']:>7.3f}{r['ssim']:>7.3f}  {views}",
              flush=True)


if __name__ == "__main__":
    main()
