"""Synthetic terrain for the truth asteroid: fractal fields, craters, boulders and albedo patches.

Pure generators on numpy arrays. Grid functions take the axes of a regular grid in a local
frame (x along columns, y along rows, km) and return (len(y), len(x)) arrays of heights along
the local z (km) or of log-albedo; point functions take body-fixed points (km).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft

HURST = 0.75
"""Hurst exponent of the self-affine roughness: the RMS relief over a baseline L grows as L**HURST."""

STEEP_EXPONENT = 4.0
"""Superellipse exponent of steep boulders: flat top, near-vertical sides."""

CRATER_EXTENT = 2.0
"""Ejecta blanket radius in crater radii; the relief is zero beyond it."""

LARGE_BOULDER_DIAMETER_KM = (3e-3, 5e-3)
LARGE_BOULDER_HEIGHT_KM = (0.8e-3, 1.2e-3)
"""Size and height ranges of a site's large boulders (`add_large_boulders`): those whose tops an
independent site's models held 0.2-0.4 m low (issue 49)."""
LARGE_BOULDER_CLEARANCE_KM = 0.01
"""How far apart a site's large boulders lie, each the largest within it: a maplet's side at the
sites' 10 cm GSD (100 nodes), so that each is the largest in the maplets about it."""


@dataclass(frozen=True)
class Crater:
    """A simple bowl crater centred at local (x_km, y_km). depth_km: rim crest to floor;
    rim_height_km: rim crest above the surroundings."""

    x_km: float
    y_km: float
    diameter_km: float
    depth_km: float
    rim_height_km: float


@dataclass(frozen=True)
class Boulder:
    """A boulder centred at local (x_km, y_km): a spherical cap, or (steep) a flat-topped
    superellipsoid with near-vertical sides. height_km: top above the local ground;
    albedo_factor: its albedo relative to the ground it sits on."""

    x_km: float
    y_km: float
    diameter_km: float
    height_km: float
    steep: bool
    albedo_factor: float


def fractal_grid(
    rng: np.random.Generator, *, shape: tuple[int, int], spacing_km: float,
    wavelength_min_km: float, wavelength_max_km: float, hurst: float = HURST,
) -> np.ndarray:
    """Unit-RMS self-affine random field on a regular grid, by filtering white noise with FFTs.

    The amplitude spectrum is a power law (k**2 + k_max**2)**(-(1 + hurst) / 2), flattened above
    wavelength_max_km and tapered below wavelength_min_km so that the field stays resolved.
    """
    # FFT sizes with small prime factors; the field is periodic, so cropping it is harmless
    padded = (scipy.fft.next_fast_len(shape[0], real=True), scipy.fft.next_fast_len(shape[1], real=True))
    spectrum = scipy.fft.rfft2(rng.standard_normal(padded), workers=-1)
    ky = 2 * np.pi * scipy.fft.fftfreq(padded[0], d=spacing_km)
    kx = 2 * np.pi * scipy.fft.rfftfreq(padded[1], d=spacing_km)
    k2 = ky[:, None] ** 2 + kx[None, :] ** 2
    k_low = 2 * np.pi / wavelength_max_km
    k_high = 2 * np.pi / wavelength_min_km
    gain = (k2 + k_low**2) ** (-(1 + hurst) / 2) * np.exp(-k2 / k_high**2)
    gain[0, 0] = 0.0
    spectrum *= gain
    field = scipy.fft.irfft2(spectrum, s=padded, workers=-1)[: shape[0], : shape[1]]
    return field / field.std()


@dataclass(frozen=True)
class PlaneWaves:
    """A random field in 3-D as a sum of plane waves a cos(k . p + phase), normalised to unit
    RMS over all its waves. wavenumbers: (K, 3) rad/km; amplitudes and phases: (K,)."""

    wavenumbers: np.ndarray
    amplitudes: np.ndarray
    phases: np.ndarray

    def __call__(self, points_km: np.ndarray, *, cutoff_km: float | None = None, chunk: int = 65536) -> np.ndarray:
        """Field at body-fixed points (N, 3), km. cutoff_km: Gaussian low-pass that halves waves of
        that wavelength (ISO 16610 convention), for resolution limits or a smoothed copy."""
        amp = self.amplitudes
        keep = np.ones(len(amp), dtype=bool)
        if cutoff_km is not None:
            amp = amp * gaussian_transfer(np.linalg.norm(self.wavenumbers, axis=1), cutoff_km)
            keep = amp > 1e-6 * amp.max()
        amp = amp[keep]
        # float32 phases keep ~1e-3 rad accuracy at these wavenumbers: ample for noise, twice as fast
        kk = self.wavenumbers[keep].T.astype(np.float32)
        ph = self.phases[keep].astype(np.float32)
        out = np.empty(len(points_km))
        for s in range(0, len(points_km), chunk):
            p = np.asarray(points_km[s : s + chunk], dtype=np.float32)
            out[s : s + chunk] = np.cos(p @ kk + ph) @ amp
        return out


