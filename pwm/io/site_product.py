"""Local terrain product of a site: heights, albedo, slope and roughness on the site frame's
grid as a PDS4 Product_Observational (four Array_2D_Image objects in one binary file) with a PNG
preview, and the same layers for the GIS and ISIS rasters (site_layers; pwm.io.terrain).

Arrays are [line, sample] with line 0 the northernmost (+y) row and samples running east (+x),
as the Cartography area's upper-left corner has them; heights in metres along the site frame's
z, big-endian IEEE doubles; albedo, slope (deg from the site frame's z, the regional normal: the
tilt of the plane fitted over the baseline) and roughness (m, RMS about that plane; pwm.site)
big-endian IEEE singles. Nodes without data (NaN) are stored as MISSING and declared as the
missing_constant.

The label is of PDS4 information model 1.16.0.0 (INFORMATION_MODEL) with the Cartography
dictionary (CART_NS): the bounding latitudes and longitudes of the nodes, the orthographic
projection of the site frame (pwm.io.terrain.SiteProjection) with its upper-left corner and
pixel size, and the body's radii as the geodetic model; a Source_Product_Internal names the
shape model version it was sampled from. Every label written is validated against the schema
files shipped in pwm/data/pds4_schema (label_schema), never fetched from the network.
"""

from __future__ import annotations

import functools
import re
import xml.etree.ElementTree as ET
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import xmlschema
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LightSource
from matplotlib.figure import Figure
from scipy.ndimage import distance_transform_edt

from pwm.frames import LocalFrame, unit_to_latlon
from pwm.io.pds4 import PDS_NS, XSI_NS, build_elements, checksum_md5, utc_iso
from pwm.io.terrain import SiteProjection, TerrainLayer
from pwm.site import BASELINE_M, roughness_m, slope_deg

MISSING = -1.0e32  # the PDS convention for missing real values
INFORMATION_MODEL = "1.16.0.0"  # schema files 1G00, Cartography 1G00_1950
CART_NS = "http://pds.nasa.gov/pds4/cart/v1"
GEOM_NS = "http://pds.nasa.gov/pds4/geom/v1"
SCHEMA_DIR = Path(__file__).resolve().parents[1] / "data" / "pds4_schema"
# namespace -> schema file (without suffix) in SCHEMA_DIR, as https://pds.nasa.gov/pds4/ has it
_SCHEMAS = {PDS_NS: "pds/v1/PDS4_PDS_1G00", CART_NS: "cart/v1/PDS4_CART_1G00_1950",
            GEOM_NS: "geom/v1/PDS4_GEOM_1G00_1920"}
_HEIGHT = ("IEEE754MSBDouble", ">f8")  # (PDS4 data_type, numpy dtype)
_SINGLE = ("IEEE754MSBSingle", ">f4")


class SiteProductFiles(NamedTuple):
    """Paths of a written site product."""

    label: Path
    data: Path
    preview: Path


def site_layers(height_km: np.ndarray, albedo: np.ndarray, *, spacing_m: float,
                baseline_m: float = BASELINE_M, sigma_km: np.ndarray | None = None) -> list[TerrainLayer]:
    """A site's terrain layers on its grid (rows y increasing, NaN where no data): height (m
    along the site frame's z), albedo, slope (deg) and roughness (m) over the baseline, and the
    heights' 1-sigma uncertainty (m) where the model has one."""
    height_m = np.asarray(height_km, dtype=np.float64) * 1e3
    uncertain = [] if sigma_km is None else [
        TerrainLayer("height_sigma", np.asarray(sigma_km, dtype=np.float64) * 1e3, "m",
                     "One-sigma uncertainty (m) of the height at each node, from how the images "
                     "agree with the refined shape (pwm.uncertainty); no data where no refined "
                     "maplet covers the node.")]
    return [
        TerrainLayer("height", height_m, "m",
                     "Height (m) along the site frame z axis (the regional normal) from the site "
                     "frame origin."),
        TerrainLayer("albedo", np.asarray(albedo, dtype=np.float64), "",
                     "Normal albedo (unitless) at the same nodes as the heights."),
        TerrainLayer("slope", slope_deg(height_m, spacing_m=spacing_m, baseline_m=baseline_m),
                     "deg",
                     f"Slope (deg): angle from the site frame z axis (the regional normal) of the "
                     f"normal of the plane fitted over the square of side {baseline_m:g} m "
                     f"centred on each node."),
        TerrainLayer("roughness", roughness_m(height_m, spacing_m=spacing_m, baseline_m=baseline_m),
                     "m",
                     f"Roughness (m): RMS deviation of the heights from the plane fitted over the "
                     f"square of side {baseline_m:g} m centred on each node."),
    ] + uncertain


