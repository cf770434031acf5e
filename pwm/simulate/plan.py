"""Observation planning: when and from where each simulated image is taken.

Pure geometry. The Sun's body-fixed direction over time is passed in as a function, so the plan
follows the same ephemeris and rotation model that the written kernels carry.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pwm.camera import Camera, look_at
from pwm.frames import LocalFrame, latlon_to_unit, local_sun

AU_KM = 149_597_870.7
SunFunction = Callable[[np.ndarray], np.ndarray]


@dataclass
class Observation:
    """One planned image. position: camera centre, body-fixed km; rotation: body-fixed -> the
    SPICE instrument frame (what the CK carries; the image frame may be a mirror of it)."""

    name: str
    et: float
    position: np.ndarray
    rotation: np.ndarray
    emission_deg: float
    azimuth_deg: float
    target_incidence_deg: float


def sun_states(epochs: np.ndarray, *, pole: np.ndarray, subsolar_lat_deg: tuple[float, float],
               distance_km: float = 1.2 * AU_KM) -> np.ndarray:
    """States (n, 6) of the Sun relative to the body in the pole's (inertial) frame, km and km/s.

    The subsolar latitude drifts linearly between the two values over the epochs, as the body's
    orbital motion slowly changes the season; the body's spin supplies the daily hour angle.
    """
    pole = np.asarray(pole, float) / np.linalg.norm(pole)
    e1 = np.cross(pole, [0.0, 0.0, 1.0]) if abs(pole[2]) < 0.99 else np.cross(pole, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    t = np.asarray(epochs, float)
    span = max(t[-1] - t[0], 1.0)
    lat0, lat1 = np.radians(subsolar_lat_deg)
    lat = lat0 + (lat1 - lat0) * (t - t[0]) / span
    rate = (lat1 - lat0) / span
    pos = distance_km * (np.cos(lat)[:, None] * e1 + np.sin(lat)[:, None] * pole)
    vel = distance_km * rate * (-np.sin(lat)[:, None] * e1 + np.cos(lat)[:, None] * pole)
    return np.hstack([pos, vel])


def time_for_incidence(sun: SunFunction, frame: LocalFrame, *, day_start_et: float, incidence_deg: float, morning: bool,
                       search_s: float = 6 * 3600.0, step_s: float = 20.0) -> float:
    """The epoch within one search window when the Sun stands at `incidence_deg` over the site,
    in the morning (Sun in the east) or afternoon; the closest feasible incidence if unreachable."""
    ets = day_start_et + np.arange(0.0, search_s, step_s)
    inc, az = local_sun(sun(ets), frame)
    side = (az < 180.0) if morning else (az >= 180.0)
    lit = inc < 85.0
    ok = side & lit
    if not ok.any():
        ok = lit
    if not ok.any():
        raise ValueError("the site is never lit in the search window")
    cost = np.where(ok, np.abs(inc - incidence_deg), np.inf)
    return float(ets[np.argmin(cost)])


def view_direction(frame: LocalFrame, emission_deg: float, azimuth_deg: float) -> np.ndarray:
    """Body-fixed unit vector from the site towards a camera at the given emission and azimuth."""
    e, a = np.radians(emission_deg), np.radians(azimuth_deg)
    local = np.array([np.sin(e) * np.sin(a), np.sin(e) * np.cos(a), np.cos(e)])
    return local @ frame.rotation


def plan_site(*, frame: LocalFrame, sun: SunFunction, start_et: float, campaign_s: float, range_km: float,
              views: list[tuple[float, float]], incidences_deg: tuple[float, ...], aim_scatter_km: float,
              rng: np.random.Generator, prefix: str) -> list[Observation]:
    """Images of a site: one per (emission, azimuth) view, at incidences cycling through the list,
    alternating morning and afternoon so the Sun's azimuth varies across the set."""
    obs = []
    n = len(views)
    for k, (emission, azimuth) in enumerate(views):
        incidence = incidences_deg[k % len(incidences_deg)]
        day = start_et + campaign_s * k / max(n, 1)
        et = time_for_incidence(sun, frame, day_start_et=day, incidence_deg=incidence, morning=(k % 2 == 0))
        aim = (frame.to_body(np.array([*rng.normal(0.0, aim_scatter_km, 2), 0.0])) if aim_scatter_km > 0
               else frame.origin)
        position = aim + range_km * view_direction(frame, emission, azimuth)
        pose = look_at(position, aim, up=frame.rotation[1])
        obs.append(Observation(f"{prefix}{k:03d}", et, pose.position, pose.rotation, emission, azimuth, incidence))
    return obs


