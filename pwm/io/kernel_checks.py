"""Checks a SPICE kernel must pass before it is trusted, beyond SPICE opening it.

Binary kernels are read through: SPICE's object and coverage readers look only at a file's
summaries, so a kernel cut short after them would be accepted and fail every later geometry
(DAFBEGGTEND). `check_daf` and `check_das` hold every segment's data to lie within the file and
read its ends (SPK segments are evaluated). Text kernels that assign a body's or the time
system's constants are checked for type and sanity (`check_constants`), and one may not change a
constant another kernel already set (`redefinitions`), since geometry already catalogued was
computed with it: the constants come from SPICE's own parser, read from its pool by
`pool_constants`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import spiceypy as sp

from pwm.io.spice_kernels import KernelError, spice_message

_DAF_RECORD_BYTES = 1024
_DAS_RECORD_BYTES = 1024
_WORD_BYTES = 8
_POOL_ROOM = 1000  # names and values asked of SPICE's pool at a time

# The body and time constants that move geometry: a body's shape and rotation, and TDB - UTC.
CONSTANT_TEMPLATES = ("BODY*", "DELTET/*")
_BODY_CONSTANT = re.compile(
    r"BODY-?\d+_(RADII|POLE_RA|POLE_DEC|PM|LONG_AXIS|NUT_PREC_(RA|DEC|PM|ANGLES)"
    r"|CONSTANTS_REF_FRAME|CONSTANTS_JED_EPOCH)")
# TT - TAI is 32.184 s by definition; an LSK off it shifts every UTC -> ET conversion.
DELTA_T_A_S = 32.184
DELTA_T_A_TOLERANCE_S = 1e-3
_SAME = 1e-12  # relative: the same value written another way (32.184 and 3.2184D1)

Value = tuple[float, ...] | tuple[str, ...]


class KernelCheckError(KernelError):
    """A kernel refused by a check here: `code` says which (kernel_truncated, kernel_constants,
    kernel_redefines), the message why."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def is_constant(name: str) -> bool:
    """True for a pool variable that is a body's shape or rotation constant or a DELTET one."""
    return name.startswith("DELTET/") or _BODY_CONSTANT.fullmatch(name) is not None


# ---------------------------------------------------------------------------------------------
# Binary kernels read through


def check_daf(path: Path, *, evaluate_spk: bool = False) -> int:
    """Check every segment of a DAF (SPK, CK, binary PCK) lies within the file and its first
    and last words read; with evaluate_spk, each SPK segment is evaluated at its start, middle
    and end. Returns the number of segments; KernelCheckError (kernel_truncated) otherwise."""
    size = path.stat().st_size
    handle = sp.dafopr(str(path))
    try:
        nd, ni = sp.dafhsf(handle)
        count = 0
        for count, summary in enumerate(_daf_summaries(handle, nd, ni), 1):
            _daf_segment(path, handle, summary, (nd, ni), count, size=size,
                         evaluate_spk=evaluate_spk)
        return count
    finally:
        sp.dafcls(handle)


def _daf_summaries(handle: int, nd: int, ni: int) -> Iterator[np.ndarray]:
    sp.dafbfs(handle)
    size = nd + (ni + 1) // 2
    while sp.daffna():
        yield np.asarray(sp.dafgs(size), dtype=float)[:size]


def _daf_segment(path: Path, handle: int, summary: np.ndarray, counts: tuple[int, int], n: int,
                 *, size: int, evaluate_spk: bool) -> None:
    doubles, ints = sp.dafus(summary, *counts)
    begin, end = int(ints[-2]), int(ints[-1])  # the segment's first and last word
    if not 1 <= begin <= end or end * _WORD_BYTES > size:
        raise KernelCheckError("kernel_truncated", (
            f"{path.name}: segment {n}'s data (words {begin} to {end}, up to byte "
            f"{end * _WORD_BYTES}) is not within the file's {size} bytes"))
    _read(path, n, sp.dafgda, handle, begin, begin)
    _read(path, n, sp.dafgda, handle, end, end)
    if evaluate_spk:
        start, stop = float(doubles[0]), float(doubles[1])
        for et in (start, (start + stop) / 2, stop):
            _read(path, n, sp.spkpvn, handle, summary, et)


def _read(path: Path, segment: int, read: Callable[..., object], *args: Any) -> None:
    try:
        read(*args)
    except sp.utils.exceptions.SpiceyError as exc:
        raise KernelCheckError("kernel_truncated", f"{path.name}: segment {segment}'s data "
                               f"does not read: {spice_message(exc)}") from None


def check_das(path: Path) -> int:
    """Check a DSK (DAS): the file holds every record its file record counts, and each type-2
    segment's last vertex and plate read. Returns the number of segments; KernelCheckError
    (kernel_truncated) otherwise."""
    size = path.stat().st_size
    handle = sp.dasopr(str(path))
    try:
        free = int(sp.dashfs(handle)[4])  # the first record past the data
        if (free - 1) * _DAS_RECORD_BYTES > size:
            raise KernelCheckError("kernel_truncated", (
                f"{path.name}: its records run to byte {(free - 1) * _DAS_RECORD_BYTES}, past "
                f"the file's {size} bytes"))
        count = 0
        with sp.no_found_check():
            dla, found = sp.dlabfs(handle)
            while found:
                count += 1
                _dsk_segment(path, handle, dla, count)
                dla, found = sp.dlafns(handle, dla)
        return count
    finally:
        sp.dascls(handle)


