"""How maplets are tiled and refined: one frozen configuration, the only source of these settings'
defaults for `pwm refine`, `pwm run`, ingest, the workers and the API.

Its `digest` names the settings that change what one maplet's refinement gives; the catalog
puts it in each refinement's input hash (service.refinement), so that a changed setting
re-refines. The tiling settings (nodes, overlap, spacing) are not in it: they make other maplets,
and a maplet's own grid is part of its input hash already.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from typing import Any, get_args

from pwm.knowledge import KnowledgeErrors
from pwm.photoclinometry import SOLVER, Mode, Solver
from pwm.weights import RULES, Rules

MODES: tuple[str, ...] = get_args(Mode)
"""The refinement modes: 'pwm' (pixel and region weights) and 'standard' (weights off)."""


@dataclass(frozen=True)
class RefinementConfig:
    """Every setting of tiling and refining maplets.

    mode: 'pwm' or 'standard' (pwm.photoclinometry.refine). nodes: nodes per side of a maplet.
    overlap: fraction of a maplet's side shared with each neighbour. spacing_gsd: node spacing in
    image GSDs (the median pixel scale of the images that see the region). passes: refinement
    passes of `pwm refine`, each from the previous pass's fused model (the catalog refines a
    maplet once per input, against the current published model). search_px: how far (px) the
    images may be off the maplets, from the pose knowledge; beyond a pixel they are registered
    first (pwm.pipeline.refine_maplet). height_sweep_px: within a pixel, how much parallax between
    the images a maplet's height is swept over before it is refined (0: not swept).
    shape_window_nodes: within a pixel, a maplet of at least twice this many nodes a side is also
    bent by the parallax its images show in square parts of about this many nodes a side (0: not).
    min_images: fewest usable images a maplet is refined from; with fewer it keeps its start.
    tile_radius_km: the operations tile each place the images see (pwm.footprints) only within
    this of its centre (None: all of it).
    rules: the weighting (pwm.weights.Rules); solver: the iteration (pwm.photoclinometry.Solver).
    knowledge: the 1-sigma pose knowledge (pwm.knowledge) of kernels that state none; None: as
    good as the images need. With it, the operations adjust a downlink's poses before refining
    (service.spg.adjust_downlink), and each image's registration search grows to three sigma of
    its line of sight after the adjustment.
    """

    mode: Mode = "pwm"
    nodes: int = 100
    overlap: float = 0.25
    spacing_gsd: float = 1.0
    passes: int = 2
    search_px: float = 1.0
    height_sweep_px: float = 16.0
    shape_window_nodes: int = 20
    min_images: int = 3
    tile_radius_km: float | None = None
    rules: Rules = field(default=RULES)
    solver: Solver = field(default=SOLVER)
    knowledge: KnowledgeErrors | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode {self.mode!r}: expected one of {', '.join(MODES)}")
        if self.nodes < 8:
            raise ValueError(f"{self.nodes} nodes per side: at least 8")
        if not 0.0 <= self.overlap <= 0.75:
            raise ValueError(f"overlap {self.overlap} is outside [0, 0.75]")
        if not 0.25 <= self.spacing_gsd <= 2.0:
            raise ValueError(f"spacing {self.spacing_gsd} GSD is outside [0.25, 2]")
        if self.passes < 1:
            raise ValueError("at least one pass")
        if self.search_px < 0:
            raise ValueError(f"search of {self.search_px} px: must be non-negative")
        if self.height_sweep_px < 0:
            raise ValueError(f"height sweep of {self.height_sweep_px} px: must be non-negative")
        if self.shape_window_nodes != 0 and self.shape_window_nodes < 8:
            raise ValueError(f"shape windows of {self.shape_window_nodes} nodes: 0 (off) or at least 8")
        if self.min_images < 1:
            raise ValueError("a maplet is refined from at least one image")
        if self.tile_radius_km is not None and not self.tile_radius_km > 0:
            raise ValueError(f"tile radius {self.tile_radius_km} km: must be positive")

    def digest(self) -> str:
        """sha256 of the settings that change one maplet's refinement (mode, search, image count,
        weighting rules, solver)."""
        payload: dict[str, Any] = {"mode": self.mode, "search_px": self.search_px,
                                   "height_sweep_px": self.height_sweep_px,
                                   "shape_window_nodes": self.shape_window_nodes, "min_images": self.min_images,
                                   "rules": dataclasses.asdict(self.rules), "solver": dataclasses.asdict(self.solver)}
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


DEFAULTS = RefinementConfig()
