"""Stereo photogrammetry against the proving ground's truth: per scenario the photogrammetric
model's RMS (GSD) next to the start model's, pose errors before and after the adjustment,
runtime and peak memory; then the time of feature extraction and matching for 40 images.

    .venv/bin/python bench/spg.py [--sims /tmp/sims] [--scenarios global-coarse site site-ke]
                                  [--out DIR] [--timing site site-polar]

Simulations are read from SIMS/<scenario> (downlink/ and truth/), never re-made. Attitude is
the rotation angle between corrected and true camera axes; line of sight is where the true
boresight's ground point lands with the corrected pose, in pixels from where it belongs: with a
narrow field of view a lateral position error and a pointing error move the image alike, so the
images fix their sum (the line of sight) far better than either alone.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from accuracy import pwm  # bench/ is on sys.path when this script runs
from scipy.spatial.transform import Rotation

from pwm.camera import Pose, project
from pwm.evaluate.report import evaluate
from pwm.io.downlink import read_views
from pwm.io.meshio import read_mesh
from pwm.raytrace import RayTracer
from pwm.spg import PoseCorrection
from pwm.spg.features import extract, match_guided
from pwm.spg.pairs import choose_pairs


def pose_errors(downlink: Path, truth: Path, corrections: dict[str, PoseCorrection] | None) -> dict:
    """RMS over images of position (m), attitude (urad) and line-of-sight (px) errors."""
    manifest = json.loads((truth / "manifest.json").read_text())
    sc = manifest["scenario"]
    views = read_views(downlink, instrument_id=sc["instrument_id"], target=sc["target"], body_frame=sc["body_frame"], corrections=corrections)
    true = {Path(im["label"]).stem: im for im in manifest["images"]}
    pos, att, los = [], [], []
    for v in views:
        t = true[v.name]
        pose = Pose(np.array(t["position_km"]), np.array(t["rotation"]))
        ground = pose.position + pose.boresight * t["site_range_km"]
        pos.append(np.linalg.norm(v.pose.position - pose.position) * 1e3)
        att.append(Rotation.from_matrix(v.pose.rotation @ pose.rotation.T).magnitude() * 1e6)
        los.append(np.linalg.norm(project(ground, v.camera, v.pose) - project(ground, v.camera, pose)))
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    return {"position_m": rms(pos), "attitude_urad": rms(att), "line_of_sight_px": rms(los)}


def feature_timing(sims: Path, names: list[str], count: int) -> dict:
    """Seconds to extract features from `count` images (taken in turn from the scenarios) and to
    match the pairs chosen among them, with 2 threads."""
    chosen = []
    for name in names:
        downlink = sims / name / "downlink"
        views = read_views(downlink, instrument_id=-64361, target="BENNU", body_frame="IAU_BENNU")
        chosen.append((views[: count - sum(len(v) for v, _ in chosen)], read_mesh(downlink / "start_model.obj")))
        if sum(len(v) for v, _ in chosen) >= count:
            break
    images = sum(len(v) for v, _ in chosen)
    clock = time.perf_counter()
    features = [extract([v.image for v in views], threads=2) for views, _ in chosen]
    extract_s = time.perf_counter() - clock
    pairs = matches = 0
    clock = time.perf_counter()
    for (views, model), feats in zip(chosen, features):
        for p in choose_pairs(views, RayTracer(model)):
            a, b = views[p.first], views[p.second]
            matches += len(match_guided(feats[p.first], feats[p.second], camera_a=a.camera, pose_a=a.pose, camera_b=b.camera,
                                        pose_b=b.pose, max_error_px=45.0))
            pairs += 1
    return {"images": images, "extract_s": extract_s, "match_s": time.perf_counter() - clock, "pairs": pairs, "matches": matches}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sims", type=Path, default=Path("/tmp/sims"))
    parser.add_argument("--scenarios", nargs="+", default=["global-coarse", "site", "site-ke"])
    parser.add_argument("--out", type=Path, default=Path("out/bench-spg"))
    parser.add_argument("--timing", nargs="+", default=["site", "site-polar"])
    args = parser.parse_args()
    header = (f"{'scenario':<14}{'points':>7}{'res px':>7}{'RMS start':>10}{'RMS spg':>8}{'pos m':>14}{'att urad':>14}"
              f"{'LOS px':>13}{'time s':>8}{'peak GiB':>9}")
    rows = []
    for name in args.scenarios:
        downlink, truth, out = args.sims / name / "downlink", args.sims / name / "truth", args.out / name
        seconds, peak = pwm("spg", str(downlink), "--start", str(downlink / "start_model.obj"), "--out", str(out))
        stats = json.loads((out / "spg.json").read_text())
        corrections = {k: PoseCorrection(**v) for k, v in json.loads((out / "corrections.json").read_text())["images"].items()}
        before, after = pose_errors(downlink, truth, None), pose_errors(downlink, truth, corrections)
        rms_start = evaluate(downlink / "start_model.obj", truth_dir=truth)["rms_gsd"]
        rms_spg = evaluate(out / "spg.ply", truth_dir=truth)["rms_gsd"]
        rows.append(f"{name:<14}{stats['points']:>7}{stats['residual_rms_px']:>7.2f}{rms_start:>10.2f}{rms_spg:>8.2f}"
                    f"{before['position_m']:>7.2f}>{after['position_m']:<6.2f}{before['attitude_urad']:>7.0f}>{after['attitude_urad']:<6.0f}"
                    f"{before['line_of_sight_px']:>6.1f}>{after['line_of_sight_px']:<6.1f}{seconds:>8.0f}{peak:>9.2f}")
        print(rows[-1], flush=True)
    print("\nstereo photogrammetry (RMS in image GSDs after ICP; errors RMS over images, before>after)")
    print(header)
    print("\n".join(rows))
    t = feature_timing(args.sims, args.timing, 40)
    print(f"\nfeatures: {t['images']} images of 1024x1024, 2 threads: extraction {t['extract_s']:.1f} s, "
          f"matching {t['pairs']} pairs {t['match_s']:.1f} s ({t['matches']} matches), total {t['extract_s'] + t['match_s']:.1f} s")


if __name__ == "__main__":
    main()
