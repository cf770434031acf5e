"""Rays dropped down a local frame onto a surface: the one sampler of heights over a frame's
x-y plane, used by tiling (maplet heights and centres), evaluation (model and truth heights)
and site products (pwm.site).

A ray starts at height top_km over local (x, y) and goes down the frame's z; the first surface
it meets gives the height there, top_km - t. Each caller chooses top_km above all the surface
it samples, so that the first hit is the top.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pwm.frames import LocalFrame
from pwm.raytrace import Hits, RayTracer


def drop_rays(tracer: RayTracer, frame: LocalFrame, x_km: np.ndarray, y_km: np.ndarray, *, top_km: float,
              bottom_km: float = -np.inf, on_facets: bool = False) -> tuple[Hits, np.ndarray]:
    """First hits of rays cast down the frame's z from top_km at local (x_km, y_km) (flat arrays
    of one length), and the heights (km along z) they meet the surface at, NaN on a miss. A hit
    below bottom_km is a miss: a ray through a pinhole of the surface meets the body's far side,
    hundreds of metres down.

    The heights are top_km - t, t in Embree's single precision (about 1e-7 of top_km's distance
    from the body centre off), or with on_facets the z of the hit points rebuilt in double
    precision on the facets (RayTracer.hit_points), as the site products take them; tiling and
    evaluation keep the former, which their published results were made with."""
    origins = frame.to_body(np.column_stack([x_km, y_km, np.full(len(x_km), top_km)]))
    down = np.broadcast_to(-frame.normal, origins.shape)
    hits = tracer.intersect(origins, down)
    heights = top_km - hits.t
    through = hits.hit & (heights < bottom_km)
    if through.any():
        hits = replace(hits, face=np.where(through, -1, hits.face), t=np.where(through, np.inf, hits.t))
    if on_facets:
        return hits, frame.to_local(tracer.hit_points(origins, down, hits))[:, 2]
    return hits, np.where(hits.hit, heights, np.nan)
