"""Evaluation figures written as PNG files (matplotlib's Agg canvas, no pyplot state)."""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def height_error_map(
    path: str | os.PathLike[str],
    x_km: np.ndarray,
    y_km: np.ndarray,
    error_m: np.ndarray,
    *,
    title: str,
) -> None:
    """Map of model minus truth height (m) on a site-frame grid: x_km (nx,), y_km (ny,) node
    coordinates, error_m (ny, nx); nan where there is no model. Axes in metres, diverging colours
    with limits symmetric about zero at the 99th percentile of |error|; north (the site frame's
    +y, pwm.frames.local_frame) up."""
    error = np.ma.masked_invalid(np.asarray(error_m, float))
    limit = float(np.percentile(np.abs(error.compressed()), 99)) if error.count() else 1.0
    limit = limit if limit > 0 else 1.0
    fig = _figure(6.0, 5.0)
    ax = fig.add_subplot()
    mesh = ax.pcolormesh(
        np.asarray(x_km) * 1e3,
        np.asarray(y_km) * 1e3,
        error,
        cmap="RdBu_r",
        vmin=-limit,
        vmax=limit,
        shading="auto",
    )
    fig.colorbar(mesh, ax=ax, label="model - truth height (m)", extend="both")
    ax.set_aspect("equal")
    ax.set_xlabel("x, site frame (m)")
    ax.set_ylabel("y, site frame (m)")
    ax.set_title(title)
    north_arrow(ax)
    fig.savefig(path, dpi=120)


def class_map(
    path: str | os.PathLike[str],
    x_km: np.ndarray,
    y_km: np.ndarray,
    masks: dict[str, np.ndarray],
    error_m: np.ndarray,
    *,
    title: str,
) -> None:
    """Where each class lies (left; a node in several shows the first named) beside |error| (m,
    right), on a site-frame grid as height_error_map's; nan error is left blank on both."""
    from matplotlib.colors import ListedColormap

    names = list(masks)
    label = np.full(np.shape(error_m), len(names), float)
    for k in reversed(range(len(names))):
        label[masks[names[k]]] = k
    label[~np.isfinite(error_m)] = np.nan
    colours = ListedColormap(["#d62728", "#ff7f0e", "#9467bd", "#1f77b4", "#e0e0e0"][: len(names)] + ["#e0e0e0"])
    fig = _figure(12.0, 5.0)
    x_m, y_m = np.asarray(x_km) * 1e3, np.asarray(y_km) * 1e3
    ax = fig.add_subplot(1, 2, 1)
    mesh = ax.pcolormesh(x_m, y_m, np.ma.masked_invalid(label), cmap=colours, vmin=-0.5, vmax=len(names) + 0.5,
                         shading="auto")
    bar = fig.colorbar(mesh, ax=ax, ticks=range(len(names) + 1))
    bar.ax.set_yticklabels([*names, "elsewhere"])
    ax.set_title(title)
    ax2 = fig.add_subplot(1, 2, 2)
    magnitude = np.ma.masked_invalid(np.abs(np.asarray(error_m, float)))
    top = float(np.percentile(magnitude.compressed(), 99)) if magnitude.count() else 1.0
    shown = ax2.pcolormesh(x_m, y_m, magnitude, cmap="magma", vmin=0, vmax=top if top > 0 else 1.0, shading="auto")
    fig.colorbar(shown, ax=ax2, label="|model - truth| height (m)", extend="max")
    for a in (ax, ax2):
        a.set_aspect("equal")
        a.set_xlabel("x, site frame (m)")
        a.set_ylabel("y, site frame (m)")
        north_arrow(a)
    fig.savefig(path, dpi=120)


def profiles(
    path: str | os.PathLike[str],
    profiles: list[tuple[np.ndarray, np.ndarray, np.ndarray, str]],
    *,
    columns: int = 3,
) -> None:
    """Small multiples of height profiles: each (distance_m, truth_height_m, model_height_m,
    label) in its own panel, truth and model on the same axes."""
    columns = min(columns, max(len(profiles), 1))
    rows = max(math.ceil(len(profiles) / columns), 1)
    fig = _figure(4.0 * columns, 3.0 * rows)
    for i, (distance, truth, model, label) in enumerate(profiles):
        ax = fig.add_subplot(rows, columns, i + 1)
        ax.plot(distance, truth, color="black", label="truth")
        ax.plot(distance, model, color="tab:red", linestyle="--", label="model")
        ax.set_title(label, fontsize="medium")
        ax.set_xlabel("distance (m)")
        ax.set_ylabel("height (m)")
        if i == 0:
            ax.legend(fontsize="small")
    fig.savefig(path, dpi=120)


