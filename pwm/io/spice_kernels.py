"""SPICE kernels: write SPK (type 13) and CK (type 3) files and meta-kernels; load them.

spiceypy keeps one kernel pool per process, so load kernels through `kernel_pool`, which
clears the pool on entry and on exit. Writing a CK needs the LSK and the spacecraft's SCLK
loaded (epochs are converted to encoded SCLK), and the FK when the reference frame is not
built in.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import spiceypy as sp

import pwm
from pwm.knowledge import KnowledgeErrors, format_knowledge_errors, parse_knowledge_errors

BUNDLED_DIR = Path(__file__).resolve().parent.parent / "data" / "spice"
HERMITE_DEGREE = 7  # 4 states per window: smooth trajectories sampled every few minutes
_COMMENT = f"Written by pwm {pwm.__version__} (pwm.io.spice_kernels)."
_CHUNK = 60  # kernel-pool strings are cut at 80 characters: longer values use '+' continuation
_MK_VARIABLES = ("PATH_VALUES", "PATH_SYMBOLS", "KERNELS_TO_LOAD")
# The most kernels one meta-kernel may name: SPICE's pool holds 15000 string values in all
# (szpool MAXLIN), which one meta-kernel's list would otherwise fill (KERNELPOOLFULL), leaving
# no room for the FK and IK. Real ones name hundreds. service.settings.Settings overrides.
MAX_METAKERNEL_ENTRIES = 5000
_SCAN_CHUNK = 1 << 20


class KernelError(RuntimeError):
    """A kernel set that cannot be used: missing files or inconsistent instrument keywords."""

    def __init__(self, message: str, missing: Sequence[Path] = ()) -> None:
        super().__init__(message)
        self.missing = list(missing)


@dataclass(frozen=True)
class SpkSegment:
    """States of `body` relative to `center` in `frame`.

    epochs: (n,) ET seconds, strictly increasing; states: (n, 6) km and km/s.
    """

    body: int
    center: int
    epochs: np.ndarray
    states: np.ndarray
    frame: str = "J2000"


@dataclass(frozen=True)
class CkSegment:
    """Attitude of frame `frame_id` relative to `reference`, clocked by SCLK `sclk_id`.

    epochs: (n,) ET seconds, strictly increasing. rotations: (n, 3, 3) matrices taking
    `reference` vectors into the frame (the sense of pxform(reference, frame)).
    angular_velocities: (n, 3) rad/s, of the frame relative to `reference`, in `reference`
    coordinates. interval_starts: ET of the first epoch of each interpolation interval (one per
    observation window); SPICE interpolates only between epochs of the same interval.
    """

    frame_id: int
    sclk_id: int
    epochs: np.ndarray
    rotations: np.ndarray
    angular_velocities: np.ndarray
    interval_starts: Sequence[float]
    reference: str = "J2000"


def spice_message(exc: sp.utils.exceptions.SpiceyError) -> str:
    """SPICE's short and long error message on one line."""
    return f"{exc.short}: {' '.join(exc.long.split())}" if exc.short else " ".join(str(exc).split())


def bundled_kernels() -> dict[str, Path]:
    """The generic and OSIRIS-REx kernels shipped in pwm/data/spice, by file name."""
    return {p.name: p for p in sorted(BUNDLED_DIR.iterdir()) if p.is_file()}


def write_spk(path: str | Path, *, segments: Sequence[SpkSegment], comments: Sequence[str] = ()) -> None:
    """Write an SPK of Hermite type-13 segments (overwrites `path`), with `comments` (lines)."""
    path = Path(path)
    path.unlink(missing_ok=True)
    handle = sp.spkopn(str(path), "pwm SPK", 1024)
    try:
        sp.dafac(handle, [_COMMENT, *comments])
        for seg in segments:
            epochs = np.ascontiguousarray(seg.epochs, dtype=float)
            states = np.ascontiguousarray(seg.states, dtype=float).reshape(len(epochs), 6)
            degree = min(HERMITE_DEGREE, 2 * len(epochs) - 1)
            sp.spkw13(handle, seg.body, seg.center, seg.frame, epochs[0], epochs[-1],
                      f"pwm {seg.body} wrt {seg.center}", degree, len(epochs), states, epochs)
    finally:
        sp.spkcls(handle)


