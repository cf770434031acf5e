"""The kernel registry: a downlink's SPICE kernel files catalogued once per content (sha256),
with the time windows their SPKs (per body) and CKs (per frame) cover; and the catalog's kernel
set for loading.

A file is a kernel when its extension is a SPICE one or it starts like a kernel (KPL/, DAF/,
DAS/). Its kind comes from SPICE's getfat, else from the extension. Text kernels are loaded to
check them (and because CK coverage needs the LSK and SCLK); binary ones are opened by SPICE's
object readers; a file SPICE refuses is recorded rejected with SPICE's message. Meta-kernels are
registered, and the files they name (relative PATH_VALUES resolved against the meta-kernel, as
SPICE does) are registered too, ahead of the other files of their kind so that their order
carries over into load order. Kernels come only from inside the downlink being ingested or the
configured kernel library (KernelScope): a symbolic link or a meta-kernel's entry resolving
elsewhere is refused with the reason (service.models.DownlinkFile), never read, so that no
downlink can bring in a file of the host or change the geometry through another's kernels.
Rejected kernels are judged again when seen again: a CK refused for
want of its SCLK is accepted once the SCLK has arrived.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import spiceypy as sp
from sqlalchemy import select
from sqlalchemy.orm import Session

from pwm.io.pds4 import file_sha256
from pwm.io.spice_geometry import coverage_ck, coverage_spk
from pwm.io.spice_kernels import (
    MAX_METAKERNEL_ENTRIES,
    KernelError,
    kernel_pool,
    metakernel_files,
    spice_message,
)
from service.models import Acceptance, DownlinkFile, Kernel, KernelCoverage, KernelKind, utcnow

log = logging.getLogger(__name__)

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
    why a file was rejected (also when unchanged), code how (kernel: SPICE refused it)."""

    path: Path
    kind: KernelKind | None
    result: str
    reason: str | None = None
    code: str = "kernel"


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


def _windows(path: Path, kind: KernelKind, scope: KernelScope
             ) -> dict[int, list[tuple[float, float]]]:
    """Check a kernel with SPICE and return its coverage windows (ET) per NAIF id.

    Text kernels are loaded into the current pool; raises SpiceyError or KernelError. A
    meta-kernel's entries outside the scope are refused on their own (_candidates), not here.
    """
    if kind is KernelKind.SPK:
        return {int(body): coverage_spk(path, int(body)) for body in sp.spkobj(str(path))}
    if kind is KernelKind.CK:
        return {int(frame): coverage_ck(path, int(frame)) for frame in sp.ckobj(str(path))}
    if kind is KernelKind.DSK:
        sp.dskobj(str(path))
    elif kind is KernelKind.MK:
        missing = [f for f in metakernel_files(path, max_entries=scope.max_metakernel_entries)
                   if scope.allows(f) and not f.is_file()]
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


@dataclass(frozen=True)
class KernelScope:
    """Where a downlink's kernels may come from: files inside its own directory, or inside the
    configured kernel library, with symbolic links resolved; and how many kernels one
    meta-kernel may name."""

    directory: Path
    library: Path | None = None
    max_metakernel_entries: int = MAX_METAKERNEL_ENTRIES

    def allows(self, path: Path) -> bool:
        real = path.resolve()
        return any(real.is_relative_to(root.resolve())
                   for root in (self.directory, self.library) if root is not None)

    def outside(self, path: Path, named_by: Path | None = None) -> str:
        """Why `path` is refused: where it resolves, and what it had to be inside."""
        where = " or ".join(str(r) for r in (self.directory, self.library) if r is not None)
        by = f"named by {named_by.name}: " if named_by is not None else ""
        return f"{by}{path} resolves to {path.resolve()}, outside {where}"


@dataclass(frozen=True)
class Refused:
    """A file refused before it is read as a kernel: a code and why (service.models.DownlinkFile)."""

    path: Path
    code: str
    reason: str


def _candidates(scope: KernelScope, refused: list[Refused]) -> list[Path]:
    """Kernel files under the scope's directory and the files its meta-kernels name, in
    registration order: by kind, and within a kind meta-kernel order first, then path order.
    A meta-kernel's entry resolving outside the scope is refused into `refused` and not read;
    files of the directory resolving outside it (symbolic links) are not read either (ingest
    records those, service.ingest)."""
    found = [p for p in sorted(scope.directory.rglob("*"))
             if scope.allows(p) and p.is_file() and is_kernel_file(p)]
    named: list[Path] = []
    for mk in (p for p in found if kernel_kind(p) is KernelKind.MK):
        try:
            files = metakernel_files(mk, max_entries=scope.max_metakernel_entries)
        except (sp.utils.exceptions.SpiceyError, KernelError):
            continue  # the meta-kernel itself is rejected with the reason when it is registered
        for f in files:
            if not scope.allows(f):
                refused.append(Refused(f, "outside_downlink", scope.outside(f, named_by=mk)))
            elif f.is_file():
                named.append(f)
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


