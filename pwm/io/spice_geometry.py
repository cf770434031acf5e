"""Observation geometry read from the loaded SPICE kernel pool: camera, pose, Sun, coverage.

Pure functions of the pool (load kernels with pwm.io.spice_kernels.kernel_pool). Positions in km,
times in ET seconds. Poses are returned in pwm.camera's image frame (+X along samples, +Y along
lines, +Z boresight), which `image_axes` relates to the SPICE instrument frame: for OCAMS the
sample axis is the instrument +Y, so the image frame is a mirror of the instrument frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import spiceypy as sp

from pwm.camera import Camera, Pose
from pwm.geometry import Ellipsoid
from pwm.io.spice_kernels import KernelError

FOV_ROOM = 64  # boundary vectors getfov may return; camera FOVs have 4
FOCAL_TOLERANCE = 0.02  # keyword focal length must match the FOV-derived one to 2 %
MAX_BORESIGHT_TILT = np.radians(1.0)  # pwm.camera puts the boresight on +Z
# The Sun direction of a view is the apparent one; the camera position is geometric (light time
# over the km ranges of proximity operations moves the body by far less than a pixel).
ABCORR = "LT+S"


def spacecraft_of(instrument_id: int) -> int:
    """NAIF spacecraft id of an instrument or spacecraft frame id (-64361 -> -64)."""
    if instrument_id > -1000:
        raise ValueError(f"{instrument_id} is not a NAIF instrument id (spacecraft * 1000 - n)")
    return -(-instrument_id // 1000)


def camera_from_kernel(instrument_id: int) -> Camera:
    """Pinhole camera (pixels) from the instrument kernel of `instrument_id`.

    Size from INS<id>_PIXEL_SAMPLES/LINES; principal point from INS<id>_CCD_CENTER (taken as
    zero-based pixel-centre coordinates, as in the OCAMS IK) or the detector centre. The focal
    length comes from the FOV corners, or from FOCAL_LENGTH / PIXEL_SIZE (or PIXEL_PITCH) when
    both exist: their unit ratio is inferred as the power of 1000 that agrees with the FOV to 2 %
    (KernelError if none does), and the keyword value is then used for its extra digits.
    """
    width = int(_keyword(instrument_id, "PIXEL_SAMPLES")[0])
    height = int(_keyword(instrument_id, "PIXEL_LINES")[0])
    center = _optional_keyword(instrument_id, "CCD_CENTER")
    cx, cy = center[:2] if center is not None else ((width - 1) / 2, (height - 1) / 2)
    fov_focal = _fov_focal(instrument_id, width, height)
    focal = _keyword_focal(instrument_id, fov_focal)
    fx, fy = focal if focal is not None else fov_focal
    return Camera(width=width, height=height, fx=float(fx), fy=float(fy), cx=float(cx),
                  cy=float(cy))


def _optional_keyword(instrument_id: int, name: str) -> np.ndarray | None:
    variable = f"INS{instrument_id}_{name}"
    if not sp.expool(variable):
        return None
    return np.atleast_1d(sp.gdpool(variable, 0, sp.dtpool(variable)[0]))


def _keyword(instrument_id: int, name: str) -> np.ndarray:
    value = _optional_keyword(instrument_id, name)
    if value is None:
        raise KernelError(f"INS{instrument_id}_{name} is not in the kernel pool (IK loaded?)")
    return value


def _fov_focal(instrument_id: int, width: int, height: int) -> np.ndarray:
    """(fx, fy) px putting the FOV edges on the detector edges (width/2 from the centre)."""
    shape, frame, boresight, _, bounds = sp.getfov(instrument_id, FOV_ROOM)
    if shape not in ("RECTANGLE", "POLYGON"):
        raise KernelError(f"instrument {instrument_id}: FOV shape {shape} is not a camera's")
    if np.arccos(np.clip(boresight[2] / np.linalg.norm(boresight), -1, 1)) > MAX_BORESIGHT_TILT:
        raise KernelError(f"instrument {instrument_id}: boresight {boresight} is not +Z of {frame}")
    tangents = np.abs(bounds[:, :2] / bounds[:, 2:3]).max(axis=0)
    return np.array([width, height]) / 2 / tangents


def _keyword_focal(instrument_id: int, fov_focal: np.ndarray) -> np.ndarray | None:
    """(fx, fy) px from FOCAL_LENGTH and the pixel size, units inferred; None without them."""
    length = _optional_keyword(instrument_id, "FOCAL_LENGTH")
    pixel = _optional_keyword(instrument_id, "PIXEL_SIZE")
    if pixel is None:
        pixel = _optional_keyword(instrument_id, "PIXEL_PITCH")
    if length is None or pixel is None:
        return None
    ratio = length[0] / np.resize(pixel, 2)
    for unit_ratio in 1000.0 ** np.arange(-2, 3):  # m/m, mm/micron, m/mm, mm/m, ...
        if np.all(np.abs(ratio * unit_ratio / fov_focal - 1) < FOCAL_TOLERANCE):
            return ratio * unit_ratio
    raise KernelError(
        f"instrument {instrument_id}: FOCAL_LENGTH {length[0]} / pixel size {pixel} agrees with "
        f"the FOV focal length {fov_focal} px in no unit ratio")


def instrument_frame(instrument_id: int) -> str:
    """Name of the frame the instrument's FOV is defined in."""
    return sp.getfov(instrument_id, FOV_ROOM)[1]


