"""Benchmark the site slope map: a refined version's slopes (pwm.site.slope_deg) against the
slopes of the truth height field, on the truth's site frame. Prints a table.

    .venv/bin/python bench/site_slope.py DATA_DIR SIM [--version V] [--spacing-m 0.13 0.25 0.5]
                                         [--baseline-m 1.0]

DATA_DIR: the pwm data directory the `site` scenario was run into (`pwm run SIM/downlink`);
SIM: the simulation (`pwm simulate SIM --scenario site`), whose truth/grid.npz holds the truth
heights on the frame of truth/truth.json. The version is first registered to the truth by ICP over
the site (pwm.evaluate.report.register_to_truth, as `pwm evaluate` does). For each spacing, its
surface is sampled on a square grid of that spacing in the truth frame (rays down its z axis,
pwm.site.sample_grid, as the site maps and products are), the truth heights are
interpolated bilinearly at the same nodes, raw and after a box average over the spacing (the
truth at that resolution: raw, the truth's relief finer than the grid aliases into its slopes),
and the slope of each is taken the same way: at the nodes (central differences) and over the
baseline (the tilt of the plane fitted over it, what the site product and the console's site
maps carry); the RMS and the 95th percentile of the difference are over the nodes within the
truth's evaluation radius where all are known. Aim: within 2 degrees RMS.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.interpolate import RegularGridInterpolator
from scipy.ndimage import uniform_filter

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pwm.evaluate.report import in_site, register_to_truth  # noqa: E402
from pwm.frames import LocalFrame  # noqa: E402
from pwm.mesh import Mesh  # noqa: E402
from pwm.simulate.truth import load as load_truth  # noqa: E402
from pwm.site import BASELINE_M, sample_grid, slope_deg  # noqa: E402
from service.catalog import open_catalog  # noqa: E402
from service.settings import Settings  # noqa: E402
from service.versions import get_version, version_mesh  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data_dir", type=Path)
    parser.add_argument("sim", type=Path)
    parser.add_argument("--version", default="latest")
    parser.add_argument("--spacing-m", type=float, nargs="+", default=[0.13, 0.25, 0.5])
    parser.add_argument("--baseline-m", type=float, default=BASELINE_M,
                        help="the slope product's baseline (m)")
    args = parser.parse_args()
    truth = json.loads((args.sim / "truth" / "truth.json").read_text())
    frame = LocalFrame(origin=np.array(truth["origin_km"]), rotation=np.array(truth["rotation"]))
    reach_km = truth["eval_radius_km"]
    grid = np.load(args.sim / "truth" / "grid.npz")
    truth_step_m = float(grid["x_km"][1] - grid["x_km"][0]) * 1e3

    def truth_at(height_km: np.ndarray) -> RegularGridInterpolator:
        return RegularGridInterpolator((grid["y_km"], grid["x_km"]), height_km,
                                       bounds_error=False, fill_value=np.nan)
    sessions = open_catalog(Settings(data_dir=args.data_dir))
    with sessions() as session:
        version = get_version(session, args.version)
        number = version.version
        mesh = version_mesh(args.data_dir, version)
    manifest = json.loads((args.sim / "truth" / "manifest.json").read_text())
    truth_model = load_truth(args.sim / "truth")
    transform, _ = register_to_truth(mesh, truth_model, region=in_site(mesh.vertices, truth_model),
                                     gsd_km=manifest["scenario"]["gsd_km"], whole_body=False)
    mesh = Mesh(transform.apply(mesh.vertices), mesh.faces, mesh.albedo)
    print(f"version {number} against the truth of {args.sim}, within {reach_km * 1e3:.0f} m of "
          f"the site centre")
    print("| spacing m | slope | nodes | slope mean deg: truth, truth averaged, model | RMS diff deg: "
          "raw, averaged | 95% abs diff deg: raw, averaged |")
    print("|---|---|---|---|---|---|")
    for spacing_m in args.spacing_m:
        half = int(np.ceil(reach_km * 1e3 / spacing_m))
        axis = np.arange(-half, half + 1) * spacing_m * 1e-3
        model = sample_grid(mesh, frame, axis, axis).height_km * 1e3
        yy, xx = np.meshgrid(axis, axis, indexing="ij")
        nodes = np.stack([yy, xx], axis=-1)
        box = max(1, round(spacing_m / truth_step_m))
        truths = [truth_at(grid["height_km"])(nodes) * 1e3,
                  truth_at(uniform_filter(grid["height_km"], box, mode="nearest"))(nodes) * 1e3]
        for label, baseline_m in (("at nodes", None), (f"over {args.baseline_m:g} m", args.baseline_m)):
            model_slope = slope_deg(model, spacing_m=spacing_m, baseline_m=baseline_m)
            true_slopes = [slope_deg(true, spacing_m=spacing_m, baseline_m=baseline_m) for true in truths]
            inside = ((np.hypot(xx, yy) <= reach_km) & np.isfinite(model_slope)
                      & np.isfinite(true_slopes[0]) & np.isfinite(true_slopes[1]))
            diffs = [model_slope[inside] - true[inside] for true in true_slopes]
            means = ", ".join(f"{a[inside].mean():.2f}" for a in (*true_slopes, model_slope))
            rms = ", ".join(f"{np.sqrt(np.mean(d ** 2)):.2f}" for d in diffs)
            p95 = ", ".join(f"{np.percentile(np.abs(d), 95):.2f}" for d in diffs)
            print(f"| {spacing_m:g} | {label} | {inside.sum()} | {means} | {rms} | {p95} |", flush=True)

if __name__ == "__main__":
    main()
