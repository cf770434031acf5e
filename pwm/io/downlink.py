"""Read a downlink directory (PDS4 images + SPICE kernels with a meta-kernel) into views: image
arrays with their camera, pose and Sun direction, ready for refinement. The catalog
(service.views) is the other source of the same views.

What each image is comes from its label and the kernels, by the rules ingest uses
(pwm.io.labels): its observer, its instrument (each image gets its own instrument's camera, so
a downlink of several cameras works), its target and the target's body-fixed frame. A product
that cannot give a view is skipped with the code and reason ingest would reject it with, and
the rest are read; only a downlink with no usable image at all is an error.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import spiceypy as sp

from pwm.camera import Camera, PoseCorrection
from pwm.io.labels import (
    COVERAGE_ERRORS,
    body_code,
    body_name,
    exposure_et,
    exposure_times,
    find_labels,
    frame_of,
    instrument_code,
    instrument_named,
    known_instruments,
    name_variants,
    observer_code,
    target_frame,
)
from pwm.io.pds4 import ImageProduct, ProductError, read_image_product
from pwm.io.spice_geometry import camera_from_kernel, camera_pose, spacecraft_of, sun_direction
from pwm.io.spice_kernels import KernelError, kernel_pool, spice_message
from pwm.views import View


class NoUsableImages(ValueError):
    """A downlink none of whose products gives a view; the message says why."""


@dataclass(frozen=True)
class Skipped:
    """A product that gave no view: its label, the code and the reason (ingest's codes)."""

    path: str
    code: str
    reason: str


@dataclass
class DownlinkViews:
    """The views of a downlink (in label order), the products skipped, and the target (as its
    labels name it, and its NAIF id) and body-fixed frame the views' poses and Sun directions are
    in; instruments: NAIF id -> name of the cameras the views come from."""

    views: list[View]
    skipped: list[Skipped]
    target: str
    target_id: int
    body_frame: str
    instruments: dict[int, str] = field(default_factory=dict)


class _Skip(Exception):
    """named: for an unknown instrument, what the label names ('AMICA on HAYABUSA')."""

    def __init__(self, code: str, reason: str, named: str | None = None) -> None:
        super().__init__(reason)
        self.code, self.named = code, named


@dataclass(frozen=True)
class _Image:
    """A product whose label resolved: what its view needs before the geometry."""

    label: Path
    product: ImageProduct
    et: float
    instrument_id: int
    camera: Camera
    target: int
    body_frame: str


def read_downlink(directory: str | Path, *, instrument: str | None = None, target: str | None = None,
                  body_frame: str | None = None,
                  corrections: Mapping[str, PoseCorrection] | None = None) -> DownlinkViews:
    """Every usable image of a downlink as a view, with geometry from its one meta-kernel (*.tm).

    Overrides, for labels that do not say what the kernels need: `instrument` (a NAIF name or
    id) reads only that camera's images, taking it for those whose label names no instrument
    the kernels know; `target` (a SPICE name or id) and `body_frame` replace the labels' target
    and its frame. Images of another target than most of them are skipped (other_target), so
    the views share one body-fixed frame. `corrections` (by view name, e.g. from `pwm spg`) are
    applied to the SPICE poses. ValueError for a directory without exactly one meta-kernel or an
    override the kernels do not know; NoUsableImages when no product gives a view.
    """
    directory = Path(directory)
    metakernels = sorted(directory.rglob("*.tm"))
    if len(metakernels) != 1:
        raise ValueError(f"{directory}: expected one meta-kernel (*.tm), found {len(metakernels)}")
    with kernel_pool(metakernels):
        chosen = None if instrument is None else instrument_named(instrument)
        forced = None if target is None else _target_override(target, body_frame)
        cameras: dict[int, Camera | str] = {}
        resolved: list[_Image] = []
        skipped: list[Skipped] = []
        named: set[str] = set()
        for label in find_labels(directory):
            try:
                resolved.append(_resolve(label, root=directory, chosen=chosen, target=forced, body_frame=body_frame,
                                         cameras=cameras))
            except _Skip as exc:
                skipped.append(Skipped(str(label), exc.code, str(exc)))
                if exc.named is not None:
                    named.add(exc.named)
        if not resolved:
            raise NoUsableImages(_nothing_usable(directory, skipped, named))
        (main_target, frame), _ = Counter((r.target, r.body_frame) for r in resolved).most_common(1)[0]
        views, instruments = [], {}
        for image in resolved:
            try:
                if (image.target, image.body_frame) != (main_target, frame):
                    raise _Skip("other_target", f"target {body_name(image.target)} ({image.body_frame}) is not "
                                f"the downlink's main target {body_name(main_target)} ({frame}); "
                                "--target chooses")
                views.append(_view(image, corrections))
                instruments[image.instrument_id] = body_name(image.instrument_id)
            except _Skip as exc:
                skipped.append(Skipped(str(image.label), exc.code, str(exc)))
        skipped.sort(key=lambda s: s.path)
        if not views:
            raise NoUsableImages(_nothing_usable(directory, skipped, named))
        # SPICE's name for a body is the last the kernels gave it (Ryugu's FK ends with 1999JU3)
        named_as = next(r.product.target_name for r in resolved if r.target == main_target)
        return DownlinkViews(views=views, skipped=skipped, target=named_as or body_name(main_target),
                             target_id=main_target, body_frame=frame, instruments=instruments)


def _target_override(target: str, body_frame: str | None) -> tuple[int, str]:
    code = body_code(name_variants(target))
    if code is None:
        raise ValueError(f"target {target!r} is not a body the kernels know")
    frame = body_frame or frame_of(code)
    if frame is None:
        raise ValueError(f"target {target!r} ({code}) has no body-fixed frame in the kernels: give --body-frame")
    return code, frame


def _resolve(label: Path, *, root: Path, chosen: int | None, target: tuple[int, str] | None, body_frame: str | None,
             cameras: dict[int, Camera | str]) -> _Image:
    """Read a product and resolve what its label names; _Skip with ingest's code otherwise."""
    try:
        product = read_image_product(label, root=root)
        exposure_times(product)
        start_et, stop_et = exposure_et(product)
    except ProductError as exc:
        raise _Skip(exc.code, str(exc)) from exc
    except OSError as exc:  # e.g. a file gone or unreadable
        raise _Skip("unreadable", str(exc)) from exc
    except Exception as exc:  # one hostile product must not stop the rest
        raise _Skip("unreadable", f"{type(exc).__name__}: {exc}") from exc
    instrument_id = _instrument(product, chosen)
    camera = _camera(instrument_id, cameras)
    if target is None:
        code, frame = target_frame(product.target_name)
        frame = body_frame or frame
        if code is None or frame is None:
            raise _Skip("unknown_target", f"target {product.target_name!r} is " + (
                "not a body SPICE knows" if code is None else f"{code}, which has no body-fixed frame in the kernels"))
        target = code, frame
    try:
        camera = camera.subframe(first_sample=product.first_sample, first_line=product.first_line,
                                 samples=product.samples, lines=product.lines)
    except ValueError as exc:
        raise _Skip("bad_dimensions", f"{body_name(instrument_id)}: {exc}") from exc
    return _Image(label=label, product=product, et=(start_et + stop_et) / 2, instrument_id=instrument_id,
                  camera=camera, target=target[0], body_frame=target[1])


def _instrument(product: ImageProduct, chosen: int | None) -> int:
    """The image's instrument: the label's, or `chosen` (which then also filters)."""
    host = product.host_name
    if chosen is not None:
        named = instrument_code(product, spacecraft_of(chosen))
        if named is not None and named != chosen:
            raise _Skip("other_instrument", f"instrument {body_name(named)} ({named}) is not the chosen "
                        f"{body_name(chosen)} ({chosen})")
        return chosen
    observer = observer_code(host)
    if observer is None:
        raise _Skip("no_kernels", "no kernels: " + ("the label names no host (spacecraft)" if not host
                                                    else f"observer {host!r} is not a body SPICE knows"))
    code = instrument_code(product, observer)
    if code is None:
        raise _Skip("unknown_instrument", f"instrument {product.instrument_name!r} of {host!r} is not an "
                    f"instrument of {observer} in the downlink's kernels", f"{product.instrument_name} on {host}")
    return code


def _camera(instrument_id: int, cameras: dict[int, Camera | str]) -> Camera:
    """The detector of `instrument_id` from its IK, read once (_Skip if unusable)."""
    if instrument_id not in cameras:
        try:
            cameras[instrument_id] = camera_from_kernel(instrument_id)
        except KernelError as exc:
            cameras[instrument_id] = f"instrument {instrument_id}: {exc}"
        except sp.utils.exceptions.SpiceyError as exc:
            cameras[instrument_id] = f"instrument {instrument_id}: {spice_message(exc)}"
    found = cameras[instrument_id]
    if isinstance(found, str):
        raise _Skip("instrument_kernel", found)
    return found


def _view(image: _Image, corrections: Mapping[str, PoseCorrection] | None) -> View:
    target = str(image.target)
    when = f"{sp.et2utc(image.et, 'ISOC', 3)} UTC (ET {image.et:.3f})"
    try:
        pose = camera_pose(et=image.et, instrument_id=image.instrument_id, target=target,
                           body_frame=image.body_frame)
        sun = sun_direction(et=image.et, target=target, body_frame=image.body_frame)
    except sp.utils.exceptions.SpiceyError as exc:
        code = "outside_coverage" if exc.short in COVERAGE_ERRORS else "geometry"
        raise _Skip(code, f"no geometry at {when}: {spice_message(exc)}") from exc
    if corrections is not None and image.label.stem in corrections:
        pose = corrections[image.label.stem].apply(pose)
    return View(name=image.label.stem, image=image.product.data, camera=image.camera, pose=pose, sun=sun,
                et=image.et)


def _nothing_usable(directory: Path, skipped: list[Skipped], named: set[str]) -> str:
    """Why a downlink gave no view: the codes counted, and for unknown instruments what the
    labels name and what the kernels define (the pool must be loaded)."""
    codes = ", ".join(f"{n} {code}" for code, n in Counter(s.code for s in skipped).most_common())
    message = f"{directory}: no usable images ({len(skipped)} products skipped: {codes or 'none found'})"
    if named:
        defined = ", ".join(f"{n} ({c})" for c, n in known_instruments()) or "no instrument with a field of view"
        message += (f"; no images of a known instrument: the labels name {', '.join(sorted(named))}; "
                    f"the kernels define {defined}")
    return message