def image_axes(instrument_id: int) -> np.ndarray:
    """Rows: instrument-frame directions of increasing sample, increasing line, and boresight.

    From the IK's INS<id>_SPOC_FITS_NAXIS1 and _NAXIS2 (sample and line directions, as OCAMS
    kernels give them) when present, else the identity. For MapCam NAXIS1 = +Y and NAXIS2 = +X:
    samples run along the instrument +Y axis and lines along +X (a mirror, determinant -1).
    """
    names = [f"INS{instrument_id}_SPOC_FITS_NAXIS{n}" for n in (1, 2)]
    if not all(sp.expool(name) for name in names):
        return np.eye(3)
    sample, line = (np.asarray(sp.gdpool(name, 0, 3), dtype=float) for name in names)
    return np.vstack([sample, line, [0.0, 0.0, 1.0]])


def camera_pose(*, et: float, instrument_id: int, target: str, body_frame: str) -> Pose:
    """Pose at `et`: spacecraft position relative to `target` in `body_frame` (km, geometric, no
    aberration correction) and the rotation `body_frame` -> image frame (see `image_axes`)."""
    position, _ = sp.spkpos(str(spacecraft_of(instrument_id)), et, body_frame, "NONE", target)
    rotation = image_axes(instrument_id) @ sp.pxform(body_frame, instrument_frame(instrument_id), et)
    return Pose(position=np.asarray(position, dtype=float), rotation=np.asarray(rotation))


def sun_direction(*, et: float, target: str, body_frame: str, abcorr: str = "LT+S") -> np.ndarray:
    """Unit vector from `target` towards the Sun in `body_frame` at `et`.

    'LT+S' (default) gives the apparent direction of the Sun as seen from the body at `et`: the
    light arriving then left the Sun one light time earlier and is aberrated by the body's
    motion, so this is the direction that illuminates the surface. 'NONE' gives the geometric one
    (they differ by about 1e-4 rad).
    """
    position, _ = sp.spkpos("SUN", et, body_frame, abcorr, target)
    return np.asarray(position) / np.linalg.norm(position)


def ellipsoid_of(target: str) -> Ellipsoid:
    """The target's triaxial ellipsoid from the PCK radii (km)."""
    return Ellipsoid(radii=np.asarray(sp.bodvrd(target, "RADII", 3)[1], dtype=float))


def coverage_spk(path: str | Path, body: int) -> list[tuple[float, float]]:
    """Coverage windows (start, stop) ET of `body` in an SPK file."""
    return _windows(sp.spkcov(str(path), body))


def coverage_ck(path: str | Path, frame_id: int) -> list[tuple[float, float]]:
    """Coverage windows (start, stop) ET of the interpolation intervals of `frame_id` in a CK file.

    Needs the LSK and the SCLK kernel loaded.
    """
    return _windows(sp.ckcov(str(path), frame_id, False, "INTERVAL", 0.0, "TDB"))


def _windows(cover) -> list[tuple[float, float]]:
    return [tuple(sp.wnfetd(cover, i)) for i in range(sp.wncard(cover))]
