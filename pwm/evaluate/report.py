"""Measure a model against the proving ground's truth, as the OSIRIS-REx SPC tests did.

ICP registration (point-to-plane) of the model's vertices in the evaluation region, then the
distance of each to the truth surface; images rendered from the model with its albedo against
the held-out truth views; boulder heights along the site frame's z; the height error by
wavelength band (pwm.evaluate.bands) and by where it lies (pwm.evaluate.classes); PNG maps and
profiles.
This module reads the truth directory and writes plots: it is the evaluation's I/O edge.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from pwm.camera import Camera, Pose
from pwm.evaluate import plots
from pwm.evaluate.bands import BOUNDARIES_GSD, band_rms
from pwm.evaluate.classes import (
    EDGE_BAND_GSD,
    SHADOW_SHARE,
    WALL_SLOPE_DEG,
    MapletFootprint,
    boulder_size_masks,
    edge_mask,
    error_by_class,
    on_boulders,
    rim_mask,
    shadow_share,
)
from pwm.evaluate.completeness import COMPLETENESS_GSD, truth_gaps
from pwm.evaluate.distance import ClosestPoint
from pwm.evaluate.icp import RigidTransform, register
from pwm.evaluate.images import ncc, ssim
from pwm.evaluate.profiles import boulder_height_ratio
from pwm.frames import LocalFrame
from pwm.io.meshio import read_mesh
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.render import render_supersampled
from pwm.sampling import drop_rays
from pwm.simulate.terrain import Boulder
from pwm.simulate.truth import Truth, load as load_truth, sampled
from pwm.site import slope_deg

log = logging.getLogger(__name__)

ICP_POINTS = 20_000
"""Vertices used for registration (a random sample); distances use all of them."""
ICP_TOLERANCE_GSD = 1e-3
"""ICP stops once a step moves no point by more than this fraction of the GSD."""
ICP_REACH_GSD = 20.0
"""Point pairs farther apart than this many GSD are left out of the ICP steps."""


SCOPES = ("site", "global")
BOULDERS_JUDGED = 10
"""A global model is judged on this many of the body's highest boulders."""
LARGEST_BOULDERS = 4
"""A site model is judged on the height of this many of the site's largest boulders too."""
TAIL_GSD = 3.0
"""Vertices farther than this many GSD from the truth are the tail whose share of the squared
error the report gives (3% of an independent site's vertices carried 63% of it, issue 49)."""


def evaluate(model_path: str | Path, *, truth_dir: str | Path, plots_dir: str | Path | None = None,
             maplets: list[MapletFootprint] | None = None, scope: str | None = None) -> dict:
    """Figures of merit of the model at `model_path` against the truth in `truth_dir`; with the
    maplets the model was made of, the error at their edges too.

    scope: "site" (the site disc of a site downlink's truth) or "global" (the whole body, against
    a survey's truth: coverage, held-out views over the whole disc, the highest boulders); by
    default the one the truth's downlink was made for."""
    truth_dir = Path(truth_dir)
    truth = load_truth(truth_dir)
    manifest = json.loads((truth_dir / "manifest.json").read_text())
    gsd_km = manifest["scenario"]["gsd_km"]
    survey = bool(manifest["scenario"]["global_views"])
    scope = scope or ("global" if survey else "site")
    if scope not in SCOPES:
        raise ValueError(f"unknown scope {scope!r}; choose one of {', '.join(SCOPES)}")
    if (scope == "global") != survey:
        raise ValueError(f"{truth_dir} is the truth of a {'survey' if survey else 'site'} downlink "
                         f"({manifest['scenario']['name']}); scope {scope!r} needs "
                         f"{'a site' if survey else 'a survey'} downlink's truth")
    whole_body = scope == "global"
    model = read_mesh(model_path)

    region = np.ones(len(model.vertices), bool) if whole_body else in_site(model.vertices, truth)
    if region.sum() < 10:
        raise ValueError(f"{model_path}: only {region.sum()} vertices inside the evaluation region")
    transform, surface = register_to_truth(model, truth, region=region, gsd_km=gsd_km, whole_body=whole_body)
    registered = Mesh(transform.apply(model.vertices), model.faces, model.albedo)
    points = model.vertices[region]
    distance, _, _ = surface.query(registered.vertices[region])
    moved = np.linalg.norm(registered.vertices[region] - points, axis=1)

    result = {
        "model": str(model_path),
        "scope": scope,
        "gsd_m": gsd_km * 1e3,
        "region": "whole body" if whole_body else f"site disc of radius {truth.eval_radius_km * 1e3:g} m",
        "vertices_evaluated": int(region.sum()),
        # the shift of the evaluated vertices, not the translation about the body centre
        "icp": {"rotation_rad": float(np.linalg.norm(_rotvec(transform.rotation))),
                "shift_m": float(np.mean(moved) * 1e3)},
        "rms_m": float(np.sqrt(np.mean(distance**2)) * 1e3),
        "median_m": float(np.median(distance) * 1e3),
    }
    result["rms_gsd"] = result["rms_m"] / result["gsd_m"]
    result["median_gsd"] = result["median_m"] / result["gsd_m"]
    result["tail"] = _tail(distance, threshold_km=TAIL_GSD * gsd_km)
    if model.sigma is not None:
        result["sigma"] = calibration(distance, model.sigma[region])

    plots_dir = Path(plots_dir) if plots_dir is not None else None
    if plots_dir is not None:
        plots_dir.mkdir(parents=True, exist_ok=True)
    tracer = RayTracer(registered)
    if whole_body:
        result.update(_whole_body(truth, registered, tracer, vertex_error_km=distance, gsd_km=gsd_km,
                                  plots_dir=plots_dir))
    else:
        suns = np.array([image["sun_direction"] for image in manifest["images"]], float)
        result.update(_heights(truth, tracer, gsd_km=gsd_km, plots_dir=plots_dir, suns_body=suns,
                               maplets=maplets))
    if model.albedo is not None:
        result.update(_views(manifest, truth_dir, tracer, plots_dir=plots_dir, whole_body=whole_body))
    return result