def plan_global(*, sun: SunFunction, start_et: float, campaign_s: float, range_km: float, n: int,
                phases_deg: tuple[float, ...], rng: np.random.Generator, prefix: str) -> list[Observation]:
    """Whole-body images: the camera looks at the body centre from a direction at a given phase
    angle from the Sun, rotated about the Sun direction so sub-spacecraft latitudes vary."""
    obs = []
    for k in range(n):
        et = start_et + campaign_s * (k + rng.uniform(0.0, 0.5)) / n
        s = sun(np.array([et]))[0]
        perp = np.cross(s, [0.0, 0.0, 1.0])
        perp /= np.linalg.norm(perp)
        roll = 2 * np.pi * k / n * 3.0 + rng.uniform(0, 0.3)
        axis = np.cos(roll) * perp + np.sin(roll) * np.cross(s, perp)
        g = np.radians(phases_deg[k % len(phases_deg)])
        direction = np.cos(g) * s + np.sin(g) * axis
        pose = look_at(range_km * direction, np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
        obs.append(Observation(f"{prefix}{k:03d}", et, pose.position, pose.rotation, 0.0, 0.0, float(np.degrees(g))))
    return obs


def plan_approach(*, sun: SunFunction, start_et: float, campaign_s: float, range_km: float, n: int,
                  latitudes_deg: tuple[float, ...], phases_deg: tuple[float, ...], rng: np.random.Generator,
                  prefix: str, rounds: int = 2, search_s: float = 6 * 3600.0, step_s: float = 60.0,
                  ) -> list[Observation]:
    """Whole-body images as an approach survey takes them: the camera looks at the body centre
    from sub-spacecraft longitudes stepped evenly round the body `rounds` times (each round
    between the last's, from a random first longitude), at latitudes cycling through
    latitudes_deg. Image k is taken within search_s (a rotation or more) of its slot,
    campaign_s * k / n after start_et, when the phase angle comes closest to the next of
    phases_deg, the Sun alternately east and west of the view; where the latitude rules that
    phase out (it is at least the angle between the view's and the Sun's latitudes), at the
    closest one it allows."""
    per_round = -(-n // rounds)
    step = 360.0 / per_round
    first = rng.uniform(0.0, step)
    obs = []
    for k in range(n):
        lon = first + step * (k % per_round) + step * (k // per_round) / rounds
        lat = latitudes_deg[k % len(latitudes_deg)]
        direction = latlon_to_unit(lat, lon)
        ets = start_et + campaign_s * k / n + np.arange(0.0, search_s, step_s)
        s = sun(ets)
        phase = np.degrees(np.arccos(np.clip(s @ direction, -1.0, 1.0)))
        east = np.cross([0.0, 0.0, 1.0], direction)
        side = (s @ east > 0) == (k % 2 == 0)
        cost = np.abs(phase - phases_deg[k % len(phases_deg)])
        best = int(np.argmin(np.where(side, cost, np.inf) if side.any() else cost))
        pose = look_at(range_km * direction, np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
        obs.append(Observation(f"{prefix}{k:03d}", float(ets[best]), pose.position, pose.rotation, 0.0, 0.0,
                               float(phase[best])))
    return obs


def frame_room_px(camera: Camera, *, range_km: float, radius_km: float) -> float:
    """Pixels between the outline of a sphere of radius_km about the boresight's aim point, seen
    from range_km, and the nearest edge of the camera's frame (negative: it does not fit)."""
    if range_km <= radius_km:
        return -np.inf
    outline = camera.fx * radius_km / np.sqrt(range_km**2 - radius_km**2)
    edges = (camera.cx + 0.5, camera.cy + 0.5, camera.width - camera.cx - 0.5, camera.height - camera.cy - 0.5)
    return float(min(edges) - outline)