def _dsk_segment(path: Path, handle: int, dla: object, n: int) -> None:
    descriptor = sp.dskgd(handle, dla)
    if descriptor.dtype != 2:  # only type 2 has readers in SPICE's toolkit
        return

    def last() -> None:
        vertices, plates = sp.dskz02(handle, dla)
        sp.dskv02(handle, dla, vertices, 1)
        sp.dskp02(handle, dla, plates, 1)
    _read(path, n, last)


# ---------------------------------------------------------------------------------------------
# Text kernels: body and time constants


def pool_constants() -> dict[str, Value]:
    """The body and time constants (is_constant) in SPICE's pool now, by name: numbers as
    floats, strings as strings, as the kernels that set them gave them."""
    values: dict[str, Value] = {}
    for name in (n for template in CONSTANT_TEMPLATES for n in _pool_names(template)):
        if is_constant(name):
            values[name] = _pool_value(name)
    return values


def _pool_names(template: str) -> list[str]:
    names: list[str] = []
    with sp.no_found_check():
        while (found := sp.gnpool(template, len(names), _POOL_ROOM))[1]:
            names.extend(found[0])
            if len(found[0]) < _POOL_ROOM:
                break
    return names


def _pool_value(name: str) -> Value:
    count, kind = sp.dtpool(name)[:2]
    if kind == "N":
        return tuple(float(v) for v in sp.gdpool(name, 0, count))
    return tuple(str(v) for v in sp.gcpool(name, 0, count))


def check_constants(values: Mapping[str, Value]) -> None:
    """KernelCheckError (kernel_constants) naming the first constant of the wrong type or
    outside what it can be: numbers where numbers are due, all finite; radii three positive
    numbers; DELTET's DELTA_T_A within DELTA_T_A_TOLERANCE_S of 32.184 s, K and EB one number,
    M two, DELTA_AT pairs."""
    for name, value in sorted(values.items()):
        if not all(isinstance(v, float) for v in value):
            raise KernelCheckError("kernel_constants", f"{name} = {_show(value)}: numbers are "
                                   "due, not strings")
        if not all(math.isfinite(float(v)) for v in value):
            raise KernelCheckError("kernel_constants", f"{name} = {_show(value)}: not finite")
        if not _sane(name, tuple(float(v) for v in value)):
            raise KernelCheckError("kernel_constants", f"{name} = {_show(value)}: "
                                   f"{_expected(name)}")


def _sane(name: str, value: tuple[float, ...]) -> bool:
    if name.endswith("_RADII"):
        return len(value) == 3 and all(v > 0 for v in value)
    if name.endswith(("_POLE_RA", "_POLE_DEC", "_PM")):
        return 1 <= len(value) <= 3
    if name == "DELTET/DELTA_T_A":
        return len(value) == 1 and abs(value[0] - DELTA_T_A_S) <= DELTA_T_A_TOLERANCE_S
    if name in ("DELTET/K", "DELTET/EB"):
        return len(value) == 1
    if name == "DELTET/M":
        return len(value) == 2
    if name == "DELTET/DELTA_AT":
        return len(value) >= 2 and len(value) % 2 == 0
    return len(value) >= 1


def _expected(name: str) -> str:
    if name.endswith("_RADII"):
        return "three positive numbers are due (km)"
    if name.endswith(("_POLE_RA", "_POLE_DEC", "_PM")):
        return "one to three numbers are due (a polynomial in time)"
    if name == "DELTET/DELTA_T_A":
        return f"TT - TAI is {DELTA_T_A_S} s (within {DELTA_T_A_TOLERANCE_S} s)"
    if name in ("DELTET/K", "DELTET/EB"):
        return "one number is due"
    if name == "DELTET/M":
        return "two numbers are due"
    if name == "DELTET/DELTA_AT":
        return "pairs of leap-second count and date are due"
    return "at least one number is due"


def redefinitions(before: Mapping[str, Value], after: Mapping[str, Value]) -> list[str]:
    """Each constant set in `before` that `after` gives another value, or removes, as
    'NAME = new (was old)'; the same values written another way are the same. A leap-second
    table (DELTET/DELTA_AT) may grow: its catalogued leap seconds kept, later ones added."""
    changed = []
    for name, old in sorted(before.items()):
        new = after.get(name)
        if new is not None and (_same(old, new) or (
                name == "DELTET/DELTA_AT" and _same(old, new[:len(old)]))):
            continue
        changed.append(f"{name} = {'(removed)' if new is None else _show(new)} (was {_show(old)})")
    return changed


def _same(a: Value, b: Value) -> bool:
    if len(a) != len(b):
        return False
    return all(math.isclose(x, y, rel_tol=_SAME, abs_tol=0.0)
               if isinstance(x, float) and isinstance(y, float) else x == y
               for x, y in zip(a, b, strict=True))


def _show(value: Value, most: int = 6) -> str:
    shown = " ".join(repr(v) if isinstance(v, str) else f"{v:.10g}" for v in value[:most])
    return f"( {shown}{' ...' if len(value) > most else ''} )"
