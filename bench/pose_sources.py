"""What each source of image observations says about the camera's pointing, against the proving
ground's truth: after `pwm run` of a simulated survey under navigation errors, the navigation
pose model (pwm.spg.pose_models) adjusted to

- `features`: SIFT feature tracks (pwm.spg.photogrammetry.adjust_poses on the catalog's latest
  version, anchored to it), and
- `landmarks`: the maplets' landmarks alone (where each image saw each maplet's landmark once the
  refinement registered it, service.spg.landmark_tracks),

each from the TRUE poses (what is drawn is zero: anything found is a bias of the observations)
and from the kernels' poses (what is drawn is the knowledge error). Per source and start: the
misalignment and drift found (urad) with their posterior sigmas, the line of sight against the
truth (px RMS at each image's boresight ground point) and the residual RMS (px).

    .venv/bin/python bench/pose_sources.py SIM DATA [--knowledge nav:3,1,50,20]

SIM holds downlink/ and truth/ (e.g. symbolic links to a campaign's downlinks/D and truth/D);
DATA is the PWM_DATA_DIR that `pwm run SIM/downlink` filled. Only read.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sim", type=Path)
    parser.add_argument("data", type=Path)
    parser.add_argument("--knowledge", default="nav:3,1,50,20")
    args = parser.parse_args()
    os.environ["PWM_DATA_DIR"] = str(args.data)
    from sqlalchemy import select

    from pwm.camera import Pose, corrected_pose, project
    from pwm.knowledge import NavigationErrors, parse_knowledge_errors
    from pwm.spg.adjustment import bundle_adjust
    from pwm.spg.photogrammetry import adjust_poses
    from pwm.spg.pose_models import navigation_poses
    from pwm.spg.triangulation import triangulate
    from service.db import make_engine, make_sessionmaker
    from service.rows import Image
    from service.settings import get_settings
    from service.spg import landmark_tracks
    from service.versions import latest_version, version_mesh
    from service.views import catalog_views

    knowledge = parse_knowledge_errors(args.knowledge)
    if not isinstance(knowledge, NavigationErrors):
        raise SystemExit("a navigation knowledge (nav:...) is what has a misalignment to find")
    manifest = json.loads((args.sim / "truth" / "manifest.json").read_text())
    true = {Path(im["label"]).stem: im for im in manifest["images"]}
    sessions = make_sessionmaker(make_engine(get_settings().database_url))
    with sessions() as session:
        images = session.scalars(select(Image).order_by(Image.id)).all()
        views = catalog_views(session, image_ids=[im.id for im in images], pixels=True, kernel_poses=True)
        landmarks = landmark_tracks(session, {im.lidvid: k for k, im in enumerate(images)})
        version = latest_version(session)
        if version is None:
            raise SystemExit(f"{args.data} holds no model version: run the survey first")
        model = version_mesh(args.data, version)
        names = [Path(im.label_path).stem for im in images]
    view_list = [views[im.id] for im in images]
    cameras = [v.camera for v in view_list]
    kernels = [v.pose for v in view_list]
    truth = [Pose(np.array(true[n]["position_km"]), np.array(true[n]["rotation"])) for n in names]
    times = np.array([v.et for v in view_list])

    def los_px(poses: list[Pose]) -> float:
        shifts = []
        for name, pose, t, camera in zip(names, poses, truth, cameras, strict=True):
            ground = t.position + t.boresight * true[name]["site_range_km"]
            shifts.append(project(ground, camera, pose) - project(ground, camera, t))
        return float(np.sqrt(np.mean(np.sum(np.square(shifts), axis=1))))

    print(f"{args.sim}: {len(images)} images, {landmarks.n_points} landmarks ({len(landmarks.image)} observations), "
          f"version {version.version}; line of sight with the kernels' poses {los_px(kernels):.2f} px")
    print("| source | from | misalignment x / y / z, urad (sigma) | drift x / y / z, urad (sigma) | "
          "line of sight px | residual RMS px |")
    print("|---|---|---|---|---|---|")
    for start, poses in (("truth", truth), ("kernels", kernels)):
        pose_model = navigation_poses(times, poses, knowledge)
        drawn = np.zeros(len(pose_model.names))
        if start == "kernels":
            target = np.concatenate([np.r_[-np.array(true[n]["knowledge_error"]["position_m"]) * 1e-3,
                                           np.array(true[n]["knowledge_error"]["pointing_body_urad"]) * 1e-6]
                                     for n in names])
            drawn = np.linalg.lstsq(pose_model.design.toarray(), target, rcond=None)[0] * pose_model.scale
        for source in ("features", "landmarks"):
            if source == "features":
                found = adjust_poses([dataclasses.replace(v, pose=p) for v, p in zip(view_list, poses, strict=True)],
                                     model, pose_model=pose_model, anchor=True)
                unknowns = {u["name"]: (u["value"], u["posterior_sigma"]) for u in found.stats["unknowns"]}
                fixed = [found.corrections[v.name].apply(p) for v, p in zip(view_list, poses, strict=True)]
                residual = found.stats["residual_rms_px"]
            else:
                adjusted = bundle_adjust(triangulate(landmarks, cameras, poses)[0], landmarks, cameras, poses,
                                         model=pose_model)
                residual = float(np.sqrt(np.mean(adjusted.residuals_px**2)))
                sigma = np.sqrt(np.diag(adjusted.parameter_covariance(max(residual, 0.1) / np.sqrt(2))))
                unknowns = {name: (value * scale, s * scale) for name, value, scale, s in
                            zip(pose_model.names, adjusted.parameters, pose_model.scale, sigma, strict=True)}
                fixed = [corrected_pose(p, adjusted.position_corrections[i], adjusted.rotation_corrections[i])
                         for i, p in enumerate(poses)]

            drawn_by_name = dict(zip(pose_model.names, drawn, strict=True))
            print(f"| {source} | {start} | {_cells('misalignment', unknowns, drawn_by_name)} | "
                  f"{_cells('drift', unknowns, drawn_by_name)} | {los_px(fixed):.3f} | {residual:.2f} |")
    print("(found minus drawn: zero where a source is unbiased)")


def _cells(kind: str, unknowns: dict[str, tuple[float, float]], drawn: dict[str, float]) -> str:
    """Found minus drawn (urad) and the posterior sigma, per axis, of the unknowns named `kind`."""
    return " / ".join(f"{(unknowns[f'{kind} {a}'][0] - drawn[f'{kind} {a}']) * 1e6:+.1f} "
                      f"({unknowns[f'{kind} {a}'][1] * 1e6:.1f})" for a in "xyz")


if __name__ == "__main__":
    main()
