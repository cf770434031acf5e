"""How maplets are tiled and refined: one frozen configuration, the only source of these settings'
defaults for `pwm refine`, `pwm run`, ingest, the workers and the API.

Its `digest` names the settings that change what one maplet's refinement gives; the catalog
puts it in each refinement's input hash (service.refinement), so that a changed setting
re-refines. Every constant that changes a maplet's refinement (pwm.pipeline.refine_maplet and
what it calls) has its one default here or in the frozen settings nested here (`Placement`,
pwm.alignment.Registration, pwm.weights.Rules, pwm.photoclinometry.Solver); the module constants
left in those modules change no refinement (tests/test_config.py lists each with why). The
tiling settings (nodes, overlap, spacing) are not in the digest: they make other maplets, and a
maplet's own grid is part of its input hash already.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from typing import Any, get_args

from pwm.alignment import REGISTRATION, Registration
from pwm.knowledge import KnowledgeErrors
from pwm.photoclinometry import SOLVER, Mode, Solver
from pwm.uncertainty import UNCERTAINTY, Uncertainty
from pwm.weights import RULES, Rules

MODES: tuple[str, ...] = get_args(Mode)
"""The refinement modes: 'pwm' (pixel and region weights) and 'standard' (weights off)."""


@dataclass(frozen=True)
class Placement:
    """How pwm.pipeline.refine_maplet places a maplet whose start is off by pixels of parallax:
    the height sweep's gates, the coarse-first solution, the parallax rounds and the bending.

    registration_px: how well a maplet's registration places an image with exact poses (px, 1
    sigma). parallax_rounds: at most this many times a maplet is raised by its offsets' parallax
    and solved again. runaway: a parallax rise after which the solution still shows this much of
    it or more (measured on the campaign survey: 0.05-0.75 where the start was metres off,
    0.85-0.95 where the rise ran away) is undone with those after it. window_search_px: how far
    (px) each part of a maplet is registered about the maplet's offsets when it is bent.

    sweep_start: a maplet is first swept (pwm.alignment.sweep_height) where its start's faces are
    this many of its spacings or more (five levels, a survey over a site): a coarser model's
    heights are off by about a sixth of its faces (measured on campaign-tiny's survey under its
    sites and on the surveys' photogrammetric starts), which is then several spacings of
    parallax, beyond the joint solution's reach; nearer, the sweep's false optima cost more than
    it finds (bench/RESULTS.md: the survey from nothing).

    sweep_start_many, sweep_many_images: a maplet seen by sweep_many_images usable images or more
    is swept from sweep_start_many spacings (four levels): the campaign's 10 cm sites lie on its
    survey's 2 m faces (20 spacings), 0.4-1.1 m off (2-6 px of parallax), beyond the reach of the
    solution and the parallax placement; a plane sweep's false optima grow rarer with its views (2
    of 20 there, with 22-24 images), and with the 3-6 images of a small survey from nothing they
    broke its closed surface (bench/RESULTS.md: the campaign's site A swept under its survey).
    Its sweep also follows the agreement past the sweep's end (two of site A's maplets were
    1.1-1.2 m low, 16 px reached 1.3 m); with four images that ran a maplet of
    `tests/test_pipeline.py` 1.5 m off.

    coarse_factors: a swept maplet is solved first on grids this many times coarser, coarsest
    first (pwm.pipeline._coarse_first). resweep_px: a swept maplet is swept again from its
    refined heights over this much parallax (pwm.pipeline._swept_again): the first sweep, from
    the coarser start's relief, was up to 0.37 m (4.6 px) off on the campaign's site A.

    lidar_spots: a maplet with at least this many laser altimeter spots over it is placed on them
    (pwm.pipeline.placed_on_spots) instead of by its images' parallax: moved by the plane through
    the spots' height residuals, tilted along the directions in which the spots spread over at
    least lidar_spread of the maplet's half side (RMS about their centre; a profile spreads along
    itself only).
    """

    registration_px: float = 0.1  # 1 sigma (px) of an image's registration with exact poses
    parallax_rounds: int = 3  # most parallax rises of one maplet
    runaway: float = 0.8  # share of a rise left in the solution after it that undoes the rises
    window_search_px: int = 4  # registration search (px) of each part of a bent maplet
    sweep_start: float = 32.0  # start faces (in spacings) from which a maplet is swept
    sweep_start_many: float = 16.0  # the same under sweep_many_images or more
    sweep_many_images: int = 12  # usable images from which sweep_start_many applies (and the sweep follows)
    coarse_factors: tuple[int, ...] = (8, 4, 2)  # coarser grids a swept maplet is solved on first
    resweep_px: float = 8.0  # parallax (px) a swept maplet is swept again over from its refined heights
    lidar_spots: int = 10  # fewest laser altimeter spots that place a maplet
    lidar_spread: float = 0.2  # share of a maplet's half side the spots spread over to tilt it that way

    def __post_init__(self) -> None:
        if self.registration_px < 0:
            raise ValueError(f"registration of {self.registration_px} px: must be non-negative")
        if self.parallax_rounds < 0:
            raise ValueError(f"{self.parallax_rounds} parallax rounds: must be non-negative")
        if any(f < 1 for f in self.coarse_factors):
            raise ValueError(f"coarse factors {self.coarse_factors}: each at least 1")
        if self.lidar_spots < 3:
            raise ValueError(f"{self.lidar_spots} lidar spots: at least 3 place a maplet")
        if not self.lidar_spread > 0:
            raise ValueError(f"lidar spread {self.lidar_spread}: must be positive")


PLACEMENT = Placement()


@dataclass(frozen=True)
class RefinementConfig:
    """Every setting of tiling and refining maplets.

    mode: 'pwm' or 'standard' (pwm.photoclinometry.refine). nodes: nodes per side of a maplet.
    overlap: fraction of a maplet's side shared with each neighbour. spacing_gsd: node spacing in
    image GSDs (the median pixel scale of the images that see the region). passes: refinement
    passes every maplet gets, each from the previous pass's fused model. max_passes: at most this
    many (never fewer than passes; after one pass, none: `most_passes`) for a maplet that has
    not settled, one whose last pass changed its solution by more than settled_spacings node
    spacings (RMS, pwm.maplets.solution_change): the model it started from still held it back (a
    site under a survey's model that has none of the site's relief; `another_pass`).
    search_px: how far (px) the images may be off the maplets, from the pose knowledge; beyond a
    pixel they are registered first (pwm.pipeline.refine_maplet).
    height_sweep_px: within a pixel, how much parallax between the images a maplet's height is
    swept over before it is refined (0: not swept).
    shape_window_nodes: within a pixel, a maplet of at least twice this many nodes a side is also
    bent by the parallax its images show in square parts of about this many nodes a side (0: not).
    min_images: fewest usable images a maplet is refined from; with fewer it keeps its start.
    tile_radius_km: the operations tile each place the images see (pwm.footprints) only within
    this of its centre (None: all of it).
    rules: the weighting (pwm.weights.Rules); solver: the iteration (pwm.photoclinometry.Solver).
    knowledge: the 1-sigma pose knowledge (pwm.knowledge) of kernels that state none; None: as
    good as the images need. With it, the operations adjust a downlink's poses before refining
    (service.spg.adjust_downlink), and each image's registration search grows to
    knowledge_sigmas sigma of its line of sight after the adjustment.
    knowledge_sigmas: an image is searched for this many sigmas of its line of sight
    (View.los_sigma_px); service.spg.within_a_pixel judges by it whether an adjustment can matter.
    placement: how a maplet whose start is off by pixels of parallax is placed (`Placement`);
    registration: the images' registration to a maplet (pwm.alignment.Registration).
    uncertainty: how each refined node's 1-sigma height is made (pwm.uncertainty.Uncertainty).
    """

    mode: Mode = "pwm"
    nodes: int = 100
    overlap: float = 0.25
    spacing_gsd: float = 1.0
    passes: int = 2
    max_passes: int = 3
    settled_spacings: float = 0.25
    search_px: float = 1.0
    height_sweep_px: float = 16.0
    shape_window_nodes: int = 20
    min_images: int = 3
    tile_radius_km: float | None = None
    rules: Rules = field(default=RULES)
    solver: Solver = field(default=SOLVER)
    knowledge: KnowledgeErrors | None = None
    knowledge_sigmas: float = 3.0  # an image is searched for this many sigmas of its line of sight
    placement: Placement = field(default=PLACEMENT)
    registration: Registration = field(default=REGISTRATION)
    uncertainty: Uncertainty = field(default=UNCERTAINTY)

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
        if not self.settled_spacings > 0:
            raise ValueError(f"settled at {self.settled_spacings} node spacings: must be positive")
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
        if not self.knowledge_sigmas > 0:
            raise ValueError(f"knowledge sigmas {self.knowledge_sigmas}: must be positive")

    @property
    def most_passes(self) -> int:
        """The most passes a maplet is refined: a pass's change is measured against the pass
        before it, so a single pass is never followed by another."""
        return self.passes if self.passes < 2 else max(self.passes, self.max_passes)

    def another_pass(self, *, done: int, changed_spacings: float | None) -> bool:
        """Whether a maplet refined `done` passes, whose last pass changed its solution by
        `changed_spacings` node spacings (pwm.maplets.solution_change; None: not known, as
        settled), is due for another."""
        return done < self.passes or (done < self.most_passes and changed_spacings is not None
                                      and changed_spacings > self.settled_spacings)

    def digest(self) -> str:
        """sha256 of the settings that change one maplet's refinement (`digested`)."""
        return hashlib.sha256(json.dumps(self.digested(), sort_keys=True).encode()).hexdigest()

    def digested(self) -> dict[str, Any]:
        """The settings that change one maplet's refinement, as JSON values: mode, search, knowledge
        sigmas, height sweep, shape windows, image count, placement, registration, weighting rules,
        solver, uncertainty (not the tiling's, the passes or the pose knowledge: module docstring)."""
        return {"mode": self.mode, "search_px": self.search_px, "knowledge_sigmas": self.knowledge_sigmas,
                "height_sweep_px": self.height_sweep_px, "shape_window_nodes": self.shape_window_nodes,
                "min_images": self.min_images, "placement": dataclasses.asdict(self.placement),
                "registration": dataclasses.asdict(self.registration),
                "rules": dataclasses.asdict(self.rules), "solver": dataclasses.asdict(self.solver),
                "uncertainty": dataclasses.asdict(self.uncertainty)}


DEFAULTS = RefinementConfig()


@dataclass(frozen=True)
class FusionBlocks:
    """How a closed surface's fusion (pwm.volume) is split into blocks of its lattice, each fused
    on its own (pwm.blocks), so that no process holds more than a block and its margin.

    cells: lattice steps along each side of a block; a lattice that spans no more than this on
    every axis is fused whole, as one process always did. margin: lattice steps about a block
    whose sums it reads to close its own points as the whole body would (the base's bend and
    band reach that far, pwm.volume). workers: processes the blocks are fused on.
    """

    cells: int = 256
    margin: int = 48
    workers: int = 1

    def __post_init__(self) -> None:
        if self.cells < 8:
            raise ValueError(f"blocks of {self.cells} lattice steps: at least 8")
        if not 0 <= self.margin <= self.cells:
            raise ValueError(f"a margin of {self.margin} lattice steps: from 0 to the block's {self.cells}")
        if self.workers < 1:
            raise ValueError(f"{self.workers} fusion workers: at least 1")


BLOCKS = FusionBlocks()
