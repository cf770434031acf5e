"""Read a downlink directory (PDS4 images + SPICE kernels with a meta-kernel, and/or ISIS cubes
with their SPICE attached) into views: image arrays with their camera, pose and Sun direction,
ready for refinement. The catalog (service.views) is the other source of the same views.

A cube's geometry is its own (pwm.io.isis): it needs no kernels, and a downlink of cubes only
needs no meta-kernel.

What each image is comes from its label and the kernels, resolved as ingest resolves it
(pwm.io.resolve): its observer, its instrument (each image gets its own instrument's camera, so
a downlink of several cameras works), its target and the target's body-fixed frame. A product
that cannot give a view is skipped with the resolver's code and reason (ingest's), and the rest
are read; only a downlink with no usable image at all is an error.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from pwm.camera import Camera, PoseCorrection
from pwm.io.isis import Cube, is_cube, read_cube, read_cube_pixels
from pwm.io.labels import (
    body_code,
    body_name,
    find_labels,
    frame_of,
    instrument_named,
    known_instruments,
    name_variants,
)
from pwm.io.pds4 import MAX_LABEL_BYTES, MAX_PIXELS, ImageProduct, ProductError, read_image_product
from pwm.io.resolve import (
    KernelWindows,
    Refusal,
    Resolved,
    exposure,
    loaded_windows,
    pose_and_sun,
    read_once,
    resolve_label,
)
from pwm.io.spice_geometry import camera_from_kernel
from pwm.io.spice_kernels import kernel_pool
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


@dataclass(frozen=True)
class _Image:
    """A product whose label resolved (PDS4: its geometry still to come from the kernels), or a
    cube read with its geometry: what its view needs before the pixels."""

    label: Path
    source: tuple[ImageProduct, Resolved] | Cube

    @property
    def target(self) -> tuple[int, str]:
        """NAIF id of the target and its body-fixed frame."""
        if isinstance(self.source, Cube):
            return self.source.target_id, self.source.body_frame
        return self.source[1].target, self.source[1].body_frame

    @property
    def target_name(self) -> str | None:
        return self.source.target_name if isinstance(self.source, Cube) else self.source[0].target_name

    @property
    def instrument(self) -> tuple[int, str]:
        if isinstance(self.source, Cube):
            return self.source.instrument_id, self.source.instrument_name
        return self.source[1].instrument_id, body_name(self.source[1].instrument_id)


def read_downlink(directory: str | Path, *, instrument: str | None = None, target: str | None = None,
                  body_frame: str | None = None,
                  corrections: Mapping[str, PoseCorrection] | None = None) -> DownlinkViews:
    """Every usable image of a downlink as a view, with geometry from its one meta-kernel (*.tm).

    Overrides, for labels that do not say what the kernels need: `instrument` (a NAIF name or
    id) reads only that camera's images, taking it for those whose label names no instrument
    the kernels know; `target` (a SPICE name or id) and `body_frame` replace the labels' target
    and its frame. Images of another target than most of them are skipped (other_target), so
    the views share one body-fixed frame. `corrections` (by view name, e.g. from `pwm spg`) are
    applied to the SPICE (or cube) poses. ValueError for a directory of PDS4 labels without
    exactly one meta-kernel, or an override the kernels do not know; NoUsableImages when no
    product gives a view.
    """
    directory = Path(directory)
    metakernels = sorted(directory.rglob("*.tm"))
    labels = find_labels(directory)
    if len(metakernels) > 1 or (not metakernels and not all(is_cube(label) for label in labels)):
        raise ValueError(f"{directory}: expected one meta-kernel (*.tm), found {len(metakernels)}")
    with kernel_pool(metakernels):
        chosen = None if instrument is None else instrument_named(instrument)
        forced = None if target is None else _target_override(target, body_frame)
        windows = loaded_windows()
        cameras: dict[int, Camera | str] = {}
        resolved: list[_Image] = []
        skipped: list[Skipped] = []
        named: set[str] = set()
        for label in labels:
            try:
                resolved.append(_resolve(label, root=directory, windows=windows, chosen=chosen, target=forced,
                                         body_frame=body_frame, cameras=cameras))
            except Refusal as exc:
                skipped.append(Skipped(str(label), exc.code, str(exc)))
                if exc.named is not None:
                    named.add(exc.named)
        if not resolved:
            raise NoUsableImages(_nothing_usable(directory, skipped, named))
        (main_target, frame), _ = Counter(r.target for r in resolved).most_common(1)[0]
        views, instruments = [], {}
        for image in resolved:
            try:
                if image.target != (main_target, frame):
                    raise Refusal("other_target", f"target {body_name(image.target[0])} ({image.target[1]}) is not "
                                  f"the downlink's main target {body_name(main_target)} ({frame}); "
                                  "--target chooses")
                views.append(_view(image, windows, corrections))
                naif_id, name = image.instrument
                instruments[naif_id] = name
            except ProductError as exc:  # a cube's core cut short
                skipped.append(Skipped(str(image.label), exc.code, str(exc)))
            except OSError as exc:
                skipped.append(Skipped(str(image.label), "unreadable", str(exc)))
            except Refusal as exc:
                skipped.append(Skipped(str(image.label), exc.code, str(exc)))
        skipped.sort(key=lambda s: s.path)
        if not views:
            raise NoUsableImages(_nothing_usable(directory, skipped, named))
        # SPICE's name for a body is the last the kernels gave it (Ryugu's FK ends with 1999JU3)
        named_as = next(r.target_name for r in resolved if r.target[0] == main_target)
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


def _resolve(label: Path, *, root: Path, windows: KernelWindows, chosen: int | None, target: tuple[int, str] | None,
             body_frame: str | None, cameras: dict[int, Camera | str]) -> _Image:
    """Read a product and resolve what its label names (pwm.io.resolve), or a cube's label and
    geometry (checked against the overrides); Refusal with the product's or the resolver's code
    otherwise."""
    try:
        if is_cube(label):
            return _Image(label=label, source=_chosen_cube(read_cube(label, max_label_bytes=MAX_LABEL_BYTES,
                                                                     max_pixels=MAX_PIXELS), chosen, target))
        product = read_image_product(label, root=root)
        times = exposure(product)
    except ProductError as exc:
        raise Refusal(exc.code, str(exc)) from exc
    except OSError as exc:  # e.g. a file gone or unreadable
        raise Refusal("unreadable", str(exc)) from exc
    except Refusal:
        raise
    except Exception as exc:  # one hostile product must not stop the rest
        raise Refusal("unreadable", f"{type(exc).__name__}: {exc}") from exc
    resolved = resolve_label(product, times, windows=windows, instrument=chosen, target=target, body_frame=body_frame,
                             detector=lambda instrument_id: read_once(cameras, instrument_id, camera_from_kernel))
    return _Image(label=label, source=(product, resolved))


def _chosen_cube(cube: Cube, instrument: int | None, target: tuple[int, str] | None) -> Cube:
    """The cube, unless the overrides choose another instrument or target (Refusal)."""
    if instrument is not None and cube.instrument_id != instrument:
        raise Refusal("other_instrument", f"instrument {cube.instrument_name} ({cube.instrument_id}) is not the "
                      f"chosen {body_name(instrument)} ({instrument})")
    if target is not None and (cube.target_id, cube.body_frame) != target:
        raise Refusal("other_target", f"target {cube.target_name} ({cube.target_id}, {cube.body_frame}) is not the "
                      f"chosen {body_name(target[0])} ({target[1]}): a cube's frame is the one spiceinit attached")
    return cube


def _view(image: _Image, windows: KernelWindows, corrections: Mapping[str, PoseCorrection] | None) -> View:
    if isinstance(image.source, Cube):
        cube = image.source
        data, camera, pose, sun, et = read_cube_pixels(cube), cube.camera, cube.pose, cube.sun, cube.et
    else:
        product, resolved = image.source
        pose, sun = pose_and_sun(resolved, windows=windows)
        data, camera, et = product.data, resolved.camera, resolved.et
    if corrections is not None and image.label.stem in corrections:
        pose = corrections[image.label.stem].apply(pose)
    return View(name=image.label.stem, image=data, camera=camera, pose=pose, sun=sun, et=et)


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
