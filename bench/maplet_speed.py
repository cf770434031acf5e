"""Speed of refining one maplet: visibility, weights and photoclinometry of one 100 x 100-node
maplet with 10 images, on one core (issue 50's target: at most 1.0 s on `site` and `site-hard`, best of
5, nothing else running).

    .venv/bin/python bench/maplet_speed.py DOWNLINK [--nodes 100] [--images 10] [--repeat 3]

The maplet sits at the centre of the imaged region of DOWNLINK (e.g. a `site` simulation's
downlink/), tiled from its start model at the images' median pixel scale; the images are the
`images` best-weighted of those the weighting rules keep. Run it with one thread per library
(OMP_NUM_THREADS=1 etc. are set here before numpy loads) and with nothing else busy.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pwm.config import DEFAULTS, MODES  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("downlink", type=Path)
    parser.add_argument("--nodes", type=int, default=DEFAULTS.nodes)
    parser.add_argument("--images", type=int, default=10)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--mode", default=DEFAULTS.mode, choices=MODES)
    args = parser.parse_args()

    from pwm.io.downlink import read_downlink
    from pwm.io.meshio import read_mesh
    from pwm.pipeline import imaged_region, refine_maplet
    from pwm.raytrace import RayTracer
    from pwm.tiling import tile
    from pwm.weights import views_over_maplet, weigh_maplet

    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    except (AttributeError, OSError):
        pass
    views = read_downlink(args.downlink).views
    start = read_mesh(args.downlink / "start_model.obj")
    region = imaged_region(views, start)
    maplet = tile(start, spacing_km=region.spacing_km, nodes=args.nodes, centre_lat_deg=region.lat_deg,
                  centre_lon_deg=region.lon_deg, radius_km=0.1 * region.spacing_km)[0]
    tracer = RayTracer(start)
    vis, in_frame, geom = views_over_maplet(maplet, views, tracer)
    weights = weigh_maplet(maplet, vis, geom, in_frame=in_frame)
    best = np.argsort(-weights.image)[: args.images]
    chosen = [views[k] for k in sorted(best) if weights.keep[k]]
    config = dataclasses.replace(DEFAULTS, mode=args.mode)
    times = []
    for _ in range(args.repeat):
        clock = time.perf_counter()
        result = refine_maplet(maplet, chosen, tracer, config=config)
        times.append(time.perf_counter() - clock)
    print(f"maplet {maplet.name}: {maplet.n} x {maplet.n} nodes at {maplet.spacing_km * 1e3:.3f} m, "
          f"{len(result.images)} of {len(chosen)} images used, {result.iterations} iterations, mode {args.mode}")
    print(f"{'run':<6}{'seconds':>9}")
    for k, t in enumerate(times, 1):
        print(f"{k:<6}{t:>9.2f}")
    print(f"{'best':<6}{min(times):>9.2f}")


if __name__ == "__main__":
    main()
