"""Bundle adjustment with pose priors from the navigation knowledge.

Unknowns: every point (body-fixed, km) and the pose model's unknowns (pwm.spg.pose_models:
each image its own six, or a few per navigation arc and one shared misalignment), which give per
image a position correction and a rotation vector applied to the camera axes in the body-fixed
frame. Residuals: reprojection errors (px, Huber-weighted) and the priors theta ~ N(0, I).
Solved by Levenberg-Marquardt with the points eliminated (Schur complement), so the reduced
system has one unknown per pose-model unknown. Jacobian blocks are central differences per
observation: each observation depends on one point and one image's six corrections, which the
model's design maps to its unknowns.

Ties (pwm.spg.ties) hold points to planes another instrument measured, each residual its
point's distance from its plane in the plane's sigmas, weighed as the images' residuals are
(as if one pixel were their sigma, the convention of the priors) and Huber-damped alike. They
touch the points alone, so the Schur complement keeps its shape; the posterior then knows what
they fix (`Adjustment.information`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial.transform import Rotation

from pwm.camera import Camera, Pose
from pwm.spg.config import SPG_DEFAULTS, SpgConfig
from pwm.spg.pose_models import PoseModel, free_poses
from pwm.spg.ties import NO_TIES, SurfaceTies
from pwm.spg.triangulation import Tracks

STEP = np.array([1e-6] * 3 + [1e-7] * 3)
"""Central-difference steps of an image's corrections (km, rad)."""


@dataclass
class Adjustment:
    """Adjusted points (km, body-fixed); per image a position correction (km, body-fixed) and a
    rotation vector (rad, body-fixed; corrected rotation = rotation @ R(omega)^T); the
    observations' final reprojection errors (px), the ties' final distances from their planes,
    their frame's motion applied (km), and the iterations run; the pose model and its unknowns'
    values (sigma units), and the ties' frame motion (sigma units, `SurfaceTies.frame_motion`);
    the normal equations' data part at the solution, the images' (for 1 px errors) and the
    ties', whence `information`.
    """

    points: np.ndarray
    position_corrections: np.ndarray
    rotation_corrections: np.ndarray
    residuals_px: np.ndarray
    tie_distances_km: np.ndarray
    iterations: int
    model: PoseModel
    parameters: np.ndarray
    frame: np.ndarray
    images: _Normal
    ties: _TieNormal

    def information(self, noise_px: float) -> np.ndarray:
        """What the images and the ties say about the images' corrections: the normal matrix
        (6 n_img square; per image dx, dy, dz km, wx, wy, wz rad) with the points and the ties'
        frame (under its prior) eliminated and no priors of the corrections, for image
        measurements with `noise_px` (px, 1 sigma per axis)."""
        scale = 1.0 / noise_px**2
        k = len(self.frame)
        hpp = self.images.hpp * scale + self.ties.hpp + 1e-9 * np.eye(3)
        hcc = _block_diag(self.images.hcc).toarray() * scale
        if not k:
            return _schur(hcc, hpp, self.images.hpc * scale)[0]
        n = len(hcc)
        joint = _schur(np.block([[hcc, np.zeros((n, k))], [np.zeros((k, n)), self.ties.hdd]]), hpp,
                       sparse.hstack([self.images.hpc * scale, self.ties.hpd]).tocsr())[0]
        own, coupling = joint[:n, :n], joint[:n, n:]
        return own - coupling @ np.linalg.solve(joint[n:, n:] + np.eye(k), coupling.T)

    def parameter_covariance(self, noise_px: float) -> np.ndarray:
        """Posterior covariance of the model's unknowns (sigma units, prior I), for image
        measurements with `noise_px` (px, 1 sigma per axis)."""
        g = self.model.design
        reduced = np.asarray((g.T @ sparse.csr_matrix(self.information(noise_px)) @ g).todense())
        return np.linalg.inv(reduced + np.eye(g.shape[1]))

    def covariance(self, noise_px: float) -> np.ndarray:
        """Posterior covariance of the images' corrections (km, rad; 6 n_img square), priors
        included, for image measurements with `noise_px` (px, 1 sigma per axis)."""
        g = self.model.design
        return np.asarray(g @ (g @ self.parameter_covariance(noise_px)).T)


