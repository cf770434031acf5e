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
elsewhere is refused with the reason (service.rows.DownlinkFile), never read, so that no
downlink can bring in a file of the host or change the geometry through another's kernels.
Rejected kernels are judged again when seen again: a CK refused for
want of its SCLK is accepted once the SCLK has arrived.

A kernel is checked before it is trusted (pwm.io.kernel_checks): a binary one is read through,
every segment's data, not only its summaries (kernel_truncated); a text one that sets a body's
shape or rotation constants or the time system's (DELTET) must give sane numbers
(kernel_constants), and may not change a value the kernels already accepted set
(kernel_redefines): SPICE's pool is shared, later kernels win, and the geometry catalogued so
far was computed with those values. "Accepted" is the catalog's: every accepted kernel of every
downlink is loaded for every ingest (accepted_kernels), this downlink's own accepted so far
among them. To change such a constant, an operator retires the kernel that set it
(retire_kernel, `pwm kernels retire`) and the new one is accepted when delivered again; a
retired kernel is never loaded again nor judged again, and the images it served are judged
again at their downlink's next ingest.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any, cast

import spiceypy as sp
from sqlalchemy import CursorResult, Select, and_, delete, func, select, update
from sqlalchemy.orm import Session

from pwm.io.kernel_checks import (
    KernelCheckError,
    Value,
    check_constants,
    check_daf,
    check_das,
    pool_constants,
    redefinitions,
)
from pwm.io.pds4 import file_sha256
from pwm.io.spice_geometry import coverage_ck, coverage_spk
from pwm.io.spice_kernels import (
    MAX_METAKERNEL_ENTRIES,
    KernelError,
    kernel_pool,
    metakernel_files,
    spice_message,
)
from service.db import insert_ignoring_conflict
from service.rows import (
    Acceptance,
    Downlink,
    DownlinkFile,
    GeometryStatus,
    Image,
    ImageGeometry,
    ImageStatus,
    Kernel,
    KernelCoverage,
    KernelDelivery,
    KernelKind,
    utcnow,
)

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


def _windows(path: Path, kind: KernelKind, check: _Check
             ) -> dict[int, list[tuple[float, float]]]:
    """Check a kernel with SPICE and pwm.io.kernel_checks and return its coverage windows (ET)
    per NAIF id.

    Binary kernels are read through (every segment's data); text kernels are loaded into the
    current pool, and the body and time constants they set or change are checked against the
    ones loaded before. Raises SpiceyError or KernelError (KernelCheckError with its code). A
    meta-kernel's entries outside the scope are refused on their own (_candidates), not here.
    """
    # SPICE's own readers first, so that its message says what a file that is no kernel is
    if kind is KernelKind.SPK:
        bodies = sp.spkobj(str(path))
        check_daf(path, evaluate_spk=True)
        return {int(body): coverage_spk(path, int(body)) for body in bodies}
    if kind is KernelKind.CK:
        frames = sp.ckobj(str(path))
        check_daf(path)
        return {int(frame): coverage_ck(path, int(frame)) for frame in frames}
    if kind is KernelKind.DSK:
        sp.dskobj(str(path))
        check_das(path)
    elif kind is KernelKind.MK:
        scope = check.scope
        missing = [f for f in metakernel_files(path, max_entries=scope.max_metakernel_entries)
                   if scope.allows(f) and not f.is_file()]
        if missing:
            raise KernelError(f"{len(missing)} kernels it names are missing: "
                              + ", ".join(str(f) for f in missing), missing)
    elif kind is KernelKind.PCK and sp.getfat(str(path))[0] == "DAF":
        # furnsh would take an unreadable binary file for a text kernel without data.
        sp.pckfrm(str(path), sp.cell_int(1000))
        check_daf(path)
    else:
        sp.furnsh(str(path))
        _check_constants(check.constants, pool_constants())
    return {}