def write_site_product(directory: str | Path, *, name: str, frame: LocalFrame, x_km: np.ndarray,
                       y_km: np.ndarray, height_km: np.ndarray, albedo: np.ndarray,
                       projection: SiteProjection, lid: str, version: str, model_version: str,
                       source_lidvid: str, body_frame: str, target_name: str,
                       target_type: str = "Asteroid", mission: str, host_name: str,
                       start_utc: str, stop_utc: str,
                       baseline_m: float = BASELINE_M, sigma_km: np.ndarray | None = None) -> SiteProductFiles:
    """Write name.xml (PDS4 label), name.dat (heights, albedo, slope, roughness) and name.png
    (shaded relief and albedo side by side) into `directory`; existing files are never
    overwritten. Slope and roughness are computed from the heights (pwm.site) over a window of
    side baseline_m; the grid must be square (equal x and y steps).

    frame: the site frame (origin and axes in body_frame, km); x_km (nx,), y_km (ny,): regular,
    increasing node coordinates in it; height_km, albedo: (ny, nx), NaN where there is no data;
    sigma_km: the heights' 1-sigma uncertainty alike, a layer of its own (None: the model has none).
    projection: the site frame's map projection (pwm.io.terrain.site_projection).
    source_lidvid: the LIDVID the shape model version is referred to by.
    start_utc, stop_utc: time span of the images behind the model (UTC ISO-8601).
    """
    x, y = _axis(x_km, "x_km"), _axis(y_km, "y_km")
    start, stop = utc_iso(start_utc), utc_iso(stop_utc)
    shape = (len(y), len(x))
    sigma_shape = shape if sigma_km is None else np.shape(sigma_km)
    if np.shape(height_km) != shape or np.shape(albedo) != shape or sigma_shape != shape:
        raise ValueError(f"height {np.shape(height_km)}, albedo {np.shape(albedo)} and sigma "
                         f"{sigma_shape} must be (len(y_km), len(x_km)) = {shape}")
    if np.isnan(height_km).all():
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

    layers = site_layers(height_km, albedo, spacing_m=spacing_m, baseline_m=baseline_m, sigma_km=sigma_km)
    types = [_HEIGHT if layer.name == "height" else _SINGLE for layer in layers]
    # line 0 north: the grid's last row first
    arrays = [np.flipud(np.where(np.isnan(layer.values), MISSING, layer.values)).astype(dtype)
              for layer, (_, dtype) in zip(layers, types, strict=True)]
    with open(files.data, "xb") as fh:
        for array in arrays:
            fh.write(array.tobytes())
    offsets = np.cumsum([0] + [a.nbytes for a in arrays[:-1]])
    images = [_image(layer, int(offset), data_type, shape)
              for layer, (data_type, _), offset in zip(layers, types, offsets, strict=True)]
    height_m = layers[0].values
    text = _label_text([
        ("Identification_Area", [
            ("logical_identifier", lid), ("version_id", version),
            ("title", f"{target_name} site {name}: local heights and albedo from shape model "
                      f"{model_version}"),
            ("information_model_version", INFORMATION_MODEL),
            ("product_class", "Product_Observational")]),
        ("Observation_Area", [
            ("comment", f"Shape model version {model_version}. {_frame_text(frame, body_frame)}"),
            ("Time_Coordinates", [("start_date_time", start), ("stop_date_time", stop)]),
            ("Investigation_Area", [
                ("name", mission), ("type", "Mission"),
                ("Internal_Reference", [
                    ("lid_reference", "urn:nasa:pds:context:investigation:mission."
                                      + _lid_part(mission)),
                    ("reference_type", "data_to_investigation"),
                    ("comment", "Made from the mission's name: check it against the PDS "
                                "context product.")])]),
            ("Observing_System", [("Observing_System_Component", [("name", host_name),
                                                                   ("type", "Host")])]),
            ("Target_Identification", [("name", target_name), ("type", target_type)]),
            ("Discipline_Area", [_cartography(projection, frame, x, y, height_m,
                                              [layer.name for layer in layers])])]),
        ("Reference_List", [
            ("Source_Product_Internal", [
                ("lidvid_reference", source_lidvid),
                ("reference_type", "data_to_derived_source_product"),
                ("comment", f"The shape model version {model_version} the site was sampled "
                            f"from.")])]),
        ("File_Area_Observational", [
            ("File", [
                ("file_name", files.data.name),
                ("creation_date_time", datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")),
                ("file_size", files.data.stat().st_size, "byte"),
                ("md5_checksum", checksum_md5(files.data))]),
            *images])])
    errors = [f"{e.path}: {e.reason}" for e in label_schema().iter_errors(text)]
    if errors:
        raise ValueError(f"the site label does not validate against PDS4 {INFORMATION_MODEL}: "
                         + "; ".join(errors[:10]))
    with open(files.label, "x", encoding="utf-8") as fh:
        fh.write(text)
    _preview(files.preview, x, y, height_m, layers[1].values,
             title=f"{target_name} site {name} (model {model_version})")
    return files


@functools.cache
def label_schema() -> xmlschema.XMLSchema:
    """The PDS4 core and Cartography schemas (with the Geometry one Cartography imports) from
    SCHEMA_DIR: the label's remote schema locations map onto these files, and nothing outside
    SCHEMA_DIR is ever read (no download)."""
    locations = [(ns, str(SCHEMA_DIR / f"{Path(base).name}.xsd")) for ns, base in _SCHEMAS.items()]
    return xmlschema.XMLSchema(str(SCHEMA_DIR / f"{Path(_SCHEMAS[CART_NS]).name}.xsd"),
                               locations=locations, base_url=str(SCHEMA_DIR), allow="sandbox")


def _label_text(body: list[tuple]) -> str:
    # Namespaces as plain attributes, as pwm.io.pds4's labels have them; the site label adds
    # the Cartography namespace and is of a newer information model.
    used = (PDS_NS, CART_NS)
    root = ET.Element("Product_Observational", {
        "xmlns": PDS_NS, "xmlns:cart": CART_NS, "xmlns:xsi": XSI_NS,
        "xsi:schemaLocation": " ".join(f"{ns} https://pds.nasa.gov/pds4/{_SCHEMAS[ns]}.xsd"
                                       for ns in used)})
    build_elements(root, body)
    ET.indent(root, space="    ")
    models: list[ET.Element[Any]] = [
        ET.ProcessingInstruction("xml-model", f'href="https://pds.nasa.gov/pds4/{_SCHEMAS[ns]}.sch" '
                                              'schematypens="http://purl.oclc.org/dsdl/schematron"')
        for ns in used]
    return "\n".join(['<?xml version="1.0" encoding="UTF-8"?>',
                      *(ET.tostring(e, encoding="unicode") for e in [*models, root]), ""])


def _cartography(projection: SiteProjection, frame: LocalFrame, x: np.ndarray, y: np.ndarray,
                 height_m: np.ndarray, arrays: list[str]) -> tuple:
    """The cart:Cartography area: bounds of the nodes with data, the projection, the body."""
    xx, yy = np.meshgrid(x, y)
    found = ~np.isnan(height_m)
    nodes = frame.to_body(np.column_stack([xx[found], yy[found], height_m[found] * 1e-3]))
    lat, lon = unit_to_latlon(nodes)
    # longitudes about the projection's centre, so that a site across 0 deg is not split
    east_of = (np.asarray(lon) - projection.centre_lon_deg + 180.0) % 360.0 - 180.0
    step_m = float(x[1] - x[0]) * 1e3
    left, top = projection.upper_left_m(x, y)
    per_degree = float(np.radians(1.0)) * projection.sphere_radius_km * 1e3 / step_m
    a, b, c = projection.radii_km

    def deg(tag: str, value: float) -> tuple:
        return (f"cart:{tag}", f"{value:.10f}", "deg")

    return ("cart:Cartography", [
        *(("Local_Internal_Reference", [("local_identifier_reference", name),
                                        ("local_reference_type", "cartography_parameters_to_image_object")])
          for name in arrays),
        ("cart:Spatial_Domain", [("cart:Bounding_Coordinates", [
            deg("west_bounding_coordinate", projection.centre_lon_deg + float(east_of.min())),
            deg("east_bounding_coordinate", projection.centre_lon_deg + float(east_of.max())),
            deg("north_bounding_coordinate", float(np.max(lat))),
            deg("south_bounding_coordinate", float(np.min(lat)))])]),
        ("cart:Spatial_Reference_Information", [("cart:Horizontal_Coordinate_System_Definition", [
            ("cart:Planar", [
                ("cart:Map_Projection", [
                    ("cart:map_projection_name", "Orthographic"),
                    ("cart:Orthographic", [
                        deg("longitude_of_central_meridian", projection.centre_lon_deg),
                        deg("latitude_of_projection_origin", projection.centre_lat_deg)])]),
                ("cart:Planar_Coordinate_Information", [
                    ("cart:planar_coordinate_encoding_method", "Coordinate Pair"),
                    ("cart:Coordinate_Representation", [
                        ("cart:pixel_resolution_x", repr(step_m), "m/pixel"),
                        ("cart:pixel_resolution_y", repr(step_m), "m/pixel"),
                        ("cart:pixel_scale_x", repr(per_degree), "pixel/deg"),
                        ("cart:pixel_scale_y", repr(per_degree), "pixel/deg")])]),
                ("cart:Geo_Transformation", [("cart:upperleft_corner_x", repr(left), "m"),
                                             ("cart:upperleft_corner_y", repr(top), "m")])]),
            ("cart:Geodetic_Model", [
                ("cart:latitude_type", "Planetocentric"),
                ("cart:spheroid_name", f"{projection.body} (the projection's sphere: the mean of "
                                       f"the radii, {projection.sphere_radius_km:.6g} km)"),
                ("cart:a_axis_radius", repr(a), "km"), ("cart:b_axis_radius", repr(b), "km"),
                ("cart:c_axis_radius", repr(c), "km"),
                ("cart:longitude_direction", "Positive East")])])])])


def _lid_part(name: str) -> str:
    """`name` as a LID component: lower case, characters a LID cannot hold as '_'."""
    part = re.sub(r"[^a-z0-9._-]", "_", name.lower())
    return part or "unknown"


def _axis(values: np.ndarray, what: str) -> np.ndarray:
    axis = np.asarray(values, dtype=np.float64)
    step = np.diff(axis)
    if axis.ndim != 1 or len(axis) < 2 or step.min() <= 0 or np.ptp(step) > 1e-9 * step.mean():
        raise ValueError(f"{what} must be regular and increasing")
    return axis


def _frame_text(frame: LocalFrame, body_frame: str) -> str:
    def vector(v: np.ndarray) -> str:
        return "(" + ", ".join(f"{c:.12g}" for c in v) + ")"

    rows = ", ".join(f"{axis} axis {vector(v)}" for axis, v in zip("xyz", frame.rotation, strict=True))
    return (f"Site frame in {body_frame} (km): origin {vector(frame.origin)}, {rows}. "
            f"A node at site coordinates (x, y) with height h (m) lies at origin + x x + y y + "
            f"h/1000 z; x and y are the Cartography area's eastings and northings less the "
            f"origin's own (its projection's plane is the site frame's xy plane).")


def _image(layer: TerrainLayer, offset: int, data_type: str, shape: tuple) -> tuple:
    element = [("data_type", data_type), *([("unit", layer.unit)] if layer.unit else [])]
    return ("Array_2D_Image", [
        ("local_identifier", layer.name), ("offset", offset, "byte"), ("axes", 2),
        ("axis_index_order", "Last Index Fastest"), ("description", layer.description),
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