def calibration(distance_km: np.ndarray, sigma_km: np.ndarray) -> dict:
    """How well a model's 1-sigma heights tell its error: of the vertices with a sigma, the share
    within one and two sigma of the truth (0.68 and 0.95 for a Gaussian error told exactly), the
    median sigma (m), and the share of the vertices that have one."""
    told = np.isfinite(sigma_km)
    if not told.any():
        return {"vertex_share": 0.0}
    ratio = distance_km[told] / np.maximum(sigma_km[told], 1e-300)
    return {"vertex_share": float(np.mean(told)), "within_1": float(np.mean(ratio <= 1.0)),
            "within_2": float(np.mean(ratio <= 2.0)), "median_m": float(np.median(sigma_km[told]) * 1e3)}


def _tail(distance_km: np.ndarray, *, threshold_km: float) -> dict:
    """The vertices farther than threshold_km from the truth: their share of the vertices and of
    the squared error, and the RMS (m) of the others."""
    tail = distance_km > threshold_km
    squared = distance_km**2
    return {"threshold_gsd": TAIL_GSD, "vertex_share": float(np.mean(tail)),
            "squared_error_share": float(squared[tail].sum() / max(float(squared.sum()), 1e-300)),
            "rms_without_m": float(np.sqrt(np.mean(squared[~tail])) * 1e3) if (~tail).any() else float("nan")}


def _whole_body(truth: Truth, model: Mesh, tracer: RayTracer, *, vertex_error_km: np.ndarray, gsd_km: float,
                plots_dir: Path | None) -> dict:
    """Coverage (holes and missing parts, which distances from the model cannot see) and the
    highest boulders' heights; maps of both errors over latitude and longitude."""
    tolerance_km = COMPLETENESS_GSD * gsd_km
    samples, gap = truth_gaps(truth.mesh, model)
    out: dict = {"completeness": float(np.mean(gap <= tolerance_km)), "completeness_tolerance_gsd": COMPLETENESS_GSD}
    boulders = sorted(((f, f.shape) for f in truth.landforms if isinstance(f.shape, Boulder)),
                      key=lambda pair: -pair[1].height_km)[:BOULDERS_JUDGED]
    if boulders:
        truth_tracer = RayTracer(truth.mesh)
        entries = [{"origin_km": list(form.origin_km), "diameter_m": shape.diameter_km * 1e3,
                    "height_m": shape.height_km * 1e3, "steep": shape.steep,
                    "height_ratio": _boulder_height_ratio(form.frame, shape, truth_tracer, tracer, gsd_km=gsd_km)}
                   for form, shape in boulders]
        ratios = np.array([e["height_ratio"] for e in entries], float)
        out["boulders"] = entries
        out["boulder_height_ratio_median"] = float(np.nanmedian(ratios))
        out["boulder_height_ratio_min"] = float(np.nanmin(ratios))
    if plots_dir is not None:
        plots.body_map(plots_dir / "vertex_error.png", model.vertices, vertex_error_km * 1e3,
                       title="model to truth distance (m)", label="m")
        plots.coverage_map(plots_dir / "coverage.png", samples, gap * 1e3, tolerance_m=tolerance_km * 1e3)
    return out


