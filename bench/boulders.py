"""Why a site's largest boulders come out low: one maplet centred on each (or shifted off it),
refined as `pwm refine` refines it (pwm.pipeline.refine_maplet), with settings changed one at a
time (issue 49).

    .venv/bin/python bench/boulders.py SIM [--start MODEL] [--set solver.height_weight=0 ...]
                                           [--shift-m 0 0] [--nodes 100] [--boulders 4]

SIM: a site simulation (SIM/downlink, SIM/truth); MODEL: the model the maplets start from
(default the downlink's start model; a pass's fused model for the second pass). --set: a
RefinementConfig field, or one of its solver's, placement's or rules' (solver.slope_weight=0.005,
placement.coarse_factors=, shape_window_nodes=0), repeatable. --shift-m: the maplet's centre
east and north of the boulder's, m. Per boulder: its recovered height fraction (as `pwm
evaluate` measures it), the maplet's height RMS against the truth, the mean error on its top
(within half its radius) and the highest mean error of the eight sectors of its apron (one to
one and a half radii), all in m; the same for the start.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from pwm.config import DEFAULTS, RefinementConfig

TRUTH_CROP_KM = 0.008
"""Half the side of the truth's patch cropped about a boulder to measure a maplet against."""


def configured(changes: list[str]) -> RefinementConfig:
    """DEFAULTS with each NAME=VALUE (NAME a field, or nested as solver.FIELD) changed."""
    config = DEFAULTS
    for change in changes:
        name, _, text = change.partition("=")
        parts = name.split(".")
        holder = config if len(parts) == 1 else getattr(config, parts[0])
        old = getattr(holder, parts[-1])
        value: object
        if isinstance(old, tuple):
            value = tuple(int(v) for v in text.split(",") if v)
        else:
            value = type(old)(text) if not isinstance(old, bool) else text.lower() in ("1", "true", "yes")
        holder = dataclasses.replace(holder, **{parts[-1]: value})
        config = holder if len(parts) == 1 else dataclasses.replace(config, **{parts[0]: holder})
    return config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sim", type=Path)
    parser.add_argument("--start", type=Path, default=None)
    parser.add_argument("--set", dest="changes", action="append", default=[])
    parser.add_argument("--shift-m", nargs=2, type=float, default=(0.0, 0.0))
    parser.add_argument("--nodes", type=int, default=DEFAULTS.nodes)
    parser.add_argument("--boulders", type=int, default=4)
    parser.add_argument("--plots", type=Path, default=None, help="write each maplet's height error map here")
    parser.add_argument("--at", nargs=2, type=float, default=None, help="the boulder nearest this x, y (m) instead")
    parser.add_argument("--only", type=int, nargs="*", default=None, help="these of the largest (0: the largest)")
    args = parser.parse_args()

    from pwm.evaluate.classes import on_boulders
    from pwm.evaluate.profiles import boulder_height_ratio
    from pwm.frames import unit_to_latlon
    from pwm.io.downlink import read_downlink
    from pwm.io.meshio import read_mesh
    from pwm.pipeline import imaged_region, refine_maplet
    from pwm.raytrace import RayTracer
    from pwm.sampling import drop_rays
    from pwm.simulate.truth import load
    from pwm.tiling import tile

    config = dataclasses.replace(configured(args.changes), nodes=args.nodes)
    views = read_downlink(args.sim / "downlink").views
    start = read_mesh(args.start or args.sim / "downlink" / "start_model.obj")
    tracer = RayTracer(start)
    truth = load(args.sim / "truth")
    spacing = imaged_region(views, start).spacing_km * config.spacing_gsd
    inside = [b for b in truth.boulders if np.hypot(b.x_km, b.y_km) + b.diameter_km < truth.eval_radius_km]
    largest = sorted(inside, key=lambda b: -b.diameter_km)[: args.boulders]
    largest = largest if args.only is None else [largest[k] for k in args.only]
    if args.at is not None:  # the boulder nearest this point (m), wherever it lies
        largest = [min(truth.boulders, key=lambda b: np.hypot(b.x_km * 1e3 - args.at[0], b.y_km * 1e3 - args.at[1]))]
    print(f"changes: {args.changes or 'none'}; start {args.start or 'start_model.obj'}; shift {args.shift_m} m; "
          f"{config.nodes} nodes at {spacing * 1e3:.3f} m")
    print(f"{'boulder':>16}{'':>3}{'ratio':>7}{'rms':>8}{'top':>8}{'apron':>8}{'s':>6}")
    boulder_points = np.array([truth.site_point(o.x_km, o.y_km) for o in truth.boulders]).reshape(-1, 3)
    for b in largest:
        cx, cy = b.x_km + args.shift_m[0] * 1e-3, b.y_km + args.shift_m[1] * 1e-3
        # the truth about the maplet, as a small mesh to drop the maplet's rays on
        truth_tracer = RayTracer(truth.patch(cx, cy, TRUTH_CROP_KM))
        lat, lon = unit_to_latlon(truth.site_point(cx, cy))
        maplet = tile(start, spacing_km=spacing, nodes=config.nodes, centre_lat_deg=float(lat),
                      centre_lon_deg=float(lon), radius_km=0.1 * spacing)[0]
        gx, gy = np.meshgrid(maplet.axis_km, maplet.axis_km)
        top = float(np.nanmax(maplet.heights)) + 0.01
        truth_h = drop_rays(truth_tracer, maplet.frame, gx.ravel(), gy.ravel(), top_km=top)[1].reshape(gx.shape)
        centre = maplet.frame.to_local(truth.site_point(b.x_km, b.y_km)[None])[0, :2]
        # every boulder in the maplet's frame: no boulder is measured from their discs
        local = [dataclasses.replace(o, x_km=float(px), y_km=float(py)) for o, (px, py, _) in
                 zip(truth.boulders, maplet.frame.to_local(boulder_points), strict=True)]
        ground = ~on_boulders(maplet.axis_km, maplet.axis_km, local)
        clock = time.perf_counter()
        refined = refine_maplet(maplet, views, tracer, config=config).maplet.heights
        seconds = time.perf_counter() - clock
        if args.plots is not None:
            import matplotlib.pyplot as plt

            args.plots.mkdir(parents=True, exist_ok=True)
            fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
            extent = [maplet.axis_km[0] * 1e3, maplet.axis_km[-1] * 1e3] * 2
            for ax, (title, grid) in zip(axes, (("truth - start", truth_h - maplet.heights),
                                                ("model - truth", refined - truth_h),
                                                ("truth", truth_h)), strict=True):
                shown = ax.imshow(grid * 1e3, origin="lower", extent=extent, cmap="RdBu_r" if "-" in title else None,
                                  vmin=-0.4 if "-" in title else None, vmax=0.4 if "-" in title else None)
                ax.add_patch(plt.Circle(tuple(centre * 1e3), b.diameter_km * 1e3 / 2, fill=False))
                ax.set_title(f"{title} (m), x east")
                fig.colorbar(shown, ax=ax)
            fig.savefig(args.plots / f"boulder_{b.diameter_km * 1e3:.2f}.png", dpi=70)
            plt.close(fig)
        for label, heights in (("start", maplet.heights), ("refined", refined)):
            ratio = boulder_height_ratio(maplet.axis_km, maplet.axis_km, truth_h, heights, centres_km=centre[None],
                                         diameters_km=np.array([b.diameter_km]), ground=ground)[0]
            error = heights - truth_h
            r = np.hypot(gx - centre[0], gy - centre[1]) / (b.diameter_km / 2)
            sector = (np.arctan2(gy - centre[1], gx - centre[0]) // (np.pi / 4)).astype(int)
            apron = (r >= 1.0) & (r <= 1.5)
            aprons = [np.nanmean(error[apron & (sector == s)]) for s in range(-4, 4) if (apron & (sector == s)).any()]
            print(f"{b.diameter_km * 1e3:5.2f} x {b.height_km * 1e3:4.2f} m {label:>7}{ratio:7.3f}"
                  f"{np.sqrt(np.nanmean(error**2)) * 1e3:8.3f}{np.nanmean(error[r <= 0.5]) * 1e3:8.3f}"
                  f"{max(aprons) * 1e3:8.3f}{seconds if label == 'refined' else 0:6.0f}  "
                  f"apron by sector from east: {' '.join(f'{a * 1e3:+.2f}' for a in aprons)}", flush=True)


if __name__ == "__main__":
    main()
