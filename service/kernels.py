"""The kernel registry: a downlink's SPICE kernel files catalogued once per content (sha256),
with the time windows their SPKs (per body) and CKs (per frame) cover; and the catalog's kernel
set for loading.

A file is a kernel when its extension is a SPICE one or it starts like a kernel (KPL/, DAF/,
DAS/). Its kind comes from SPICE's getfat, else from the extension. Text kernels are loaded to
check them (and because CK coverage needs the LSK and SCLK); binary ones are opened by SPICE's
object readers; a file SPICE refuses is recorded rejected with SPICE's message. Meta-kernels are
registered, and the files they name (relative PATH_VALUES resolved against the meta-kernel, as
SPICE does) are registered too, ahead of the other files of their kind so that their order
carries over into load order. Rejected kernels are judged again when seen again: a CK refused for
want of its SCLK is accepted once the SCLK has arrived.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import spiceypy as sp
from sqlalchemy import select
from sqlalchemy.orm import Session

from pwm.io.pds4 import file_sha256
from pwm.io.spice_geometry import coverage_ck, coverage_spk
from pwm.io.spice_kernels import KernelError, kernel_pool, metakernel_files, spice_message
from service.models import Acceptance, Kernel, KernelCoverage, KernelKind

KIND_BY_EXTENSION = {
    ".tls": KernelKind.LSK, ".tsc": KernelKind.SCLK, ".tpc": KernelKind.PCK,
    ".bpc": KernelKind.PCK, ".tf": KernelKind.FK, ".ti": KernelKind.IK, ".bsp": KernelKind.SPK,
    ".bc": KernelKind.CK, ".tm": KernelKind.MK, ".bds": KernelKind.DSK,
}
KIND_BY_FILE_TYPE = {
    ("DAF", "SPK"): KernelKind.SPK, ("DAF", "CK"): KernelKind.CK, ("DAF", "PCK"): KernelKind.PCK,
    ("DAS", "DSK"): KernelKind.DSK, ("KPL", "LSK"): KernelKind.LSK,
    ("KPL", "SCLK"): KernelKind.SCLK, ("KPL", "PCK"): KernelKind.PCK,
    ("KPL", "FK"): KernelKind.FK, ("KPL", "IK"): KernelKind.IK, ("KPL", "MK"): KernelKind.MK,
}
# What the geometry needs, in the order SPICE wants it (time, clocks, bodies, frames, instruments,
# then ephemerides and attitude); meta-kernels and DSKs are catalogued but not loaded.
LOAD_ORDER = (KernelKind.LSK, KernelKind.SCLK, KernelKind.PCK, KernelKind.FK, KernelKind.IK,
              KernelKind.SPK, KernelKind.CK)
_REGISTER_ORDER = (KernelKind.MK, *LOAD_ORDER, KernelKind.DSK)
_KERNEL_HEADERS = (b"KPL/", b"DAF/", b"DAS/")


@dataclass(frozen=True)
class KernelOutcome:
    """What registering one file did: result is accepted, rejected or unchanged; reason says
    why a file was rejected (also when unchanged)."""

    path: Path
    kind: KernelKind | None
    result: str
    reason: str | None = None


def et_to_datetime(et: float) -> datetime:
    """ET (TDB s past J2000) as a timezone-aware UTC datetime, to the microsecond (LSK loaded).

    A time inside a leap second (23:59:60.x) is given as the first instant of the next day.
    """
    stamp = sp.et2utc(et, "ISOC", 6)
    leap = stamp[17:19] == "60"
    parsed = datetime.fromisoformat(stamp[:17] + "59" + stamp[19:] if leap else stamp)
    return (parsed.replace(second=0, microsecond=0) + timedelta(minutes=1) if leap
            else parsed).replace(tzinfo=UTC)


def is_kernel_file(path: Path) -> bool:
    """True for a SPICE kernel extension, or a file starting like a text or binary kernel."""
    if path.suffix.lower() in KIND_BY_EXTENSION:
        return True
    with open(path, "rb") as fh:
        return fh.read(4) in _KERNEL_HEADERS


def kernel_kind(path: Path) -> KernelKind | None:
    """The kind SPICE's getfat reports, else the one the extension implies (None if neither)."""
    try:
        architecture, file_type = sp.getfat(str(path))
        by_type = KIND_BY_FILE_TYPE.get((architecture, file_type))
    except sp.utils.exceptions.SpiceyError:
        by_type = None
    return by_type or KIND_BY_EXTENSION.get(path.suffix.lower())


def _windows(path: Path, kind: KernelKind) -> dict[int, list[tuple[float, float]]]:
    """Check a kernel with SPICE and return its coverage windows (ET) per NAIF id.

    Text kernels are loaded into the current pool; raises SpiceyError or KernelError.
    """
    if kind is KernelKind.SPK:
        return {int(body): coverage_spk(path, int(body)) for body in sp.spkobj(str(path))}
    if kind is KernelKind.CK:
        return {int(frame): coverage_ck(path, int(frame)) for frame in sp.ckobj(str(path))}
    if kind is KernelKind.DSK:
        sp.dskobj(str(path))
    elif kind is KernelKind.MK:
        missing = [f for f in metakernel_files(path) if not f.is_file()]
        if missing:
            raise KernelError(f"{len(missing)} kernels it names are missing: "
                              + ", ".join(str(f) for f in missing), missing)
    elif kind is KernelKind.PCK and path.suffix.lower() == ".bpc":
        # furnsh would take an unreadable binary file for a text kernel without data.
        sp.pckfrm(str(path), sp.cell_int(1000))
    else:
        sp.furnsh(str(path))
    return {}


