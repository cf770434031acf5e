"""SIFT features and guided matching with pycolmap on the CPU.

Matching is guided by the navigation poses: candidates must lie within a tolerance of the
epipolar line the SPICE poses predict, which keeps a repetitive boulder field from matching
the wrong rock. Pixel coordinates returned here follow pwm's convention (pixel centres at
integer coordinates); COLMAP puts them at +0.5, which is converted at this boundary.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import pycolmap

from pwm.camera import Camera, Pose
from pwm.spg.config import SPG_DEFAULTS, SpgConfig

COLMAP_OFFSET = 0.5  # COLMAP's pixel centres sit at +0.5

# COLMAP logs a line at INFO for every matcher it creates (one per image pair): its warnings and
# errors still reach stderr, pwm's own log says what the matching did
pycolmap.logging.minloglevel = max(pycolmap.logging.minloglevel, int(pycolmap.logging.Level.WARNING))


@dataclass
class Features:
    """SIFT keypoints of one image: xy (n, 2) as (sample, line) px; the pycolmap keypoints and
    descriptors are kept for the matcher."""

    xy: np.ndarray
    keypoints: pycolmap.FeatureKeypoints
    descriptors: pycolmap.FeatureDescriptors


def normalise(image: np.ndarray) -> np.ndarray:
    """An image as float32 in [0, 1]: a 0.5-99.5 percentile stretch, missing pixels black."""
    finite = np.isfinite(image)
    if not finite.any():
        return np.zeros(image.shape, np.float32)
    lo, hi = np.percentile(image[finite], [0.5, 99.5])
    out = np.clip((np.where(finite, image, lo) - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return np.ascontiguousarray(out, dtype=np.float32)


def extract(images: list[np.ndarray], *, first_octave: int | Sequence[int],
            windows: Sequence[tuple[slice, slice]] | None = None, config: SpgConfig = SPG_DEFAULTS) -> list[Features]:
    """SIFT features of each image (reflectance-like values, NaN where missing), in full-frame
    pixels, at most `config.max_features` each. first_octave (one, or one per image) -1 doubles
    the image first: more, finer features at about three times the cost per pixel. windows: per
    image the (lines, samples) slices to search, e.g. where the target is, so that a small target
    can be doubled cheaply."""
    octaves = [first_octave] * len(images) if isinstance(first_octave, int) else list(first_octave)
    boxes = windows or [(slice(None), slice(None))] * len(images)

    def one(k: int) -> Features:
        options = pycolmap.FeatureExtractionOptions()
        options.num_threads = 1
        options.sift.max_num_features = config.max_features
        options.sift.first_octave = octaves[k]
        options.sift.peak_threshold = config.peak_threshold
        lines, samples = boxes[k]
        extractor = pycolmap.FeatureExtractor.create(options, device=pycolmap.Device.cpu)
        keypoints, descriptors = extractor.extract_from_float32_array(normalise(images[k][lines, samples]))
        rows = pycolmap.keypoints_to_matrix(keypoints)
        if lines.start or samples.start:
            rows[:, :2] += [samples.start or 0, lines.start or 0]
            keypoints = pycolmap.keypoints_from_matrix(rows)
        return Features(xy=rows[:, :2].astype(float) - COLMAP_OFFSET, keypoints=keypoints, descriptors=descriptors)

    with ThreadPoolExecutor(max_workers=config.threads) as pool:
        return list(pool.map(one, range(len(images))))


def fundamental(camera_a: Camera, pose_a: Pose, camera_b: Camera, pose_b: Pose) -> np.ndarray:
    """Fundamental matrix (x_b^T F x_a = 0) in COLMAP pixel coordinates from two known poses."""
    rotation = pose_b.rotation @ pose_a.rotation.T
    t = pose_b.rotation @ (pose_a.position - pose_b.position)
    cross = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return np.linalg.inv(_intrinsics(camera_b)).T @ cross @ rotation @ np.linalg.inv(_intrinsics(camera_a))


def _intrinsics(camera: Camera) -> np.ndarray:
    return np.array([[camera.fx, 0.0, camera.cx + COLMAP_OFFSET], [0.0, camera.fy, camera.cy + COLMAP_OFFSET],
                     [0.0, 0.0, 1.0]])


def _colmap_camera(camera: Camera) -> pycolmap.Camera:
    return pycolmap.Camera(model="PINHOLE", width=camera.width, height=camera.height,
                           params=[camera.fx, camera.fy, camera.cx + COLMAP_OFFSET, camera.cy + COLMAP_OFFSET])


def match_guided(a: Features, b: Features, *, camera_a: Camera, pose_a: Pose, camera_b: Camera, pose_b: Pose,
                 max_error_px: float, config: SpgConfig = SPG_DEFAULTS) -> np.ndarray:
    """Matches (k, 2) of keypoint indices (a, b): mutual nearest descriptors passing the ratio
    test (`config.max_ratio`) among the candidates within `max_error_px` (Sampson distance) of the epipolar geometry
    that the poses predict."""
    if len(a.xy) == 0 or len(b.xy) == 0:
        return np.zeros((0, 2), np.int64)
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = config.threads
    options.sift.max_ratio = config.max_ratio
    matcher = pycolmap.FeatureMatcher.create(options, device=pycolmap.Device.cpu)
    geometry = pycolmap.TwoViewGeometry()
    geometry.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
    geometry.F = fundamental(camera_a, pose_a, camera_b, pose_b)
    matcher.match_guided(max_error_px, a.keypoints, a.descriptors, _colmap_camera(camera_a),
                         b.keypoints, b.descriptors, _colmap_camera(camera_b), geometry)
    return np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
