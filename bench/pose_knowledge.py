"""Pose knowledge against the proving ground's truth (issue 18): what the operations' adjustment
of a downlink's poses (service.spg.adjust_downlink, run by `pwm run` with no options) made of
the kernels' errors, and the refined model's accuracy.

    .venv/bin/python bench/pose_knowledge.py SIM [SIM ...] [--out DIR] [--workers 2] [--reuse]

Each SIM is a simulated downlink directory (downlink/ and truth/, e.g. `pwm simulate SIM
--scenario site --knowledge-error nav:3,1,50,20 --with-start-model`). It is run into a fresh
SQLite catalog under OUT/<name>/ (kept with --reuse), and the tables give per SIM: the line of
sight (where the true boresight's ground point lands, px from where it belongs, RMS over the
images) with the kernels' poses and with the corrected ones, and how much of it every image
shares in its own frame (what a camera misalignment does); per navigation arc, the position
error along-track, cross-track and radial (RMS, m) before and after; the misalignment and drift
(microradians) drawn and recovered, with the posterior sigma the adjustment gives each (the
feedback's, where the maplets' registrations adjusted the poses again); where the catalog's
lidar spots tied the points, how many and how far the images moved the spots' frame; the refined model's
RMS (GSD), NCC and SSIM on held-out views, and the run's time.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from sqlalchemy import select

from pwm.camera import Camera, Pose, project
from pwm.trajectory import track_frames

PWM = [sys.executable, "-c", "from service.cli import app; app(prog_name='pwm')"]


def run(sim: Path, work: Path, *, workers: int, reuse: bool) -> float:
    """`pwm run` of SIM's downlink into work/data; seconds (0 when reused)."""
    if reuse and (work / "model.ply").exists():
        return 0.0
    env = {**os.environ, "PWM_DATA_DIR": str(work / "data")}
    clock = time.perf_counter()
    subprocess.run([*PWM, "run", str(sim / "downlink"), "--workers", str(workers)], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=open(work / "run.log", "w"))
    seconds = time.perf_counter() - clock
    subprocess.run([*PWM, "export", "latest", "--format", "ply", "--out", str(work / "model.ply")], env=env,
                   check=True, stdout=subprocess.DEVNULL)
    subprocess.run([*PWM, "evaluate", str(work / "model.ply"), "--truth", str(sim / "truth"), "--json",
                    str(work / "evaluation.json"), "--plots", str(work / "plots")], env=env, check=True,
                   stdout=subprocess.DEVNULL)
    return seconds


def catalog_poses(work: Path) -> tuple[dict[str, tuple[Pose, Pose]], dict | None]:
    """Per image (label stem): its kernels' pose and its corrected pose; the downlink's record
    of the adjustment."""
    os.environ["PWM_DATA_DIR"] = str(work / "data")
    from service.db import make_engine, make_sessionmaker
    from service.rows import Downlink, Image
    from service.settings import get_settings
    from service.views import image_pose, kernel_pose

    get_settings.cache_clear()
    sessions = make_sessionmaker(make_engine(get_settings().database_url))
    with sessions() as session:
        poses = {Path(image.label_path).stem: (kernel_pose(image), image_pose(image))
                 for image in session.scalars(select(Image))}
        report = session.scalars(select(Downlink.pose_adjustment)).first()
    return poses, report


def pose_table(sim: Path, work: Path) -> dict:
    manifest = json.loads((sim / "truth" / "manifest.json").read_text())
    c = manifest["camera"]
    camera = Camera(width=c["width"], height=c["height"], fx=c["fx"], fy=c["fy"], cx=c["cx"], cy=c["cy"])
    true = {Path(im["label"]).stem: im for im in manifest["images"]}
    poses, report = catalog_poses(work)
    names = sorted(true, key=lambda n: true[n]["et"])
    truth = [Pose(np.array(true[n]["position_km"]), np.array(true[n]["rotation"])) for n in names]
    times = np.array([true[n]["et"] for n in names])
    los: dict[str, list] = {"before": [], "after": []}
    errors: dict[str, list] = {"before": [], "after": []}
    for name, t in zip(names, truth, strict=True):
        ground = t.position + t.boresight * true[name]["site_range_km"]
        for which, pose in zip(("before", "after"), poses[name], strict=True):
            los[which].append(project(ground, camera, pose) - project(ground, camera, t))
            errors[which].append((pose.position - t.position) * 1e3)
    frames = track_frames(times, np.array([t.position for t in truth]))
    out: dict = {}
    for which, shifts in los.items():
        # the part every image shares (in its own frame: a camera misalignment looks so) and the rest
        common = np.mean(shifts, axis=0)
        out[f"los_{which}_px"] = _rms(np.linalg.norm(shifts, axis=1))
        out[f"los_{which}_common_px"] = common.tolist()
        out[f"los_{which}_rest_px"] = _rms(np.linalg.norm(np.array(shifts) - common, axis=1))
    arcs = manifest["knowledge_error"].get("arcs") or [{"images": [true[n]["name"] for n in names]}]
    index = {true[n]["name"]: k for k, n in enumerate(names)}  # the arcs name images as the manifest does
    out["arcs"] = []
    for arc in arcs:
        ks = [index[n] for n in arc["images"] if n in index]
        out["arcs"].append({which: np.sqrt((np.einsum("kij,kj->ki", frames[ks], np.array(errors[which])[ks]) ** 2)
                                           .mean(axis=0)).tolist() for which in ("before", "after")})
    out["report"] = report
    out["unknowns_true"] = true_unknowns(manifest, names, [poses[n][0] for n in names])
    return out


