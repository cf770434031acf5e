"""A body's visual hull from its outlines against space: the first shape of a body no model
describes yet, whatever that shape is (a contact binary's lobes and neck, an elongated body's
ends), which the PCK ellipsoid cannot be.

What an image says for certain is where the body is not: the pixels that show space. A pixel
is taken for space only when it is dark, is not within a margin of a lit pixel (blur, the pose's
uncertainty, a lattice cell's size), and has no lit pixel on its sunward side in the image: a
dark pixel of the body, on its night side or in a shadow, sees a point whose ray to the Sun
leaves the body at a lit point, and that point projects on the line from the pixel towards the
Sun's image (the vanishing point of the Sun's direction). Every lattice point that some image
sees in space is carved away, coarse to fine; what remains holds the body, and its boundary is
the hull: exact along the outlines, too full in the concavities no outline shows (the neck seen
end-on, craters), which the stereo points and the maplets then bring in.

Pure arrays: views in, a mesh out (km, body-fixed).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage
from skimage.measure import marching_cubes

from pwm.camera import Camera, Pose
from pwm.decimate import decimate
from pwm.evaluate.distance import ClosestPoint
from pwm.mesh import Mesh, compact, largest_piece
from pwm.spg.config import HullConfig
from pwm.views import View

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Hull:
    """The visual hull as a mesh (km, body-fixed), whether it is closed (watertight, wound
    outwards), its volume (km^3), the lattice step it was carved at (km) and the views that
    carved something."""

    mesh: Mesh
    closed: bool
    volume_km3: float
    cell_km: float
    carving_views: int


class Outline:
    """What one image says of where the body is not (see the module's docstring): its lit
    pixels' distance map and the dark pixels that may be the body's night side or shadows."""

    def __init__(self, view: View, *, config: HullConfig) -> None:
        image = view.image
        self.finite = np.isfinite(image)
        lit = np.zeros(image.shape, dtype=bool)
        if self.finite.any():
            background, bright = np.percentile(image[self.finite],
                                               [config.background_percentile, config.bright_percentile])
            lit = self.finite & (image > background + config.lit_fraction * (bright - background))
        self.any_lit = bool(lit.any())
        # distance (px) from each pixel to the nearest lit one
        self.to_lit = ndimage.distance_transform_edt(~lit) if self.any_lit else np.full(image.shape, np.inf)
        self.behind = (_behind_lit(lit, camera=view.camera, pose=view.pose, sun=view.sun) if self.any_lit
                       else np.ones(image.shape, dtype=bool))

    def space(self, margin_px: float) -> np.ndarray:
        """(height, width) mask of the pixels that surely show space: dark, more than
        `margin_px` from a lit pixel, and with no lit pixel between them and the Sun's image."""
        return self.finite & (self.to_lit > margin_px) & ~self.behind


def _behind_lit(lit: np.ndarray, *, camera: Camera, pose: Pose, sun: np.ndarray) -> np.ndarray:
    """Pixels with a lit pixel on the image line from them towards the Sun's image: a 3D ray
    from a point towards the Sun projects on the line through the point's pixel and the Sun's
    vanishing point, towards it when the Sun is ahead of the camera, away when behind. Pixels
    are grouped by that line (its angle about the vanishing point, in bins of about a pixel) and
    ordered along it from the sunward end."""
    height, width = lit.shape
    s = pose.rotation @ (np.asarray(sun, float) / np.linalg.norm(sun))  # camera frame
    lines, samples = np.mgrid[0:height, 0:width]
    x, y = samples.ravel().astype(float), lines.ravel().astype(float)
    sxy = np.array([s[0] * camera.fx, s[1] * camera.fy])
    if np.linalg.norm(sxy) == 0.0:  # the Sun on the boresight: no shadow is in view
        return np.zeros(lit.shape, dtype=bool)
    reach = float(np.hypot(width, height))
    if abs(s[2]) * reach < 1e-6 * np.linalg.norm(sxy):
        # the Sun square to the boresight: parallel lines along its direction in the image
        d = sxy / np.linalg.norm(sxy)
        line = np.round(x * d[1] - y * d[0])
        along = -(x * d[0] + y * d[1])
    else:
        vx, vy = camera.cx + sxy[0] / s[2], camera.cy + sxy[1] / s[2]
        r = np.hypot(x - vx, y - vy)
        scale = max(float(np.hypot(max(abs(vx), abs(vx - width)), max(abs(vy), abs(vy - height)))), 1.0)
        line = np.round(np.arctan2(y - vy, x - vx) * scale)
        along = r if s[2] > 0 else -r  # sunward first: towards the vanishing point, or away from it
    order = np.lexsort((along, line))
    lit_sorted = lit.ravel()[order].astype(np.int64)
    counts = np.cumsum(lit_sorted)
    new_line = np.r_[True, line[order][1:] != line[order][:-1]]
    starts, group = np.flatnonzero(new_line), np.cumsum(new_line) - 1
    before = counts - lit_sorted - (counts[starts] - lit_sorted[starts])[group]
    behind = np.zeros(lit.size, dtype=bool)
    behind[order] = before > 0
    # the lines are binned at about a pixel: a lit pixel on the neighbouring line counts too
    return np.asarray(ndimage.binary_dilation(behind.reshape(lit.shape), iterations=1))


def visual_hull(views: list[View], *, bound_km: float, config: HullConfig) -> Hull | None:
    """The visual hull of the body the `views` see, carved in the cube of half-side `bound_km`
    about the body's origin, from config.coarse_cells a side down to the lattice step of
    config.cell_gsd times the views' finest ground sample (at most config.max_cells a side).
    None when no view carves anything, or nothing is left."""
    clock = time.perf_counter()
    ranges = np.array([np.linalg.norm(v.pose.position) for v in views])
    pixel_km = ranges / np.array([v.camera.fx for v in views])
    finest = max(config.cell_gsd * float(pixel_km.min()), 2.0 * bound_km / config.max_cells)
    cells = config.coarse_cells
    while 2.0 * bound_km / cells > finest * 1.5:
        cells *= 2
    outlines = [Outline(v, config=config) for v in views]
    if not any(o.any_lit for o in outlines):
        return None  # a view with nothing lit shows no pixel surely space: none would carve
    alive = np.ones((config.coarse_cells,) * 3, dtype=bool)
    carving = np.zeros(len(views), dtype=bool)
    level = config.coarse_cells
    while True:
        # a cell is carved by its centre's pixel: the margin covers the rest of the cell
        half_diagonal_px = 0.5 * np.sqrt(3.0) * (2.0 * bound_km / level) / pixel_km
        seen = np.zeros(alive.shape, dtype=np.int32)
        for k, (view, outline) in enumerate(zip(views, outlines, strict=True)):
            index = np.flatnonzero(alive)
            if not len(index):
                break
            space = outline.space(config.margin_px + 3.0 * view.los_sigma_px + half_diagonal_px[k])
            carved, inside = _carved(index, level=level, bound_km=bound_km, camera=view.camera, pose=view.pose,
                                     space=space)
            carving[k] |= bool(carved.any())
            alive.ravel()[index[carved]] = False
            seen.ravel()[index[inside]] += 1
        # what too few views had in frame is not known to be the body
        alive &= seen >= config.min_views
        if level >= cells or not alive.any():
            break
        alive = alive.repeat(2, axis=0).repeat(2, axis=1).repeat(2, axis=2)
        level *= 2
    cell_km = 2.0 * bound_km / level
    if not carving.any() or not alive.any():
        return None
    mesh = _surface(alive, cell_km=cell_km, bound_km=bound_km)
    surface = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    volume = float(surface.volume)
    log.info("visual hull: %d cells of %.2f m a side, %.4g km^3, %d of %d views carving (%.1f s)", level,
             cell_km * 1e3, volume, int(carving.sum()), len(views), time.perf_counter() - clock)
    return Hull(mesh=mesh, closed=bool(surface.is_watertight) and volume > 0, volume_km3=volume, cell_km=cell_km,
                carving_views=int(carving.sum()))


def _carved(index: np.ndarray, *, level: int, bound_km: float, camera: Camera, pose: Pose,
            space: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which of the lattice cells `index` (flat, of a level**3 cube) the view sees in space, and
    which it has in its frame."""
    out = np.zeros(len(index), dtype=bool)
    framed = np.zeros(len(index), dtype=bool)
    for start in range(0, len(index), _CHUNK):
        part = index[start : start + _CHUNK]
        ijk = np.stack(np.unravel_index(part, (level,) * 3), axis=1)
        centres = -bound_km + (ijk + 0.5) * (2.0 * bound_km / level)
        cam = pose.to_camera(centres)
        ahead = cam[:, 2] > 0
        px = np.round(camera.project_camera(np.where(ahead[:, None], cam, 1.0))).astype(np.int64)
        inside = ahead & (px[:, 0] >= 0) & (px[:, 0] < camera.width) & (px[:, 1] >= 0) & (px[:, 1] < camera.height)
        hit = np.zeros(len(part), dtype=bool)
        hit[inside] = space[px[inside, 1], px[inside, 0]]
        out[start : start + len(part)] = hit
        framed[start : start + len(part)] = inside
    return out, framed


_CHUNK = 1 << 21


def _surface(alive: np.ndarray, *, cell_km: float, bound_km: float) -> Mesh:
    """The boundary of the kept cells as a closed mesh (km): marching cubes at half occupancy
    over the occupancy smoothed by a cell, the largest piece kept, decimated to edges of about
    two cells."""
    occupancy = np.pad(alive.astype(np.float32), 2)
    smooth = ndimage.gaussian_filter(occupancy, sigma=1.0)
    vertices, faces, _, _ = marching_cubes(smooth, level=0.5, spacing=(cell_km,) * 3,
                                           gradient_direction="ascent", allow_degenerate=False)
    vertices = vertices - bound_km - 1.5 * cell_km  # lattice index i sits at -bound + (i - 2 + 0.5) cells
    used, faces = compact(len(vertices), faces[largest_piece(len(vertices), faces)])
    mesh = Mesh(vertices[used], faces.astype(np.int64))
    # marching cubes leaves edges of under a cell; the outlines place nothing finer than two
    target = int(mesh.face_areas().sum() / (np.sqrt(3.0) / 4.0 * (2.0 * cell_km) ** 2))
    return decimate(mesh, target) if 4 <= target < len(mesh.faces) else mesh


def clip_to(surface: Mesh, hull: Mesh) -> Mesh:
    """`surface` with each vertex outside `hull` moved onto it: the body lies within its hull,
    so a surface poking out of it is wrong there by at least that much."""
    inside = ClosestPoint(hull)
    outside = inside.signed_distance(surface.vertices) > 0
    vertices = surface.vertices.copy()
    vertices[outside] = inside.query(surface.vertices[outside])[1]
    return Mesh(vertices, surface.faces, surface.albedo)