def write_ck(path: str | Path, *, segments: Sequence[CkSegment], comments: Sequence[str] = ()) -> None:
    """Write a CK of type-3 segments with angular velocity (overwrites `path`), with `comments`.

    Quaternions are SPICE's (scalar first, m2q of the C-matrix reference -> frame).
    """
    path = Path(path)
    path.unlink(missing_ok=True)
    handle = sp.ckopn(str(path), "pwm CK", 1024)
    try:
        sp.dafac(handle, [_COMMENT, *comments])
        for seg in segments:
            epochs = np.asarray(seg.epochs, dtype=float)
            sclk = np.array([sp.sce2c(seg.sclk_id, et) for et in epochs])
            quats = np.array([sp.m2q(r) for r in np.asarray(seg.rotations, dtype=float)])
            starts = sclk[[_epoch_index(epochs, et) for et in seg.interval_starts]]
            sp.ckw03(handle, sclk[0], sclk[-1], seg.frame_id, seg.reference, True,
                     f"pwm {seg.frame_id} wrt {seg.reference}", len(sclk), sclk, quats,
                     np.ascontiguousarray(seg.angular_velocities, dtype=float), len(starts), starts)
    finally:
        sp.ckcls(handle)


KNOWLEDGE_KEYWORD = "PWM_POSE_KNOWLEDGE"
"""A line `PWM_POSE_KNOWLEDGE = TEXT` in an SPK's or CK's comment area states the 1-sigma
knowledge of the poses it carries (TEXT as pwm.knowledge.parse_knowledge_errors reads it)."""
MAX_COMMENT_LINES = 10_000  # a kernel's comment area is read this far for a statement


def knowledge_comment(errors: KnowledgeErrors) -> str:
    """The comment line that states `errors` as a kernel's pose knowledge."""
    return f"{KNOWLEDGE_KEYWORD} = {format_knowledge_errors(errors)}"


def stated_knowledge(path: str | Path) -> KnowledgeErrors | None:
    """The pose knowledge stated in the comment area of a DAF kernel (SPK, CK; see
    KNOWLEDGE_KEYWORD), or None where it states none. KernelError for a statement that does not
    parse or a file SPICE cannot open as a DAF."""
    try:
        handle = sp.dafopr(str(path))
    except sp.utils.exceptions.SpiceyError as exc:
        raise KernelError(f"{Path(path).name}: {spice_message(exc)}") from None
    try:
        lines: list[str] = []
        while len(lines) < MAX_COMMENT_LINES:
            n, chunk, done = sp.dafec(handle, 100, 1000)
            lines.extend(chunk[:n])
            if done:
                break
    finally:
        sp.dafcls(handle)
    for line in lines:
        key, sep, value = line.partition("=")
        if sep and key.strip() == KNOWLEDGE_KEYWORD:
            try:
                return parse_knowledge_errors(value)
            except ValueError as exc:
                raise KernelError(f"{Path(path).name}: {KNOWLEDGE_KEYWORD}: {exc}") from None
    return None


def write_sclk(path: str | Path, *, spacecraft: int, epoch_et: float) -> None:
    """Write a type-1 SCLK kernel for `spacecraft` (its NAIF id, negative): one partition, a
    clock of seconds (65536 ticks each) counting from 0 at `epoch_et` (TDB s past J2000) at
    exactly one second per second of TDB. For simulated downlinks of a mission whose real clock
    kernel is not at hand."""
    if spacecraft >= 0:
        raise ValueError(f"{spacecraft} is not a spacecraft NAIF id")
    n = -spacecraft
    written = (datetime(2000, 1, 1, 12) + timedelta(seconds=epoch_et)).date()  # an identifier only
    lines = ["KPL/SCLK", "", _COMMENT, "", "\\begindata", "",
             f"SCLK_KERNEL_ID = ( @{written.isoformat()} )",
             f"SCLK_DATA_TYPE_{n} = ( 1 )",
             f"SCLK01_TIME_SYSTEM_{n} = ( 1 )",  # TDB
             f"SCLK01_N_FIELDS_{n} = ( 2 )",
             f"SCLK01_MODULI_{n} = ( 4294967296 65536 )",
             f"SCLK01_OFFSETS_{n} = ( 0 0 )",
             f"SCLK01_OUTPUT_DELIM_{n} = ( 1 )",
             f"SCLK_PARTITION_START_{n} = ( 0.0 )",
             f"SCLK_PARTITION_END_{n} = ( {4294967296 * 65536 - 1:.13E} )",
             f"SCLK01_COEFFICIENTS_{n} = ( 0.0 {epoch_et:.6f} 1.0 )", "", "\\begintext", ""]
    Path(path).write_text("\n".join(lines))


def _epoch_index(epochs: np.ndarray, et: float) -> int:
    matches = np.flatnonzero(epochs == et)
    if matches.size == 0:
        raise ValueError(f"interval start {et!r} is not one of the segment epochs")
    return int(matches[0])