def _check_constants(before: dict[str, Value], after: dict[str, Value]) -> None:
    """KernelCheckError unless the constants a text kernel just loaded set or changed are
    sane, and none already set changed (geometry already catalogued used them)."""
    check_constants({name: value for name, value in after.items() if before.get(name) != value})
    changed = redefinitions(before, after)
    if changed:
        raise KernelCheckError("kernel_redefines", "redefines constants the catalog's accepted "
                               "kernels set (retire those first to change them): "
                               + "; ".join(changed))


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
    """A file refused before it is read as a kernel: a code and why (service.rows.DownlinkFile)."""

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
    the order it was catalogued (later kernels take precedence in SPICE); retired ones never."""
    rank = {kind: i for i, kind in enumerate(LOAD_ORDER)}
    rows = session.scalars(select(Kernel).where(_IN_USE, Kernel.kind.in_(LOAD_ORDER))
                           .order_by(Kernel.id))
    return sorted(rows, key=lambda k: rank[k.kind])


def coverage_windows(session: Session, kind: KernelKind) -> dict[int, list[tuple[float, float]]]:
    """ET windows per NAIF id from the accepted kernels of `kind` (SPK: bodies, CK: frames)."""
    rows = session.execute(
        select(KernelCoverage.naif_id, KernelCoverage.start_et, KernelCoverage.stop_et)
        .join(Kernel).where(Kernel.kind == kind, _IN_USE))
    windows: dict[int, list[tuple[float, float]]] = {}
    for naif_id, start, stop in rows:
        windows.setdefault(naif_id, []).append((start, stop))
    return windows


def register_kernels(session: Session, scope: KernelScope, *, downlink_id: int
                     ) -> list[KernelOutcome]:
    """Catalogue the kernels of `scope` (idempotent: known content is left alone, a retired
    kernel stays retired); the files refused are recorded as the downlink's unused files
    (record_file), and each kernel's delivery by this downlink (KernelDelivery).

    The catalog's accepted text kernels are loaded first (those still on disk), so a downlink's
    CKs can use an SCLK and LSK delivered earlier, and a text kernel is checked against the body
    and time constants they set (pwm.io.kernel_checks). A kernel SPICE refuses may have filled
    the pool before it failed (KERNELPOOLFULL): the pool is then loaded afresh with what it
    held, so that one kernel's excess never costs the next kernels their room.

    Safe beside another ingest registering the same kernels at once: each row is inserted
    unless there already (ON CONFLICT), and the ingest that loses takes the winner's row.
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
        check = _Check(scope, pool_constants())
        seen: set[str] = set()
        for path in candidates:
            digest = file_sha256(path)
            kind = kernel_kind(path)
            row = known.get(digest)
            if row is not None:
                _delivered(session, row.id, downlink_id, path)
            if digest in seen or (row is not None and (row.status is Acceptance.ACCEPTED
                                                       or row.retired_at is not None)):
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
                    outcome, accepted = _judge(session, path, kind, digest, row, downlink_id,
                                               check)
                    session.flush()
            except Exception as exc:  # one hostile file never stops the rest
                log.exception("%s: rejected on an unexpected error", path)
                outcome, accepted = KernelOutcome(
                    path, kind, "rejected", f"{type(exc).__name__}: {exc}", "unexpected"), False
                record_file(session, downlink_id=downlink_id, path=path, code="unexpected",
                            reason=outcome.reason or "")
            if kind is KernelKind.MK or (not accepted and kind in _POOL_KINDS):
                _reload(loaded)  # what the check left in the pool goes
            elif accepted and kind in _LOADED_KINDS:
                loaded.append(path)
                check.constants = pool_constants()
            outcomes.append(outcome)
    return outcomes


# Kinds whose check loads the pool (meta-kernels are parsed into it, then taken out again),
# and of those the kinds left loaded once accepted.
_LOADED_KINDS = frozenset({KernelKind.LSK, KernelKind.SCLK, KernelKind.PCK, KernelKind.FK,
                           KernelKind.IK})
_POOL_KINDS = _LOADED_KINDS | {KernelKind.MK}
_IN_USE = and_(Kernel.status == Acceptance.ACCEPTED, Kernel.retired_at.is_(None))


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


@dataclass
class _Check:
    """What a kernel is checked against: where kernels may come from, and the body and time
    constants of the kernels loaded now (the catalog's accepted ones, and this downlink's
    accepted so far)."""

    scope: KernelScope
    constants: dict[str, Value]


