"""How stereo photogrammetry matches and adjusts: one frozen configuration, the only source of these
settings' defaults for `pwm spg`, `pwm spg-catalog`, the catalog's start from nothing, a
downlink's pose adjustment and the feedback of the maplets' registrations (service.spg).

Each function of pwm.spg that uses a setting takes the whole configuration (`config`, by default
`SPG_DEFAULTS`) rather than a keyword default of its own, so that a default is written once, here.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class HullConfig:
    """How a body's visual hull is carved from its outlines (pwm.spg.hull)."""

    # a pixel is lit above this share of the way from the image's background to its bright end
    lit_fraction: float = 0.05
    # the percentiles of an image's values taken for its background and its bright end
    background_percentile: float = 1.0
    bright_percentile: float = 99.5
    # pixels about a lit one never taken for space (blur, a limb's partial pixels), besides the pose's 3 sigma
    margin_px: float = 1.0
    # a cell fewer views than this have in frame is not kept (nothing says it is the body)
    min_views: int = 3
    # the finest lattice step, in the views' finest ground samples
    cell_gsd: float = 1.0
    # lattice cells a side at the coarsest level, and at most at the finest
    coarse_cells: int = 32
    max_cells: int = 256
    # the cube carved, in the body's largest reference radius (its PCK ellipsoid's)
    bound_radii: float = 1.5
    # the hull replaces the reference figure where the stereo points lie this many times closer to it (RMS)
    preference: float = 2.0
    # a hull larger than this many times the reference figure's volume is taken for a failed carving
    max_figure_volumes: float = 1.5

    def __post_init__(self) -> None:
        if not 0.0 < self.lit_fraction < 1.0:
            raise ValueError(f"lit fraction {self.lit_fraction}: between 0 and 1")
        if not 0.0 <= self.background_percentile < self.bright_percentile <= 100.0:
            raise ValueError("hull percentiles: 0 <= background < bright <= 100")
        if self.min_views < 1:
            raise ValueError(f"{self.min_views} views to keep a hull cell: at least one")
        if self.coarse_cells < 4 or self.max_cells < self.coarse_cells:
            raise ValueError(f"hull lattice {self.coarse_cells}..{self.max_cells} cells: at least 4, coarse first")
        if min(self.preference, self.cell_gsd, self.max_figure_volumes) <= 0 or self.margin_px < 0:
            raise ValueError("hull preference, cell, margin and volume limit must be positive")
        if self.bound_radii <= 1.0:
            raise ValueError(f"a hull bound of {self.bound_radii} radii: over one")


@dataclass(frozen=True)
class SpgConfig:
    """Every setting of stereo photogrammetry (pwm.spg)."""

    # navigation position knowledge assumed without a pose model, 1 sigma per axis (km)
    sigma_position_km: float = 1e-3
    # navigation pointing knowledge assumed without a pose model, 1 sigma per axis (rad)
    sigma_pointing_rad: float = 1e-4
    # SIFT features per image at most
    max_features: int = 8192
    # SIFT first octave: -1 doubles the images; None: -1 where the model fills under `double_below` of the frame
    first_octave: int | None = None
    # the share of the frame under which the model's footprint has its image doubled (first_octave None)
    double_below: float = 0.25
    # SIFT peak threshold: the weakest contrast a feature may have
    peak_threshold: float = 0.002
    # pixels per side of the lattice on which each view's footprint on the model is traced
    footprint_grid: int = 32
    # stereo partners each image keeps (its best by overlap over the Sun angle)
    per_image: int = 6
    # the largest angle between the Suns of a pair's images (deg)
    max_sun_deg: float = 25.0
    # the least overlap of a pair, as a share of either image's footprint
    min_overlap: float = 0.2
    # the stereo angles a pair may see its common ground at (deg, least and most)
    stereo_deg: tuple[float, float] = (2.0, 50.0)
    # the ratio test of the descriptor matching: best to second-best distance at most
    max_ratio: float = 0.9
    # how far (px) a triangulated point may lie from the model along its line of sight
    model_tolerance_px: float = 30.0
    # observations whose residual (px) exceeds this after the adjustment are dropped, and it is run again
    max_residual_px: float = 3.0
    # the least stereo angle (deg) of a point that the surface is made from
    min_angle_deg: float = 2.0
    # the least stereo angle (deg) of a point that ties the block to the model (narrower: too far off along its rays)
    anchor_min_angle_deg: float = 2.0
    # point-to-plane steps at most in shifting the points onto the model to tie the block to it
    anchor_iterations: int = 20
    # a point is tied to the lidar's surface by the plane of this many nearest spots (pwm.spg.ties)
    tie_spots: int = 8
    # ... all lying within this many times the reach of a spot's own as many nearest (among the spots, not beside them)
    tie_reach: float = 2.0
    # a tie's sigma is never taken below this (km): the spots' placement between their tracks
    tie_floor_km: float = 1e-5
    # the bundle adjustment's Huber threshold (px): larger residuals are damped
    huber_px: float = 2.0
    # the bundle adjustment's iterations at most
    max_iterations: int = 20
    # the bundle adjustment stops when the cost changes by less than this share
    tolerance: float = 1e-6
    # threads for feature extraction and matching (no effect on the results)
    threads: int = 2
    # the visual hull a start from nothing carves before matching (pwm.spg.hull)
    hull: HullConfig = field(default_factory=HullConfig)

    def __post_init__(self) -> None:
        if self.sigma_position_km < 0 or self.sigma_pointing_rad < 0:
            raise ValueError("pose knowledge sigmas must be non-negative")
        if self.max_features < 1:
            raise ValueError(f"{self.max_features} features per image: at least one")
        if self.first_octave not in (None, -1, 0, 1):
            raise ValueError(f"first octave {self.first_octave}: None, -1, 0 or 1")
        if self.footprint_grid < 2:
            raise ValueError(f"a footprint lattice of {self.footprint_grid} pixels a side: at least 2")
        if self.per_image < 1:
            raise ValueError(f"{self.per_image} partners per image: at least one")
        if self.tie_spots < 4:
            raise ValueError(f"a plane of {self.tie_spots} spots: at least four, to measure their scatter")
        if self.tie_reach <= 0 or self.tie_floor_km <= 0:
            raise ValueError("a tie's reach and sigma floor must be positive")
        if self.threads < 1:
            raise ValueError(f"{self.threads} threads: at least one")


SPG_DEFAULTS = SpgConfig()
"""The photogrammetry settings' defaults."""
