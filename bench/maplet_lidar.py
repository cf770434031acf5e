"""What the lidar's weight against the images costs and gains in one maplet (issue 47.4):
maplets across a site refined as `pwm.pipeline.refine_maplet` refines them, without spots and
with the spots of the downlink's lidar over them at each weight (pwm.photoclinometry.Solver.
lidar_weight), against the truth.

    .venv/bin/python bench/maplet_lidar.py SIM [--weights none 0 1e-4 1e-3 1e-2 1e-1 1] [--maplets 6]
                                               [--nodes 100] [--images 0] [--long-m 5]

SIM: a site simulation with lidar (SIM/downlink with lidar/ and kernels/, SIM/truth), e.g.
`pwm simulate SIM --scenario site --with-start-model --start-error 1.0,5,40`: a start with
undulations of 5-40 m that the images barely see. The shots are placed through the downlink's
kernels (pwm.io.lidar.read_lidar_directory); each spot's sigma is its range's. Weight 0: the
spots place the maplet (pwm.pipeline.placed_on_spots) but do not weigh in its solution; "none":
no spots at all. --images N: only the first N of the images each maplet would use (few images).
Per weight, over the maplets: the height RMS against the truth, the error longer and shorter
than --long-m (pwm.evaluate.bands.split, as `pwm evaluate` splits a site's), the spots' RMS in
their sigmas (median over the maplets) and the refinements' seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from pwm.config import DEFAULTS

TRUTH_MARGIN_KM = 0.002
"""The truth's patch about a maplet reaches this far beyond its square."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sim", type=Path)
    parser.add_argument("--weights", nargs="*", default=["none", "0", "1e-4", "1e-3", "1e-2", "1e-1", "1"])
    parser.add_argument("--maplets", type=int, default=6)
    parser.add_argument("--nodes", type=int, default=DEFAULTS.nodes)
    parser.add_argument("--images", type=int, default=0)
    parser.add_argument("--long-m", type=float, default=5.0)
    args = parser.parse_args()

    from pwm.evaluate.bands import split
    from pwm.frames import unit_to_latlon
    from pwm.io.downlink import read_downlink
    from pwm.io.lidar import read_lidar_directory
    from pwm.io.meshio import read_mesh
    from pwm.lidar.model import usable
    from pwm.lidar.shots import Shots
    from pwm.maplets import NO_SPOTS, Spots, spots_over
    from pwm.pipeline import imaged_region, maplet_images, refine_maplet
    from pwm.raytrace import RayTracer
    from pwm.sampling import drop_rays
    from pwm.simulate.truth import load
    from pwm.tiling import tile

    views = read_downlink(args.sim / "downlink").views
    start = read_mesh(args.sim / "downlink" / "start_model.obj")
    tracer = RayTracer(start)
    truth = load(args.sim / "truth")
    products, skipped = read_lidar_directory(args.sim / "downlink")
    shots = Shots.joined([p.shots for p in products])
    good = usable(shots)
    measured = Spots(body_km=shots.spots_km()[good], sigma_km=shots.sigma_km[good])
    config = dataclasses.replace(DEFAULTS, nodes=args.nodes)
    spacing = imaged_region(views, start).spacing_km * config.spacing_gsd
    side = (config.nodes - 1) * spacing
    print(f"{len(measured.sigma_km)} spots of {len(products)} products ({len(skipped)} skipped); "
          f"{config.nodes} nodes at {spacing * 1e3:.3f} m, maplets {side * 1e3:.1f} m; "
          f"long wavelengths: beyond {args.long_m:g} m")
    # maplet centres on a ring inside the evaluated disc, where the profiles cross the site
    angles = np.linspace(0, 2 * np.pi, args.maplets, endpoint=False)
    ring = max(truth.eval_radius_km - 0.75 * side, 0.0) * 0.6
    rows = []
    for weight in args.weights:
        # "none" refines without spots, so its weight is moot
        weighed = dataclasses.replace(config, solver=dataclasses.replace(
            config.solver, lidar_weight=0.0 if weight == "none" else float(weight)))
        errors, longs, shorts, fits, seconds = [], [], [], [], 0.0
        for angle in angles:
            cx, cy = ring * np.cos(angle), ring * np.sin(angle)
            crop = truth.patch(cx, cy, side / 2 + TRUTH_MARGIN_KM)
            lat, lon = unit_to_latlon(truth.site_point(cx, cy))
            maplet = tile(start, spacing_km=spacing, nodes=config.nodes, centre_lat_deg=float(lat),
                          centre_lon_deg=float(lon), radius_km=0.1 * spacing)[0]
            gx, gy = np.meshgrid(maplet.axis_km, maplet.axis_km)
            top = float(np.nanmax(maplet.heights)) + 0.01
            truth_h = drop_rays(RayTracer(crop), maplet.frame, gx.ravel(), gy.ravel(),
                                top_km=top)[1].reshape(gx.shape)
            chosen = views
            if args.images:
                keep = maplet_images(maplet, views, tracer, rules=config.rules)[2][: args.images]
                chosen = [views[k] for k in keep]
            spots = NO_SPOTS if weight == "none" else spots_over(maplet, measured)
            clock = time.perf_counter()
            result = refine_maplet(maplet, chosen, tracer, config=weighed, spots=spots)
            seconds += time.perf_counter() - clock
            error = result.maplet.heights - truth_h
            short, long = split(error, spacing_km=spacing, boundaries_km=(args.long_m * 1e-3,))
            errors.append(np.nanmean(error**2))
            longs.append(np.nanmean(long**2))
            shorts.append(np.nanmean(short**2))
            fits.append(result.lidar_rms)
        rows.append((weight, *(np.sqrt(np.mean(v)) * 1e3 for v in (errors, longs, shorts)),
                     float(np.nanmedian(fits)) if np.isfinite(fits).any() else float("nan"), seconds))
        print(f"weight {weight}: done", flush=True)
    cut = f"{args.long_m:g} m"
    print(f"\n| lidar weight | height RMS (m) | >{cut} (m) | <{cut} (m) | spots' RMS (sigma) | s |")
    print("|---|---|---|---|---|---|")
    for weight, rms, long, short, fit, s in rows:
        print(f"| {weight} | {rms:.3f} | {long:.3f} | {short:.3f} | {fit:.2f} | {s:.0f} |")


if __name__ == "__main__":
    main()
