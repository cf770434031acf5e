"""One image product's label resolved against the loaded SPICE kernel pool: which spacecraft
and camera took it, of which target in which body-fixed frame, when, the camera of its array,
then the camera's pose and the Sun's direction; or a coded refusal that says why not.

The catalog's ingest (service.ingest) and the catalog-free commands (pwm.io.downlink) both
resolve a label here, so that a product gets one verdict and one code on both paths. Pure: a
label, the loaded pool and the coverage windows of its SPKs and CKs in (`KernelWindows`: the
catalog's, or read from the pool by `loaded_windows`), geometry or a `Refusal` out; no catalog.
The names in a label are read by the rules of pwm.io.labels.

The codes, in the order they are tried (a product gets the first that applies):
- bad_time (a pwm.io.pds4.ProductError of `exposure`): the exposure times cannot be read, or the
  stop precedes the start;
- no_kernels: the label names no host (spacecraft), or one SPICE does not know, or the kernels
  hold no SPK of it: a product of another mission or of a ground telescope, or one that came
  before its kernels. The catalog keeps it accepted without geometry, the reason stored, and
  judges it again when kernels come; the catalog-free commands, which need a view, skip it;
- other_instrument (with a chosen instrument only): the label names another camera of the
  spacecraft;
- unknown_instrument: the label's instrument is no camera of the observer that the kernels know;
- instrument_kernel: the camera's kernel (IK) is missing or unusable;
- unknown_target: the label's target is no body SPICE knows, or one without a body-fixed frame;
- geometry: no leapseconds kernel (LSK) is loaded, or SPICE fails another way (kernels that
  resolve the names but lack data);
- outside_coverage: mid-exposure lies outside the observer's SPK coverage, or SPICE has no data
  then (the reason names the spacecraft's CK frames without data then);
- bad_dimensions: the array's detector window (img:Subframe) lies outside the detector.
The callers add theirs: the product's own (pwm.io.pds4.ProductError codes, read before), and
the downlink reader's other_target (an image of another target than most of the downlink's).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import NamedTuple, TypeVar

import numpy as np
import spiceypy as sp

from pwm.camera import Camera, Pose
from pwm.io.labels import (
    COVERAGE_ERRORS,
    body_name,
    exposure_et,
    exposure_times,
    instrument_code,
    observer_code,
    target_frame,
)
from pwm.io.pds4 import ImageLabel
from pwm.io.spice_geometry import ABCORR, camera_pose, coverage_ck, coverage_spk, spacecraft_of, sun_direction
from pwm.io.spice_kernels import KernelError, spice_message

NO_KERNELS = "no_kernels"
"""The code of a product whose observer the kernels do not give (the module's docstring)."""

Windows = list[tuple[float, float]]
T = TypeVar("T")


class Refusal(Exception):
    """A product the kernels do not resolve: `code` (the module's docstring) and the reason as
    the message; instrument_id: its camera's NAIF id, once known and usable; named: for an
    unknown instrument, or one of an observer the kernels do not give, what the label names
    ('AMICA on HAYABUSA')."""

    def __init__(self, code: str, reason: str, *, instrument_id: int | None = None,
                 named: str | None = None) -> None:
        super().__init__(reason)
        self.code, self.instrument_id, self.named = code, instrument_id, named


@dataclass(frozen=True)
class KernelWindows:
    """ET coverage windows of the kernels in the pool: per body of its SPKs, per frame of its
    CKs."""

    spk: Mapping[int, Windows]
    ck: Mapping[int, Windows]


class Exposure(NamedTuple):
    """A product's exposure: start and stop (UTC), and in ET s when a leapseconds kernel is
    loaded (else None)."""

    start_utc: datetime
    stop_utc: datetime
    start_et: float | None
    stop_et: float | None


@dataclass(frozen=True)
class Resolved:
    """What a label names, resolved: the observer and the camera (NAIF ids), the camera of the
    product's array, the target (NAIF id) and its body-fixed frame, the mid-exposure ET."""

    observer: int
    instrument_id: int
    camera: Camera
    target: int
    body_frame: str
    et: float


def loaded_windows() -> KernelWindows:
    """The coverage windows of the SPKs and CKs loaded in the pool. A CK whose times the pool
    cannot read (no SCLK or LSK) gives none: its windows only name gaps in refusals."""
    spk: dict[int, Windows] = {}
    ck: dict[int, Windows] = {}
    for k in range(sp.ktotal("SPK")):
        path = sp.kdata(k, "SPK")[0]
        for body in sp.spkobj(path):
            spk.setdefault(int(body), []).extend(coverage_spk(path, int(body)))
    for k in range(sp.ktotal("CK")):
        path = sp.kdata(k, "CK")[0]
        try:
            windows = {int(frame): coverage_ck(path, int(frame)) for frame in sp.ckobj(path)}
        except sp.utils.exceptions.SpiceyError:
            continue
        for frame, found in windows.items():
            ck.setdefault(frame, []).extend(found)
    return KernelWindows(spk=spk, ck=ck)


def exposure(product: ImageLabel) -> Exposure:
    """The product's exposure times; ProductError (bad_time) where they cannot be read."""
    start, stop = exposure_times(product)
    if not sp.expool("DELTET/DELTA_AT"):
        return Exposure(start, stop, None, None)
    return Exposure(start, stop, *exposure_et(product))


def read_once(cache: dict[int, T | str], instrument_id: int, read: Callable[[int], T]) -> T:
    """`read(instrument_id)` (a camera from its kernels), once per instrument: a failure is kept
    as its reason and refused (instrument_kernel) each time."""
    if instrument_id not in cache:
        try:
            cache[instrument_id] = read(instrument_id)
        except KernelError as exc:
            cache[instrument_id] = f"instrument {instrument_id}: {exc}"
        except sp.utils.exceptions.SpiceyError as exc:
            cache[instrument_id] = f"instrument {instrument_id}: {spice_message(exc)}"
    found = cache[instrument_id]
    if isinstance(found, str):
        raise Refusal("instrument_kernel", found)
    return found


def resolve_label(product: ImageLabel, times: Exposure, *, windows: KernelWindows,
                  detector: Callable[[int], Camera], instrument: int | None = None,
                  target: tuple[int, str] | None = None, body_frame: str | None = None) -> Resolved:
    """What the product's label names, resolved against the pool, up to its geometry
    (`pose_and_sun`); Refusal with the first code that applies (the module's docstring).

    detector: the full detector's camera of an instrument (NAIF id), Refusal (instrument_kernel)
    where its kernel is unusable (`read_once`). Overrides for labels that do not say what the
    kernels need: `instrument` (NAIF id) is taken for every product whose label names no other
    camera of its spacecraft; `target` (NAIF id and frame) replaces the label's target, and
    `body_frame` its frame.
    """
    try:
        return _resolve(product, times, windows=windows, detector=detector, instrument=instrument,
                        target=target, body_frame=body_frame)
    except sp.utils.exceptions.SpiceyError as exc:  # kernels that resolve names but lack data
        raise Refusal("geometry", spice_message(exc)) from exc


def _resolve(product: ImageLabel, times: Exposure, *, windows: KernelWindows,
             detector: Callable[[int], Camera], instrument: int | None,
             target: tuple[int, str] | None, body_frame: str | None) -> Resolved:
    host = product.host_name or ""
    observer = observer_code(host) if instrument is None else spacecraft_of(instrument)
    if observer is None or observer not in windows.spk:
        raise Refusal(NO_KERNELS, "no kernels: " + (
            "the label names no host (spacecraft)" if observer is None and not host else
            f"observer {host!r} is not a body SPICE knows" if observer is None else
            f"the kernels hold no SPK for observer {host or body_name(observer)!r} ({observer})"),
            named=f"{product.instrument_name} on {host}" if product.instrument_name and host else None)
    named = instrument_code(product, observer)
    if instrument is not None and named is not None and named != instrument:
        raise Refusal("other_instrument", f"instrument {body_name(named)} ({named}) is not the chosen "
                      f"{body_name(instrument)} ({instrument})")
    instrument_id = instrument if instrument is not None else named
    if instrument_id is None:
        raise Refusal("unknown_instrument", f"instrument {product.instrument_name!r} of {host!r} is not an "
                      f"instrument of {observer} in the kernels", named=f"{product.instrument_name} on {host}")
    full = detector(instrument_id)
    if target is None:
        code, frame = target_frame(product.target_name)
        frame = body_frame or frame
        if code is None or frame is None:
            raise Refusal("unknown_target", f"target {product.target_name!r} is " + (
                "not a body SPICE knows" if code is None
                else f"{code}, which has no body-fixed frame in the kernels"), instrument_id=instrument_id)
        target = code, frame
    if times.start_et is None or times.stop_et is None:
        raise Refusal("geometry", "the kernels hold no leapseconds kernel (LSK)", instrument_id=instrument_id)
    et = (times.start_et + times.stop_et) / 2  # mid-exposure
    if not _covered(windows.spk[observer], et):
        raise Refusal("outside_coverage", f"{_when(et)} is outside the SPK coverage of observer {observer}: "
                      f"{_describe(windows.spk[observer])}", instrument_id=instrument_id)
    try:
        camera = full.subframe(first_sample=product.first_sample, first_line=product.first_line,
                               samples=product.samples, lines=product.lines)
    except ValueError as exc:
        raise Refusal("bad_dimensions", f"{body_name(instrument_id)}: {exc}", instrument_id=instrument_id) from exc
    return Resolved(observer=observer, instrument_id=instrument_id, camera=camera, target=target[0],
                    body_frame=target[1], et=et)


def pose_and_sun(image: Resolved, *, windows: KernelWindows) -> tuple[Pose, np.ndarray]:
    """The camera's pose and the Sun's direction (corrected by ABCORR) at the image's
    mid-exposure, in its target's body-fixed frame, from the pool (what
    pwm.geometry.view_geometry takes). Refusal outside_coverage where SPICE has no data then, or the spacecraft's CKs
    have none (named), geometry on another SPICE failure."""
    target = str(image.target)
    try:
        pose = camera_pose(et=image.et, instrument_id=image.instrument_id, target=target,
                           body_frame=image.body_frame)
        sun = sun_direction(et=image.et, target=target, body_frame=image.body_frame, abcorr=ABCORR)
    except sp.utils.exceptions.SpiceyError as exc:
        gaps = [f for f, w in windows.ck.items()
                if f <= -1000 and spacecraft_of(f) == image.observer and not _covered(w, image.et)]
        if exc.short in COVERAGE_ERRORS or gaps:
            detail = f"; no CK data then for frames {', '.join(map(str, sorted(gaps)))}" if gaps else ""
            raise Refusal("outside_coverage", f"no geometry at {_when(image.et)}{detail}: {spice_message(exc)}",
                          instrument_id=image.instrument_id) from exc
        raise Refusal("geometry", f"no geometry at {_when(image.et)}: {spice_message(exc)}",
                      instrument_id=image.instrument_id) from exc
    return pose, sun


def _covered(windows: Windows, et: float) -> bool:
    return any(start <= et <= stop for start, stop in windows)


def _when(et: float) -> str:
    return f"{sp.et2utc(et, 'ISOC', 3)} UTC (ET {et:.3f})"


def _describe(windows: Windows) -> str:
    first, last = min(w[0] for w in windows), max(w[1] for w in windows)
    return f"{len(windows)} window(s) spanning {sp.et2utc(first, 'ISOC', 3)} to {sp.et2utc(last, 'ISOC', 3)} UTC"
