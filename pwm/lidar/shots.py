"""Laser altimeter shots as the rest of pwm sees them: each shot's time, where it left from and
which way it went in the body-fixed frame, its one-way range, and whether it is usable (and if
not, why). Readers (pwm.io.lidar) and the simulator make them; the strip adjustment and the
lidar shape model (pwm.lidar) take them. Lengths in km, times in TDB seconds past J2000.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np


class Invalid(enum.IntEnum):
    """Why a shot is not used (VALID: it is). Kept per shot, never dropped silently."""

    VALID = 0
    FLAGGED = 1  # the product's own validity flag says so
    RANGE_LIMITS = 2  # outside the instrument's range limits
    NOT_FINITE = 3  # a time, range or direction that is not a finite number
    NO_INTERCEPT = 4  # no surface of the current model near the spot
    OUTSIDE_KERNELS = 5  # no pose for the shot's time in the kernels


@dataclass(frozen=True)
class Shots:
    """N shots of one track or product (arrays of length N; body-fixed frame `frame`).

    et: shot time; origin_km (N, 3): the instrument's position; direction (N, 3): the shot's
    unit direction; range_km: one-way range; sigma_km: the range's 1 sigma; intensity: the
    return's strength where the product gives it (else None); invalid: an Invalid code each.
    """

    frame: str
    et: np.ndarray
    origin_km: np.ndarray
    direction: np.ndarray
    range_km: np.ndarray
    sigma_km: np.ndarray
    invalid: np.ndarray
    intensity: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.et)
        shapes = {"origin_km": (n, 3), "direction": (n, 3), "range_km": (n,), "sigma_km": (n,), "invalid": (n,)}
        if self.intensity is not None:
            shapes["intensity"] = (n,)
        for name, shape in shapes.items():
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"{name} has shape {np.shape(getattr(self, name))}, expected {shape}")

    def __len__(self) -> int:
        return len(self.et)

    @property
    def valid(self) -> np.ndarray:
        """(N,) the shots in use."""
        return np.asarray(self.invalid) == Invalid.VALID

    def spots_km(self) -> np.ndarray:
        """(N, 3) where each shot met the surface, body-fixed."""
        return self.origin_km + self.range_km[:, None] * self.direction

    @staticmethod
    def joined(parts: list[Shots]) -> Shots:
        """The shots of `parts` one after another (intensity kept only where every part has it).
        ValueError for none, or parts in different frames."""
        frames = {p.frame for p in parts}
        if len(frames) != 1:
            raise ValueError(f"shots in {len(frames)} frames ({', '.join(sorted(frames))}) cannot be joined: "
                             "one body-fixed frame is needed")
        intensity = (np.concatenate([p.intensity for p in parts if p.intensity is not None])
                     if all(p.intensity is not None for p in parts) else None)
        return Shots(frame=frames.pop(), intensity=intensity, **{
            name: np.concatenate([getattr(p, name) for p in parts])
            for name in ("et", "origin_km", "direction", "range_km", "sigma_km", "invalid")})

    def take(self, which: np.ndarray) -> Shots:
        """The shots selected by a boolean mask or an index array, in that order."""
        return Shots(frame=self.frame, et=self.et[which], origin_km=self.origin_km[which],
                     direction=self.direction[which], range_km=self.range_km[which], sigma_km=self.sigma_km[which],
                     invalid=self.invalid[which],
                     intensity=None if self.intensity is None else self.intensity[which])

    def marked(self, where: np.ndarray, reason: Invalid) -> Shots:
        """These shots with those at `where` (still valid) marked invalid for `reason`."""
        invalid = np.array(self.invalid, copy=True)
        invalid[np.asarray(where) & (invalid == Invalid.VALID)] = reason
        return Shots(frame=self.frame, et=self.et, origin_km=self.origin_km, direction=self.direction,
                     range_km=self.range_km, sigma_km=self.sigma_km, invalid=invalid, intensity=self.intensity)
