"""Site terrain rasters for GIS and ISIS: a site's layers (heights, albedo, slope, roughness on the
site frame's grid) as a GeoTIFF or an ISIS3 cube written through GDAL (rasterio), and the map
projection that places the site frame's grid on the body.

The projection (`SiteProjection`) is an orthographic one on a sphere of the body's mean radius,
centred on the direction of the site frame's z axis (the regional normal) and turned so that its
eastings and northings run along the frame's x (east) and y (north) axes: the orthographic plane
is the site frame's xy plane, so a node at site coordinates (x, y) has easting x + x0 and
northing y + y0, (x0, y0) being the frame origin's own projection. Heights stay what the site
product holds: metres along the frame's z from its origin, not above the sphere.

Rasters are one band per layer, row 0 the northernmost (+y) line as GIS expects, with band
descriptions and units, nodata where there is no surface, the projection as WKT and the
version, body, body-fixed frame and site frame as dataset metadata. ISIS cubes hold 32-bit
reals only; GeoTIFFs keep doubles.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pvl
import rasterio
from rasterio.crs import CRS
from rasterio.transform import from_origin

from pwm.frames import LocalFrame, unit_to_latlon

ISIS_NULL = float(np.float32(-3.4028226550889045e38))  # ISIS's Null special pixel for 32-bit reals
GEOTIFF_NODATA = -1.0e32  # as the site product's missing_constant
_LABEL_READ = 1 << 16  # GDAL's ISIS3 writer reserves this much for an attached label


class TerrainDriver(enum.StrEnum):
    """The GDAL driver a terrain raster is written with."""

    GEOTIFF = "GTiff"
    ISIS3 = "ISIS3"


@dataclass(frozen=True)
class TerrainLayer:
    """One band: a (ny, nx) array on the site grid (rows y increasing, NaN where no surface),
    its name, unit ('' for unitless) and a description."""

    name: str
    values: np.ndarray
    unit: str
    description: str


@dataclass(frozen=True)
class SiteProjection:
    """Orthographic projection of a site frame onto the sphere of the body's mean radius.

    body: the body's name; radii_km: its triaxial radii (the kernels'); centre_lat_deg,
    centre_lon_deg: planetocentric latitude and east longitude of the projection's centre (the
    frame's z); offset_km: the projection (easting, northing) of the frame's origin."""

    body: str
    radii_km: tuple[float, float, float]
    centre_lat_deg: float
    centre_lon_deg: float
    offset_km: tuple[float, float]

    @property
    def sphere_radius_km(self) -> float:
        return sum(self.radii_km) / 3.0

    def upper_left_m(self, x_km: np.ndarray, y_km: np.ndarray) -> tuple[float, float]:
        """Easting and northing (m) of the outer corner of the grid's first node on its
        northernmost line: nodes are cell centres, rows north first."""
        half_m = float(x_km[1] - x_km[0]) * 1e3 / 2
        return ((float(x_km[0]) + self.offset_km[0]) * 1e3 - half_m,
                (float(y_km[-1]) + self.offset_km[1]) * 1e3 + half_m)

    def wkt(self) -> str:
        """The projected CRS as WKT1 (GDAL's, also what the ISIS3 driver maps to a mapping group)."""
        name = self.body.replace('"', "'")
        radius_m = self.sphere_radius_km * 1e3
        return (f'PROJCS["{name} orthographic about the site",'
                f'GEOGCS["{name} (sphere, planetocentric)",DATUM["{name}",'
                f'SPHEROID["{name} mean sphere",{radius_m!r},0]],'
                'PRIMEM["Reference_Meridian",0],UNIT["degree",0.0174532925199433]],'
                'PROJECTION["Orthographic"],'
                f'PARAMETER["latitude_of_origin",{self.centre_lat_deg!r}],'
                f'PARAMETER["central_meridian",{self.centre_lon_deg!r}],'
                'PARAMETER["false_easting",0],PARAMETER["false_northing",0],UNIT["metre",1]]')


def site_projection(frame: LocalFrame, *, body: str, radii_km: Sequence[float]) -> SiteProjection:
    """The orthographic projection whose plane is `frame`'s xy plane with eastings along its x.

    The projection's east at its centre is (-sin lon0, cos lon0, 0); lon0 is chosen to make it
    the frame's x, which is east (pwm.frames.local_frame) except at a pole, where the frame's x
    is the body's +X projected and lon0 follows it. ValueError for radii that are not three
    positive numbers or a frame whose x is not horizontal."""
    radii = tuple(float(r) for r in radii_km)
    if len(radii) != 3 or not all(math.isfinite(r) and r > 0 for r in radii):
        raise ValueError(f"radii_km must be three positive numbers, got {radii_km}")
    x_axis, y_axis, z_axis = np.asarray(frame.rotation, dtype=float)
    if abs(x_axis[2]) > 1e-6:
        raise ValueError("the site frame's x axis is not parallel to the equator")
    lat, _ = unit_to_latlon(z_axis)
    lon0 = math.degrees(math.atan2(-x_axis[0], x_axis[1]))
    origin = np.asarray(frame.origin, dtype=float)
    return SiteProjection(body=body, radii_km=(radii[0], radii[1], radii[2]),
                          centre_lat_deg=float(lat), centre_lon_deg=lon0,
                          offset_km=(float(x_axis @ origin), float(y_axis @ origin)))


def write_terrain(path: str | Path, *, driver: TerrainDriver, layers: Sequence[TerrainLayer],
                  x_km: np.ndarray, y_km: np.ndarray, projection: SiteProjection,
                  metadata: Mapping[str, str]) -> None:
    """Write `layers` on the site grid x_km (nx,), y_km (ny,) (regular, increasing, equal
    steps) as a raster of `driver` at `path` (never overwritten), georeferenced by
    `projection`, with `metadata` (name -> text) as dataset tags. ValueError for bad input."""
    path = Path(path)
    x, y = np.asarray(x_km, dtype=np.float64), np.asarray(y_km, dtype=np.float64)
    for axis, what in ((x, "x_km"), (y, "y_km")):
        step = np.diff(axis)
        if axis.ndim != 1 or len(axis) < 2 or step.min() <= 0 or np.ptp(step) > 1e-9 * step.mean():
            raise ValueError(f"{what} must be regular and increasing")
    dx, dy = x[1] - x[0], y[1] - y[0]
    if abs(dy - dx) > 1e-9 * dx:
        raise ValueError(f"x_km and y_km must have the same step, got {dx} and {dy}")
    if not layers:
        raise ValueError("no layers to write")
    if len({layer.name for layer in layers}) != len(layers):
        raise ValueError("layer names must differ")
    for layer in layers:
        if np.shape(layer.values) != (len(y), len(x)):
            raise ValueError(f"layer {layer.name!r} is {np.shape(layer.values)}, the grid "
                             f"{(len(y), len(x))}")
    if path.exists():
        raise FileExistsError(f"{path} exists; a product is written once")
    dtype, nodata = ((np.float32, ISIS_NULL) if driver is TerrainDriver.ISIS3
                     else (np.float64, GEOTIFF_NODATA))
    step_m = dx * 1e3
    west, north = projection.upper_left_m(x, y)
    # rows north first: the site grid's last line (largest y) becomes row 0
    bands = np.stack([np.flipud(np.where(np.isnan(layer.values), nodata,
                                         np.asarray(layer.values, dtype=np.float64)))
                      for layer in layers]).astype(dtype)
    options = {"COMPRESS": "DEFLATE", "PREDICTOR": "3"} if driver is TerrainDriver.GEOTIFF else {}
    # No .aux.xml beside the file: a product is one file. GDAL writes an ISIS3 cube's label and
    # data in one .cub (DATA_LOCATION LABEL, its default).
    with rasterio.Env(GDAL_PAM_ENABLED="NO"), rasterio.open(
            path, "w", driver=driver.value, width=len(x), height=len(y), count=len(layers),
            dtype=dtype, nodata=nodata, crs=CRS.from_wkt(projection.wkt()),
            transform=from_origin(west, north, step_m, step_m), **options) as dst:
        dst.write(bands)
        if driver is TerrainDriver.GEOTIFF:
            dst.descriptions = tuple(layer.name for layer in layers)
            dst.units = tuple(layer.unit for layer in layers)
            for index, layer in enumerate(layers, 1):
                dst.update_tags(index, DESCRIPTION=layer.description)
            dst.update_tags(**dict(metadata))
    if driver is TerrainDriver.ISIS3:
        _label_cube(path, layers, metadata)


def _label_cube(path: Path, layers: Sequence[TerrainLayer], metadata: Mapping[str, str]) -> None:
    """Add to the ISIS cube GDAL wrote the groups ISIS keeps band names and units in (BandBin)
    and the product's metadata (a group of its own), in the label's reserved bytes.

    GDAL's ISIS3 writer keeps descriptions, units and metadata only in a sidecar file; the
    label it reserves (Label Bytes) has room for them."""
    with open(path, "r+b") as fh:
        head = fh.read(_LABEL_READ)
        end = head.find(b"\nEnd\n")
        if end < 0:
            raise ValueError(f"{path}: GDAL wrote no ISIS label end within {_LABEL_READ} bytes")
        label = pvl.loads(head[:end + 5].decode("ascii"))
        reserved = int(label["Label"]["Bytes"])
        label["IsisCube"].append("BandBin", pvl.PVLGroup([
            ("Name", [layer.name for layer in layers]),
            ("Unit", [layer.unit or "none" for layer in layers]),
            ("Description", [layer.description for layer in layers])]))
        label["IsisCube"].append("PwmTerrain", pvl.PVLGroup(list(metadata.items())))
        # GDAL reads the label up to a line end after END
        text = pvl.dumps(label, encoder=pvl.encoder.ISISEncoder()).encode("ascii") + b"\n"
        if len(text) > reserved:
            raise ValueError(f"the ISIS label needs {len(text)} bytes, GDAL reserved {reserved}")
        fh.seek(0)
        fh.write(text + b"\0" * (reserved - len(text)))
