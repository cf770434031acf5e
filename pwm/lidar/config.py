"""Every setting of the lidar science (pwm.lidar): how shots split into tracks, how a track is
registered to a model, when the model -> tracks -> model loop stops, and how a shape model is
made from spots. One frozen `LidarConfig` is the only home of their defaults. Lengths in km,
angles in degrees or radians as named, times in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LidarConfig:
    """The lidar settings, each default with why.

    Tracks (pwm.lidar.tracks):
    max_gap_s: a pause longer than this starts a new track. A lidar fires at 1-10000 Hz; a pause
        of a minute is a change of pointing or a downlink gap, after which the spacecraft's
        position and attitude errors are no longer the same rigid error.
    max_sweep_deg: a track ends where the sub-spacecraft point has swept this far around the body
        from the track's first shot. The seed's rule is that a window must not wind too far around
        the body for one rigid correction to hold; orbit-determination errors change over about a
        tenth of an orbit, and 30 degrees (a twelfth) still sees enough relief to register on.
    min_shots: a track of fewer valid shots is not corrected (6 unknowns need many more
        equations than 6 to be robust to outliers).
    crossover_km: spots of two tracks this close form a crossover (their height difference
        along the normal measures how far apart the tracks are there).

    Registration (pwm.lidar.strips):
    icp_iterations, icp_tolerance_km: a track's ICP stops after this many linearisations, or
        once the correction's largest step (translation, or rotation times the track's extent)
        is below the tolerance: a millimetre is well below any lidar's range noise.
    huber_k: the residuals' Huber threshold in robust sigmas (1.345: 95% efficiency on normal
        residuals while bounding outliers' pull).
    condition: a direction of the normal equations (with the prior) whose eigenvalue is below
        this fraction of the largest is left uncorrected with an infinite sigma (a profile's
        slide along a flat surface); 1e-6 is far below any well-observed direction's share.
    sigma_segments: a correction's sigma is widened to what the residuals themselves say where
        they say more (pwm.lidar.strips: the sandwich covariance with the shots' scores summed
        over this many runs of consecutive shots): errors shared by neighbouring shots (the
        model's, or the ground a footprint averages) do not shrink with the shots' number. Ten
        runs: enough for the sum over runs to be a variance, few enough that each run holds
        many shots whose shared error it sees.
    prior_rotation_rad, prior_translation_km: the 1 sigma of the knowledge errors a correction
        undoes, held as a prior, so that a direction the shots barely see (a straight profile's
        turn about itself) stays near zero with the prior's sigma instead of wandering by its
        own large one. A milliradian is far beyond a star tracker's error and a reconstructed
        pointing's (tens of microradians) and 100 m beyond a survey's navigation error (metres
        to tens of metres): loose enough never to hold back an error the shots do see. inf: none.

    disagree_sigmas: a track whose spots lie off a version, on the mean, by more than this many
        of its own sigmas (its placement's, from its strip correction, and its spots' scatter over
        their number) disagrees with that version: it is flagged in the version's lidar figures
        rather than averaged in. Three: a track in agreement is flagged once in 370.
    intercept_km: a spot whose shot's ray meets the model further than this from it has no
        intercept near the model (other ground: a grazing shot's ray past a limb); it is left
        out of the registration and of the residuals. 100 m: beyond any knowledge error the
        prior allows, so a spot is never dropped for being off by what the adjustment corrects.

    The loop (pwm.lidar.strips.adjust):
    loop_tolerance_km: the loop stops once no track's correction changed by more than this
        between two rounds (a tenth of a metre: well below the model's voxel).
    loop_rounds: at most this many model -> tracks -> model rounds. The seed converged in one
        or two; here the first round takes out the metres and the next ones change the tracks
        by decimetres, less each round (tests/test_lidar_strips.py: 6.7, 1.4, 0.40, 0.21, 0.14 m),
        but the model a track follows swells a little each round (about the kernel's bias), so
        rounds past five buy little and cost a model each.

    Model from nothing (pwm.lidar.model):
    normal_neighbours: spots whose plane fit gives each spot's normal (enough to average range
        noise, few enough to stay local).
    max_incidence_deg: spots whose shot met the surface further than this from its normal are
        left out of the model: beyond, the footprint smears along the surface and which side of
        the fitted plane faces the shot is nearly a tie (a flipped normal lays a false surface).
    voxel_spacings: the model's lattice step in spot spacings (the median distance of a spot to
        its nearest neighbour): 2 keeps a few spots per cell; at 1.5 the lattice resolves the
        spots' noise, whose false creases break the surface's closure.
    kernel_spacings: the Gaussian width, in spot spacings, over which the spots nearest a
        lattice point share its distance: a spot's tangent plane stands off a convex surface by
        the square of the distance from the spot over twice the radius of curvature, so a wider
        kernel swells the model (by the width squared over the radius), and the loop, whose
        tracks follow the model, would compound it. 1 spacing: narrower, the distances jump from
        one spot's plane to the next and open the surface; wider, it swells.
    kernel_widenings: where tracks still disagree by about a kernel (the first model, from the
        unadjusted spots), the surface may open; the kernel is then widened by half, at most
        this many times (measured: 100,000 shots of 64 tracks 3 m apart close at 1.5 spacings).
    reach_voxels: how far from the spots their signed distances are laid on the lattice, in
        voxels: 3 bridges the gaps between neighbouring tracks of a survey.
    coarse_factor: the closed first surface, which fills what the spots left bare, is made on a
        lattice this many times coarser (gaps up to reach_voxels * coarse_factor voxels close).
    """

    max_gap_s: float = 60.0
    max_sweep_deg: float = 30.0
    min_shots: int = 30
    crossover_km: float = 0.002

    icp_iterations: int = 20
    icp_tolerance_km: float = 1e-6
    huber_k: float = 1.345
    condition: float = 1e-6
    sigma_segments: int = 10
    prior_rotation_rad: float = 1e-3
    prior_translation_km: float = 0.1
    intercept_km: float = 0.1
    disagree_sigmas: float = 3.0

    loop_tolerance_km: float = 1e-4
    loop_rounds: int = 5

    normal_neighbours: int = 12
    max_incidence_deg: float = 75.0
    voxel_spacings: float = 2.0
    kernel_spacings: float = 1.0
    kernel_widenings: int = 2
    reach_voxels: float = 3.0
    coarse_factor: float = 4.0

    def __post_init__(self) -> None:
        positive = {name: getattr(self, name) for name in (
            "max_gap_s", "max_sweep_deg", "crossover_km", "intercept_km", "icp_tolerance_km", "huber_k", "condition",
            "disagree_sigmas", "loop_tolerance_km", "voxel_spacings", "kernel_spacings", "reach_voxels")}
        for name, value in positive.items():
            if not value > 0 or value == float("inf"):
                raise ValueError(f"{name} must be a positive finite number, not {value}")
        for name in ("prior_rotation_rad", "prior_translation_km"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive (inf: no prior), not {getattr(self, name)}")
        if not 0 < self.max_incidence_deg < 90:
            raise ValueError(f"max_incidence_deg must be in (0, 90), not {self.max_incidence_deg}")
        if not 0 < self.max_sweep_deg <= 180:
            raise ValueError(f"max_sweep_deg must be in (0, 180], not {self.max_sweep_deg}")
        if not self.condition < 1:
            raise ValueError(f"condition must be below 1, not {self.condition}")
        if self.sigma_segments < 1:
            raise ValueError(f"sigma_segments must be at least 1, not {self.sigma_segments}")
        if self.min_shots < 6:
            raise ValueError(f"min_shots must be at least 6 (the correction's unknowns), not {self.min_shots}")
        if not 0 <= self.kernel_widenings <= 10:
            raise ValueError(f"kernel_widenings must be in 0..10, not {self.kernel_widenings}")
        if self.normal_neighbours < 3:
            raise ValueError(f"normal_neighbours must be at least 3, not {self.normal_neighbours}")
        for name in ("icp_iterations", "loop_rounds"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, not {getattr(self, name)}")
        if not self.coarse_factor >= 1:
            raise ValueError(f"coarse_factor must be at least 1, not {self.coarse_factor}")


LIDAR = LidarConfig()
"""The default settings."""