def plane_waves(
    rng: np.random.Generator, *, wavelength_min_km: float, wavelength_max_km: float,
    n_waves: int = 192, hurst: float = HURST,
) -> PlaneWaves:
    """Random isotropic plane waves with log-uniform wavelengths and a power-law spectrum
    (amplitude ~ wavelength**hurst), normalised so that the full sum has unit RMS."""
    direction = rng.standard_normal((n_waves, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    wavelength = np.exp(rng.uniform(np.log(wavelength_min_km), np.log(wavelength_max_km), n_waves))
    phases = rng.uniform(0.0, 2 * np.pi, n_waves)
    amplitudes = wavelength**hurst
    amplitudes /= np.sqrt(0.5 * np.sum(amplitudes**2))
    return PlaneWaves(wavenumbers=direction * (2 * np.pi / wavelength)[:, None], amplitudes=amplitudes, phases=phases)


def gaussian_transfer(k: np.ndarray, cutoff_km: float) -> np.ndarray:
    """Transfer function of the Gaussian low-pass whose gain is 1/2 at wavelength cutoff_km."""
    return np.exp(-np.log(2.0) * (np.asarray(k) * cutoff_km / (2 * np.pi)) ** 2)


def gaussian_sigma_km(cutoff_km: float) -> float:
    """Standard deviation (km) of the spatial Gaussian with gain 1/2 at wavelength cutoff_km."""
    return cutoff_km * np.sqrt(2 * np.log(2.0)) / (2 * np.pi)


def power_law(rng: np.random.Generator, n: int, lo: float | np.ndarray, hi: float | np.ndarray,
               slope: float) -> np.ndarray:
    """Sizes between lo and hi with a cumulative distribution N(>D) ~ D**-slope."""
    u = rng.uniform(0.0, 1.0, n)
    return (lo**-slope - u * (lo**-slope - hi**-slope)) ** (-1.0 / slope)


def sample_craters(rng: np.random.Generator, *, n: int, site_size_km: float, resolution_km: float) -> list[Crater]:
    """n craters 3-15 m across (cumulative slope 2), centred in the site square, each resolved by
    at least 20 grid spacings and at most half the site across; depth/diameter 0.1-0.2."""
    d_min = max(3e-3, 20 * resolution_km)
    d_max = max(min(15e-3, site_size_km / 2), d_min)
    diameter = power_law(rng, n, d_min, d_max, 2.0)
    centre = rng.uniform(-site_size_km / 2, site_size_km / 2, (n, 2))
    depth = diameter * rng.uniform(0.1, 0.2, n)
    return [Crater(x_km=float(c[0]), y_km=float(c[1]), diameter_km=float(d), depth_km=float(h),
                   rim_height_km=float(0.25 * h)) for c, d, h in zip(centre, diameter, depth, strict=True)]


def sample_boulders(
    rng: np.random.Generator, *, n: int, n_steep: int, site_size_km: float, resolution_km: float,
) -> list[Boulder]:
    """n non-overlapping boulders inside the site square, the first n_steep of them steep.

    Rounded boulders are spherical caps 2-6 m across with height/radius 0.3-0.5 (foot slopes
    below 53 deg); steep ones are 1-6 m across with height/radius 0.6-1. Heights 0.5-3 m. Every
    boulder spans at least 16 grid spacings and at most a third of the site.
    """
    if not 0 <= n_steep <= n:
        raise ValueError("n_steep must lie between 0 and n")
    steep = np.arange(n) < n_steep
    cap = site_size_km / 3
    d_lo = np.where(steep, 1e-3, 2e-3)
    d_lo = np.minimum(np.maximum(d_lo, 16 * resolution_km), cap)
    d_hi = np.maximum(min(6e-3, cap), d_lo)
    diameter = power_law(rng, n, d_lo, d_hi, 2.5)
    ratio = np.where(steep, rng.uniform(0.6, 1.0, n), rng.uniform(0.3, 0.5, n))
    height = np.clip(ratio * diameter / 2, 5e-4, 3e-3)
    height = np.minimum(height, np.where(steep, 1.0, 0.5) * diameter / 2)
    albedo = np.exp(rng.uniform(-0.35, 0.35, n))
    order = np.argsort(-diameter, kind="stable")
    centre = np.empty((n, 2))
    for m, k in enumerate(order):
        reach = diameter[k] / 2 + diameter[order[:m]] / 2 + 2 * resolution_km
        for _ in range(2000):
            c = rng.uniform(-site_size_km / 2 + diameter[k] / 2, site_size_km / 2 - diameter[k] / 2, 2)
            if np.all(np.hypot(*(centre[:m] - c).T) > reach):
                break
        else:
            raise ValueError(f"cannot place {n} non-overlapping boulders in a {site_size_km * 1e3:g} m site")
        centre[m] = c
    return [Boulder(x_km=float(c[0]), y_km=float(c[1]), diameter_km=float(diameter[k]), height_km=float(height[k]),
                    steep=bool(steep[k]), albedo_factor=float(albedo[k])) for c, k in zip(centre, order, strict=True)]


def add_large_boulders(
    rng: np.random.Generator, boulders: list[Boulder], *, n: int, site_size_km: float, clearance_km: float,
    resolution_km: float,
) -> list[Boulder]:
    """The site's boulders with n large ones added first: rounded caps 3-5 m across and 0.8-1.2 m
    tall (foot slopes 50-80 deg), centred within the inner half of the site square and at least
    clearance_km apart, so that each is the largest boulder within clearance_km of it: the
    boulders that overlap one, or lie within clearance_km of it and are not smaller, are dropped.
    """
    if n < 0:
        raise ValueError(f"{n} large boulders: must be non-negative")
    if n == 0:
        return list(boulders)
    if LARGE_BOULDER_DIAMETER_KM[0] < 16 * resolution_km:
        raise ValueError(f"a {resolution_km * 1e3:g} m grid cannot resolve {LARGE_BOULDER_DIAMETER_KM[0] * 1e3:g} m "
                         "boulders")
    diameter = rng.uniform(*LARGE_BOULDER_DIAMETER_KM, n)
    height = np.minimum(rng.uniform(*LARGE_BOULDER_HEIGHT_KM, n), diameter / 2)
    albedo = np.exp(rng.uniform(-0.35, 0.35, n))
    inner = site_size_km / 4
    centre = np.empty((n, 2))
    for k in range(n):
        for _ in range(2000):
            c = rng.uniform(-inner, inner, 2)
            if np.all(np.hypot(*(centre[:k] - c).T) >= clearance_km):
                break
        else:
            raise ValueError(f"cannot place {n} large boulders {clearance_km * 1e3:g} m apart in a "
                             f"{site_size_km * 1e3:g} m site")
        centre[k] = c
    large = [Boulder(x_km=float(c[0]), y_km=float(c[1]), diameter_km=float(d), height_km=float(h), steep=False,
                     albedo_factor=float(a)) for c, d, h, a in zip(centre, diameter, height, albedo, strict=True)]

    def kept(b: Boulder) -> bool:
        for big in large:
            gap = np.hypot(b.x_km - big.x_km, b.y_km - big.y_km)
            if gap < (b.diameter_km + big.diameter_km) / 2 + 2 * resolution_km:
                return False
            if gap < clearance_km and b.diameter_km >= big.diameter_km:
                return False
        return True

    return large + [b for b in boulders if kept(b)]


def crater_profile(crater: Crater, r_km: np.ndarray) -> np.ndarray:
    """Crater relief (km) at distances r_km from its centre: parabolic bowl inside the rim,
    ejecta decaying as r**-3 outside and reaching zero at CRATER_EXTENT radii."""
    radius = crater.diameter_km / 2
    s = np.asarray(r_km) / radius
    bowl = crater.rim_height_km - crater.depth_km * (1 - s**2)
    tail = 1 / CRATER_EXTENT**3
    ejecta = crater.rim_height_km * (np.maximum(s, 1.0) ** -3 - tail) / (1 - tail)
    return np.where(s <= 1, bowl, np.where(s < CRATER_EXTENT, ejecta, 0.0))


def boulder_profile(boulder: Boulder, r_km: np.ndarray) -> np.ndarray:
    """Boulder height above its local ground (km) at distances r_km from its centre."""
    a = boulder.diameter_km / 2
    h = boulder.height_km
    s = np.minimum(np.asarray(r_km) / a, 1.0)
    if boulder.steep:
        return h * (1 - s**STEEP_EXPONENT) ** (1 / STEEP_EXPONENT)
    sphere = (a**2 + h**2) / (2 * h)
    return np.sqrt(np.maximum(sphere**2 - (s * a) ** 2, 0.0)) - (sphere - h)


def _window(x_km: np.ndarray, y_km: np.ndarray, cx: float, cy: float, reach: float):
    """Row and column slices of the grid within `reach` of (cx, cy), and the distances there."""
    j0, j1 = np.searchsorted(x_km, [cx - reach, cx + reach])
    i0, i1 = np.searchsorted(y_km, [cy - reach, cy + reach])
    r = np.hypot(x_km[None, j0:j1] - cx, y_km[i0:i1, None] - cy)
    return (slice(i0, i1), slice(j0, j1)), r


def crater_relief(x_km: np.ndarray, y_km: np.ndarray, craters: list[Crater]) -> np.ndarray:
    """Summed relief of the craters on the grid, km."""
    out = np.zeros((len(y_km), len(x_km)))
    for c in craters:
        win, r = _window(x_km, y_km, c.x_km, c.y_km, CRATER_EXTENT * c.diameter_km / 2)
        out[win] += crater_profile(c, r)
    return out


def boulder_relief(x_km: np.ndarray, y_km: np.ndarray, boulders: list[Boulder]) -> tuple[np.ndarray, np.ndarray]:
    """Relief (km) and log-albedo offset of the (non-overlapping) boulders on the grid.

    The albedo ramps in over the lowest tenth of each boulder so that it follows the outline
    without a one-node jump at the foot of rounded boulders.
    """
    relief = np.zeros((len(y_km), len(x_km)))
    log_albedo = np.zeros_like(relief)
    for b in boulders:
        win, r = _window(x_km, y_km, b.x_km, b.y_km, b.diameter_km / 2)
        z = np.where(r < b.diameter_km / 2, boulder_profile(b, r), 0.0)
        relief[win] += z
        log_albedo[win] += np.log(b.albedo_factor) * np.clip(z / (0.1 * b.height_km), 0.0, 1.0)
    return relief, log_albedo


def albedo_patches(rng: np.random.Generator, x_km: np.ndarray, y_km: np.ndarray, *, site_size_km: float) -> np.ndarray:
    """Log-albedo of darker and brighter Gaussian patches 1-8 m across (about one per 64 m^2,
    at least three), with amplitudes of 10-30 %, centred in the site."""
    n = max(3, round(site_size_km**2 / 8e-3**2))
    centre = rng.uniform(-site_size_km / 2, site_size_km / 2, (n, 2))
    sigma = rng.uniform(0.5e-3, min(4e-3, site_size_km / 4), n)
    amplitude = rng.choice([-1.0, 1.0], n) * rng.uniform(0.1, 0.3, n)
    out = np.zeros((len(y_km), len(x_km)))
    for (cx, cy), s, a in zip(centre, sigma, amplitude, strict=True):
        win, r = _window(x_km, y_km, cx, cy, 3 * s)
        out[win] += a * np.exp(-0.5 * (r / s) ** 2)
    return out


def cobble_relief(rng: np.random.Generator, x_km: np.ndarray, y_km: np.ndarray, *, cover: float, site_size_km: float,
                  resolution_km: float) -> np.ndarray:
    """Relief (km) of a regolith of cobbles: rounded rocks 0.3-3 m across (at least 12 grid
    spacings), cumulative size slope 2.5 as on Bennu, covering about `cover` of the site square.

    Rocks may pile up: where two overlap the higher surface wins. These sub-metre rocks are
    what a shape model at metre scale cannot hold and what pixel-scale refinement must recover.
    """
    d_lo = max(3e-4, 12 * resolution_km)
    d_hi = max(3.0e-3, d_lo)
    mean_area = np.pi / 4 * np.mean(power_law(np.random.default_rng(0), 4096, d_lo, d_hi, 2.5) ** 2)
    n = int(round(cover * site_size_km**2 / mean_area))
    diameter = power_law(rng, n, d_lo, d_hi, 2.5)
    height = diameter / 2 * rng.uniform(0.6, 1.0, n)
    centre = rng.uniform(-site_size_km / 2, site_size_km / 2, (n, 2))
    relief = np.zeros((len(y_km), len(x_km)))
    for (cx, cy), d, h in zip(centre, diameter, height, strict=True):
        win, r = _window(x_km, y_km, cx, cy, d / 2)
        rock = Boulder(x_km=cx, y_km=cy, diameter_km=d, height_km=h, steep=False, albedo_factor=1.0)
        relief[win] = np.maximum(relief[win], np.where(r < d / 2, boulder_profile(rock, r), 0.0))
    return relief