def write_metakernel(path: str | Path, *, kernels: Sequence[str | Path]) -> None:
    """Write a KPL/MK loading `kernels` in order, by directories relative to the meta-kernel's
    own, as pwm reads them (metakernel_files): a copied downlink then names its own kernels,
    not the original's. (SPICE's furnsh reads relative PATH_VALUES against the working
    directory: load it through kernel_pool, or from the meta-kernel's directory.)"""
    path = Path(path)
    here = Path(os.path.abspath(path)).parent
    files = [Path(os.path.abspath(k)) for k in kernels]
    if any("'" in str(f) for f in files):
        raise ValueError("kernel paths with a quote character cannot be written to a meta-kernel")
    dirs = list(dict.fromkeys(f.parent for f in files))
    symbols = [f"D{i}" for i in range(len(dirs))]
    names = [f"${symbols[dirs.index(f.parent)]}/{f.name}" for f in files]
    lines = ["KPL/MK", "", _COMMENT, "", "\\begindata", ""]
    lines += _assignment("PATH_VALUES", [os.path.relpath(d, here) for d in dirs])
    lines += _assignment("PATH_SYMBOLS", symbols)
    lines += _assignment("KERNELS_TO_LOAD", names)
    lines += ["\\begintext", ""]
    path.write_text("\n".join(lines))


def _assignment(name: str, values: Sequence[str]) -> list[str]:
    pieces = [f"'{piece}'" for value in values for piece in _continued(value)]
    return [f"   {name} = (", *(f"      {p}" for p in pieces), "   )", ""]


def _continued(value: str) -> list[str]:
    """Split a string into pool-sized pieces, each but the last ending in the '+' continuation."""
    pieces = []
    while len(value) > _CHUNK:
        cut = _CHUNK
        while value[cut - 1] == "+":  # a piece ending in a literal '+' would read as a continuation
            cut -= 1
        pieces.append(value[:cut] + "+")
        value = value[cut:]
    return [*pieces, value]


def _quoted_values(path: Path) -> int:
    """How many quoted strings a text kernel holds at most (its quote characters over two),
    counted in chunks without holding the file."""
    quotes = 0
    with open(path, "rb") as fh:
        while chunk := fh.read(_SCAN_CHUNK):
            quotes += chunk.count(b"'")
    return quotes // 2


def metakernel_files(path: str | Path, *, max_entries: int = MAX_METAKERNEL_ENTRIES) -> list[Path]:
    """The files a meta-kernel names, in order; relative paths resolved against its directory.

    Parsed by SPICE itself (ldpool); its path variables are then removed from the pool, as
    furnsh does. KernelError, before SPICE reads it, for a meta-kernel whose strings could
    name more than max_entries kernels.
    """
    mk = Path(os.path.abspath(path))
    if (strings := _quoted_values(mk)) > max_entries:
        raise KernelError(f"{mk.name} holds {strings} strings, more than the {max_entries} "
                          "kernels a meta-kernel may name (kernel pool room)")
    sp.ldpool(str(mk))
    try:
        values = [_pool_string(name) for name in _MK_VARIABLES]
    finally:
        for name in _MK_VARIABLES:
            if sp.expool(name):
                sp.dvpool(name)
    dirs = {sym: os.path.join(mk.parent, val) for sym, val in zip(values[1], values[0], strict=False)}

    def substitute(match: re.Match) -> str:
        if match.group(1) not in dirs:
            raise KernelError(f"{mk}: unknown path symbol ${match.group(1)}")
        return dirs[match.group(1)]

    names = [re.sub(r"\$(\w+)", substitute, name) for name in values[2]]
    return [Path(os.path.normpath(os.path.join(mk.parent, n))) for n in names]


def _pool_string(name: str) -> list[str]:
    """The strings of a pool variable, continued pieces joined (SPICE's stpool)."""
    strings: list[str] = []
    with sp.no_found_check():
        while (found := sp.stpool(name, len(strings), "+"))[2]:
            strings.append(found[0])
    return strings


def load_metakernel(path: str | Path) -> list[Path]:
    """Load the kernels a meta-kernel names once all exist; returns them in load order.

    Raises KernelError listing every missing file before any kernel is loaded.
    """
    files = metakernel_files(path)
    missing = [f for f in files if not f.is_file()]
    if missing:
        listing = "\n  ".join(str(f) for f in missing)
        raise KernelError(f"{path}: {len(missing)} of {len(files)} kernels missing:\n  {listing}",
                          missing)
    for f in files:
        sp.furnsh(str(f))
    return files


@contextlib.contextmanager
def kernel_pool(paths: Iterable[str | Path]) -> Iterator[None]:
    """Clear the kernel pool, load `paths` (meta-kernels through load_metakernel), clear on exit."""
    sp.kclear()
    try:
        for p in paths:
            if sp.getfat(str(p)) == ("KPL", "MK"):
                load_metakernel(p)
            else:
                sp.furnsh(str(p))
        yield
    finally:
        sp.kclear()