def _verdict(path: Path, kind: KernelKind, check: _Check
             ) -> tuple[list[KernelCoverage], Acceptance, str | None, str | None]:
    """Coverage rows, status, rejection code and reason of one kernel."""
    try:
        return _coverage_rows(_windows(path, kind, check)), Acceptance.ACCEPTED, None, None
    except sp.utils.exceptions.SpiceyError as exc:
        return [], Acceptance.REJECTED, "kernel", spice_message(exc)
    except KernelCheckError as exc:
        return [], Acceptance.REJECTED, exc.code, str(exc)
    except KernelError as exc:
        return [], Acceptance.REJECTED, "kernel", str(exc)


def _judge(session: Session, path: Path, kind: KernelKind, digest: str, row: Kernel | None,
           downlink_id: int, check: _Check) -> tuple[KernelOutcome, bool]:
    """Check one new or previously rejected kernel and record the verdict; the outcome, and
    whether the kernel is accepted (ours, or the verdict of an ingest that recorded it first)."""
    coverage, status, code, reason = _verdict(path, kind, check)
    values = dict(path=str(path), kind=kind, status=status, rejection_code=code,
                  rejection_reason=reason)
    if row is None:
        row, ours = _insert_or_get(session, digest, downlink_id=downlink_id,
                                   size_bytes=path.stat().st_size, **values)
        _delivered(session, row.id, downlink_id, path)
        result = status.value if ours else "unchanged"
    else:
        # Only while still rejected and not retired: a concurrent ingest's verdict stands.
        ours = cast(CursorResult[Any], session.execute(
            update(Kernel).where(Kernel.id == row.id, Kernel.status == Acceptance.REJECTED,
                                 Kernel.retired_at.is_(None)).values(**values)
            .execution_options(synchronize_session=False))).rowcount == 1
        if ours:
            session.execute(delete(KernelCoverage).where(KernelCoverage.kernel_id == row.id))
        # still rejected is no news, though SPICE's message may differ (e.g. where the pool filled)
        result = ("unchanged" if not ours or (row.status, row.kind) == (status, kind)
                  else status.value)
        row = _fresh(session, digest)
    if ours:
        for window in coverage:
            window.kernel_id = row.id
        session.add_all(coverage)
    accepted = row.status is Acceptance.ACCEPTED and row.retired_at is None
    return KernelOutcome(path, kind, result, row.rejection_reason,
                         row.rejection_code or "kernel"), accepted


def _insert_or_get(session: Session, digest: str, **values: Any) -> tuple[Kernel, bool]:
    """The kernel row of `digest`, inserted with `values` unless another ingest did first;
    and whether this one inserted it."""
    inserted = session.execute(insert_ignoring_conflict(
        session, Kernel, unique=[Kernel.sha256], sha256=digest, **values)
        .returning(Kernel.id)).scalar_one_or_none()
    return _fresh(session, digest), inserted is not None


def _fresh(session: Session, digest: str) -> Kernel:
    return session.scalars(select(Kernel).filter_by(sha256=digest)
                           .execution_options(populate_existing=True)).one()


def _delivered(session: Session, kernel_id: int, downlink_id: int, path: Path) -> None:
    """Record that the downlink delivered the kernel (once per downlink)."""
    session.execute(insert_ignoring_conflict(
        session, KernelDelivery, unique=[KernelDelivery.kernel_id, KernelDelivery.downlink_id],
        kernel_id=kernel_id, downlink_id=downlink_id, path=str(path)))


# ---------------------------------------------------------------------------------------------
# An operator's view: the kernels, and retiring one

RETIRED = "retired"  # the status `pwm kernels` shows for a retired kernel, whatever its verdict
_IDS_PER_STATEMENT = 500


@dataclass(frozen=True)
class KernelListing:
    """One kernel as `pwm kernels` lists it: status accepted, rejected or retired; reason: why
    rejected or retired; coverage: the first and last ET its windows cover (SPK, CK)."""

    id: int
    kind: KernelKind
    name: str
    path: str
    status: str
    code: str | None
    reason: str | None
    coverage: tuple[float, float] | None
    downlinks: list[str]