def _project(points: np.ndarray, position: np.ndarray, rotation: np.ndarray, cam: np.ndarray) -> np.ndarray:
    """Per observation: points (n, 3) km through poses (n, 3), (n, 3, 3) and intrinsics rows
    (fx, fy, cx, cy) to (sample, line)."""
    c = np.einsum("nij,nj->ni", rotation, points - position)
    return np.column_stack([cam[:, 0] * c[:, 0] / c[:, 2] + cam[:, 2], cam[:, 1] * c[:, 1] / c[:, 2] + cam[:, 3]])


def bundle_adjust(points: np.ndarray, tracks: Tracks, cameras: list[Camera], poses: list[Pose], *,
                  model: PoseModel | None = None, sigma_position_km: float | None = None,
                  sigma_pointing_rad: float | None = None, ties: SurfaceTies = NO_TIES,
                  config: SpgConfig = SPG_DEFAULTS) -> Adjustment:
    """Adjust `points` and the poses' corrections to the observations in `tracks`, and the
    points to their `ties`, whose frame moves as its prior allows (Huber threshold, in px or a
    tie's sigmas; iterations and tolerance: `config`'s).

    model: how the corrections depend on their unknowns (default: every image free, with priors
    sigma_position_km and sigma_pointing_rad per axis, by default `config`'s). Point unknowns are in metres and the
    model's in units of their prior sigma, which keeps the normal equations well conditioned.
    """
    n_img, n_pt, obs_img, obs_pt = len(poses), len(points), tracks.image, tracks.point
    if model is None:
        model = free_poses(n_img, sigma_position_km=config.sigma_position_km if sigma_position_km is None
                           else sigma_position_km,
                           sigma_pointing_rad=config.sigma_pointing_rad if sigma_pointing_rad is None
                           else sigma_pointing_rad)
    huber_px = config.huber_px
    if model.n_images != n_img:
        raise ValueError(f"a pose model of {model.n_images} images for {n_img} images")
    cam = np.array([[c.fx, c.fy, c.cx, c.cy] for c in cameras])[obs_img]
    pos0 = np.array([p.position for p in poses])
    rot0 = np.array([p.rotation for p in poses])
    design = model.design
    n_theta = design.shape[1]
    moves = ties.frame_motion()  # (n_ties, k): a tie's plane offset per unit of the frame's unknowns
    x_pts = points.copy()
    unknowns = np.zeros(n_theta + moves.shape[1])  # the model's, then the ties' frame's

    def pose_arrays(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return pos0 + d[:, :3], rot0 @ Rotation.from_rotvec(d[:, 3:]).as_matrix().transpose(0, 2, 1)

    def residuals(xpt: np.ndarray, u: np.ndarray) -> np.ndarray:
        pos, rot = pose_arrays(model.corrections(u[:n_theta]))
        return (_project(xpt[obs_pt], pos[obs_img], rot[obs_img], cam) - tracks.xy).ravel()

    def tie_residuals(xpt: np.ndarray, u: np.ndarray) -> np.ndarray:
        return (ties.distances_km(xpt) - moves @ u[n_theta:]) / ties.sigma_km

    def cost(r: np.ndarray, rt: np.ndarray, u: np.ndarray) -> float:
        a = np.abs(np.concatenate([r, rt]))
        return float(np.sum(np.where(a <= huber_px, 0.5 * a**2, huber_px * (a - 0.5 * huber_px))) + 0.5 * np.sum(u**2))

    def huber(r: np.ndarray) -> np.ndarray:  # IRLS Huber weights
        return np.minimum(1.0, huber_px / np.maximum(np.abs(r), 1e-12))

    def normal(u: np.ndarray, r: np.ndarray, rt: np.ndarray) -> tuple[_Normal, _TieNormal]:
        jp, jc = _jacobians(x_pts, model.corrections(u[:n_theta]), obs_pt, obs_img, cam, pose_arrays)
        images = _normal(jp, jc, huber(r).reshape(-1, 2), r.reshape(-1, 2), obs_pt, obs_img, n_pt, n_img)
        return images, _tie_normal(ties, moves, huber(rt), rt, n_pt)

    r, rt = residuals(x_pts, unknowns), tie_residuals(x_pts, unknowns)
    current = cost(r, rt, unknowns)
    damping = 1e-3
    iterations = 0
    for iterations in range(1, config.max_iterations + 1):  # noqa: B007 (the count done is returned)
        images, tied = normal(unknowns, r, rt)
        step_pts, step = _solve(images, tied, design, unknowns, damping)
        while True:
            trial_pts, trial = x_pts + step_pts * 1e-3, unknowns + step
            r_trial, rt_trial = residuals(trial_pts, trial), tie_residuals(trial_pts, trial)
            new = cost(r_trial, rt_trial, trial)
            if new < current or damping > 1e6:
                break
            damping *= 10.0
            step_pts, step = _solve(images, tied, design, unknowns, damping)
        if new >= current:
            break
        improvement = (current - new) / max(current, 1e-300)
        x_pts, unknowns, r, rt, current = trial_pts, trial, r_trial, rt_trial, new
        damping = max(damping / 10.0, 1e-7)
        if improvement < config.tolerance:
            break
    d = model.corrections(unknowns[:n_theta])
    images, tied = normal(unknowns, r, rt)
    return Adjustment(points=x_pts, position_corrections=d[:, :3], rotation_corrections=d[:, 3:],
                      residuals_px=np.linalg.norm(r.reshape(-1, 2), axis=1), tie_distances_km=rt * ties.sigma_km,
                      iterations=iterations, model=model, parameters=unknowns[:n_theta],
                      frame=unknowns[n_theta:], images=images, ties=tied)


def _jacobians(x_pts, corrections, obs_pt, obs_img, cam, pose_arrays) -> tuple[np.ndarray, np.ndarray]:
    """Per observation, d(sample, line) / d(point, m): (n, 2, 3) and / d(its image's six
    corrections, km and rad): (n, 2, 6)."""
    n = len(obs_pt)
    pos, rot = pose_arrays(corrections)
    p = x_pts[obs_pt]
    jp = np.empty((n, 2, 3))
    h = 1e-3  # m
    for k in range(3):
        e = np.zeros(3)
        e[k] = h * 1e-3
        jp[:, :, k] = (_project(p + e, pos[obs_img], rot[obs_img], cam)
                       - _project(p - e, pos[obs_img], rot[obs_img], cam)) / (2 * h)
    jc = np.empty((n, 2, 6))
    for k in range(6):
        e = np.zeros_like(corrections)
        e[:, k] = STEP[k]
        plus, minus = pose_arrays(corrections + e), pose_arrays(corrections - e)
        jc[:, :, k] = (_project(p, plus[0][obs_img], plus[1][obs_img], cam)
                       - _project(p, minus[0][obs_img], minus[1][obs_img], cam)) / (2 * STEP[k])
    return jp, jc


@dataclass
class _Normal:
    """The data part of the normal equations: point blocks (n_pt, 3, 3) and gradient (n_pt, 3),
    pose blocks (n_img, 6, 6) and gradient (n_img, 6), the point-pose coupling (3 n_pt, 6 n_img)."""

    hpp: np.ndarray
    gp: np.ndarray
    hcc: np.ndarray
    gc: np.ndarray
    hpc: sparse.csr_matrix


def _normal(jp, jc, w, r, obs_pt, obs_img, n_pt, n_img) -> _Normal:
    wjp, wjc = jp * w[:, :, None], jc * w[:, :, None]
    hpp = np.zeros((n_pt, 3, 3))
    np.add.at(hpp, obs_pt, np.einsum("nki,nkj->nij", wjp, jp))
    gp = np.zeros((n_pt, 3))
    np.add.at(gp, obs_pt, np.einsum("nki,nk->ni", wjp, r))
    hcc = np.zeros((n_img, 6, 6))
    np.add.at(hcc, obs_img, np.einsum("nki,nkj->nij", wjc, jc))
    gc = np.zeros((n_img, 6))
    np.add.at(gc, obs_img, np.einsum("nki,nk->ni", wjc, r))
    # coupling blocks H_pc (3 per point x 6 per image), one 3x6 block per observation
    hpc_blocks = np.einsum("nki,nkj->nij", wjp, jc)
    rows = (3 * obs_pt[:, None, None] + np.arange(3)[None, :, None]).repeat(6, axis=2)
    cols = (6 * obs_img[:, None, None] + np.arange(6)[None, None, :]).repeat(3, axis=1)
    hpc = sparse.csr_matrix((hpc_blocks.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n_pt, 6 * n_img))
    return _Normal(hpp=hpp, gp=gp, hcc=hcc, gc=gc, hpc=hpc)


@dataclass
class _TieNormal:
    """The ties' part of the normal equations: point blocks (n_pt, 3, 3) and gradient (n_pt, 3),
    the point-frame coupling (3 n_pt, k), the frame's block (k, k) and gradient (k)."""

    hpp: np.ndarray
    gp: np.ndarray
    hpd: sparse.csr_matrix
    hdd: np.ndarray
    gd: np.ndarray


def _tie_normal(ties: SurfaceTies, moves: np.ndarray, w: np.ndarray, r: np.ndarray, n_pt: int) -> _TieNormal:
    jt = ties.normal * (1e-3 / ties.sigma_km)[:, None]  # d(residual) / d(point, m)
    jd = -moves / ties.sigma_km[:, None]  # d(residual) / d(frame unknowns)
    hpp = np.zeros((n_pt, 3, 3))
    np.add.at(hpp, ties.point, np.einsum("n,ni,nj->nij", w, jt, jt))
    gp = np.zeros((n_pt, 3))
    np.add.at(gp, ties.point, (w * r)[:, None] * jt)
    k = moves.shape[1]
    rows = (3 * ties.point[:, None, None] + np.arange(3)[None, :, None]).repeat(k, axis=2)
    cols = np.broadcast_to(np.arange(k)[None, None, :], rows.shape)
    hpd = sparse.csr_matrix((np.einsum("n,ni,nj->nij", w, jt, jd).ravel(), (rows.ravel(), cols.ravel())),
                            shape=(3 * n_pt, k))
    return _TieNormal(hpp=hpp, gp=gp, hpd=hpd, hdd=np.einsum("n,ni,nj->ij", w, jd, jd), gd=jd.T @ (w * r))


def _schur(hcc_dense: np.ndarray, hpp: np.ndarray, hpc: sparse.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """The pose system with the points eliminated, and the inverse point blocks."""
    hpp_inv = np.linalg.inv(hpp)
    return hcc_dense - (hpc.T @ _block_diag(hpp_inv) @ hpc).toarray(), hpp_inv


def _solve(images: _Normal, ties: _TieNormal, design: sparse.csr_matrix, unknowns: np.ndarray,
           damping: float) -> tuple[np.ndarray, np.ndarray]:
    """One damped Gauss-Newton step with the points eliminated: (point steps in m, steps of the
    model's unknowns and then of the ties' frame's)."""
    n_pt, n_theta = len(images.hpp), design.shape[1]
    hpp = images.hpp + ties.hpp
    hpp = hpp + damping * (hpp * np.eye(3) + 1e-9 * np.eye(3))
    k = len(unknowns) - n_theta
    hcc = np.zeros((len(unknowns), len(unknowns)))
    hcc[:n_theta, :n_theta] = np.asarray((design.T @ _block_diag(images.hcc) @ design).todense())
    hcc[n_theta:, n_theta:] = ties.hdd
    hcc += np.eye(len(unknowns))  # priors N(0, I)
    hcc += damping * np.diag(np.diag(hcc))
    gc = np.concatenate([design.T @ images.gc.ravel(), ties.gd]) + unknowns
    coupling = sparse.hstack([images.hpc @ design, ties.hpd]).tocsr() if k else (images.hpc @ design).tocsr()
    schur, hpp_inv = _schur(hcc, hpp, coupling)
    gp = images.gp + ties.gp
    rhs = -gc + coupling.T @ (_block_diag(hpp_inv) @ gp.ravel())
    step = np.linalg.solve(schur, rhs)
    step_pts = -np.einsum("nij,nj->ni", hpp_inv, gp + (coupling @ step).reshape(n_pt, 3))
    return step_pts, step


def _block_diag(blocks: np.ndarray) -> sparse.csr_matrix:
    """A sparse block-diagonal matrix from (n, b, b) blocks."""
    n, b, _ = blocks.shape
    base = b * np.arange(n)[:, None, None]
    rows = np.broadcast_to(base + np.arange(b)[None, :, None], blocks.shape)
    cols = np.broadcast_to(base + np.arange(b)[None, None, :], blocks.shape)
    return sparse.csr_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())), shape=(n * b, n * b))