def true_unknowns(manifest: dict, names: list[str], kernels: list[Pose]) -> dict[str, float] | None:
    """The navigation pose model's unknowns (pwm.spg.pose_models, built on the kernels' poses as
    the adjustment builds it) that best give the corrections undoing the errors drawn (km, rad)."""
    from pwm.knowledge import NavigationErrors
    from pwm.spg.pose_models import navigation_poses

    stated = manifest["knowledge_error"]
    if stated["mode"] != "navigation":
        return None
    errors = NavigationErrors(along_m=stated["along_m"], cross_m=stated["cross_m"],
                              misalign_urad=stated["misalign_urad"], drift_urad=stated["drift_urad"])
    true = {Path(im["label"]).stem: im for im in manifest["images"]}
    model = navigation_poses(np.array([true[n]["et"] for n in names]), kernels, errors)
    target = np.concatenate([np.r_[-np.array(true[n]["knowledge_error"]["position_m"]) * 1e-3,
                                   np.array(true[n]["knowledge_error"]["pointing_body_urad"]) * 1e-6] for n in names])
    theta = np.linalg.lstsq(model.design.toarray(), target, rcond=None)[0]
    return {name: float(v * scale) for name, v, scale in zip(model.names, theta, model.scale, strict=True)}


def _rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sims", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=Path("/tmp/pose_knowledge"))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--reuse", action="store_true")
    args = parser.parse_args()
    for sim in args.sims:
        work = args.out / sim.name
        work.mkdir(parents=True, exist_ok=True)
        seconds = run(sim, work, workers=args.workers, reuse=args.reuse)
        table = pose_table(sim, work)
        evaluation = json.loads((work / "evaluation.json").read_text())
        report = table["report"] or {}
        print(f"\n{sim}: knowledge {report.get('knowledge')} ({report.get('source')}), {report.get('note')}; "
              f"pwm run {seconds:.0f} s, adjustment {report.get('seconds', 0):.0f} s")
        feedback = report.get("feedback") or {}
        if feedback:
            print(f"  registrations fed back: {feedback['note']}; {feedback['landmarks']} landmarks, "
                  f"{feedback.get('feature_tracks', 0)} feature tracks, {feedback.get('seconds', 0):.0f} s")
        final = feedback if feedback.get("note") == "adjusted" else report  # the corrections stored
        if final.get("ties"):
            print(f"  tied to {report.get('lidar_spots')} lidar spots: {final['ties']} points, RMS "
                  f"{final['tie_rms_m']:.3f} m from their planes; the spots' frame moved by "
                  f"{'/'.join(f'{v:.2f}' for v in final.get('tie_frame_shift_m', []))} m, "
                  f"{'/'.join(f'{v:.0f}' for v in final.get('tie_frame_turn_urad', []))} urad")
        print(f"  line of sight RMS (px, against the truth): {table['los_before_px']:.2f} -> "
              f"{table['los_after_px']:.2f} ({1 - table['los_after_px'] / table['los_before_px']:.0%} cut); "
              f"posterior 1 sigma {final.get('los_posterior_px', float('nan')):.2f}")
        print(f"  of which common to every image (image frame, px): "
              f"{'/'.join(f'{v:.2f}' for v in table['los_before_common_px'])} -> "
              f"{'/'.join(f'{v:.2f}' for v in table['los_after_common_px'])}; the rest "
              f"{table['los_before_rest_px']:.2f} -> {table['los_after_rest_px']:.2f} px RMS")
        for k, arc in enumerate(table["arcs"]):
            print(f"  arc {k} position RMS along/cross/radial (m): "
                  f"{'/'.join(f'{v:.2f}' for v in arc['before'])} -> {'/'.join(f'{v:.2f}' for v in arc['after'])}")
        truth = table["unknowns_true"] or {}
        for u in final.get("unknowns", []):
            if u["name"] in truth and ("misalignment" in u["name"] or "drift" in u["name"]):
                print(f"  {u['name']:<16} true {truth[u['name']] * 1e6:7.1f} found {u['value'] * 1e6:7.1f} urad, "
                      f"posterior sigma {u['posterior_sigma'] * 1e6:5.1f} (prior {u['prior_sigma'] * 1e6:.0f})")
        print(f"  refined model: RMS {evaluation['rms_gsd']:.3f} GSD, NCC {evaluation['ncc']:.3f}, "
              f"SSIM {evaluation['ssim']:.3f}")
        (work / "pose_knowledge.json").write_text(json.dumps({"seconds": seconds, **table, "evaluation": evaluation},
                                                             indent=1, default=str))


if __name__ == "__main__":
    main()