def image_comparison(
    path: str | os.PathLike[str],
    truth_image: np.ndarray,
    model_image: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    title: str,
) -> None:
    """Truth and model images side by side on the same grey scale, and model minus truth. With a
    mask, only its pixels are drawn and set the scales, cropped to them: a site a few percent
    of the frame would otherwise be a speck, its scales set by the sky."""
    truth = np.asarray(truth_image, float)
    model = np.asarray(model_image, float)
    if mask is not None:
        keep = np.asarray(mask, bool)
        if keep.any():
            rows, cols = np.flatnonzero(keep.any(axis=1)), np.flatnonzero(keep.any(axis=0))
            crop = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
            truth, model = (np.where(keep, image, np.nan)[crop] for image in (truth, model))
    finite = truth[np.isfinite(truth)]
    low, high = np.percentile(finite, [0.5, 99.5]) if finite.size else (0.0, 1.0)
    difference = model - truth
    finite_diff = np.abs(difference[np.isfinite(difference)])
    limit = float(np.percentile(finite_diff, 99)) if finite_diff.size else 1.0
    limit = limit if limit > 0 else 1.0
    fig = _figure(13.0, 4.5)
    panels: list[tuple[str, np.ndarray, dict[str, Any]]] = [
        ("truth", truth, {"cmap": "gray", "vmin": low, "vmax": high}),
        ("model", model, {"cmap": "gray", "vmin": low, "vmax": high}),
        ("model - truth", difference, {"cmap": "RdBu_r", "vmin": -limit, "vmax": limit}),
    ]
    for i, (name, image, style) in enumerate(panels):
        ax = fig.add_subplot(1, 3, i + 1)
        shown = ax.imshow(image, interpolation="nearest", **style)
        ax.set_title(name)
        ax.set_axis_off()
        fig.colorbar(shown, ax=ax, shrink=0.75)
    fig.suptitle(title)
    fig.savefig(path, dpi=120)


def body_map(path: str | os.PathLike[str], points_km: np.ndarray, values: np.ndarray, *, title: str,
             label: str, limits: tuple[float, float] | None = None) -> None:
    """Values at body-fixed points (N, 3) on a map of planetocentric longitude and latitude,
    coloured over limits (default: the 1st to the 99th percentile), the largest drawn last (a
    whole body's errors or coverage at a glance: the few bad places must show over the many)."""
    v = np.asarray(values, float)
    order = np.argsort(v, kind="stable")
    v = v[order]
    p = np.asarray(points_km, float)[order]
    lon = np.degrees(np.arctan2(p[:, 1], p[:, 0])) % 360.0
    lat = np.degrees(np.arcsin(np.clip(p[:, 2] / np.linalg.norm(p, axis=1), -1.0, 1.0)))
    low, high = limits if limits is not None else np.percentile(v, [1, 99]) if v.size else (0.0, 1.0)
    fig = _figure(8.0, 4.2)
    ax = fig.add_subplot()
    dots = ax.scatter(lon, lat, c=v, s=1.0, cmap="viridis", vmin=low, vmax=max(high, low + 1e-12), linewidths=0)
    fig.colorbar(dots, ax=ax, label=label)
    ax.set_xlim(0, 360)
    ax.set_ylim(-90, 90)
    ax.set_xlabel("east longitude (deg)")
    ax.set_ylabel("latitude (deg)")
    ax.set_title(title)
    north_arrow(ax)
    fig.savefig(path, dpi=120)


def coverage_map(path: str | os.PathLike[str], points_km: np.ndarray, gap_m: np.ndarray, *,
                 tolerance_m: float) -> None:
    """The distance (m) from truth points (N, 3) to the model on a fixed scale up to tolerance_m,
    beyond which a point is not covered: a coverage of 99% coloured by percentile is one colour."""
    body_map(path, points_km, gap_m, title=f"truth to model distance (m): not covered at {tolerance_m:g} m or more",
             label="m", limits=(0.0, tolerance_m))


def north_arrow(ax: Axes) -> None:
    """An arrow marked N in the map's top right corner, pointing up: north on a map whose y grows
    northwards (latitude, or a site frame's y)."""
    ax.annotate("N", xy=(0.95, 0.97), xytext=(0.95, 0.84), xycoords="axes fraction", ha="center", va="center",
                fontweight="bold", arrowprops={"arrowstyle": "-|>", "color": "black"})


def _figure(width_in: float, height_in: float) -> Figure:
    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig
