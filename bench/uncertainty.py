"""How well a refined site's 1-sigma heights tell its error (issue 49.3): each site refined as
`pwm refine` refines it (pwm.pipeline.refine_region, both passes), the fused model registered to
the truth by ICP as `pwm evaluate` registers it, and, of the vertices with a sigma, the share
within one and two sigma of the truth (0.68 and 0.95 for a Gaussian error told exactly), for
every sigma scaled by each factor given: scaling Uncertainty's floor and gain alike scales every
node's sigma, and the fused sigma with it, by that factor. Also the median sigma and error (GSD),
and the share within one and two sigma by error class (vertices beyond 3 GSD, the rest).

    .venv/bin/python bench/uncertainty.py SIM [SIM ...] [--scales 0.5 0.6 0.7 0.8 1] [--workers 2]

SIM: a site simulation with a start model (`pwm simulate --scenario site --with-start-model`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from pwm.config import DEFAULTS
from pwm.evaluate.report import TAIL_GSD, in_site, register_to_truth
from pwm.io.downlink import read_downlink
from pwm.io.meshio import read_mesh
from pwm.pipeline import imaged_region, refine_region
from pwm.simulate.truth import load


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sims", nargs="+", type=Path)
    parser.add_argument("--scales", nargs="+", type=float, default=[0.5, 0.6, 0.7, 0.8, 1.0])
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    print(f"uncertainty: {DEFAULTS.uncertainty}")
    print(f"{'site':<12}{'scale':>6}{'within 1':>10}{'within 2':>10}{'median sigma':>14}{'median error':>14}"
          f"{'>3 GSD: w1':>12}{'w2':>6}{'rest: w1':>10}{'w2':>6}{'s':>6}")
    for sim in args.sims:
        manifest = json.loads((sim / "truth" / "manifest.json").read_text())
        scenario = manifest["scenario"]
        gsd = scenario["gsd_km"]
        views = read_downlink(sim / "downlink").views
        start = read_mesh(sim / "downlink" / "start_model.obj")
        truth = load(sim / "truth")
        region = imaged_region(views, start)
        # as bench/accuracy.py has `pwm refine` refine a site
        region = dataclasses.replace(region, radius_km=1.3 * scenario["site_size_km"] / 2,
                                     spacing_km=DEFAULTS.spacing_gsd * region.spacing_km)
        clock = time.perf_counter()
        model, _ = refine_region(start, views, region, config=DEFAULTS, workers=args.workers)
        seconds = time.perf_counter() - clock
        assert model.sigma is not None
        inside = in_site(model.vertices, truth)
        transform, surface = register_to_truth(model, truth, region=inside, gsd_km=gsd, whole_body=False)
        distance, _, _ = surface.query(transform.apply(model.vertices)[inside])
        sigma = model.sigma[inside]
        told = np.isfinite(sigma)
        distance, sigma = distance[told], sigma[told]
        tail = distance > TAIL_GSD * gsd
        for scale in args.scales:
            ratio = distance / (scale * sigma)

            def share(mask: np.ndarray, k: float, ratio: np.ndarray = ratio) -> float:
                return float(np.mean(ratio[mask] <= k)) if mask.any() else float("nan")

            everywhere = np.ones(len(ratio), bool)
            print(f"{sim.name:<12}{scale:6.2f}{share(everywhere, 1):10.3f}{share(everywhere, 2):10.3f}"
                  f"{np.median(scale * sigma) / gsd:14.3f}{np.median(distance) / gsd:14.3f}"
                  f"{share(tail, 1):12.3f}{share(tail, 2):6.3f}{share(~tail, 1):10.3f}{share(~tail, 2):6.3f}"
                  f"{seconds:6.0f}", flush=True)


if __name__ == "__main__":
    main()
