"""How well a downlink's kernels know the camera poses: the 1-sigma knowledge errors.

The simulator draws errors of these sizes into the kernels it writes (pwm.simulate.knowledge);
operations take them from configuration or from what the kernels state (pwm.io.spice_kernels)
to model the poses in the bundle adjustment (pwm.spg.pose_models) and to size the images'
registration. Two modes:

- `IndependentErrors`: independent errors per image, position per axis (m) and pointing per
  axis (rad).
- `NavigationErrors`: errors as navigation delivers them, smooth over each arc
  (pwm.trajectory): RMS per arc along-track, cross-track and radial (m), one camera-to-bus
  misalignment shared by every image and a pointing drift over the downlink (microradians).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pwm.trajectory import ARC_GAP_S

RADIAL_FRACTION = 0.5  # radial RMS as a fraction of the cross-track RMS


def _check(name: str, value: float) -> None:
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a finite non-negative number, not {value}")


@dataclass(frozen=True)
class IndependentErrors:
    """Independent Gaussian errors per image: 1 sigma per axis, position (m) and pointing (rad)."""

    position_m: float = 0.0
    pointing_rad: float = 0.0

    def __post_init__(self) -> None:
        _check("position_m", self.position_m)
        _check("pointing_rad", self.pointing_rad)


EXACT = IndependentErrors()
"""No knowledge error: the downlink's kernels carry the true poses."""


@dataclass(frozen=True)
class NavigationErrors:
    """Navigation-like errors (see the module's docstring): RMS per arc along-track and
    cross-track (m; radial is RADIAL_FRACTION of cross-track), the misalignment's norm and the
    drift over the downlink (microradians)."""

    along_m: float
    cross_m: float
    misalign_urad: float
    drift_urad: float
    orbit_period_s: float | None = None  # None: each arc's duration
    arc_gap_s: float = ARC_GAP_S

    @property
    def radial_m(self) -> float:
        return RADIAL_FRACTION * self.cross_m

    def __post_init__(self) -> None:
        for name in ("along_m", "cross_m", "misalign_urad", "drift_urad"):
            _check(name, getattr(self, name))
        if self.orbit_period_s is not None and not (math.isfinite(self.orbit_period_s) and self.orbit_period_s > 0):
            raise ValueError(f"orbit_period_s must be positive, not {self.orbit_period_s}")
        if not self.arc_gap_s > 0:
            raise ValueError(f"arc_gap_s must be positive, not {self.arc_gap_s}")


KnowledgeErrors = IndependentErrors | NavigationErrors


def shared_frame_sigma(errors: KnowledgeErrors, *, range_km: float, radius_km: float) -> tuple[float, float]:
    """The 1 sigma per axis of the shift (km) and turn (rad) of what an instrument places under
    these errors from `range_km` off a body of `radius_km` (a lidar's spots): its measurements
    share the spacecraft's trajectory and attitude errors, so their frame is placed no better
    than one pose is (the largest position sigma, and the pointing's at that range, together),
    and turned by as much over the body's radius. Under navigation errors the pointing is the
    bus's drift alone: the camera's misalignment is the camera's, each instrument being aligned
    with the bus on its own."""
    if isinstance(errors, IndependentErrors):
        position_m, pointing_rad = errors.position_m, errors.pointing_rad
    else:
        position_m = max(errors.along_m, errors.cross_m, errors.radial_m)
        pointing_rad = errors.drift_urad * 1e-6
    shift_km = math.hypot(position_m * 1e-3, pointing_rad * range_km)
    return shift_km, shift_km / radius_km

USAGE = "expected POS_M,POINT_RAD (e.g. 1,1e-4) or nav:ALONG_M,CROSS_M,MISALIGN_URAD,DRIFT_URAD (e.g. nav:3,1,50,20)"


def format_knowledge_errors(errors: KnowledgeErrors) -> str:
    """The text `parse_knowledge_errors` reads back as `errors` (its default period and arc gap)."""
    if isinstance(errors, IndependentErrors):
        return f"{errors.position_m:g},{errors.pointing_rad:g}"
    return f"nav:{errors.along_m:g},{errors.cross_m:g},{errors.misalign_urad:g},{errors.drift_urad:g}"


def parse_knowledge_errors(text: str) -> KnowledgeErrors:
    """`POS_M,POINT_RAD` or `nav:ALONG_M,CROSS_M,MISALIGN_URAD,DRIFT_URAD`; ValueError, with a
    message that says what is wrong, for anything else."""
    mode, sep, values = text.strip().rpartition(":")
    if sep and mode.strip().lower() != "nav":
        raise ValueError(f"unknown knowledge-error mode {mode.strip()!r}: {USAGE}")
    names = (("along_m", "cross_m", "misalign_urad", "drift_urad") if sep else ("position_m", "pointing_rad"))
    parts = [p.strip() for p in values.split(",")]
    if len(parts) != len(names):
        raise ValueError(f"{len(parts)} value(s) in {text!r}, {len(names)} wanted: {USAGE}")
    numbers = {}
    for name, part in zip(names, parts, strict=True):
        try:
            numbers[name] = float(part)
        except ValueError:
            raise ValueError(f"{name} {part!r} is not a number: {USAGE}") from None
        _check(name, numbers[name])
    return NavigationErrors(**numbers) if sep else IndependentErrors(**numbers)
