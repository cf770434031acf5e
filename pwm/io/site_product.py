"""Local terrain product of a site: heights, albedo, slope and roughness on the site frame's
grid as a PDS4 Product_Observational (four Array_2D_Image objects in one binary file) with a PNG
preview.

Arrays are [line, sample] = [i (y), j (x)] with x and y increasing; heights in metres along
the site frame's z, big-endian IEEE doubles; albedo, slope (deg from the site frame's z, the
regional normal: the tilt of the plane fitted over the baseline) and roughness (m, RMS about
that plane; pwm.site) big-endian IEEE singles. Nodes without data (NaN) are stored as MISSING and declared as the
missing_constant.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import NamedTuple

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LightSource
from matplotlib.figure import Figure
from scipy.ndimage import distance_transform_edt

from pwm.frames import LocalFrame
from pwm.io.pds4 import INFORMATION_MODEL, checksum_md5, label_text, utc_iso
from pwm.site import BASELINE_M, roughness_m, slope_deg

MISSING = -1.0e32  # the PDS convention for missing real values
_HEIGHT = ("IEEE754MSBDouble", ">f8")  # (PDS4 data_type, numpy dtype)
_SINGLE = ("IEEE754MSBSingle", ">f4")


class SiteProductFiles(NamedTuple):
    """Paths of a written site product."""

    label: Path
    data: Path
    preview: Path


def write_site_product(directory: str | Path, *, name: str, frame: LocalFrame, x_km: np.ndarray,
                       y_km: np.ndarray, height_km: np.ndarray, albedo: np.ndarray, lid: str,
                       version: str, model_version: str, body_frame: str, target_name: str,
                       target_type: str = "Asteroid", mission: str, host_name: str,
                       start_utc: str, stop_utc: str,
                       baseline_m: float = BASELINE_M) -> SiteProductFiles:
    """Write name.xml (PDS4 label), name.dat (heights, albedo, slope, roughness) and name.png
    (shaded relief and albedo side by side) into `directory`; existing files are never
    overwritten. Slope and roughness are computed from the heights (pwm.site) over a window of
    side baseline_m; the grid must be square (equal x and y steps).

    frame: the site frame (origin and axes in body_frame, km); x_km (nx,), y_km (ny,): regular,
    increasing node coordinates in it; height_km, albedo: (ny, nx), NaN where there is no data.
    start_utc, stop_utc: time span of the images behind the model (UTC ISO-8601).
    """
    x, y = _axis(x_km, "x_km"), _axis(y_km, "y_km")
    start, stop = utc_iso(start_utc), utc_iso(stop_utc)
    height_m = np.asarray(height_km, dtype=np.float64) * 1e3
    albedo = np.asarray(albedo, dtype=np.float64)
    if height_m.shape != (len(y), len(x)) or albedo.shape != height_m.shape:
        raise ValueError(f"height {height_m.shape} and albedo {albedo.shape} must be "
                         f"(len(y_km), len(x_km)) = {(len(y), len(x))}")
    if np.isnan(height_m).all():
        raise ValueError("height_km has no data")
    spacing_m = (x[1] - x[0]) * 1e3
    if abs((y[1] - y[0]) * 1e3 - spacing_m) > 1e-9 * spacing_m:
        raise ValueError(f"x_km and y_km must have the same step, got {x[1] - x[0]} and "
                         f"{y[1] - y[0]}")
    if Path(name).name != name:
        raise ValueError(f"name {name!r} must be a bare file name")
    files = SiteProductFiles(*(Path(directory) / f"{name}.{ext}" for ext in ("xml", "dat", "png")))
    for path in files:
        if path.exists():
            raise FileExistsError(f"{path} exists; a product is written once")

    slope = slope_deg(height_m, spacing_m=spacing_m, baseline_m=baseline_m)
    roughness = roughness_m(height_m, spacing_m=spacing_m, baseline_m=baseline_m)
    contents = [
        ("height", height_m, _HEIGHT, "m",
         "Height (m) along the site frame z axis; the site frame and grid are described in the "
         "Observation_Area comment."),
        ("albedo", albedo, _SINGLE, None, "Normal albedo (unitless) at the same nodes as the "
                                          "heights."),
        ("slope", slope, _SINGLE, "deg",
         f"Slope (deg): angle from the site frame z axis (the regional normal) of the normal of "
         f"the plane fitted over the square of side {baseline_m:g} m centred on each node."),
        ("roughness", roughness, _SINGLE, "m",
         f"Roughness (m): RMS deviation of the heights from the plane fitted over the square "
         f"of side {baseline_m:g} m centred on each node."),
    ]
    arrays = [np.where(np.isnan(a), MISSING, a).astype(dtype) for _, a, (_, dtype), *_ in contents]
    with open(files.data, "xb") as fh:
        for array in arrays:
            fh.write(array.tobytes())
    frame_text = _frame_text(frame, body_frame, x, y)
    offsets = np.cumsum([0] + [a.nbytes for a in arrays[:-1]])
    images = [_image(local_id, int(offset), data_type, unit, height_m.shape, description)
              for (local_id, _, (data_type, _), unit, description), offset
              in zip(contents, offsets, strict=True)]
    text = label_text([
        ("Identification_Area", [
            ("logical_identifier", lid), ("version_id", version),
            ("title", f"{target_name} site {name}: local heights and albedo from shape model "
                      f"{model_version}"),
            ("information_model_version", INFORMATION_MODEL),
            ("product_class", "Product_Observational")]),
        ("Observation_Area", [
            ("comment", f"Shape model version {model_version}. {frame_text}"),
            ("Time_Coordinates", [("start_date_time", start), ("stop_date_time", stop)]),
            ("Investigation_Area", [("name", mission), ("type", "Mission")]),
            ("Observing_System", [("Observing_System_Component", [("name", host_name),
                                                                   ("type", "Host")])]),
            ("Target_Identification", [("name", target_name), ("type", target_type)])]),
        ("File_Area_Observational", [
            ("File", [
                ("file_name", files.data.name),
                ("creation_date_time", datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")),
                ("file_size", files.data.stat().st_size, "byte"),
                ("md5_checksum", checksum_md5(files.data))]),
            *images])])
    with open(files.label, "x", encoding="utf-8") as fh:
        fh.write(text)
    _preview(files.preview, x, y, height_m, albedo, title=f"{target_name} site {name} "
             f"(model {model_version})")
    return files


def _axis(values: np.ndarray, what: str) -> np.ndarray:
    axis = np.asarray(values, dtype=np.float64)
    step = np.diff(axis)
    if axis.ndim != 1 or len(axis) < 2 or step.min() <= 0 or np.ptp(step) > 1e-9 * step.mean():
        raise ValueError(f"{what} must be regular and increasing")
    return axis


def _frame_text(frame: LocalFrame, body_frame: str, x: np.ndarray, y: np.ndarray) -> str:
    def vector(v: np.ndarray) -> str:
        return "(" + ", ".join(f"{c:.12g}" for c in v) + ")"

    rows = ", ".join(f"{axis} axis {vector(v)}" for axis, v in zip("xyz", frame.rotation, strict=True))
    return (f"Site frame in {body_frame} (km): origin {vector(frame.origin)}, {rows}. "
            f"Node (line i, sample j), both from 0, lies at origin + x_j x + y_i y + h z with "
            f"x_j = {x[0]:.12g} + j * {x[1] - x[0]:.12g} km and "
            f"y_i = {y[0]:.12g} + i * {y[1] - y[0]:.12g} km.")


def _image(local_id: str, offset: int, data_type: str, unit: str | None, shape: tuple,
           description: str) -> tuple:
    element = [("data_type", data_type), *([("unit", unit)] if unit else [])]
    return ("Array_2D_Image", [
        ("local_identifier", local_id), ("offset", offset, "byte"), ("axes", 2),
        ("axis_index_order", "Last Index Fastest"), ("description", description),
        ("Element_Array", element),
        ("Axis_Array", [("axis_name", "Line"), ("elements", shape[0]), ("sequence_number", 1)]),
        ("Axis_Array", [("axis_name", "Sample"), ("elements", shape[1]), ("sequence_number", 2)]),
        ("Special_Constants", [("missing_constant", repr(MISSING))])])


def _preview(path: Path, x: np.ndarray, y: np.ndarray, height_m: np.ndarray,
             albedo: np.ndarray, *, title: str) -> None:
    """Shaded relief (light from the upper left, -x +y) and albedo, +y up, axes in m."""
    step_m = (x[1] - x[0]) * 1e3
    # LightSource takes row 0 as the top of the picture: flip so that +y is up
    height_m, albedo = np.flipud(height_m), np.flipud(albedo)
    missing = np.isnan(height_m)
    # gaps take their nearest node's height so that they do not shade their neighbours
    nearest = distance_transform_edt(missing, return_distances=False, return_indices=True)
    relief = LightSource(azdeg=315, altdeg=45).hillshade(height_m[tuple(nearest)], dx=step_m,
                                                         dy=step_m)
    relief[missing] = np.nan
    half = step_m / 2
    extent = (x[0] * 1e3 - half, x[-1] * 1e3 + half, y[0] * 1e3 - half, y[-1] * 1e3 + half)
    fig = Figure(figsize=(10.0, 4.5), layout="constrained")
    FigureCanvasAgg(fig)
    for k, (image, label) in enumerate([(relief, "shaded relief"), (albedo, "normal albedo")]):
        ax = fig.add_subplot(1, 2, k + 1)
        shown = ax.imshow(np.ma.masked_invalid(image), cmap="gray", extent=extent, origin="upper")
        if k == 1:
            fig.colorbar(shown, ax=ax, shrink=0.8)
        ax.set_title(label)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    fig.suptitle(title)
    fig.savefig(path, dpi=100)