def register_kernels(session: Session, scope: KernelScope, *, downlink_id: int
                     ) -> list[KernelOutcome]:
    """Catalogue the kernels of `scope` (idempotent: known content is left alone); the files
    refused are recorded as the downlink's unused files (record_file).

    The catalog's accepted text kernels are loaded first (those still on disk), so a downlink's
    CKs can use an SCLK and LSK delivered earlier. A kernel SPICE refuses may have filled the
    pool before it failed (KERNELPOOLFULL): the pool is then loaded afresh with what it held,
    so that one kernel's excess never costs the next kernels their room.
    """
    known = {k.sha256: k for k in session.scalars(select(Kernel))}
    loaded = [Path(k.path) for k in accepted_kernels(session)
              if k.kind not in (KernelKind.SPK, KernelKind.CK) and Path(k.path).is_file()]
    outcomes = []
    with kernel_pool(loaded):
        refused: list[Refused] = []
        candidates = _candidates(scope, refused)
        _reload(loaded)  # meta-kernels were parsed into the pool
        for item in refused:
            new = record_file(session, downlink_id=downlink_id, path=item.path, code=item.code,
                              reason=item.reason)
            outcomes.append(KernelOutcome(item.path, None, "rejected" if new else "unchanged",
                                          item.reason, item.code))
        seen: set[str] = set()
        for path in candidates:
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
                reason = "SPICE does not recognise the file type"
                new = record_file(session, downlink_id=downlink_id, path=path,
                                  code="unknown_type", reason=reason)
                outcomes.append(KernelOutcome(path, None, "rejected" if new else "unchanged",
                                              reason, "unknown_type"))
                continue
            try:
                with session.begin_nested():
                    outcome = _judge(session, path, kind, digest, row, downlink_id, scope)
                    session.flush()
            except Exception as exc:  # one hostile file never stops the rest
                log.exception("%s: rejected on an unexpected error", path)
                outcome = KernelOutcome(path, kind, "rejected", f"{type(exc).__name__}: {exc}",
                                        "unexpected")
                record_file(session, downlink_id=downlink_id, path=path, code="unexpected",
                            reason=outcome.reason or "")
            if outcome.result == "rejected" and kind in _POOL_KINDS:
                _reload(loaded)
            elif outcome.result == "accepted" and kind in _LOADED_KINDS:
                loaded.append(path)
            outcomes.append(outcome)
    return outcomes


# Kinds whose check loads the pool (meta-kernels are parsed into it, then taken out again),
# and of those the kinds left loaded once accepted.
_LOADED_KINDS = frozenset({KernelKind.LSK, KernelKind.SCLK, KernelKind.PCK, KernelKind.FK,
                           KernelKind.IK})
_POOL_KINDS = _LOADED_KINDS | {KernelKind.MK}


def _reload(paths: list[Path]) -> None:
    """Empty the pool and load `paths` again (none of them meta-kernels)."""
    sp.kclear()
    for path in paths:
        sp.furnsh(str(path))


def record_file(session: Session, *, downlink_id: int, path: Path, code: str, reason: str
                ) -> bool:
    """Record (or update) why a file of the downlink is not used; False if it was recorded
    so already."""
    row = session.scalars(select(DownlinkFile).filter_by(downlink_id=downlink_id,
                                                         path=str(path))).one_or_none()
    if row is None:
        session.add(DownlinkFile(downlink_id=downlink_id, path=str(path), code=code,
                                 reason=reason))
        session.flush()
        return True
    row.seen_at = utcnow()
    if (row.code, row.reason) == (code, reason):
        return False
    row.code, row.reason = code, reason
    return True


def _judge(session: Session, path: Path, kind: KernelKind, digest: str, row: Kernel | None,
           downlink_id: int, scope: KernelScope) -> KernelOutcome:
    """Check one new or previously rejected kernel and record the verdict."""
    try:
        coverage = _coverage_rows(_windows(path, kind, scope))
        status, reason = Acceptance.ACCEPTED, None
    except sp.utils.exceptions.SpiceyError as exc:
        coverage, status, reason = [], Acceptance.REJECTED, spice_message(exc)
    except KernelError as exc:
        coverage, status, reason = [], Acceptance.REJECTED, str(exc)
    if row is None:
        session.add(Kernel(path=str(path), kind=kind, sha256=digest,
                           size_bytes=path.stat().st_size, status=status,
                           rejection_reason=reason, downlink_id=downlink_id, coverage=coverage))
        return KernelOutcome(path, kind, status.value, reason)
    # still rejected is no news, though SPICE's message may differ (e.g. where the pool filled)
    unchanged = (row.status, row.kind) == (status, kind)
    row.path, row.kind, row.status, row.rejection_reason = str(path), kind, status, reason
    row.coverage = coverage
    return KernelOutcome(path, kind, "unchanged" if unchanged else status.value, reason)