def kernel_listing(session: Session) -> list[KernelListing]:
    """Every catalogued kernel, in the order catalogued, with the downlinks that delivered it."""
    spans = {kernel_id: (start, stop) for kernel_id, start, stop in session.execute(
        select(KernelCoverage.kernel_id, func.min(KernelCoverage.start_et),
               func.max(KernelCoverage.stop_et)).group_by(KernelCoverage.kernel_id))}
    delivered: dict[int, list[str]] = {}
    for kernel_id, name in session.execute(
            select(KernelDelivery.kernel_id, Downlink.name).join(Downlink)
            .order_by(KernelDelivery.id)):
        delivered.setdefault(kernel_id, []).append(name)
    return [KernelListing(
        id=k.id, kind=k.kind, name=Path(k.path).name, path=k.path,
        status=RETIRED if k.retired_at is not None else k.status.value,
        code=None if k.retired_at is not None else k.rejection_code,
        reason=k.retirement_reason if k.retired_at is not None else k.rejection_reason,
        coverage=spans.get(k.id), downlinks=delivered.get(k.id, []))
        for k in session.scalars(select(Kernel).order_by(Kernel.id))]


@dataclass(frozen=True)
class Retirement:
    """What retiring a kernel did: the images whose geometry it withdrew, and the downlinks that
    hold them (each one's next ingest judges them again, with the kernels left)."""

    kernel_id: int
    name: str
    images: int
    downlinks: list[tuple[str, str]]  # name, directory


def retire_kernel(session: Session, kernel_id: int, *, reason: str) -> Retirement:
    """Retire a kernel: it is no longer loaded, nor judged again when delivered again. The
    images whose geometry it may have served lose their geometry, with a reason naming the
    retirement, and so become kernel-dependent: the next ingest of their downlink computes it
    again. Served: for an SPK or CK, the accepted images with geometry whose mid-exposure time
    lies in its coverage; for a text kernel (LSK, SCLK, PCK, FK, IK), every one. Their pose
    corrections, made on its geometry, go too, and they are weighed again into the maplets'
    coverage once their geometry is back. LookupError for an unknown id."""
    kernel = session.get(Kernel, kernel_id)
    if kernel is None:
        raise LookupError(f"no kernel {kernel_id} in the catalog")
    name = Path(kernel.path).name
    served = _served(kernel) if kernel.retired_at is None else None
    if kernel.retired_at is None:
        kernel.retired_at, kernel.retirement_reason = utcnow(), reason
        session.flush()
    ids = [] if served is None else list(session.scalars(served))
    downlinks = [(n, p) for n, p in session.execute(
        select(Downlink.name, Downlink.path).where(Downlink.id.in_(
            select(Image.downlink_id).where(Image.id.in_(ids)))).order_by(Downlink.id))] if ids else []
    why = f"kernel {kernel.id} ({name}) retired: {reason}"
    for first in range(0, len(ids), _IDS_PER_STATEMENT):
        chunk = ids[first:first + _IDS_PER_STATEMENT]
        session.execute(delete(ImageGeometry).where(ImageGeometry.image_id.in_(chunk)))
        session.execute(update(Image).where(Image.id.in_(chunk)).values(
            geometry_status=GeometryStatus.UNAVAILABLE, geometry_unavailable_reason=why,
            coverage_computed_at=None, pose_dx_km=None, pose_dy_km=None, pose_dz_km=None,
            pose_rx_rad=None, pose_ry_rad=None, pose_rz_rad=None, pose_corrected_at=None,
            pose_sigma=None).execution_options(synchronize_session=False))
    log.info("%s; %d images lose their geometry", why, len(ids))
    return Retirement(kernel.id, name, len(ids), downlinks)


def _served(kernel: Kernel) -> Select[Any] | None:
    """The images whose geometry `kernel` may have given, as a query of their ids."""
    if kernel.status is not Acceptance.ACCEPTED or kernel.kind not in LOAD_ORDER:
        return None
    query = select(Image.id).where(Image.status == ImageStatus.ACCEPTED,
                                   Image.geometry_status == GeometryStatus.COMPUTED)
    if kernel.kind in (KernelKind.SPK, KernelKind.CK):
        mid = (Image.start_et + Image.stop_et) / 2
        query = query.where(select(KernelCoverage.id).where(
            KernelCoverage.kernel_id == kernel.id, KernelCoverage.start_et <= mid,
            KernelCoverage.stop_et >= mid).exists())
    return query.order_by(Image.id)