def _boulder_height_ratio(frame: LocalFrame, boulder: Boulder, truth: RayTracer, model: RayTracer, *,
                          gsd_km: float) -> float:
    """Model relief over truth relief of a boulder centred on its frame, both measured the same
    way (profiles.boulder_height_ratio) on a grid of that frame at half a GSD or finer."""
    diameter = boulder.diameter_km
    step = min(0.5 * gsd_km, diameter / 20)
    axis = np.arange(-1.5 * diameter, 1.5 * diameter + step / 2, step)
    top = boulder.height_km + diameter
    truth_h = heights_in_frame(truth, frame, axis, axis, top_km=top, nudge_km=1e-3 * step)
    model_h = heights_in_frame(model, frame, axis, axis, top_km=top, nudge_km=1e-3 * step)
    return float(boulder_height_ratio(axis, axis, truth_h, model_h, centres_km=np.zeros((1, 2)),
                                      diameters_km=np.array([diameter]), curved=True)[0])


def maplet_footprints(report: dict) -> list[MapletFootprint]:
    """The maplets' squares from a `pwm refine` report (maplets.json): each entry's origin_km,
    rotation and half_km."""
    return [MapletFootprint(frame=LocalFrame(origin=np.asarray(m["origin_km"], float),
                                             rotation=np.asarray(m["rotation"], float)),
                            half_km=float(m["half_km"])) for m in report["maplets"]]


def in_site(points_body: np.ndarray, truth: Truth) -> np.ndarray:
    """True for points inside the evaluation disc of the site (measured in the site frame's x-y) on
    the site's side of the body: within the disc's radius of its plane, not on the far side."""
    local = truth.site_frame.to_local(points_body)
    return (np.hypot(local[:, 0], local[:, 1]) <= truth.eval_radius_km) & (np.abs(local[:, 2]) <= truth.eval_radius_km)


def near_site(truth: Truth, *, margin_km: float) -> Mesh:
    """The truth faces with a vertex within margin_km (km) of the evaluation disc's cylinder,
    height included: the only ones that can be closest to a model vertex in the disc that lies
    within margin_km of the truth (the full site truth has tens of millions of faces)."""
    local = truth.site_frame.to_local(truth.mesh.vertices)
    reach = truth.eval_radius_km + margin_km
    near = (np.hypot(local[:, 0], local[:, 1]) <= reach) & (np.abs(local[:, 2]) <= reach)
    return Mesh(truth.mesh.vertices, truth.mesh.faces[near[truth.mesh.faces].any(axis=1)])


def register_to_truth(model: Mesh, truth: Truth, *, region: np.ndarray, gsd_km: float,
                      whole_body: bool) -> tuple[RigidTransform, ClosestPoint]:
    """ICP of ICP_POINTS of the model's vertices in `region` onto the truth (the whole body, or
    the faces near the site), pairs within ICP_REACH_GSD; the transform and the truth surface.

    The whole body is registered on the truth's base, without the site patch: a point tens of
    metres off a patch of decimetre facets has hundreds of thousands of vertices within its
    reach, and a patch a tenth of the body across places nothing the base does not."""
    reach_km = ICP_REACH_GSD * gsd_km
    surface = ClosestPoint(truth.mesh if whole_body else near_site(truth, margin_km=2 * reach_km))
    points = model.vertices[region]
    if whole_body:  # nor the model's points over the patch, which would pair with the hole's rim
        local = truth.site_frame.to_local(points)
        half = max(float(np.abs(truth.x_km).max()), float(np.abs(truth.y_km).max())) + reach_km
        points = points[~((np.abs(local[:, :2]) <= half).all(axis=1) & (np.abs(local[:, 2]) <= half))]
    sample = points[np.random.default_rng(0).permutation(len(points))[:ICP_POINTS]]
    registration = ClosestPoint(truth.base_mesh()) if whole_body else surface
    return register(sample, registration, max_distance_km=reach_km,
                    tolerance_km=ICP_TOLERANCE_GSD * gsd_km), surface