def _coverage_rows(windows: dict[int, list[tuple[float, float]]]) -> list[KernelCoverage]:
    return [KernelCoverage(naif_id=naif_id, start_et=start, stop_et=stop,
                           start_utc=et_to_datetime(start), stop_utc=et_to_datetime(stop))
            for naif_id, spans in windows.items() for start, stop in spans]


def _candidates(directory: Path) -> list[Path]:
    """Kernel files under `directory` and the files its meta-kernels name, in registration
    order: by kind, and within a kind meta-kernel order first, then path order."""
    found = [p for p in sorted(directory.rglob("*")) if p.is_file() and is_kernel_file(p)]
    named: list[Path] = []
    for mk in (p for p in found if kernel_kind(p) is KernelKind.MK):
        try:
            named += [f for f in metakernel_files(mk) if f.is_file()]
        except (sp.utils.exceptions.SpiceyError, KernelError):
            pass  # the meta-kernel itself is rejected with the reason when it is registered
    unique = list(dict.fromkeys(Path(os.path.abspath(p)) for p in [*named, *found]))
    rank: dict[KernelKind | None, int] = {kind: i for i, kind in enumerate(_REGISTER_ORDER)}
    return sorted(unique, key=lambda p: rank.get(kernel_kind(p), len(rank)))


def accepted_kernels(session: Session) -> list[Kernel]:
    """The catalog's accepted kernels of the kinds geometry loads, in LOAD_ORDER, each kind in
    the order it was catalogued (later kernels take precedence in SPICE)."""
    rank = {kind: i for i, kind in enumerate(LOAD_ORDER)}
    rows = session.scalars(select(Kernel).where(Kernel.status == Acceptance.ACCEPTED,
                                                Kernel.kind.in_(LOAD_ORDER)).order_by(Kernel.id))
    return sorted(rows, key=lambda k: rank[k.kind])


def coverage_windows(session: Session, kind: KernelKind) -> dict[int, list[tuple[float, float]]]:
    """ET windows per NAIF id from the accepted kernels of `kind` (SPK: bodies, CK: frames)."""
    rows = session.execute(
        select(KernelCoverage.naif_id, KernelCoverage.start_et, KernelCoverage.stop_et)
        .join(Kernel).where(Kernel.kind == kind, Kernel.status == Acceptance.ACCEPTED))
    windows: dict[int, list[tuple[float, float]]] = {}
    for naif_id, start, stop in rows:
        windows.setdefault(naif_id, []).append((start, stop))
    return windows


def register_kernels(session: Session, directory: Path, *, downlink_id: int
                     ) -> list[KernelOutcome]:
    """Catalogue the kernels under `directory` (idempotent: known content is left alone).

    The catalog's accepted text kernels are loaded first (those still on disk), so a downlink's
    CKs can use an SCLK and LSK delivered earlier.
    """
    known = {k.sha256: k for k in session.scalars(select(Kernel))}
    preload = [k for k in accepted_kernels(session) if k.kind not in (KernelKind.SPK,
                                                                      KernelKind.CK)]
    outcomes = []
    with kernel_pool(Path(k.path) for k in preload if Path(k.path).is_file()):
        seen: set[str] = set()
        for path in _candidates(directory):
            digest = file_sha256(path)
            kind = kernel_kind(path)
            row = known.get(digest)
            if digest in seen or (row is not None and row.status is Acceptance.ACCEPTED):
                if row is not None and not Path(row.path).is_file():
                    row.path = str(path)  # the catalogued copy moved: keep it loadable
                outcomes.append(KernelOutcome(path, kind, "unchanged"))
                continue
            seen.add(digest)
            if kind is None:
                outcomes.append(KernelOutcome(path, None, "rejected",
                                              "SPICE does not recognise the file type"))
                continue
            outcomes.append(_judge(session, path, kind, digest, row, downlink_id))
    return outcomes


def _judge(session: Session, path: Path, kind: KernelKind, digest: str, row: Kernel | None,
           downlink_id: int) -> KernelOutcome:
    """Check one new or previously rejected kernel and record the verdict."""
    try:
        coverage, status, reason = _coverage_rows(_windows(path, kind)), Acceptance.ACCEPTED, None
    except sp.utils.exceptions.SpiceyError as exc:
        coverage, status, reason = [], Acceptance.REJECTED, spice_message(exc)
    except KernelError as exc:
        coverage, status, reason = [], Acceptance.REJECTED, str(exc)
    if row is None:
        session.add(Kernel(path=str(path), kind=kind, sha256=digest,
                           size_bytes=path.stat().st_size, status=status,
                           rejection_reason=reason, downlink_id=downlink_id, coverage=coverage))
        return KernelOutcome(path, kind, status.value, reason)
    unchanged = (row.status, row.rejection_reason, row.kind) == (status, reason, kind)
    row.path, row.kind, row.status, row.rejection_reason = str(path), kind, status, reason
    row.coverage = coverage
    return KernelOutcome(path, kind, "unchanged" if unchanged else status.value, reason)
