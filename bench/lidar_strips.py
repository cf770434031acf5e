"""Strip adjustment and the lidar shape model from nothing at size: synthetic raster tracks of
Castalia (each ray-cast on the truth from a short arc 5 km out, then given a drawn rigid error and
range noise), adjusted to the truth and from nothing. Prints one table: tracks, shots, the spots'
RMS distance to the truth before and after (m), the crossovers' RMS height (m), time (s) and the
peak of numpy's memory (MiB, tracemalloc: Embree's own is not in it), and the process's peak
resident memory at the end.

    .venv/bin/python bench/lidar_strips.py [--shots 100000] [--tracks 64] [--noise-m 0.3]
                                           [--position-m 3] [--attitude-urad 50] [--seed 46]
"""

from __future__ import annotations

import argparse
import resource
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from pwm.evaluate.closure import closure
from pwm.io.meshio import read_shape_model
from pwm.lidar.config import LidarConfig
from pwm.lidar.model import lidar_residuals, spot_normals
from pwm.lidar.shots import Shots
from pwm.lidar.strips import adjust, corrected, register_track
from pwm.lidar.tracks import crossovers, track_ids
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer

SHAPE = Path(__file__).parents[1] / "pwm" / "data" / "shapes" / "castalia_radar_hudson1994.obj"
DISTANCE_KM = 5.0
HALF_ANGLE = 0.17  # the body's apparent half width from DISTANCE_KM, with a margin
SWEEP_DEG = 5.0


def survey(truth: Mesh, *, shots: int, tracks: int, noise_km: float, position_km: float, attitude_rad: float,
           rng: np.random.Generator) -> Shots:
    """`tracks` rasters from directions spread over the sphere (an hour apart), about `shots`
    shots on the body in all, each under a drawn rotation about the spacecraft and translation."""
    tracer = RayTracer(truth)
    # about a third of a raster over the body's apparent disc meets it
    side = max(2, int(np.ceil(np.sqrt(shots / tracks / 0.35))))
    k = np.arange(tracks) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / tracks), np.pi * (1 + 5 ** 0.5) * k
    centres = np.column_stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])
    u, v = (a.ravel() for a in np.meshgrid(np.linspace(-HALF_ANGLE, HALF_ANGLE, side),
                                           np.linspace(-HALF_ANGLE, HALF_ANGLE, side)))
    parts = []
    for i, centre in enumerate(centres):
        axis = np.cross(centre, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        angle = np.linspace(-0.5, 0.5, side * side) * np.radians(SWEEP_DEG)
        origin = DISTANCE_KM * Rotation.from_rotvec(angle[:, None] * axis).apply(centre)
        boresight = -origin / DISTANCE_KM
        direction = boresight + u[:, None] * axis + v[:, None] * np.cross(boresight, axis)
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        hits = tracer.intersect(origin, direction)
        origin, direction, t = origin[hits.hit], direction[hits.hit], hits.t[hits.hit]
        rotation = Rotation.from_rotvec(rng.normal(0.0, attitude_rad, 3))
        mean = origin.mean(axis=0)
        parts.append((3600.0 * i + 0.01 * np.arange(len(t)),
                      rotation.apply(origin - mean) + mean + rng.normal(0.0, position_km, 3),
                      rotation.apply(direction), t + rng.normal(0.0, noise_km, len(t))))
    et, origin, direction, range_km = (np.concatenate([p[c] for p in parts]) for c in range(4))
    return Shots(frame="CASTALIA_FIXED", et=et, origin_km=origin, direction=direction, range_km=range_km,
                 sigma_km=np.full(len(et), noise_km), invalid=np.zeros(len(et), dtype=np.int64))


def measured(step: Callable[[], Any]) -> tuple[Any, float, float]:
    """step()'s value, wall time (s) and numpy's peak memory during it (MiB)."""
    tracemalloc.reset_peak()
    start = time.perf_counter()
    value = step()
    seconds = time.perf_counter() - start
    return value, seconds, tracemalloc.get_traced_memory()[1] / 2 ** 20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shots", type=int, default=100_000)
    parser.add_argument("--tracks", type=int, default=64)
    parser.add_argument("--noise-m", type=float, default=0.3)
    parser.add_argument("--position-m", type=float, default=3.0)
    parser.add_argument("--attitude-urad", type=float, default=50.0)
    parser.add_argument("--seed", type=int, default=46)
    args = parser.parse_args()
    if not (1 <= args.tracks <= args.shots <= 10_000_000):
        parser.error("need 1 <= tracks <= shots <= 10,000,000")
    truth = read_shape_model(SHAPE)
    shots = survey(truth, shots=args.shots, tracks=args.tracks, noise_km=args.noise_m / 1000,
                   position_km=args.position_m / 1000, attitude_rad=args.attitude_urad * 1e-6,
                   rng=np.random.default_rng(args.seed))
    tracemalloc.start()
    track, seconds, peak = measured(lambda: track_ids(shots))
    rows = [("tracks", seconds, peak, "")]

    def crossing(s: Shots) -> float:
        return crossovers(s.spots_km(), track, spot_normals(s.spots_km(), s.origin_km), radius_km=0.005).rms_km()

    before = lidar_residuals(shots, truth, track).rms_km
    xo, seconds, peak = measured(lambda: crossing(shots))
    rows.append(("crossovers", seconds, peak, f"{xo * 1000:.2f} m RMS height"))
    to_truth, seconds, peak = measured(lambda: adjust(shots, truth))
    rows.append(("adjust to the truth", seconds, peak,
                 f"{before * 1000:.2f} -> {lidar_residuals(to_truth.shots, truth, track).rms_km * 1000:.2f} m; "
                 f"crossovers {crossing(to_truth.shots) * 1000:.2f} m"))
    alone, seconds, peak = measured(lambda: adjust(shots))
    # lidar alone cannot see the tracks' common error: measured also after one rigid fit to the truth
    whole = corrected(alone.shots, register_track(alone.shots, RayTracer(truth), config=LidarConfig(
        prior_rotation_rad=np.inf, prior_translation_km=np.inf)))
    rows.append(("from nothing", seconds, peak,
                 f"{before * 1000:.2f} -> {lidar_residuals(alone.shots, truth, track).rms_km * 1000:.2f} m; "
                 f"{len(alone.changes)} rounds, converged {alone.converged}; model {len(alone.model.faces)} faces, "
                 f"closed {closure(alone.model).closed}; after a rigid fit "
                 f"{lidar_residuals(whole, truth, track).rms_km * 1000:.2f} m; changes (m) "
                 + " ".join(f"{c * 1000:.2f}" for c in alone.changes)))
    print(f"{int(track.max()) + 1} tracks, {len(shots)} shots on Castalia; noise {args.noise_m} m, errors "
          f"{args.position_m} m and {args.attitude_urad} urad (1 sigma per axis)")
    print(f"{'step':<22}{'time s':>9}{'peak MiB':>10}  result")
    for name, seconds, peak, note in rows:
        print(f"{name:<22}{seconds:>9.2f}{peak:>10.0f}  {note}")
    print(f"process peak resident memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20:.2f} GiB")


if __name__ == "__main__":
    main()