def site_heights(tracer: RayTracer, truth: Truth, x_km: np.ndarray, y_km: np.ndarray) -> np.ndarray:
    """Heights (km) of the tracer's surface along the site frame's z at grid nodes, nan where missed.

    Rays come down from above the highest truth relief (heights_in_frame), passing a thousandth
    of a truth grid step beside the nodes.
    """
    return heights_in_frame(tracer, truth.site_frame, x_km, y_km, top_km=float(np.nanmax(truth.height_km)) + 0.05,
                            nudge_km=1e-3 * truth.resolution_km)


def heights_in_frame(tracer: RayTracer, frame: LocalFrame, x_km: np.ndarray, y_km: np.ndarray, *, top_km: float,
                     nudge_km: float) -> np.ndarray:
    """Heights (km) along the frame's z of the tracer's surface at the grid nodes (len(y), len(x)),
    nan where missed. Rays come down the -z axis from top_km, so the first hit is the top; they
    pass nudge_km beside the nodes, because a mesh with vertices exactly on the nodes (a truth
    grid) would otherwise put rays on edges, where single precision lets some slip through."""
    gx, gy = np.meshgrid(np.asarray(x_km) + 1.3 * nudge_km, np.asarray(y_km) + 0.7 * nudge_km)
    return drop_rays(tracer, frame, gx.ravel(), gy.ravel(), top_km=top_km)[1].reshape(gx.shape)


def _heights(truth: Truth, tracer: RayTracer, *, gsd_km: float, plots_dir: Path | None, suns_body: np.ndarray,
             maplets: list[MapletFootprint] | None) -> dict:
    """Boulder height ratios, the height-error map on the truth grid (thinned to GSD/2), and
    that error by wavelength band and by class."""
    stride = max(1, int(round(0.5 * gsd_km / truth.resolution_km)))
    spacing_km = stride * truth.resolution_km
    x, y = truth.x_km[::stride], truth.y_km[::stride]
    truth_h = truth.height_km[::stride, ::stride]
    model_h = site_heights(tracer, truth, x, y)
    inside = np.hypot(*np.meshgrid(x, y)) <= truth.eval_radius_km
    error = np.where(inside, model_h - truth_h, np.nan)
    boulders = [b for b in truth.boulders if np.hypot(b.x_km, b.y_km) + b.diameter_km < truth.eval_radius_km]
    out: dict = {"height_error_rms_m": float(np.sqrt(np.nanmean(error**2)) * 1e3),
                 "bands_rms_m": {name: rms * 1e3 for name, rms in band_rms(
                     error, spacing_km=spacing_km, boundaries_km=tuple(b * gsd_km for b in BOUNDARIES_GSD)).items()}}
    masks = _classes(truth, x, y, truth_h, spacing_km=spacing_km, gsd_km=gsd_km, suns_body=suns_body,
                     maplets=maplets)
    out["classes_m"] = _in_m(error_by_class(error, masks))
    if boulders:
        # off every boulder of the whole truth: those across the disc's edge too
        ground = ~on_boulders(x, y, truth.boulders)
        ratios = boulder_height_ratio(x, y, truth_h, model_h, centres_km=np.array([[b.x_km, b.y_km] for b in boulders]),
                                      diameters_km=np.array([b.diameter_km for b in boulders]), ground=ground)
        steep = np.array([b.steep for b in boulders])
        out["boulders"] = [{"x_m": b.x_km * 1e3, "y_m": b.y_km * 1e3, "diameter_m": b.diameter_km * 1e3,
                            "height_m": b.height_km * 1e3, "steep": b.steep, "height_ratio": float(r)}
                           for b, r in zip(boulders, ratios, strict=True)]
        out["boulder_height_ratio_median"] = float(np.nanmedian(ratios))
        out["steep_boulder_height_ratio_median"] = float(np.nanmedian(ratios[steep])) if steep.any() else None
        largest = np.argsort([-b.diameter_km for b in boulders], kind="stable")[:LARGEST_BOULDERS]
        out["largest_boulder_height_ratios"] = [float(ratios[k]) for k in largest]
        out["largest_boulder_height_ratio_min"] = float(np.nanmin(ratios[largest]))
        out["boulder_sizes_m"] = _in_m(error_by_class(error, boulder_size_masks(x, y, boulders)))
    if plots_dir is not None:
        plots.height_error_map(plots_dir / "height_error.png", x, y, error * 1e3, title="model - truth height (m)")
        plots.class_map(plots_dir / "error_classes.png", x, y, masks, error * 1e3,
                        title="where the error lies")
        if boulders:
            plots.profiles(plots_dir / "boulder_profiles.png",
                           [_profile(b, x, y, truth_h, model_h) for b in boulders[:6]])
    return out


