"""Where the height error lies: on boulder walls, at crater rims, at maplet edges, in shadow, or
elsewhere, so that each remedy is judged by what it fixes.

Classes are drawn on the evaluation grid of the site frame (x, y in km, heights along z) from
what only the proving ground knows (the truth's heights and craters, the images' Sun directions)
and from the maplets' frames. A node may belong to several classes; `elsewhere` is the nodes in
none.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pwm.frames import LocalFrame
from pwm.raytrace import RayTracer
from pwm.simulate.terrain import Boulder, Crater

WALL_SLOPE_DEG = 60.0
"""Steeper than this (from the site's regional normal): a boulder wall."""
RIM_BAND = 0.15
"""Within this fraction of a crater's radius of its rim crest: the rim."""
EDGE_BAND_GSD = 2.0
"""Within this many GSD of a maplet's border: its edge."""
SHADOW_SHARE = 0.5
"""Shadowed in at least this share of the images: in shadow."""
CLASSES = ("walls", "rims", "maplet edges", "shadow", "elsewhere")
BOULDER_REACH = 0.75
"""A boulder's nodes lie within this many of its diameters of its centre: its disc and an apron
half its radius wide, where a model that holds its top low may hold its foot high."""
BOULDER_SIZE_CLASSES_M = (1.0, 2.0, 3.0)
"""Boulder diameters (m) that bound the size classes: below 1 m, 1-2 m, 2-3 m, 3 m and above."""


@dataclass(frozen=True)
class MapletFootprint:
    """A maplet's square in the body: its frame and half its side (km)."""

    frame: LocalFrame
    half_km: float


def rim_mask(x_km: np.ndarray, y_km: np.ndarray, craters: list[Crater], band: float = RIM_BAND) -> np.ndarray:
    """Nodes (len(y), len(x)) within band * radius of a crater's rim crest."""
    gx, gy = np.meshgrid(x_km, y_km)
    mask = np.zeros(gx.shape, bool)
    for c in craters:
        radius = c.diameter_km / 2
        mask |= np.abs(np.hypot(gx - c.x_km, gy - c.y_km) - radius) <= band * radius
    return mask


def boulder_size_masks(x_km: np.ndarray, y_km: np.ndarray, boulders: list[Boulder],
                       bounds_m: tuple[float, ...] = BOULDER_SIZE_CLASSES_M, *,
                       reach_diameters: float = BOULDER_REACH) -> dict[str, np.ndarray]:
    """Nodes (len(y), len(x)) within reach_diameters diameters of a boulder (by default its
    apron too), by the boulder's size class ('boulders <1 m', 'boulders 1-2 m', ...,
    'boulders >=3 m' for the default bounds)."""
    edges = [f"{b:g}" for b in bounds_m]
    names = [f"boulders <{edges[0]} m", *(f"boulders {a}-{b} m" for a, b in zip(edges, edges[1:], strict=False)),
             f"boulders >={edges[-1]} m"]
    x, y = np.asarray(x_km), np.asarray(y_km)
    masks = {name: np.zeros((len(y), len(x)), bool) for name in names}
    for b in boulders:
        reach = reach_diameters * b.diameter_km
        cols = slice(np.searchsorted(x, b.x_km - reach), np.searchsorted(x, b.x_km + reach, side="right"))
        rows = slice(np.searchsorted(y, b.y_km - reach), np.searchsorted(y, b.y_km + reach, side="right"))
        near = np.hypot(x[cols][None, :] - b.x_km, y[rows][:, None] - b.y_km) <= reach
        masks[names[int(np.searchsorted(bounds_m, b.diameter_km * 1e3, side="right"))]][rows, cols] |= near
    return masks


def on_boulders(x_km: np.ndarray, y_km: np.ndarray, boulders: list[Boulder]) -> np.ndarray:
    """Nodes (len(y), len(x)) on any boulder's disc (its apron not): ground no boulder is
    measured from (`pwm.evaluate.profiles.boulder_height_ratio`'s ground is the rest)."""
    return np.any(list(boulder_size_masks(x_km, y_km, boulders, reach_diameters=0.5).values()), axis=0)


def edge_mask(points_body: np.ndarray, footprints: list[MapletFootprint], band_km: float) -> np.ndarray:
    """Points (..., 3, body-fixed km) within band_km inside the border of any maplet: where
    fusion joins a maplet to its neighbours."""
    flat = points_body.reshape(-1, 3)
    near_edge = np.zeros(len(flat), bool)
    for f in footprints:
        local = f.frame.to_local(flat)
        depth = f.half_km - np.maximum(np.abs(local[:, 0]), np.abs(local[:, 1]))
        near_edge |= (depth >= 0) & (depth <= band_km)
    return near_edge.reshape(points_body.shape[:-1])


def shadow_share(tracer: RayTracer, points_body: np.ndarray, normals_body: np.ndarray,
                 suns_body: np.ndarray) -> np.ndarray:
    """Share of the Sun directions (k, 3, unit, body-fixed) for which each surface point
    (..., 3) is in shadow: facing away, or with the Sun hidden by the tracer's surface."""
    flat, normal = points_body.reshape(-1, 3), normals_body.reshape(-1, 3)
    shadowed = np.zeros(len(flat))
    for sun in suns_body:
        facing = normal @ sun > 0
        hidden = np.ones(len(flat), bool)
        start = flat[facing] + tracer.offset * normal[facing]
        hidden[facing] = tracer.occluded(start, np.broadcast_to(sun, start.shape))
        shadowed += hidden
    return (shadowed / max(len(suns_body), 1)).reshape(points_body.shape[:-1])


def error_by_class(error: np.ndarray, masks: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """RMS, 95th percentile of |error| and node count of each class (same unit as the error;
    nan nodes left out), with `elsewhere` for the nodes in no class."""
    valid = np.isfinite(error)
    anywhere = np.zeros(error.shape, bool)
    for mask in masks.values():
        anywhere |= mask
    out = {}
    for name, mask in {**masks, "elsewhere": ~anywhere}.items():
        values = np.abs(error[mask & valid])
        out[name] = {"nodes": int(values.size),
                     "rms": float(np.sqrt(np.mean(values**2))) if values.size else float("nan"),
                     "p95": float(np.percentile(values, 95)) if values.size else float("nan")}
    return out
