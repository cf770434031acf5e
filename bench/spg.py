"""Stereo photogrammetry against the proving ground's truth: per scenario the photogrammetric
model's RMS (GSD) next to the start model's, pose errors before and after the adjustment,
runtime and peak memory; then the time of feature extraction and matching for 40 images.

    .venv/bin/python bench/spg.py [--sims /tmp/sims] [--scenarios global-coarse site site-ke]
                                  [--out DIR] [--timing site site-polar] [--refine site-ke]

Simulations are read from SIMS/<scenario> (downlink/ and truth/), never re-made. Attitude is
the rotation angle between corrected and true camera axes; line of sight is where the true
boresight's ground point lands with the corrected pose, in pixels from where it belongs: with a
narrow field of view a lateral position error and a pointing error move the image alike, so the
images fix their sum (the line of sight) far better than either alone; the third table shows it
from the adjustment's own normal matrix (pwm.spg.uncertainty). Scenarios named by --refine are
then refined (`pwm refine --corrections`) from their photogrammetric model.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from accuracy import pwm  # bench/ is on sys.path when this script runs
from scipy.spatial.transform import Rotation

from pwm.camera import Pose, project
from pwm.evaluate.report import evaluate
from pwm.io.downlink import read_downlink
from pwm.io.meshio import read_mesh
from pwm.raytrace import RayTracer
from pwm.spg import PoseCorrection
from pwm.spg.config import SpgConfig
from pwm.spg.photogrammetry import match_views
from service.cli.spg import read_corrections

ERRORS = [("position_m", 7, 2), ("lateral_m", 7, 2), ("along_m", 7, 2), ("attitude_urad", 7, 0), ("across_urad", 7, 0),
          ("line_of_sight_px", 6, 1), ("line_of_sight_m", 6, 2)]
ERROR_LABELS = ["pos m", "lateral m", "along m", "att urad", "across urad", "LOS px", "LOS m"]
SIGMAS = [("lateral_m", 7, 2), ("along_m", 7, 2), ("pointing_urad", 7, 0), ("los_px", 6, 2)]
SIGMA_LABELS = ["lateral m", "along m", "pointing urad", "LOS px"]


def pose_errors(downlink: Path, truth: Path, corrections: dict[str, PoseCorrection] | None) -> dict:
    """RMS over images of position (m; lateral to the boresight and along it), attitude (urad;
    across the boresight) and line-of-sight errors (px, and m on the ground at the site range)."""
    manifest = json.loads((truth / "manifest.json").read_text())
    views = read_downlink(downlink, corrections=corrections).views
    true = {Path(im["label"]).stem: im for im in manifest["images"]}
    pos, lateral, along, att, across, los, los_m = [], [], [], [], [], [], []
    for v in views:
        t = true[v.name]
        pose = Pose(np.array(t["position_km"]), np.array(t["rotation"]))
        ground = pose.position + pose.boresight * t["site_range_km"]
        d = pose.rotation @ (v.pose.position - pose.position) * 1e3  # camera axes, m
        # camera axes, urad
        turn = pose.rotation @ Rotation.from_matrix(v.pose.rotation.T @ pose.rotation).as_rotvec() * 1e6
        pos.append(np.linalg.norm(d))
        lateral.append(np.linalg.norm(d[:2]))
        along.append(abs(d[2]))
        att.append(np.linalg.norm(turn))
        across.append(np.linalg.norm(turn[:2]))
        los.append(np.linalg.norm(project(ground, v.camera, v.pose) - project(ground, v.camera, pose)))
        los_m.append(los[-1] * t["site_range_km"] / v.camera.fx * 1e3)
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    return {"position_m": rms(pos), "lateral_m": rms(lateral), "along_m": rms(along), "attitude_urad": rms(att),
            "across_urad": rms(across), "line_of_sight_px": rms(los), "line_of_sight_m": rms(los_m)}


def feature_timing(sims: Path, names: list[str], count: int) -> dict:
    """Seconds to extract features from `count` images (taken in turn from the scenarios) and to
    match the pairs chosen among them, with 2 threads (pwm.spg.photogrammetry.match_views)."""
    chosen = []
    for name in names:
        downlink = sims / name / "downlink"
        views = read_downlink(downlink).views
        chosen.append((views[: count - sum(len(v) for v, _ in chosen)], read_mesh(downlink / "start_model.obj")))
        if sum(len(v) for v, _ in chosen) >= count:
            break
    runs = [match_views(views, RayTracer(model), config=SpgConfig(threads=2)) for views, model in chosen]
    return {"images": sum(len(v) for v, _ in chosen), "extract_s": sum(m.extract_s for m in runs),
            "match_s": sum(m.match_s for m in runs),
            "pairs": sum(len(m.pairs) for m in runs),
            "matches": sum(sum(len(x) for x in m.matches.values()) for m in runs)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sims", type=Path, default=Path("/tmp/sims"))
    parser.add_argument("--scenarios", nargs="+", default=["global-coarse", "site", "site-ke"])
    parser.add_argument("--out", type=Path, default=Path("out/bench-spg"))
    parser.add_argument("--timing", nargs="+", default=["site", "site-polar"])
    parser.add_argument("--refine", nargs="*", default=["site-ke"],
                        help="scenarios refined from their photogrammetric model")
    args = parser.parse_args()
    models, errors, spread, refined = [], [], [], []
    for name in args.scenarios:
        downlink, truth, out = args.sims / name / "downlink", args.sims / name / "truth", args.out / name
        seconds, peak = pwm("spg", str(downlink), "--start", str(downlink / "start_model.obj"), "--out", str(out))
        stats = json.loads((out / "spg.json").read_text())
        corrections = read_corrections(out / "corrections.json")
        before, after = pose_errors(downlink, truth, None), pose_errors(downlink, truth, corrections)
        rms_start = evaluate(downlink / "start_model.obj", truth_dir=truth)["rms_gsd"]
        rms_spg = evaluate(out / "spg.ply", truth_dir=truth)["rms_gsd"]
        models.append(f"{name:<14}{stats['features']:>9}{stats['matches']:>8}{stats['points']:>7}"
                      f"{stats['point_spacing_km'] * 1e3:>8.2f}{stats['residual_rms_px']:>7.2f}"
                      f"{stats['surface_vertices']:>9}{rms_start:>10.2f}{rms_spg:>8.2f}{seconds:>8.0f}{peak:>9.2f}")
        errors.append(f"{name:<14}" + "".join(f"{before[k]:>{w}.{d}f}>{after[k]:<6.{d}f}" for k, w, d in ERRORS))
        u = stats["uncertainty"]
        spread.append(f"{name:<14}"
                      + "".join(f"{u[k + '_prior']:>{w}.{d}f}>{u[k + '_posterior']:<6.{d}f}" for k, w, d in SIGMAS)
                      + f"{u['los_one_image_px']:>9.3f}{u['pointing_one_image_urad']:>10.0f}"
                      + f"{u['pointing_alone_urad']:>10.1f}"
                      + f"{u['lateral_pointing_correlation']:>10.5f}")
        print(models[-1], errors[-1], spread[-1], sep="\n", flush=True)
        if name in args.refine:
            seconds, peak = pwm("refine", str(downlink), "--start", str(out / "spg.ply"),
                                "--corrections", str(out / "corrections.json"), "--out", str(out / "refined"))
            r = evaluate(out / "refined" / "refined.ply", truth_dir=truth)
            refined.append(f"{name:<14}{rms_start:>10.2f}{rms_spg:>8.2f}{r['rms_gsd']:>12.2f}{r['ncc']:>7.3f}"
                           f"{r['ssim']:>7.3f}{seconds:>8.0f}{peak:>9.2f}")
            print(refined[-1], flush=True)
    print("\nstereo photogrammetry (RMS in image GSDs after ICP; spacing: median distance between points)")
    print(f"{'scenario':<14}{'features':>9}{'matches':>8}{'points':>7}{'spacing':>8}{'res px':>7}{'vertices':>9}"
          f"{'RMS start':>10}{'RMS spg':>8}{'time s':>8}{'peak GiB':>9}")
    print("\n".join(models))
    print("\npose errors against the truth, RMS over images, before>after (lateral/along/across: the camera's "
          "boresight axes)")
    print(f"{'scenario':<14}"
          + "".join(f"{label:>{w + 7}}" for label, (_, w, _) in zip(ERROR_LABELS, ERRORS, strict=True)))
    print("\n".join(errors))
    print("\npredicted 1-sigma, median over images, prior>posterior (the adjustment's normal matrix at its "
          "residuals); then one"
          "\nimage with all others known: its line of sight (px), its pointing (urad) with its position free "
          "and known, and the"
          "\n|correlation| of its lateral position with the pointing that mimics it")
    print(f"{'scenario':<14}"
          + "".join(f"{label:>{w + 7}}" for label, (_, w, _) in zip(SIGMA_LABELS, SIGMAS, strict=True))
          + f"{'LOS1 px':>9}{'pt1 urad':>10}{'pt|pos':>10}{'corr':>10}")
    print("\n".join(spread))
    if refined:
        print("\nrefinement started from the photogrammetric model with the corrected poses (RMS in GSDs)")
        print(f"{'scenario':<14}{'RMS start':>10}{'RMS spg':>8}{'RMS refined':>12}{'NCC':>7}{'SSIM':>7}{'time s':>8}"
              f"{'peak GiB':>9}")
        print("\n".join(refined))
    t = feature_timing(args.sims, args.timing, 40)
    print(f"\nfeatures: {t['images']} images of 1024x1024, 2 threads: extraction {t['extract_s']:.1f} s, "
          f"matching {t['pairs']} pairs {t['match_s']:.1f} s ({t['matches']} matches), total "
          f"{t['extract_s'] + t['match_s']:.1f} s")


if __name__ == "__main__":
    main()
