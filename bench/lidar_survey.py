"""Strip adjustment and the lidar model from nothing on a simulated downlink's lidar (issue 46's
acceptance: `campaign`'s survey under `nav:` knowledge errors), judged against what the proving
ground drew: the shots read through the downlink's kernels as the catalog-free commands read them
(pwm.io.lidar.read_lidar_directory), the truth surface, and each shot's true origin and direction
(truth/lidar_spots.npz: the kernels' errors drawn, `drawn`).

Three adjustments, each as one table row: to the truth surface (what strip adjustment can do with
a perfect model), from nothing (the loop model -> tracks -> model, no model given) and, for that
model, the global evaluation of `pwm evaluate --scope global` (RMS after ICP, coverage within 2
GSD, the mean offset that ICP removed, closure), with the model's distances to the truth as it was
placed, before any ICP (on a body nearly round about an axis, ICP's turn about it is barely
determined, and the shift it reports with it says little of the placement). Per track, the
correction to the truth against the rigid motion that undoes the drawn error (`drawn`): the share
of its six parameters within 3 sigma.

    .venv/bin/python bench/lidar_survey.py SIM/downlinks/1-campaign-survey SIM/truth/1-campaign-survey [--exact]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from pwm.evaluate.closure import closure
from pwm.evaluate.distance import ClosestPoint
from pwm.evaluate.report import evaluate
from pwm.io.lidar import read_lidar_directory
from pwm.io.meshio import read_shape_model, write_ply
from pwm.lidar.model import lidar_residuals
from pwm.lidar.shots import Shots
from pwm.lidar.strips import Correction, adjust
from pwm.lidar.tracks import NO_TRACK
from pwm.raytrace import RayTracer

DRAWN_ITERATIONS = 3  # Gauss-Newton steps of `drawn`: a few for errors of metres and tens of microradians


def drawn(correction: Correction, shots: Shots, track: np.ndarray, true: dict[str, np.ndarray],
          tracer: RayTracer) -> np.ndarray:
    """(rotation, translation about the correction's centre) of the drawn error as a track's rigid
    correction: the rigid motion that best maps each valid spot as the kernels place it onto the
    same range along the true origin and direction (truth/lidar_spots.npz), in the metric of a
    registration to a surface (point-to-plane, the truth's normals; Gauss-Newton from none).
    The view's error itself is not one rigid motion (a turn of the pointing turns each shot about
    its own origin, and the spacecraft moves hundreds of metres through a window); what of it
    slides along the surface no registration to a surface can see."""
    mine = (track == correction.track) & shots.valid
    at = np.searchsorted(true["et"], shots.et[mine])
    origin, direction = true["origin_km"][at], true["direction"][at]
    hits = tracer.intersect(origin, direction)
    normal = np.asarray(tracer.face_normals)[hits.face[hits.hit]]
    read = shots.spots_km()[mine][hits.hit]
    undone = (origin + shots.range_km[mine, None] * direction)[hits.hit]
    about = correction.about_km
    turn, shift = Rotation.identity(), np.zeros(3)
    for _ in range(DRAWN_ITERATIONS):
        moved = turn.apply(read - about) + about + shift
        residual = np.einsum("ij,ij->i", moved - undone, normal)
        design = np.hstack([np.cross(moved - about, normal), normal])
        step = np.linalg.lstsq(design, -residual, rcond=None)[0]
        increment = Rotation.from_rotvec(step[:3])
        turn, shift = increment * turn, increment.apply(shift) + step[3:]
    return np.r_[turn.as_rotvec(), shift]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("downlink", type=Path, help="a simulated downlink with lidar/ and kernels/")
    parser.add_argument("truth", type=Path, help="its truth/ directory")
    parser.add_argument("--exact", action="store_true",
                        help="the shots as exact kernels place them (the truth's origins and directions): the same "
                             "downlink simulated without knowledge errors")
    args = parser.parse_args()
    manifest = json.loads((args.truth / "manifest.json").read_text())
    gsd_m = manifest["gsd_m"]
    noise_m = manifest["lidar"]["range_noise_m"]
    products, skipped = read_lidar_directory(args.downlink)
    if skipped:
        raise SystemExit(f"products not read: {skipped}")
    shots = Shots.joined([p.shots for p in products])
    truth = read_shape_model(args.truth / "mesh.ply")
    true = dict(np.load(args.truth / "lidar_spots.npz"))
    tracer = RayTracer(truth)
    knowledge = {k: v for k, v in manifest["knowledge_error"].items() if k != "arcs"}
    if args.exact:  # a seed's shots are the same whatever the errors (pwm.simulate.campaign)
        at = np.searchsorted(true["et"], shots.et)
        shots = replace(shots, origin_km=np.where(shots.valid[:, None], true["origin_km"][at], shots.origin_km),
                        direction=np.where(shots.valid[:, None], true["direction"][at], shots.direction))
        knowledge = {"mode": "exact"}
    print(f"{args.downlink.name}: {len(shots)} shots, {int(shots.valid.sum())} valid; knowledge {knowledge}; "
          f"range noise {noise_m} m; GSD {gsd_m:.2f} m")

    clock = time.perf_counter()
    to_truth = adjust(shots, truth)
    seconds_truth = time.perf_counter() - clock
    before = lidar_residuals(shots, truth, to_truth.track)
    after = lidar_residuals(to_truth.shots, truth, to_truth.track)
    clock = time.perf_counter()
    alone = adjust(shots)
    seconds_alone = time.perf_counter() - clock
    from_nothing = lidar_residuals(alone.shots, truth, alone.track)

    print(f"{'spots to the truth surface':<34}{'mean m':>9}{'RMS m':>9}{'p95 m':>9}{'cut':>8}{'time s':>9}")
    for name, r, seconds in (("as read (unadjusted)", before, 0.0), ("adjusted to the truth", after, seconds_truth),
                             ("adjusted from nothing", from_nothing, seconds_alone)):
        cut = 1 - r.rms_km / before.rms_km
        print(f"{name:<34}{r.mean_km * 1e3:>9.3f}{r.rms_km * 1e3:>9.3f}{r.p95_km * 1e3:>9.3f}{cut:>8.1%}"
              f"{seconds:>9.1f}")

    z = []
    for t, c in to_truth.corrections.items():
        if t == NO_TRACK or not np.isfinite(c.sigma).all():
            continue
        truth_params = drawn(c, shots, to_truth.track, true, tracer)
        z.append((np.r_[c.rotation_rad, c.translation_km] - truth_params) / c.sigma)
    zs = np.abs(np.array(z))
    print(f"tracks corrected to the truth: {len(zs)} of {len(to_truth.corrections)}; parameters within 3 sigma of "
          f"the drawn error: {np.mean(zs <= 3):.1%} (rotation {np.mean(zs[:, :3] <= 3):.1%}, translation "
          f"{np.mean(zs[:, 3:] <= 3):.1%}); tracks with all six: {np.mean((zs <= 3).all(axis=1)):.1%}; largest |z| "
          f"{zs.max():.2f}; RMS z {np.sqrt(np.mean(zs ** 2)):.2f}")

    # placed as made, before any ICP: the model's vertices' signed distances to the truth
    placed = ClosestPoint(truth).signed_distance(alone.model.vertices) * 1e3
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "lidar_model.ply"
        write_ply(path, alone.model)
        figures = evaluate(path, truth_dir=args.truth, scope="global")
    print(f"lidar model from nothing: {len(alone.model.faces)} faces, closed {closure(alone.model).closed}, "
          f"{len(alone.changes)} rounds (changes m: {' '.join(f'{c * 1e3:.2f}' for c in alone.changes)}), "
          f"converged {alone.converged}")
    print(f"  RMS after ICP {figures['rms_gsd']:.3f} GSD ({figures['rms_m']:.3f} m), median "
          f"{figures['median_gsd']:.3f} GSD, coverage (2 GSD) {figures['completeness']:.4f}, mean offset ICP removed "
          f"{figures['icp']['shift_m'] / gsd_m:.3f} GSD ({figures['icp']['shift_m']:.3f} m), ICP turn "
          f"{figures['icp']['rotation_rad'] * 1e6:.1f} urad")
    print(f"  before ICP: the model's vertices {placed.mean():+.3f} m mean ({placed.mean() / gsd_m:+.3f} GSD), "
          f"{np.sqrt(np.mean(placed ** 2)):.3f} m RMS ({np.sqrt(np.mean(placed ** 2)) / gsd_m:.3f} GSD) from the truth")


if __name__ == "__main__":
    main()
