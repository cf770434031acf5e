"""LAS 1.4 point clouds of a shape model's vertices (laspy), for PDAL and other point tools.

Coordinates are metres in the body-fixed frame (the model's km times 1000), stored as scaled
integers at SCALE_M (0.1 mm) or coarser where a body is too large for 32-bit integers at it;
the albedo, when the model has one, is an extra dimension `albedo` (float32). The header's
system identifier names the version, its generating software pwm; an OGC WKT record
(LASF_Projection 2112) states the body-fixed Cartesian frame on the body's mean sphere, and a
text record (pwm 1) says in words what the file holds. Written uncompressed: laspy compresses
LAZ only through an optional backend (lazrs or laszip).
"""

from __future__ import annotations

import math
from pathlib import Path

import laspy
import numpy as np

SCALE_M = 1e-4
_INT32_SPAN = 2.0e9  # integer steps a coordinate may span about its offset, with margin
_HEADER_TEXT = 32  # bytes of the header's system identifier and generating software


def body_fixed_wkt(*, body: str, frame: str, radius_km: float) -> str:
    """WKT1 of the body-fixed Cartesian frame in metres on the body's mean sphere."""
    if not (math.isfinite(radius_km) and radius_km > 0):
        raise ValueError(f"radius_km must be positive, got {radius_km}")
    name, frame = body.replace('"', "'"), frame.replace('"', "'")
    return (f'GEOCCS["{name} body-fixed ({frame})",DATUM["{name}",'
            f'SPHEROID["{name} mean sphere",{radius_km * 1e3!r},0]],'
            'PRIMEM["Reference_Meridian",0],UNIT["metre",1],'
            'AXIS["X",OTHER],AXIS["Y",EAST],AXIS["Z",NORTH]]')


def write_las(path: str | Path, *, vertices_km: np.ndarray, albedo: np.ndarray | None,
              crs_wkt: str, system_identifier: str, description: str) -> None:
    """Write the points `vertices_km` (N, 3; km, body-fixed) as LAS 1.4 at `path` (never
    overwritten), in metres, with `albedo` (N,) as an extra dimension when given.
    system_identifier: at most 32 ASCII characters (the header's); description: what the file
    holds, kept as a text record. ValueError for bad input."""
    path = Path(path)
    points = np.asarray(vertices_km, dtype=np.float64) * 1e3
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"vertices_km must be (N, 3) with N > 0, got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("vertices_km has values that are not finite")
    if albedo is not None and np.shape(albedo) != (len(points),):
        raise ValueError(f"albedo is {np.shape(albedo)}, the vertices {len(points)}")
    if len(system_identifier) > _HEADER_TEXT or not system_identifier.isascii():
        raise ValueError(f"system_identifier must be at most {_HEADER_TEXT} ASCII characters")
    if path.exists():
        raise FileExistsError(f"{path} exists; a product is written once")
    header = laspy.LasHeader(version="1.4", point_format=6)
    offset = (points.min(axis=0) + points.max(axis=0)) / 2
    span = float(np.abs(points - offset).max())
    # the finest power of ten at or above SCALE_M that keeps every point in 32-bit integers
    scale = max(SCALE_M, 10.0 ** math.ceil(math.log10(max(span, 1e-300) / _INT32_SPAN)))
    header.offsets, header.scales = offset, np.full(3, scale)
    header.system_identifier = system_identifier
    header.generating_software = "pwm"
    header.global_encoding.wkt = True
    header.vlrs.append(laspy.VLR(user_id="LASF_Projection", record_id=2112,
                                 description="OGC WKT", record_data=crs_wkt.encode("ascii") + b"\0"))
    header.vlrs.append(laspy.VLR(user_id="pwm", record_id=1, description="what this file holds",
                                 record_data=description.encode("ascii") + b"\0"))
    if albedo is not None:
        header.add_extra_dim(laspy.ExtraBytesParams(name="albedo", type=np.float32,
                                                    description="normal albedo"))
    cloud = laspy.LasData(header)
    cloud.x, cloud.y, cloud.z = points.T
    if albedo is not None:
        cloud.albedo = np.asarray(albedo, dtype=np.float32)
    with open(path, "xb") as fh:
        cloud.write(fh)
