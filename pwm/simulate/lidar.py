"""The proving ground's laser altimeter: its settings (`LidarSpec`), its kernels (a frame fixed to
the camera's and an IK with its boresight, beam and range limits), and its shots, ranged on the
truth surface from the true poses.

A shot's return is the mean range over its footprint: `footprint_rays` rays spread over the
beam's divergence, as a real return's waveform centroid averages the ground it lights. Shots
are taken through each view's kernel window (the kernels hold the spacecraft there), as
profiles (a fixed boresight while the body turns beneath: NEAR's or Hayabusa's lidar) or
rasters (a scan mirror sweeping a grid over the body or site: OSIRIS-REx's OLA; each shot's
direction in the instrument frame goes into the product).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import spiceypy as sp
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.spatial.transform import Rotation

from pwm.io.lidar import RANGE_LIMITS_KEYWORD, RANGE_SIGMA_KEYWORD
from pwm.raytrace import RayTracer

LIDAR_NAME = "PWM_LIDAR"  # the simulated lidar's instrument and frame name
LIDAR_CODE_OFFSET = 780  # its NAIF id: spacecraft * 1000 - this (free in the ORX and HYB2 kernels)
NO_RETURN = 2  # the plain layout's flag of a shot with no return (0: a return)
MIN_RETURN_FRACTION = 0.5  # a return needs this fraction of its footprint's rays on the surface
_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


class LidarSpec(BaseModel):
    """A scenario's laser altimeter. pattern: profiles along track or rasters; shots_per_view
    shots in each view's kernel window, over window_fraction of it; range_noise_m: 1 sigma of
    a range; dropout: the fraction of shots with no return; divergence_urad: the beam's full
    angle, sampled by footprint_rays rays; range_limits_km: what it can range; raster_margin:
    a raster's half width over the body's (or site's) apparent half width."""

    model_config = ConfigDict(frozen=True)

    pattern: Literal["profile", "raster"]
    shots_per_view: int = Field(100, ge=1, le=100_000)
    window_fraction: float = Field(0.8, gt=0.0, lt=1.0)
    range_noise_m: float = Field(0.05, ge=0.0, le=100.0)
    dropout: float = Field(0.02, ge=0.0, lt=1.0)
    divergence_urad: float = Field(100.0, gt=0.0, le=10_000.0)
    footprint_rays: int = Field(7, ge=1, le=64)
    range_limits_km: tuple[float, float] = (0.0, 100.0)
    raster_margin: float = Field(1.0, gt=0.0, le=3.0)

    @model_validator(mode="after")
    def _ordered_limits(self) -> LidarSpec:
        if not 0.0 <= self.range_limits_km[0] < self.range_limits_km[1]:
            raise ValueError(f"range_limits_km must be 0 <= min < max, not {self.range_limits_km}")
        return self


def lidar_code(spacecraft: int) -> int:
    """The simulated lidar's NAIF id on `spacecraft` (-64 -> -64780)."""
    return spacecraft * 1000 - LIDAR_CODE_OFFSET


def write_lidar_kernels(kernel_dir: Path, *, spec: LidarSpec, spacecraft: int, camera_frame: str,
                        camera_misalignment_rad: np.ndarray | None = None) -> list[Path]:
    """The lidar's FK (PWM_LIDAR, fixed to `camera_frame`: co-boresighted with the camera) and
    IK (a circular FOV of the beam's half angle on +Z, the range limits and sigma, km).

    camera_misalignment_rad: the error of the camera's alignment with the bus in the kernels
    these join (a rotation vector in the camera frame, `pwm.simulate.knowledge`). The lidar is
    aligned with the bus on its own, so its FK, which the mission derives from the two
    alignments, states it turned back by that error: its shots read through those kernels carry
    the bus's errors but not the camera's misalignment.
    """
    code = lidar_code(spacecraft)
    # TKFRAME_MATRIX takes a vector from the camera frame to the lidar's (checked with pxform)
    alignment = (np.eye(3) if camera_misalignment_rad is None
                 else Rotation.from_rotvec(np.asarray(camera_misalignment_rad, float)).as_matrix().T)
    rows = "\n".join("    " + " ".join(f"{v:.17g}" for v in row) for row in alignment)
    fk, ik = kernel_dir / "fk" / "pwm_lidar.tf", kernel_dir / "ik" / "pwm_lidar.ti"
    for path in (fk, ik):
        path.parent.mkdir(parents=True, exist_ok=True)
    fk.write_text(f"""KPL/FK

The simulated laser altimeter's frame (pwm.simulate.lidar): fixed to {camera_frame}, so that it
ranges along the camera's boresight (+Z), as the lidar's own alignment with the bus and the
camera's as these kernels know it give it.

\\begindata

NAIF_BODY_NAME += ( '{LIDAR_NAME}' )
NAIF_BODY_CODE += ( {code} )

FRAME_{LIDAR_NAME} = {code}
FRAME_{code}_NAME = '{LIDAR_NAME}'
FRAME_{code}_CLASS = 4
FRAME_{code}_CLASS_ID = {code}
FRAME_{code}_CENTER = {spacecraft}
TKFRAME_{code}_RELATIVE = '{camera_frame}'
TKFRAME_{code}_SPEC = 'MATRIX'
TKFRAME_{code}_MATRIX = (
{rows}
)

\\begintext
""")
    ik.write_text(f"""KPL/IK

The simulated laser altimeter (pwm.simulate.lidar): its beam (full divergence
{spec.divergence_urad:g} urad), range limits and range sigma (km).

\\begindata

INS{code}_FOV_FRAME = '{LIDAR_NAME}'
INS{code}_FOV_SHAPE = 'CIRCLE'
INS{code}_BORESIGHT = ( 0.0 0.0 1.0 )
INS{code}_FOV_CLASS_SPEC = 'ANGLES'
INS{code}_FOV_REF_VECTOR = ( 1.0 0.0 0.0 )
INS{code}_FOV_REF_ANGLE = ( {spec.divergence_urad / 2 * 1e-6:.9e} )
INS{code}_FOV_ANGLE_UNITS = 'RADIANS'
INS{code}_{RANGE_LIMITS_KEYWORD} = ( {spec.range_limits_km[0]!r} {spec.range_limits_km[1]!r} )
INS{code}_{RANGE_SIGMA_KEYWORD} = ( {spec.range_noise_m * 1e-3!r} )

\\begintext
""")
    return [fk, ik]


@dataclass(frozen=True)
class SimulatedShots:
    """What the lidar measured and what was true, per shot. et: TDB s; direction_instrument:
    (N, 3) in the lidar frame; range_km: as measured (noisy; 0 with no return); returned: a
    return came back; true_range_km: the footprint's mean range without noise; centre_range_km:
    the central ray's alone; origin_km, direction, spot_km: the true origin, unit direction and
    spot (origin + true_range * direction), body-fixed (NaN with no return); intensity: the
    footprint's fraction on the surface times the cosine of incidence of the central ray."""

    et: np.ndarray
    direction_instrument: np.ndarray
    range_km: np.ndarray
    returned: np.ndarray
    true_range_km: np.ndarray
    centre_range_km: np.ndarray
    origin_km: np.ndarray
    direction: np.ndarray
    spot_km: np.ndarray
    intensity: np.ndarray


def footprint_offsets(n: int, half_angle: float) -> np.ndarray:
    """(n, 2) tangent-plane offsets (radians) of a footprint's rays, spread evenly over the beam's
    disc (a sunflower), the first on the axis, the others moved together so that their mean is
    the axis: a beam is symmetric about its axis, and a few rays of a sunflower are not (seven
    have their centroid 0.087 of the half angle off it), which on a slope would bias every
    return's range as a pointing error of that size would (0.25 m at 58 km with a 100 urad beam)."""
    if n == 1:
        return np.zeros((1, 2))
    j = np.arange(n)
    radius = half_angle * np.sqrt(j / (n - 1))
    offsets = np.column_stack([radius * np.cos(j * _GOLDEN_ANGLE), radius * np.sin(j * _GOLDEN_ANGLE)])
    offsets[1:] -= offsets[1:].mean(axis=0)
    return offsets


def raster_directions(n: int, half_angle: float) -> np.ndarray:
    """(n, 3) unit directions of a boustrophedon raster of at least n points over a square of
    +-half_angle about +Z (the first n of ceil(sqrt(n))^2)."""
    side = math.ceil(math.sqrt(n))
    steps = np.tan(np.linspace(-half_angle, half_angle, side)) if side > 1 else np.zeros(1)
    rows = [steps if r % 2 == 0 else steps[::-1] for r in range(side)]
    grid = np.array([(x, steps[r], 1.0) for r, row in enumerate(rows) for x in row])[:n]
    return grid / np.linalg.norm(grid, axis=1, keepdims=True)


def range_footprints(tracer: RayTracer, *, origins: np.ndarray, directions: np.ndarray,
                     half_angle: float, rays: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per shot (origins, unit directions (N, 3), body-fixed km): the mean range over its
    footprint's rays that meet the surface (NaN where fewer than MIN_RETURN_FRACTION do), the
    central ray's range, and the fraction of rays that met it."""
    n = len(origins)
    offsets = footprint_offsets(rays, half_angle)
    helper = np.where(np.abs(directions[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(directions, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(directions, e1)
    ray_dirs = (directions[:, None, :] + np.tan(offsets[None, :, :1]) * e1[:, None, :]
                + np.tan(offsets[None, :, 1:]) * e2[:, None, :])
    ray_dirs /= np.linalg.norm(ray_dirs, axis=2, keepdims=True)
    flat_o = np.repeat(origins, rays, axis=0)
    flat_d = ray_dirs.reshape(-1, 3)
    hits = tracer.intersect(flat_o, flat_d)
    points = tracer.hit_points(flat_o, flat_d, hits)
    ranges = np.linalg.norm(points - flat_o, axis=1).reshape(n, rays)
    met = np.isfinite(ranges)
    fraction = met.mean(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(met, ranges, 0.0).sum(axis=1) / met.sum(axis=1)
    mean[fraction < MIN_RETURN_FRACTION] = np.nan
    return mean, ranges[:, 0], fraction


def take_shots(tracer: RayTracer, *, spec: LidarSpec, view_times: list[float], window_s: float,
               spacecraft: int, target: str, body_frame: str, extent_km: float,
               rng: np.random.Generator) -> SimulatedShots:
    """The lidar's shots through each view's kernel window (view_times, the windows' centres;
    window_s their half width), from the poses of the loaded (true) kernels, ranged on the
    tracer's (truth) surface. extent_km: the half width of what a raster sweeps (the body's
    radius, or half the site), at the distance of the boresight's ground."""
    half_beam = spec.divergence_urad / 2 * 1e-6
    half_span = spec.window_fraction * window_s
    ets, local_dirs, origins, turns = [], [], [], []
    for t0 in view_times:
        times = t0 + np.linspace(-half_span, half_span, spec.shots_per_view)
        view_origins = np.array([sp.spkpos(str(spacecraft), float(t), body_frame, "NONE", target)[0] for t in times])
        view_turns = np.array([sp.pxform(LIDAR_NAME, body_frame, float(t)) for t in times])
        if spec.pattern == "raster":
            centre = view_turns[len(times) // 2] @ np.array([0.0, 0.0, 1.0])
            mid_range = range_footprints(tracer, origins=view_origins[len(times) // 2][None],
                                         directions=centre[None], half_angle=0.0, rays=1)[1][0]
            ground = mid_range if np.isfinite(mid_range) else float(np.linalg.norm(view_origins[0]))
            half = math.atan(spec.raster_margin * extent_km / ground)
            dirs = raster_directions(spec.shots_per_view, half)
        else:
            dirs = np.tile([0.0, 0.0, 1.0], (len(times), 1))
        ets.append(times)
        local_dirs.append(dirs)
        origins.append(view_origins)
        turns.append(view_turns)
    et = np.concatenate(ets)
    local = np.concatenate(local_dirs)
    origin = np.concatenate(origins)
    direction = np.einsum("nij,nj->ni", np.concatenate(turns), local)
    true_range, centre_range, fraction = range_footprints(tracer, origins=origin, directions=direction,
                                                          half_angle=half_beam, rays=spec.footprint_rays)
    noise = rng.normal(0.0, spec.range_noise_m * 1e-3, len(et))
    dropped = rng.random(len(et)) < spec.dropout
    returned = np.isfinite(true_range) & ~dropped
    measured = np.where(returned, true_range + noise, 0.0)
    spot = origin + true_range[:, None] * direction
    hits = tracer.intersect(origin, direction)
    normals = np.asarray(tracer.face_normals)[np.where(hits.hit, hits.face, 0)]
    cosine = np.clip(-(normals * direction).sum(axis=1), 0.0, 1.0)
    intensity = np.where(returned, fraction * np.where(hits.hit, cosine, 0.0), 0.0)
    return SimulatedShots(et=et, direction_instrument=local, range_km=measured, returned=returned,
                          true_range_km=true_range, centre_range_km=centre_range, origin_km=origin,
                          direction=direction, spot_km=np.where(returned[:, None], spot, np.nan), intensity=intensity)


def save_true_spots(path: Path, shots: SimulatedShots) -> None:
    """The proving ground's record of the shots (truth/lidar_spots.npz)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, et=shots.et, spot_km=shots.spot_km, origin_km=shots.origin_km,
                        direction=shots.direction, true_range_km=shots.true_range_km,
                        centre_range_km=shots.centre_range_km, range_km=shots.range_km, returned=shots.returned)
