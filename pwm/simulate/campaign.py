"""Simulate a mission downlink from a truth asteroid: the orchestration, with all its file output.

OUT/downlink/ holds what a real downlink holds (PDS4 products, SPICE kernels with a meta-kernel,
a starting shape model, and a manifest written last); OUT/truth/ holds what only the proving
ground knows (the truth model, the true kernels, held-out views, the manifest of true geometry).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import spiceypy as sp

from pwm.camera import Camera, Pose
from pwm.frames import local_sun, unit_to_latlon
from pwm.io.lidar import write_lidar_product
from pwm.io.meshio import write_obj
from pwm.io.pds4 import file_sha256, write_image_product
from pwm.io.spice_geometry import camera_from_kernel, camera_pose, instrument_frame, spacecraft_of, sun_direction
from pwm.io.spice_kernels import (
    BUNDLED_DIR,
    CkSegment,
    SpkSegment,
    kernel_pool,
    knowledge_comment,
    write_ck,
    write_metakernel,
    write_spk,
)
from pwm.knowledge import EXACT, IndependentErrors, KnowledgeErrors
from pwm.mesh import Mesh
from pwm.photometry import PHOTOMETRY
from pwm.raytrace import RayTracer
from pwm.render import render_supersampled
from pwm.simulate.detector import choose_exposure, to_dn
from pwm.simulate.knowledge import manifest_entries, perturb
from pwm.simulate.landforms import Clearing, Landform, apply_landforms, sample_landforms
from pwm.simulate.lidar import LIDAR_NAME, NO_RETURN, LidarSpec, save_true_spots, take_shots, write_lidar_kernels
from pwm.simulate.missions import MISSIONS, Mission
from pwm.simulate.optics import blur, flat_field
from pwm.simulate.plan import Observation, frame_room_px, plan_approach, plan_global, plan_site, sun_states
from pwm.simulate.scenarios import Campaign, Scenario
from pwm.simulate.truth import (
    SiteSpec,
    Truth,
    build_base,
    build_truth,
    low_pass,
    save as save_truth,
    site_frames,
    stitch_sites,
    undulations,
)

log = logging.getLogger(__name__)

SUN, SSB = 10, 0
CK_FRAME_CLASS = 3  # SPICE frame class of frames whose attitude a CK gives
WINDOW_S = 60.0  # each image sits in the middle of a short observation window of the kernels
EXPOSURE_S = 0.004  # labels carry start and stop; the geometry is at mid-exposure
OPTICS_STREAM = 21  # the random stream of the camera's flat field
KNOWLEDGE_STREAM = 22  # the random stream of navigation-like knowledge errors
CAMPAIGN_STREAM = 23  # a campaign's downlinks each draw from their own stream
LANDFORM_STREAM = 24  # the craters and boulders over a campaign's body
LIDAR_STREAM = 25  # the lidar's range noise and dropouts
SKY_MARGIN = 0.05  # an approach survey's body stays this fraction of the half frame clear of its edges


def simulate(out: str | Path, *, scenario: Scenario, seed: int = 0,
             knowledge: KnowledgeErrors = EXACT, with_start_model: bool = False) -> dict:
    """Write OUT/downlink and OUT/truth for `scenario`; returns the truth manifest.

    A mission's first downlinks come with no shape model; with_start_model puts one into the
    downlink (start_model.obj: the truth low-passed, with the scenario's undulations), as an
    earlier campaign would have left it.

    The downlink's kernels carry the true poses with the `knowledge` errors
    (pwm.simulate.knowledge; none by default); the images are rendered from the truth, and are
    the same for a seed whatever the errors.
    """
    out = Path(out)
    clock = time.perf_counter()
    base = MISSIONS[scenario.mission].base_shape()
    log.info("building the truth asteroid (%s)", scenario.name)
    truth = build_truth(
        base=base, site_lat_deg=scenario.site_lat_deg, site_lon_deg=scenario.site_lon_deg,
        site_size_km=scenario.site_size_km, resolution_km=scenario.truth_resolution_km, seed=seed,
        base_edge_km=scenario.base_edge_km, global_roughness_km=scenario.global_roughness_km,
        n_craters=scenario.n_craters, n_boulders=scenario.n_boulders, steep_boulders=scenario.steep_boulders,
        cobble_cover=scenario.cobble_cover, large_boulders=scenario.large_boulders,
    )
    log.info("truth: %d vertices, %d faces (%.1f s)", len(truth.mesh.vertices), len(truth.mesh.faces),
             time.perf_counter() - clock)
    start = start_model(truth, scenario=scenario, base=base, seed=seed) if with_start_model else None
    return _downlink(out / "downlink", out / "truth", scenario=scenario, truth=truth, seed=seed, knowledge=knowledge,
                     start=start, rng=np.random.default_rng(seed))


def simulate_campaign(out: str | Path, *, campaign: Campaign, seed: int = 0, knowledge: KnowledgeErrors = EXACT,
                      with_start_model: bool = False) -> dict:
    """Write a campaign: OUT/downlinks/K-NAME/ in time order (the survey first, then each site)
    and OUT/truth/K-NAME/ beside each, all of one truth asteroid; OUT/truth/campaign.json lists
    them. Returns that list.

    The survey's truth directory holds the whole body with the sites' patches thinned to the
    body's own spacing (what a metre-scale model is judged against; its images saw the full
    patches); each site's holds the whole truth with that site's patch last. with_start_model:
    the survey downlink brings a start model; the sites never do (the catalog's model is theirs).
    """
    out = Path(out)
    clock = time.perf_counter()
    survey = campaign.survey
    base = MISSIONS[survey.mission].base_shape()
    log.info("building the campaign's truth asteroid (%s)", campaign.name)
    body = build_base(base, base_edge_km=survey.base_edge_km, seed=seed, global_roughness_km=survey.global_roughness_km)
    sites = [SiteSpec(lat_deg=s.site_lat_deg, lon_deg=s.site_lon_deg, size_km=s.site_size_km,
                      resolution_km=s.truth_resolution_km, n_craters=s.n_craters, n_boulders=s.n_boulders,
                      steep_boulders=s.steep_boulders, cobble_cover=s.cobble_cover, large_boulders=s.large_boulders)
             for s in campaign.sites]
    landforms = _landforms(body, campaign=campaign, sites=sites, seed=seed)
    body = apply_landforms(body, landforms)
    params = dict(base_edge_km=survey.base_edge_km, global_roughness_km=survey.global_roughness_km,
                  campaign=campaign.name)
    stitched = stitch_sites(body, sites, seed=seed, params=params, landforms=landforms)
    del body
    log.info("truth built (%.1f s)", time.perf_counter() - clock)
    entries = []
    for k, scenario in enumerate(campaign.downlinks):
        name = f"{k + 1}-{scenario.name}"
        # every downlink's images come from the full truth; the survey's is judged on the thinned one
        truth = stitched.truth(max(k - 1, 0))
        thin = stitched.truth(0, thin_to_km=survey.base_edge_km) if k == 0 else None
        start = (start_model(thin, scenario=scenario, base=base, seed=seed)
                 if with_start_model and thin is not None else None)
        manifest = _downlink(out / "downlinks" / name, out / "truth" / name, scenario=scenario, truth=truth,
                             saved=thin, seed=seed, knowledge=knowledge, start=start,
                             rng=np.random.default_rng([seed, CAMPAIGN_STREAM, k]))
        del truth, thin
        entries.append({"name": name, "downlink": f"downlinks/{name}", "truth": f"truth/{name}",
                        "scope": "global" if scenario.global_views else "site", "images": manifest["image_count"],
                        "gsd_m": manifest["gsd_m"], "start_utc": scenario.start_utc})
    summary = {"campaign": campaign.model_dump(mode="json"), "seed": seed, "downlinks": entries,
               "elapsed_s": round(time.perf_counter() - clock, 2)}
    (out / "truth" / "campaign.json").write_text(json.dumps(summary, indent=1))
    return summary


def _landforms(body: Mesh, *, campaign: Campaign, sites: list[SiteSpec], seed: int) -> list[Landform]:
    """The campaign's craters and boulders over the body, clear of every site's square and margin."""
    clearings = [Clearing(centre_km=frame.origin, radius_km=s.clear_radius_km)
                 for s, frame in zip(sites, site_frames(body, sites), strict=True)]
    return sample_landforms(body, np.random.default_rng([seed, LANDFORM_STREAM]), n_craters=campaign.craters,
                            n_boulders=campaign.boulders, n_steep=campaign.steep_boulders,
                            crater_diameter_km=_km(campaign.crater_diameter_m),
                            boulder_diameter_km=_km(campaign.boulder_diameter_m),
                            clearings=clearings)


def _km(range_m: tuple[float, float]) -> tuple[float, float]:
    return range_m[0] * 1e-3, range_m[1] * 1e-3


def _downlink(downlink: Path, truth_dir: Path, *, scenario: Scenario, truth: Truth, seed: int,
              knowledge: KnowledgeErrors, start: Mesh | None, rng: np.random.Generator,
              saved: Truth | None = None) -> dict:
    """Render one downlink of `scenario` from `truth` into `downlink`, and write what the proving
    ground knows of it (`saved`, by default the truth itself, and the manifest) into truth_dir."""
    for d in (downlink, truth_dir):
        if d.exists():
            shutil.rmtree(d)
    clock = time.perf_counter()
    mission = MISSIONS[scenario.mission]
    fixed = _copy_fixed_kernels(downlink / "kernels", mission)
    fixed += mission.made_up_kernels(downlink / "kernels")

    with kernel_pool(fixed):
        detector = camera_from_kernel(scenario.instrument_id)
        camera, window = _readout(detector, scenario)
        start_et = sp.str2et(scenario.start_utc)
        campaign_s = scenario.campaign_days * 86400.0
        sun_spk = downlink / "kernels" / "spk" / f"pwm_{scenario.name}_sun.bsp"
        _write_sun(sun_spk, scenario=scenario, start_et=start_et, campaign_s=campaign_s)
        sp.furnsh(str(sun_spk))
        observations, validation = _plan(scenario, truth=truth, camera=camera, start_et=start_et,
                                         campaign_s=campaign_s, rng=rng)
        _apart(observations + validation)
        for obs in observations + validation:
            # on the millisecond grid of the labels' UTC times, so that mid-exposure is exact
            obs.et = sp.utc2et(sp.et2utc(obs.et, "ISOC", 3))

        true_kernels = _write_pose_kernels(truth_dir / "kernels", scenario=scenario, mission=mission,
                                           observations=observations + validation)
        noisy, misalignment, drawn = _perturb(observations, errors=knowledge, rng=rng, seed=seed)
        downlink_kernels = _write_pose_kernels(downlink / "kernels", scenario=scenario, mission=mission,
                                               observations=noisy,
                                               comments=[] if knowledge == EXACT else [knowledge_comment(knowledge)])
        if scenario.lidar is not None:
            # the truth's lidar FK and the downlink's differ by the camera's misalignment alone
            for folder, kernels, error in ((truth_dir / "kernels", true_kernels, None),
                                           (downlink / "kernels", downlink_kernels, misalignment)):
                kernels += write_lidar_kernels(
                    folder, spec=scenario.lidar, spacecraft=spacecraft_of(scenario.instrument_id),
                    camera_frame=instrument_frame(scenario.instrument_id), camera_misalignment_rad=error)

    all_fixed = fixed + [sun_spk]
    (downlink / "kernels" / "mk").mkdir(parents=True, exist_ok=True)
    write_metakernel(downlink / "kernels" / "mk" / f"pwm_{scenario.name}.tm", kernels=all_fixed + downlink_kernels)
    truth_mk = truth_dir / "kernels" / "truth.tm"
    write_metakernel(truth_mk, kernels=all_fixed + true_kernels)

    tracer = RayTracer(truth.mesh)
    photometry = PHOTOMETRY[scenario.photometry]
    # Its own random stream, so that scenarios with a perfect camera draw what they always drew.
    flat = flat_field((camera.height, camera.width), scenario.optics.flat_field_rms,
                      np.random.default_rng([seed, OPTICS_STREAM]))
    images = []
    with kernel_pool([truth_mk]):
        # Render from the pose read back through SPICE, so products and kernels agree.
        for k, obs in enumerate(observations):
            pose, sun = _geometry(obs.et, scenario)
            view = render_supersampled(tracer, camera=camera, pose=pose, sun_direction=sun,
                                       factor=scenario.supersample, photometry=photometry)
            seen = view.reflectance if scenario.optics.perfect else blur(view.reflectance, scenario.optics) * flat
            images.append(_write_product(downlink / "images", obs=obs, view=seen, scenario=scenario,
                                         seed=seed, mission=mission, window=window, rng=rng))
            images[-1].update(_true_geometry(obs, pose=pose, sun=sun, truth=truth, camera=camera))
            images[-1]["knowledge_error"] = drawn[1][k]
            log.info("image %d/%d %s rendered", k + 1, len(observations), obs.name)
        held_out = []
        for obs in validation:
            # What the surface looks like, through no camera: the held-out truth is not blurred.
            pose, sun = _geometry(obs.et, scenario)
            view = render_supersampled(tracer, camera=camera, pose=pose, sun_direction=sun,
                                       factor=scenario.supersample, photometry=photometry)
            path = truth_dir / "validation" / f"{obs.name}.npz"
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(path, reflectance=view.reflectance.astype(np.float32), hit=view.hit, shadow=view.shadow,
                                in_site=_in_site(view.points, truth), position=pose.position, rotation=pose.rotation,
                                sun=sun)
            held_out.append({"name": obs.name, "file": f"validation/{obs.name}.npz",
                             **_true_geometry(obs, pose=pose, sun=sun, truth=truth, camera=camera)})
        lidar = (None if scenario.lidar is None else
                 _lidar(downlink, truth_dir, spec=scenario.lidar, scenario=scenario, truth=truth, tracer=tracer,
                        observations=observations, seed=seed, mission=mission))

    wavelength_km = 30.0 * scenario.gsd_km
    if start is not None:
        write_obj(downlink / "start_model.obj", start)
    save_truth(saved or truth, truth_dir)

    manifest = {
        "scenario": scenario.model_dump(mode="json"),
        "seed": seed,
        "gsd_m": scenario.gsd_km * 1e3,
        "base_shape": {"file": mission.shape, "scale": mission.scale},
        "image_count": len(images),
        "knowledge_error": drawn[0],
        "subframe": None if window is None else {"first_line": window[0], "first_sample": window[1]},
        "camera": {"instrument_id": scenario.instrument_id, "width": camera.width, "height": camera.height,
                   "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy},
        "start_model": {"file": "downlink/start_model.obj" if start is not None else None,
                        "low_pass_wavelength_m": wavelength_km * 1e3,
                        "vertex_spacing_m": 10.0 * scenario.gsd_km * 1e3,
                        "undulation_rms_m": scenario.start_error_rms_gsd * scenario.gsd_km * 1e3,
                        "undulation_band_m": list(scenario.start_error_band_m)},
        "images": images,
        "validation": held_out,
        "truth_kernels": "kernels/truth.tm",
        **({} if lidar is None else {"lidar": lidar}),
        "elapsed_s": round(time.perf_counter() - clock, 2),
    }
    (truth_dir / "manifest.json").write_text(json.dumps(manifest, indent=1))
    _write_downlink_manifest(downlink, scenario=scenario)
    log.info("simulated %d images in %.1f s", len(images), time.perf_counter() - clock)
    return manifest


def _lidar(downlink: Path, truth_dir: Path, *, spec: LidarSpec, scenario: Scenario, truth: Truth, tracer: RayTracer,
           observations: list[Observation], seed: int, mission: Mission) -> dict:
    """The lidar's shots through the views' windows of the loaded true kernels, written as one
    product into downlink/lidar (read through the downlink's kernels, they carry its knowledge
    errors, as the images do), with the true spots in truth_dir/lidar_spots.npz; what the
    manifest records of them."""
    extent_km = (float(np.linalg.norm(truth.mesh.vertices, axis=1).max()) if scenario.global_views
                 else scenario.site_size_km / 2)
    shots = take_shots(tracer, spec=spec, view_times=[obs.et for obs in observations], window_s=WINDOW_S,
                       spacecraft=spacecraft_of(scenario.instrument_id), target=scenario.target,
                       body_frame=scenario.body_frame, extent_km=extent_km,
                       rng=np.random.default_rng([seed, LIDAR_STREAM]))
    basename = f"pwm_{scenario.name}_lidar"
    label, data = write_lidar_product(
        directory=downlink / "lidar", basename=basename,
        lid=f"urn:nasa:pds:pwm_sim_{scenario.name.replace('-', '_')}_s{seed}:{basename}",
        et=shots.et, range_km=shots.range_km, flag=np.where(shots.returned, 0, NO_RETURN),
        start_utc=sp.et2utc(float(shots.et.min()), "ISOC", 6), stop_utc=sp.et2utc(float(shots.et.max()), "ISOC", 6),
        mission=mission.name, host_name=mission.host, instrument_name=LIDAR_NAME, target_name=mission.target_label,
        title=f"Simulated {scenario.name} lidar shots ({spec.pattern})", intensity=shots.intensity,
        direction=shots.direction_instrument if spec.pattern == "raster" else None)
    save_true_spots(truth_dir / "lidar_spots.npz", shots)
    return {"label": f"lidar/{label.name}", "data": f"lidar/{data.name}", "spots": "lidar_spots.npz",
            "shots": len(shots.et), "returns": int(shots.returned.sum()), "pattern": spec.pattern,
            "range_noise_m": spec.range_noise_m}


def start_model(truth: Truth, *, scenario: Scenario, base: Mesh, seed: int) -> Mesh:
    """The shape model the downlink starts from, "low-passed to ten GSD": vertices every 10 GSD,
    and an anti-aliasing filter that keeps half the amplitude at 30 GSD, so little remains at the
    20 GSD Nyquist wavelength; plus the scenario's smooth undulations. A site scenario's start is
    the truth's site patch so smoothed on the truth's base; a global one's is the whole body
    rebuilt from `base` with its roughness so smoothed (the truth's base would be the truth
    itself wherever the images look)."""
    wavelength_km, spacing_km = 30.0 * scenario.gsd_km, 10.0 * scenario.gsd_km
    if scenario.global_views:
        return build_base(base, base_edge_km=spacing_km, seed=seed, global_roughness_km=scenario.global_roughness_km,
                          low_pass_km=wavelength_km)
    shortest_m, longest_m = scenario.start_error_band_m
    error = (undulations(truth, rms_km=scenario.start_error_rms_gsd * scenario.gsd_km, shortest_km=shortest_m * 1e-3,
                         longest_km=longest_m * 1e-3, seed=seed) if scenario.start_error_rms_gsd > 0 else None)
    return low_pass(truth, wavelength_km=wavelength_km, spacing_km=spacing_km, error_km=error)


def _readout(detector: Camera, scenario: Scenario) -> tuple[Camera, tuple[int, int] | None]:
    """The camera of the pixels read out, and the zero-based (first_line, first_sample) of the window."""
    if scenario.subframe_px is None:
        return detector, None
    n = scenario.subframe_px
    first_sample, first_line = int(round(detector.cx + 0.5 - n / 2)), int(round(detector.cy + 0.5 - n / 2))
    camera = detector.subframe(first_sample=first_sample, first_line=first_line, samples=n, lines=n)
    return camera, (first_line, first_sample)


def _copy_fixed_kernels(kernel_dir: Path, mission: Mission) -> list[Path]:
    paths = []
    for name, kind in mission.kernels.items():
        dest = kernel_dir / kind / Path(name).name
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(BUNDLED_DIR / name, dest)
        paths.append(dest)
    return paths


def _write_sun(path: Path, *, scenario: Scenario, start_et: float, campaign_s: float) -> None:
    """The target relative to the Sun, and the Sun at the barycentre, as real kernel sets chain them."""
    epochs = np.arange(start_et - 86400.0, start_et + campaign_s + 2 * 86400.0, 3600.0)
    pole = sp.pxform(scenario.body_frame, "J2000", start_et) @ np.array([0.0, 0.0, 1.0])
    sun = sun_states(epochs, pole=pole, subsolar_lat_deg=scenario.subsolar_lat_deg)
    body = sp.bodn2c(scenario.target)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_spk(path, segments=[SpkSegment(body=body, center=SUN, epochs=epochs, states=-sun),
                              SpkSegment(body=SUN, center=SSB, epochs=epochs, states=np.zeros_like(sun))])


def _plan(scenario: Scenario, *, truth: Truth, camera: Camera, start_et: float, campaign_s: float,
          rng: np.random.Generator) -> tuple[list[Observation], list[Observation]]:
    def sun(ets: np.ndarray) -> np.ndarray:
        return np.array([sun_direction(et=float(t), target=scenario.target,
                                       body_frame=scenario.body_frame) for t in ets])

    range_km = scenario.gsd_km * camera.fx
    if scenario.global_views:
        radii = np.linalg.norm(truth.mesh.vertices, axis=1)
        kw: dict[str, Any] = dict(sun=sun, campaign_s=campaign_s, range_km=range_km + float(radii.mean()),
                                  phases_deg=scenario.incidences_deg, rng=rng)
        if scenario.survey_latitudes_deg:
            room = frame_room_px(camera, range_km=kw["range_km"], radius_km=float(radii.max()))
            if room < SKY_MARGIN * min(camera.width, camera.height) / 2:
                raise ValueError(f"{scenario.name}: at {scenario.gsd_km * 1e3:g} m GSD the body, {radii.max():.3f} "
                                 f"km from its centre at most, does not fit in the {camera.width}x{camera.height} px "
                                 f"frame with sky round it ({room:.0f} px to spare)")
            kw["latitudes_deg"] = scenario.survey_latitudes_deg
            return (plan_approach(start_et=start_et, n=scenario.n_azimuths, prefix="img", **kw),
                    plan_approach(start_et=start_et + 0.37 * 86400.0, n=scenario.n_validation, prefix="val",
                                  rounds=1, **kw))
        return (plan_global(start_et=start_et, n=scenario.n_azimuths, prefix="img", **kw),
                plan_global(start_et=start_et + 0.37 * 86400.0, n=scenario.n_validation, prefix="val", **kw))
    views = [(0.0, 0.0)] * scenario.n_nadir + scenario.off_nadir_views()
    kw = dict(frame=truth.site_frame, sun=sun, campaign_s=campaign_s, range_km=range_km,
              aim_scatter_km=scenario.pointing_scatter_km, rng=rng)
    val_views = [(25.0, 45.0 + 360.0 * k / max(scenario.n_validation, 1)) for k in range(scenario.n_validation)]
    val_inc = tuple(np.linspace(min(scenario.incidences_deg) + 5, max(scenario.incidences_deg) - 5,
                                max(scenario.n_validation, 1)))
    return (plan_site(start_et=start_et, views=views, incidences_deg=scenario.incidences_deg, prefix="img", **kw),
            plan_site(start_et=start_et + 0.41 * 86400.0, views=val_views, incidences_deg=val_inc, prefix="val", **kw))


def _apart(observations: list[Observation]) -> None:
    """Move any image planned within two kernel windows of the one before it (an image and a
    held-out view may seek the same Sun in overlapping searches) to just after that: the camera
    stays where it was planned, the Sun turns by a few degrees."""
    previous = -np.inf
    for obs in sorted(observations, key=lambda o: o.et):
        obs.et = max(obs.et, previous + 2 * WINDOW_S + 1.0)
        previous = obs.et


def _write_pose_kernels(kernel_dir: Path, *, scenario: Scenario, mission: Mission,
                        observations: list[Observation], comments: list[str] | None = None) -> list[Path]:
    """SPK of the spacecraft and CKs of the spacecraft and, where a CK gives the camera frame
    (its mount), of the camera, one window per image; `comments` in the SPK's and the CKs'
    comment areas (the pose knowledge they state).

    The spacecraft holds an inertial attitude and position through each short window, so the
    kernels give exactly the planned pose at the image epoch. A camera frame fixed to the
    spacecraft by the FK (a TK frame) turns the spacecraft's attitude by its mount; one a CK
    gives is mounted with the identity.
    """
    camera_frame = instrument_frame(scenario.instrument_id)
    frame_id, spacecraft_frame = sp.namfrm(camera_frame), sp.namfrm(mission.spacecraft_frame)
    ck_mounted = sp.frinfo(frame_id)[1] == CK_FRAME_CLASS
    # spacecraft -> camera; constant for a TK frame, so any epoch gives it
    mount = np.eye(3) if ck_mounted else sp.pxform(mission.spacecraft_frame, camera_frame, 0.0)
    sc = spacecraft_of(scenario.instrument_id)
    body = sp.bodn2c(scenario.target)
    order = sorted(observations, key=lambda o: o.et)
    gaps = np.diff([o.et for o in order])
    if (gaps <= 2 * WINDOW_S).any():
        raise ValueError("two planned images are closer in time than their kernel windows")
    spk_segments, epochs, rotations = [], [], []
    for obs in order:
        window = obs.et + np.array([-WINDOW_S, 0.0, WINDOW_S])
        to_j2000 = sp.pxform(scenario.body_frame, "J2000", obs.et)
        position = to_j2000 @ obs.position
        states = np.tile(np.concatenate([position, np.zeros(3)]), (3, 1))
        spk_segments.append(SpkSegment(body=sc, center=body, epochs=window, states=states))
        epochs.append(window)
        rotations.append(np.repeat((mount.T @ obs.rotation @ to_j2000.T)[None], 3, axis=0))
    epochs_a = np.concatenate(epochs)
    rot_a = np.concatenate(rotations)
    name = f"pwm_{scenario.name}"
    spk = kernel_dir / "spk" / f"{name}_sc.bsp"
    ck_sc = kernel_dir / "ck" / f"{name}_sc.bc"
    ck_mount = kernel_dir / "ck" / f"{name}_struct.bc"
    for p in (spk, ck_sc, ck_mount):
        p.parent.mkdir(parents=True, exist_ok=True)
    comments = comments or []
    write_spk(spk, segments=spk_segments, comments=comments)
    # the spacecraft clock carries the spacecraft's own NAIF id
    write_ck(ck_sc, segments=[CkSegment(frame_id=spacecraft_frame, sclk_id=sc, epochs=epochs_a, rotations=rot_a,
                                        angular_velocities=np.zeros((len(epochs_a), 3)),
                                        interval_starts=[e[0] for e in epochs])], comments=comments)
    if not ck_mounted:
        return [spk, ck_sc]
    span = np.array([epochs_a[0], epochs_a[-1]])
    write_ck(ck_mount, segments=[CkSegment(frame_id=frame_id, sclk_id=sc, epochs=span,
                                           rotations=np.repeat(np.eye(3)[None], 2, axis=0),
                                           angular_velocities=np.zeros((2, 3)), interval_starts=[span[0]],
                                           reference=mission.spacecraft_frame)], comments=comments)
    return [spk, ck_sc, ck_mount]


def _perturb(observations: list[Observation], *, errors: KnowledgeErrors, rng: np.random.Generator,
             seed: int) -> tuple[list[Observation], np.ndarray, tuple[dict, list[dict]]]:
    """Navigation knowledge: the true poses with `errors`, the camera's misalignment among them
    (rad, a rotation vector in the camera frame), and what the truth manifest records of them
    (the summary, and an entry per observation).

    Independent errors come from the simulation's stream, as they always did. Navigation-like
    ones come from their own stream, and the simulation's stream makes the draws of independent
    errors all the same, so that the images of a seed are the same whatever the errors."""
    def arrays(obs: list[Observation]) -> dict[str, Any]:
        return {"times": np.array([o.et for o in obs]), "positions_km": np.array([o.position for o in obs]),
                "rotations": np.array([o.rotation for o in obs])}

    if isinstance(errors, IndependentErrors):
        drawn = perturb(errors, rng=rng, **arrays(observations))
    else:
        perturb(EXACT, rng=rng, **arrays(observations))
        drawn = perturb(errors, rng=np.random.default_rng([seed, KNOWLEDGE_STREAM]), **arrays(observations))
    noisy = [Observation(obs.name, obs.et, drawn.positions_km[k], drawn.rotations[k], obs.emission_deg,
                         obs.azimuth_deg, obs.target_incidence_deg) for k, obs in enumerate(observations)]
    return noisy, drawn.misalignment_rad, manifest_entries(errors, drawn, [obs.name for obs in observations])


def _geometry(et: float, scenario: Scenario) -> tuple[Pose, np.ndarray]:
    pose = camera_pose(et=et, instrument_id=scenario.instrument_id, target=scenario.target,
                       body_frame=scenario.body_frame)
    return pose, sun_direction(et=et, target=scenario.target, body_frame=scenario.body_frame)


def _write_product(directory: Path, *, obs: Observation, view: np.ndarray, scenario: Scenario, seed: int,
                   mission: Mission, window: tuple[int, int] | None, rng: np.random.Generator) -> dict:
    expected_max = max(float(np.percentile(view[view > 0], 99.9)) if (view > 0).any() else 0.05, 1e-4)
    exposure = choose_exposure(expected_max, full_well_dn=scenario.full_well_dn, fill=scenario.exposure_fill,
                               error=scenario.exposure_error, rng=rng)
    dn = to_dn(view, exposure, full_well_dn=scenario.full_well_dn, gain_e_per_dn=scenario.gain_e_per_dn,
               read_noise_dn=scenario.read_noise_dn, rng=rng)
    utc = sp.et2utc(obs.et - EXPOSURE_S / 2, "ISOC", 3) + "Z"
    stop = sp.et2utc(obs.et + EXPOSURE_S / 2, "ISOC", 3) + "Z"
    basename = f"pwm_{scenario.name}_{obs.name}"
    directory.mkdir(parents=True, exist_ok=True)
    label, data = write_image_product(
        directory=directory, basename=basename, dn=dn, scaling_factor=exposure.scaling, value_offset=0.0,
        # The scenario and seed in the bundle's name: simulations that differ in either are different products,
        # so that their downlinks can be ingested into one catalog side by side.
        lid=f"urn:nasa:pds:pwm_sim_{scenario.name.replace('-', '_')}_s{seed}:{basename}", start_utc=utc, stop_utc=stop,
        mission=mission.name, host_name=mission.host,
        instrument_name=mission.instrument_label or instrument_frame(scenario.instrument_id),
        target_name=mission.target_label, title=f"Simulated {scenario.name} image {obs.name}", exposure_s=EXPOSURE_S,
        subframe=window,
    )
    return {"name": obs.name, "label": f"images/{label.name}", "data": f"images/{data.name}", "start_utc": utc,
            "et": obs.et, "scaling": exposure.scaling, "true_gain": exposure.true_gain}


def _true_geometry(obs: Observation, *, pose: Pose, sun: np.ndarray, truth: Truth, camera: Camera) -> dict:
    """The geometry the proving ground knows: true pose, Sun, the sub-spacecraft point and phase
    angle at the body centre, and angles at the site centre."""
    frame = truth.site_frame
    incidence, sun_az = local_sun(sun, frame)
    to_cam = pose.position - frame.origin
    rng_km = float(np.linalg.norm(to_cam))
    emission = float(np.degrees(np.arccos(np.clip(to_cam @ frame.normal / rng_km, -1, 1))))
    phase = float(np.degrees(np.arccos(np.clip(to_cam @ sun / rng_km, -1, 1))))
    lat, lon = unit_to_latlon(pose.position)
    body_phase = np.degrees(np.arccos(np.clip(pose.position @ sun / np.linalg.norm(pose.position), -1, 1)))
    return {"position_km": pose.position.tolist(), "rotation": pose.rotation.tolist(), "sun_direction": sun.tolist(),
            "sub_spacecraft_lat_deg": float(lat), "sub_spacecraft_lon_deg": float(lon),
            "phase_deg": float(body_phase),
            "site_incidence_deg": float(incidence), "site_sun_azimuth_deg": float(sun_az),
            "site_emission_deg": emission,
            "site_phase_deg": phase, "site_range_km": rng_km, "site_gsd_m": rng_km / camera.fx * 1e3}


def _in_site(points: np.ndarray, truth: Truth) -> np.ndarray:
    """Pixels whose surface point lies in the evaluation disc (False off the body)."""
    flat = points.reshape(-1, 3)
    ok = np.isfinite(flat[:, 0])
    inside = np.zeros(len(flat), dtype=bool)
    local = truth.site_frame.to_local(flat[ok])
    inside[ok] = np.hypot(local[:, 0], local[:, 1]) <= truth.eval_radius_km
    return inside.reshape(points.shape[:2])


def _write_downlink_manifest(downlink: Path, *, scenario: Scenario) -> None:
    """List every file with its checksum; written last, so its presence marks the downlink complete."""
    files = sorted(p for p in downlink.rglob("*") if p.is_file())
    entries = [{"path": p.relative_to(downlink).as_posix(), "bytes": p.stat().st_size,
                "sha256": file_sha256(p)} for p in files]
    (downlink / "manifest.json").write_text(json.dumps({"scenario": scenario.name, "files": entries}, indent=1))