def _in_m(figures_by_class: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """error_by_class's figures (km) in m, node counts as they are."""
    return {name: {k: v * 1e3 if k != "nodes" else v for k, v in figures.items()}
            for name, figures in figures_by_class.items()}


def _classes(truth: Truth, x: np.ndarray, y: np.ndarray, truth_h: np.ndarray, *, spacing_km: float, gsd_km: float,
             suns_body: np.ndarray, maplets: list[MapletFootprint] | None) -> dict[str, np.ndarray]:
    """The class masks on the evaluation grid: walls and rims from the truth, shadow from the
    images' Suns over the truth at the grid's resolution, maplet edges when the maplets are known."""
    frame = truth.site_frame
    gx, gy = np.meshgrid(x, y)
    points = frame.to_body(np.stack([gx, gy, truth_h], axis=-1).reshape(-1, 3)).reshape(gx.shape + (3,))
    dz_dy, dz_dx = np.gradient(truth_h, spacing_km)
    local_normals = np.stack([-dz_dx, -dz_dy, np.ones_like(truth_h)], axis=-1)
    local_normals /= np.linalg.norm(local_normals, axis=-1, keepdims=True)
    # shadows cast by the truth as the grid holds it, without the averaging of a coarser model
    coarse = RayTracer(sampled(truth, spacing_km=spacing_km, average_km=truth.resolution_km))
    masks = {"walls": slope_deg(truth_h * 1e3, spacing_m=spacing_km * 1e3) > WALL_SLOPE_DEG,
             "rims": rim_mask(x, y, truth.craters)}
    if maplets:
        masks["maplet edges"] = edge_mask(points, maplets, EDGE_BAND_GSD * gsd_km)
    masks["shadow"] = shadow_share(coarse, points, local_normals @ frame.rotation, suns_body) >= SHADOW_SHARE
    return masks


def _profile(boulder, x: np.ndarray, y: np.ndarray, truth_h: np.ndarray, model_h: np.ndarray) -> tuple:
    row = int(np.argmin(np.abs(y - boulder.y_km)))
    cols = np.abs(x - boulder.x_km) <= 1.5 * boulder.diameter_km
    label = f"{'steep ' if boulder.steep else ''}boulder {boulder.diameter_km * 1e3:.1f} m"
    return ((x[cols] - boulder.x_km) * 1e3, truth_h[row, cols] * 1e3, model_h[row, cols] * 1e3, label)


def _views(manifest: dict, truth_dir: Path, tracer: RayTracer, *, plots_dir: Path | None, whole_body: bool) -> dict:
    """NCC and SSIM of the model rendered with its albedo against each held-out truth view,
    over the pixels lit and seen in both (on the site, or anywhere on the body). The model is
    imaged as the view's camera imaged the truth, its pixels the mean of as many rays
    (the scenario's supersample): a model sampled one ray per pixel would be judged on aliasing
    the truth's view does not have. The model image is first scaled to the truth's brightness by
    least squares: a model's albedo is only known up to the images' calibration."""
    c = manifest["camera"]
    camera = Camera(width=c["width"], height=c["height"], fx=c["fx"], fy=c["fy"], cx=c["cx"], cy=c["cy"])
    rays = int(manifest["scenario"].get("supersample", 1))
    scores = []
    for view in manifest["validation"]:
        data = np.load(truth_dir / view["file"])
        pose = Pose(position=data["position"], rotation=data["rotation"])
        model = render_supersampled(tracer, camera=camera, pose=pose, sun_direction=data["sun"], factor=rays)
        truth_img = data["reflectance"].astype(float)
        seen = data["hit"] if whole_body else data["in_site"] & data["hit"]
        mask = seen & ~data["shadow"] & model.hit & ~model.shadow
        if mask.sum() < 100:
            log.warning("view %s: only %d comparable pixels; skipped", view["name"], mask.sum())
            continue
        m = model.reflectance
        scale = float(np.sum(truth_img[mask] * m[mask]) / max(np.sum(m[mask] ** 2), 1e-300))
        scores.append({"view": view["name"], "pixels": int(mask.sum()), "ncc": ncc(truth_img, m, mask),
                       "ssim": ssim(truth_img, scale * m, mask), "brightness_scale": scale})
        if plots_dir is not None:
            plots.image_comparison(plots_dir / f"view_{view['name']}.png", truth_img, scale * m, mask=mask,
                                   title=f"held-out view {view['name']}: truth | model | difference")
    if not scores:
        return {"views": []}
    return {"views": scores, "ncc": float(np.mean([s["ncc"] for s in scores])),
            "ssim": float(np.mean([s["ssim"] for s in scores]))}


def _rotvec(rotation: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rotation).as_rotvec()


def format_table(result: dict) -> str:
    """A plain-text table of the headline figures."""
    rows = [("model", result["model"]), ("region", result["region"]), ("vertices", str(result["vertices_evaluated"])),
            ("RMS", f"{result['rms_m']:.4f} m = {result['rms_gsd']:.3f} GSD"),
            ("median", f"{result['median_m']:.4f} m = {result['median_gsd']:.3f} GSD"),
            ("ICP", f"mean shift {result['icp']['shift_m']:.4f} m, rotation {result['icp']['rotation_rad']:.2e} rad")]
    if "completeness" in result:
        rows.append(("coverage", f"{result['completeness']:.3f} of the true surface within "
                                 f"{result['completeness_tolerance_gsd']:g} GSD of the model"))
    if "height_error_rms_m" in result:
        rows.append(("height-error RMS", f"{result['height_error_rms_m']:.4f} m"))
    if "ncc" in result:
        rows += [("NCC (held-out)", f"{result['ncc']:.4f}"), ("SSIM (held-out)", f"{result['ssim']:.4f}")]
    if result.get("boulder_height_ratio_median") is not None:
        rows.append(("boulder height ratio", f"{result['boulder_height_ratio_median']:.3f} (median)"))
    if result.get("boulder_height_ratio_min") is not None:
        rows.append((f"highest {len(result['boulders'])} boulders",
                     f"{result['boulder_height_ratio_min']:.3f} of their height (least)"))
    if result.get("steep_boulder_height_ratio_median") is not None:
        rows.append(("steep boulders", f"{result['steep_boulder_height_ratio_median']:.3f} (median)"))
    if result.get("largest_boulder_height_ratios"):
        rows.append((f"largest {len(result['largest_boulder_height_ratios'])} boulders",
                     " ".join(f"{r:.3f}" for r in result["largest_boulder_height_ratios"]) + " of their height"))
    if "tail" in result:
        tail = result["tail"]
        rows.append((f"beyond {tail['threshold_gsd']:g} GSD",
                     f"{tail['vertex_share']:.3f} of the vertices carry {tail['squared_error_share']:.3f} of the "
                     f"squared error; RMS without them {tail['rms_without_m']:.4f} m"))
    sigma = result.get("sigma")
    if sigma is not None and sigma["vertex_share"] > 0:
        rows.append(("height sigma", f"{sigma['within_1']:.3f} of the vertices within 1 sigma of the truth, "
                                     f"{sigma['within_2']:.3f} within 2; median sigma {sigma['median_m']:.4f} m over "
                                     f"{sigma['vertex_share']:.3f} of the vertices"))
    rows += [(f"band {name}", f"{rms:.4f} m") for name, rms in result.get("bands_rms_m", {}).items()]
    rows += [(f"{name}", f"RMS {c['rms']:.4f} m, p95 {c['p95']:.4f} m over {c['nodes']} nodes")
             for name, c in result.get("classes_m", {}).items()]
    rows += [(f"{name if name != 'elsewhere' else 'off boulders'}",
              f"RMS {c['rms']:.4f} m, p95 {c['p95']:.4f} m over {c['nodes']} nodes")
             for name, c in result.get("boulder_sizes_m", {}).items()]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
