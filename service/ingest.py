"""`pwm ingest DIR`: catalogue a downlink's SPICE kernels, PDS4 image products and ISIS cubes,
with the viewing geometry of each image.

Kernels come first (service.kernels). Then every *.xml label (and *.cub cube, below) is read
with pwm.io.pds4.read_image_label, inside a kernel pool holding the catalog's accepted kernels,
and becomes one Image row:
- accepted with its geometry (its label resolved against the kernel pool by pwm.io.resolve,
  the same resolver as the catalog-free commands', its view by pwm.geometry.view_geometry);
- accepted with geometry unavailable, and why ("no kernels: ..."), when the resolver refuses it
  as no_kernels: the catalog has no kernels at all for its observer (products of other
  missions, ground telescopes, or of kernels still to come);
- rejected with a code and a reason: a ProductError code, or the resolver's (pwm.io.resolve:
  bad_time, unknown_instrument, instrument_kernel, unknown_target, geometry, outside_coverage,
  bad_dimensions);
- conflict: the LIDVID is catalogued already with other content (label + data sha256); the
  first good copy stays authoritative.
A laser altimetry product (a label whose table of shots is in a layout pwm.io.lidar knows)
becomes one LidarProduct row, keyed by its LIDVID and content as an image is: its table read
within the limits (IngestLimits.max_lidar_shots), its target and body-fixed frame resolved
against the kernel pool, each shot placed with SPICE at its time (pwm.io.lidar.place_shots:
unusable shots kept, with why), grouped into tracks (pwm.lidar.tracks.track_ids, one
LidarTrack row each with its span, cone and box), and its shots stored in the artifact store
as one compressed array file (pwm.io.lidar.write_shots), never one row per shot. Rejected
with a code: the reader's (pwm.io.pds4.ProductError: not_lidar, unknown_layout, truncated,
too_many_shots, ...), unknown_target, unknown_instrument, bad_kernel, no_shots, geometry,
outside_coverage (no shot's time in the kernels). Judged again when seen again: those
rejected for their kernels or their transfer, and those accepted with shots outside the
kernels. Another copy of an accepted LIDVID with other content is recorded as a file not used
(code conflict); a broken copy's row is taken by the next whole one.

An ISIS cube (*.cub, pwm.io.isis) is a product of one file whose geometry is its own: its
attached SPICE tables give its pose and Sun, its label the camera and the target's ellipsoid,
no kernels needed (a cube without them is rejected no_attached_spice). Its LIDVID is
isis:<ProductId>::1.0, or isis:<sha256 of its label>::1.0 for a label without a ProductId; its
content digest the whole file's; it is judged, kept and replaced as any product.

A product's identity is its good content. A copy rejected for how it arrived (TRANSFER_CODES: a
data file not there yet, cut short, off its label's checksum or its downlink's manifest.json,
unreadable; or an error of the ingest's own) holds its LIDVID only until another copy comes: a
whole one takes its row (its id kept) and is judged as any, in the same directory or another
downlink, in the same ingest or a later one; the broken copy, where it is still offered
elsewhere, stays on as a conflict (a copy not used). Where the downlink's manifest lists a product's files
with sha256, they are checked against it: a product that does not match waits as `incomplete`.

Idempotent: a product already catalogued with the same content is left alone, except that one
whose outcome depends on kernels (rejected for instrument, target, coverage or geometry, or
accepted without geometry) or on its transfer is judged again, so images that arrive before
their kernels or whole after a broken transfer are taken up by a later ingest. One bad file
never stops the rest. Concurrent ingests of different downlinks share the unique rows
(instruments, images) race-free: the one that loses an insert takes the winner's row.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import re
import socket
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any, cast

import numpy as np
import spiceypy as sp
from sqlalchemy import CursorResult, Engine, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from pwm.camera import Camera
from pwm.geometry import Ellipsoid, MeshSurface, Surface, ViewGeometry, view_geometry
from pwm.io.isis import Cube, cube_key, is_cube, read_cube, read_cube_pixels
from pwm.io.labels import LABEL_SUFFIXES, body_name, target_frame
from pwm.io.lidar import is_lidar_label, place_shots, read_lidar_table, write_shots
from pwm.io.pds4 import ImageLabel, ProductError, read_array, read_image_label
from pwm.io.resolve import (
    NO_KERNELS,
    Exposure,
    KernelWindows,
    Refusal,
    exposure,
    pose_and_sun,
    read_once,
    resolve_label,
)
from pwm.io.spice_geometry import ABCORR, camera_from_kernel, ellipsoid_of, instrument_frame, spacecraft_of
from pwm.io.spice_kernels import kernel_pool
from pwm.lidar.config import LIDAR
from pwm.lidar.shots import Invalid
from pwm.lidar.tracks import track_extents, track_ids
from pwm.mesh import Mesh
from pwm.parallel import Progress
from service.artifacts import scratch_file, store_artifact
from service.db import insert_ignoring_conflict, make_sessionmaker, session_scope
from service.kernels import (
    KernelOutcome,
    KernelScope,
    accepted_kernels,
    coverage_windows,
    record_file,
    register_kernels,
    spice_message,
)
from service.rows import (
    Acceptance,
    Downlink,
    DownlinkStatus,
    GeometryStatus,
    Image,
    ImageGeometry,
    ImageStatus,
    Instrument,
    KernelKind,
    LidarProduct,
    LidarTrack,
    utcnow,
)
from service.settings import IngestLimits, get_settings

log = logging.getLogger(__name__)

COMMIT_EVERY = 200  # products per transaction: a crash loses at most this much, re-run resumes
# Outcomes that new kernels can change: such products are judged again on every ingest.
KERNEL_DEPENDENT_CODES = frozenset(
    {"unknown_instrument", "instrument_kernel", "unknown_target", "outside_coverage", "geometry"})
INCOMPLETE = "incomplete"  # a product's file differs from the downlink's manifest
UNEXPECTED = "unexpected"  # an error of the ingest's own, no verdict on the product
# Rejections for how a copy arrived, not for what its product is (pwm.io.pds4.ProductError codes
# and INCOMPLETE): judged again when seen again, and another copy may take their place.
TRANSFER_CODES = frozenset({"missing_file", "size_mismatch", "md5_mismatch", "truncated",
                            "unreadable", INCOMPLETE})
_PROVISIONAL_CODES = TRANSFER_CODES | {UNEXPECTED}
_UNIDENTIFIED = "unidentified:"
# Lidar outcomes that new kernels can change (outside_coverage: no shot's time in them).
LIDAR_KERNEL_CODES = frozenset({"unknown_instrument", "unknown_target", "bad_kernel", "geometry", "outside_coverage"})
CONFLICT = "conflict"  # a copy of a catalogued product with other content: not used
_CUBE_LID, _CUBE_VID = "isis:", "1.0"
_HASH_CHUNK = 1 << 20
# Column sizes of service.rows.Image: a LIDVID must leave room for a conflict's suffix.
_LIDVID_CHARS, _VID_CHARS, _CONFLICT_SUFFIX = 255, 32, 17
_VID = re.compile(r"\d+\.\d+")
# Files of a downlink that are neither kernels nor products, and are expected: its manifest
# and the start model the conductor imports (service.conductor.START_MODEL_NAME).
_DELIVERY_FILES = frozenset({"manifest.json", "start_model.obj"})
_WAIT_S = 1.0  # how often an ingest waiting for another's downlink looks again


@dataclass
class Counts:
    accepted: int = 0
    rejected: int = 0
    unchanged: int = 0


@dataclass(frozen=True)
class Failure:
    """A file rejected by this ingest: what, the short code, and why."""

    path: str
    code: str
    reason: str


@dataclass
class IngestReport:
    """What one ingest did. Rejections include conflicts; failures list this run's rejections
    (files left unchanged are not repeated); warnings are about the catalog, or a manifest not
    read, not this downlink's files."""

    downlink: str
    kernels: Counts = field(default_factory=Counts)
    images: Counts = field(default_factory=Counts)
    geometry_unavailable: int = 0
    lidar: Counts = field(default_factory=Counts)
    lidar_shots: int = 0  # shots of the lidar products this ingest accepted
    lidar_valid_shots: int = 0  # of which usable
    failures: list[Failure] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    elapsed_s: float = 0.0

    @property
    def failed(self) -> int:
        return len(self.failures)

    def summary(self) -> str:
        k, i, lidar = self.kernels, self.images, self.lidar
        said = (f"; lidar products {lidar.accepted} accepted ({self.lidar_shots} shots, {self.lidar_valid_shots} "
                f"valid), {lidar.rejected} rejected, {lidar.unchanged} unchanged"
                if lidar.accepted + lidar.rejected + lidar.unchanged else "")
        return (f"{self.downlink}: kernels {k.accepted} accepted, {k.rejected} rejected, "
                f"{k.unchanged} unchanged; images {i.accepted} accepted "
                f"({self.geometry_unavailable} without geometry), {i.rejected} rejected, "
                f"{i.unchanged} unchanged{said}; {self.failed} failed; {self.elapsed_s:.1f} s")


@dataclass(frozen=True)
class _Identity:
    """A label's product key and the sha256 of the label and the data files it names."""

    lid: str
    vid: str
    data_path: Path | None
    sha256: str
    size_bytes: int
    files: frozenset[Path] = frozenset()  # the files the label names
    # the product's rejection before it is read: a LIDVID that cannot key it (keyed by the
    # label's sha256 then), too many files named
    rejection: tuple[str, str] | None = None
    # the sha256 and size of each of its files the manifest lists
    digests: Mapping[Path, tuple[str, int]] = field(default_factory=dict)

    @property
    def lidvid(self) -> str:
        return f"{self.lid}::{self.vid}"


@dataclass
class _Known:
    """A catalogued product version: enough to decide what a new copy of it means. seen: judged
    (or recorded) by this ingest already."""

    id: int | None
    sha256: str
    status: ImageStatus
    code: str | None
    geometry_status: GeometryStatus
    seen: bool = False

    @property
    def kernel_dependent(self) -> bool:
        if self.status is ImageStatus.ACCEPTED:
            return self.geometry_status is not GeometryStatus.COMPUTED
        return self.status is ImageStatus.REJECTED and self.code in KERNEL_DEPENDENT_CODES

    @property
    def broken(self) -> bool:
        """A copy rejected for its transfer (or on an unexpected error): no verdict on the
        product, so it holds its LIDVID only until another copy comes."""
        return self.status is ImageStatus.REJECTED and self.code in _PROVISIONAL_CODES

    @property
    def provisional(self) -> bool:
        """Its outcome may change with the same content: judged again when seen again."""
        return self.kernel_dependent or self.broken


@dataclass(frozen=True)
class _Outcome:
    status: ImageStatus
    code: str | None = None
    reason: str | None = None
    geometry_status: GeometryStatus = GeometryStatus.UNAVAILABLE
    geometry_reason: str | None = None
    product: ImageLabel | None = None
    instrument_id: int | None = None
    times: Exposure | None = None
    geometry: ImageGeometry | None = None
    cube: Cube | None = None  # what a cube's label gave, in place of `product`

    @property
    def verdict(self) -> tuple:
        return (self.status, self.code, self.reason, self.geometry_status, self.geometry_reason)


@dataclass(frozen=True)
class _Listed:
    """A file as the downlink's manifest lists it."""

    sha256: str
    size_bytes: int | None


class IngestTakenOver(RuntimeError):
    """Another ingest took this one's downlink over, this one having gone without a commit for
    longer than limits.stale_s: it stops, its uncommitted work rolled back, and leaves the
    downlink to the other."""


def ingest_directory(catalog: sessionmaker[Session] | Engine, directory: Path, *,
                     downlink_name: str | None = None, shape: Mesh | None = None,
                     limits: IngestLimits | None = None, data_dir: Path | None = None,
                     progress: Progress | None = None) -> IngestReport:
    """Catalogue the SPICE kernels and PDS4 products under `directory` as one downlink.

    downlink_name defaults to the directory's name (a suffix is added when another directory
    holds that name); a directory whose manifest.json is a catalogued downlink's is a repeat
    delivery of that downlink (its repeat_count and last_seen_at record it). shape: the current
    shape model of the target (body-fixed, km); boresight and corner intercepts use it instead
    of the PCK ellipsoid. The images are catalogued only: weighing them against a model is a
    later stage's (service.conductor.weigh), once their poses are final. limits: what is
    accepted (default service.settings); kernels come only from `directory` and
    limits.kernel_library.

    One ingest of a downlink at a time: another waits while the first's claim is live
    (Downlink.ingest_owner, renewed at each commit) and takes it over once its owner is gone or
    stale (limits.stale_s without a commit). Every file under `directory` ends up a kernel, a
    product's label or data file, or a DownlinkFile with why it is not used. SPICE's
    process-wide kernel pool is cleared on the way in and out (pwm.io.spice_kernels.kernel_pool).
    progress: told how many of the products have been judged (stage "ingest").
    """
    sessions = make_sessionmaker(catalog) if isinstance(catalog, Engine) else catalog
    limits = limits or get_settings().ingest_limits()
    data_dir = Path(data_dir) if data_dir is not None else get_settings().data_dir
    directory = Path(directory).resolve()
    if not directory.is_dir():
        raise NotADirectoryError(f"{directory} is not a directory")
    clock = time.perf_counter()
    downlink_id, name = _claim(sessions, directory, downlink_name, limits)
    report = IngestReport(downlink=name)
    try:
        scope = KernelScope(directory, limits.kernel_library, limits.max_metakernel_entries)
        with _owned(sessions, downlink_id) as session:
            outcomes = register_kernels(session, scope, downlink_id=downlink_id)
        _count_kernels(report, outcomes)
        labels, others = _walk(sessions, directory, downlink_id, report)
        manifest = _read_manifest(directory, limits, report)
        named = _ingest_images(sessions, directory, labels, downlink_id=downlink_id,
                               report=report, shape=None if shape is None else MeshSurface(shape),
                               limits=limits, manifest=manifest, data_dir=data_dir, progress=progress)
        used = {o.path for o in outcomes} | named | set(labels)
        with _owned(sessions, downlink_id) as session:
            for path in others:
                if path not in used and path.name not in _DELIVERY_FILES:
                    _unused(session, report, downlink_id, path, "unknown_type",
                            "neither a SPICE kernel nor a PDS4 label, nor a file a label names")
    except BaseException:
        _release(sessions, downlink_id, DownlinkStatus.FAILED)
        raise
    _release(sessions, downlink_id, DownlinkStatus.INGESTED)
    report.elapsed_s = time.perf_counter() - clock
    log.info("%s", report.summary())
    return report


def _owner() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _owner_gone(owner: str | None) -> bool:
    """True when `owner` ("host:pid") is a process of this host that no longer runs."""
    host, _, pid = (owner or "").rpartition(":")
    if host != socket.gethostname() or not pid.isdigit():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # someone else's process: alive
        return False
    return False


def _claim(sessions: sessionmaker[Session], directory: Path, name: str | None,
           limits: IngestLimits) -> tuple[int, str]:
    """Take the downlink of `directory` for this ingest (status ingesting, owner this
    process); wait while another ingest holds it, take it over when that one is stale."""
    owner, waited = _owner(), False
    while True:
        with session_scope(sessions) as session:
            downlink, new = _downlink(session, directory, name)
            now = utcnow()
            stale = or_(Downlink.status != DownlinkStatus.INGESTING,
                        Downlink.ingest_heartbeat_at.is_(None),
                        Downlink.ingest_heartbeat_at < now - timedelta(seconds=limits.stale_s))
            if _owner_gone(downlink.ingest_owner):
                stale = or_(stale, Downlink.ingest_owner == downlink.ingest_owner)
            taken = cast(CursorResult[Any], session.execute(
                update(Downlink).where(Downlink.id == downlink.id, stale)
                .values(status=DownlinkStatus.INGESTING, ingest_owner=owner,
                        ingest_heartbeat_at=now)
                .execution_options(synchronize_session=False))).rowcount == 1
            if taken:
                if not new:  # delivered (or ingested) again
                    session.execute(update(Downlink).where(Downlink.id == downlink.id).values(
                        repeat_count=Downlink.repeat_count + 1, last_seen_at=now)
                        .execution_options(synchronize_session=False))
                if downlink.status is DownlinkStatus.INGESTING:
                    log.warning("%s: taking over the stale ingest of %s", downlink.name,
                                downlink.ingest_owner)
                return downlink.id, downlink.name
            holder = downlink.ingest_owner
        if not waited:
            log.info("%s is being ingested by %s: waiting", directory, holder)
            waited = True
        time.sleep(_WAIT_S)


def _release(sessions: sessionmaker[Session], downlink_id: int, status: DownlinkStatus) -> None:
    """End this ingest's claim with `status`, unless another ingest has taken it over."""
    with session_scope(sessions) as session:
        session.execute(update(Downlink).where(Downlink.id == downlink_id,
                                               Downlink.ingest_owner == _owner())
                        .values(status=status, ingest_owner=None, ingest_heartbeat_at=utcnow())
                        .execution_options(synchronize_session=False))


def _heartbeat(session: Session, downlink_id: int) -> None:
    """Renew this ingest's claim in the transaction about to commit; IngestTakenOver (that
    transaction is to be rolled back) when another ingest has taken the downlink over."""
    renewed = cast(CursorResult[Any], session.execute(
        update(Downlink).where(Downlink.id == downlink_id, Downlink.ingest_owner == _owner())
        .values(ingest_heartbeat_at=utcnow())
        .execution_options(synchronize_session=False))).rowcount
    if renewed != 1:
        holder = session.scalar(select(Downlink.ingest_owner).where(Downlink.id == downlink_id))
        raise IngestTakenOver(f"downlink {downlink_id} was taken over by the ingest of {holder}: "
                              "this one stops, what it had not committed rolled back")


@contextmanager
def _owned(sessions: sessionmaker[Session], downlink_id: int) -> Iterator[Session]:
    """A transaction of this ingest's, committed only while it still holds its downlink's claim
    (renewed with it): an ingest taken over as stale writes nothing more."""
    with session_scope(sessions) as session:
        yield session
        _heartbeat(session, downlink_id)


def _downlink(session: Session, directory: Path, name: str | None) -> tuple[Downlink, bool]:
    """The downlink row for `directory`, and whether it is new: found by name if given, else
    by path, else by its manifest (a repeat delivery), else new."""
    if name is not None:
        found = session.scalars(select(Downlink).filter_by(name=name)).one_or_none()
    else:
        found = session.scalars(select(Downlink).filter_by(path=str(directory))
                                .order_by(Downlink.id)).first()
    manifest = directory / "manifest.json"
    digest = _sha256([manifest]) if manifest.is_file() and not manifest.is_symlink() else None
    if found is None and digest is not None:
        found = session.scalars(select(Downlink).filter_by(manifest_sha256=digest)
                                .order_by(Downlink.id)).first()
    elif found is not None and name is not None:
        found.path = str(directory)
    if found is not None:
        return found, False
    if name is None:
        taken = set(session.scalars(select(Downlink.name).where(
            Downlink.name.startswith(directory.name))))
        name = next(n for n in (directory.name if i == 0 else f"{directory.name}-{i + 1}"
                                for i in range(len(taken) + 1)) if n not in taken)
    # Inserted unless a concurrent ingest just did: two first ingests share one row.
    session.execute(insert_ignoring_conflict(
        session, Downlink, unique=[Downlink.name], name=name, path=str(directory),
        manifest_sha256=digest, received_at=utcnow(), status=DownlinkStatus.RECEIVED,
        repeat_count=0, last_seen_at=utcnow()))
    return session.scalars(select(Downlink).filter_by(name=name)
                           .execution_options(populate_existing=True)).one(), True


def _walk(sessions: sessionmaker[Session], directory: Path, downlink_id: int,
          report: IngestReport) -> tuple[list[Path], list[Path]]:
    """The labels under `directory` and its other files, in path order; files resolving
    outside it (symbolic links) are recorded as unused and in neither list."""
    labels: list[Path] = []
    others: list[Path] = []
    with _owned(sessions, downlink_id) as session:
        for path in sorted(directory.rglob("*")):
            if not path.resolve().is_relative_to(directory):
                _unused(session, report, downlink_id, path, "outside_downlink",
                        f"{path} resolves to {path.resolve()}, outside {directory}")
            elif path.is_file():
                (labels if path.suffix.lower() in LABEL_SUFFIXES else others).append(path)
            elif not path.is_dir():
                _unused(session, report, downlink_id, path, "unknown_type",
                        "not a regular file (a device, pipe or socket)")
    return labels, others


def _unused(session: Session, report: IngestReport, downlink_id: int, path: Path, code: str,
            reason: str) -> None:
    if record_file(session, downlink_id=downlink_id, path=path, code=code, reason=reason):
        report.failures.append(Failure(str(path), code, reason))


def _count_kernels(report: IngestReport, outcomes: list[KernelOutcome]) -> None:
    for outcome in outcomes:
        setattr(report.kernels, outcome.result, getattr(report.kernels, outcome.result) + 1)
        if outcome.result == "rejected":
            report.failures.append(Failure(str(outcome.path), outcome.code, outcome.reason or ""))


def _read_manifest(directory: Path, limits: IngestLimits, report: IngestReport
                   ) -> dict[Path, _Listed]:
    """The files the downlink's manifest.json lists with a sha256, by path (as `pwm simulate`
    writes it: {"files": [{"path", "bytes", "sha256"}]}, paths relative to the downlink); none
    when there is no manifest, and none, with a warning, when it cannot be read (read whole, so
    bounded as a label is)."""
    manifest = directory / "manifest.json"
    if not manifest.is_file() or manifest.is_symlink():
        return {}
    try:
        if manifest.stat().st_size > limits.max_label_bytes:
            raise ValueError(f"more than {limits.max_label_bytes} bytes")
        entries = json.loads(manifest.read_bytes())["files"]
        if not isinstance(entries, list):
            raise TypeError("its files are not a list")
    except (OSError, ValueError, LookupError, TypeError) as exc:
        report.warnings.append(f"{manifest} not read, its products not checked against it: "
                               f"{type(exc).__name__}: {exc}")
        return {}
    listed = {}
    for entry in entries:
        if isinstance(entry, dict) and isinstance(entry.get("path"), str) \
                and isinstance(entry.get("sha256"), str):
            size = entry.get("bytes")
            listed[directory / entry["path"]] = _Listed(
                entry["sha256"].lower(), size if isinstance(size, int) else None)
    return listed


def _hash_files(paths: list[Path], listed: Mapping[Path, _Listed] | None = None
                ) -> tuple[str, dict[Path, tuple[str, int]], int]:
    """One read of `paths`: the sha256 of their bytes one after another (a product's identity),
    the sha256 and size of each of them `listed` (in the manifest), and the bytes read after
    the first file."""
    whole = hashlib.sha256()
    own: dict[Path, tuple[str, int]] = {}
    after_first = 0
    for n, path in enumerate(paths):
        single = hashlib.sha256() if listed and path in listed else None
        size = 0
        with open(path, "rb") as fh:
            while chunk := fh.read(_HASH_CHUNK):
                whole.update(chunk)
                size += len(chunk)
                if single is not None:
                    single.update(chunk)
        if single is not None:
            own[path] = (single.hexdigest(), size)
        after_first += size if n else 0
    return whole.hexdigest(), own, after_first


def _sha256(paths: list[Path]) -> str:
    return _hash_files(paths)[0]


def _identify(label: Path, directory: Path, limits: IngestLimits,
              manifest: Mapping[Path, _Listed]) -> _Identity:
    """The product's LIDVID and content digest, read leniently: a label too broken or too large
    to name its product, or naming it by an identifier the catalog cannot hold, is keyed by its
    own sha256 (lid 'unidentified:<sha256>', vid '0'); `rejection` says why for the latter.
    Each file the label names is read once however often it is named; a label naming files
    more often than limits.max_label_files is rejected for it, none of its files read. A cube
    is keyed as the module's docstring says (`_identify_cube`)."""
    if is_cube(label):
        return _identify_cube(label, directory, limits, manifest)
    size = label.stat().st_size
    raw = label.read_bytes() if size <= limits.max_label_bytes else None
    root = None
    if raw is not None:
        try:
            root = ET.fromstring(raw)
        except ET.ParseError:
            pass
    lid = vid = None
    names: list[str] = []
    if root is not None:
        lid = (root.findtext("{*}Identification_Area/{*}logical_identifier") or "").strip()
        vid = (root.findtext("{*}Identification_Area/{*}version_id") or "").strip()
        names = [e.text.strip() for e in root.iterfind(".//{*}File/{*}file_name") if e.text]
    files = list(dict.fromkeys(label.parent / n for n in names if n and Path(n).name == n))
    problem = None if not lid or not vid else _identifier_problem(lid, vid)
    rejection = None if problem is None else ("bad_identifier", problem)
    if len(names) > limits.max_label_files:
        rejection = rejection or ("too_many_files", (
            f"the label names files {len(names)} times, more than the {limits.max_label_files} "
            "file references a product may have (PWM_MAX_LABEL_FILES)"))
        existing = []
    else:
        # only the downlink's own files are read: a link out of it is the product's rejection
        existing = [f for f in files if f.is_file() and f.resolve().is_relative_to(directory)]
    digest, digests, size_bytes = _hash_files([label, *existing], manifest)
    if not lid or not vid or problem:
        lid, vid = _UNIDENTIFIED + _sha256([label]), "0"
    return _Identity(lid=lid, vid=vid, data_path=files[0] if files else None, sha256=digest,
                     size_bytes=size_bytes, files=frozenset(files), rejection=rejection,
                     digests=digests)


def _identify_cube(label: Path, directory: Path, limits: IngestLimits,
                   manifest: Mapping[Path, _Listed]) -> _Identity:
    """A cube's LIDVID (isis:<ProductId or label sha256>::1.0, from its label alone: a copy cut
    short in its core or tables keys as the whole one) and the sha256 of the file; a cube whose
    label cannot be read is keyed by the file's sha256 (and rejected for its label when judged)."""
    digest, digests, _ = _hash_files([label], manifest)
    size = label.stat().st_size
    try:
        lid = _CUBE_LID + cube_key(label, max_label_bytes=limits.max_label_bytes)
    except ProductError:
        return _Identity(lid=_UNIDENTIFIED + digest, vid="0", data_path=label, sha256=digest, size_bytes=size,
                         digests=digests)
    problem = _identifier_problem(lid, _CUBE_VID)
    return _Identity(lid=_UNIDENTIFIED + digest if problem else lid, vid="0" if problem else _CUBE_VID,
                     data_path=label, sha256=digest, size_bytes=size, digests=digests,
                     rejection=None if problem is None else ("bad_identifier", problem))


def _identifier_problem(lid: str, vid: str) -> str | None:
    """Why a label's LID and VID cannot key a product, None if they can: the LIDVID is
    LID::VID, so neither may hold '::' (or two products would share one), and both must fit
    their columns."""
    if "::" in lid or ":" in vid:
        return (f"logical_identifier {lid[:80]!r} and version_id {vid[:40]!r} do not make a "
                "LIDVID: a LID has no '::' and a VID no ':'")
    if not _VID.fullmatch(vid) or len(vid) > _VID_CHARS:
        return f"version_id {vid[:40]!r} is not a PDS4 version (major.minor, at most {_VID_CHARS} characters)"
    if len(lid) + 2 + len(vid) + _CONFLICT_SUFFIX > _LIDVID_CHARS:
        return (f"LIDVID {lid[:80]!r}... is {len(lid) + 2 + len(vid)} characters, more than the "
                f"{_LIDVID_CHARS - _CONFLICT_SUFFIX} the catalog keeps")
    return None


class _Catalog:
    """The image pass's view of the catalog and of the loaded kernel pool."""

    def __init__(self, session: Session, downlink_id: int, shape: Surface | None,
                 directory: Path, limits: IngestLimits, manifest: Mapping[Path, _Listed], data_dir: Path) -> None:
        self.session, self.downlink_id, self.shape = session, downlink_id, shape
        self.directory, self.limits, self.manifest = directory, limits, manifest
        self.data_dir = data_dir
        self.lidar_seen: set[str] = set()  # the LIDVIDs of the lidar products this ingest judged
        self.windows = KernelWindows(spk=coverage_windows(session, KernelKind.SPK),
                                     ck=coverage_windows(session, KernelKind.CK))
        self.instruments: dict[int, Instrument | str] = {
            i.naif_id: i for i in session.scalars(select(Instrument))}
        self.ellipsoids: dict[str, Ellipsoid] = {}
        self.known: dict[tuple[str, str], list[_Known]] = {}
        for lid, vid, known in self._rows(select(Image.lid, Image.vid)):
            self.known.setdefault((lid, vid), []).append(known)

    def _rows(self, query: Any) -> Iterator[tuple[str, str, _Known]]:
        rows = self.session.execute(query.add_columns(
            Image.id, Image.sha256, Image.status, Image.rejection_code, Image.geometry_status))
        for lid, vid, *known in rows:
            yield lid, vid, _Known(*known)

    def reread(self, identity: _Identity) -> list[_Known]:
        """The catalog's copies of the identity's LIDVID as they are now (another ingest may
        have added one since this one read them)."""
        return [k for *_, k in self._rows(select(Image.lid, Image.vid).where(
            Image.lid == identity.lid, Image.vid == identity.vid))]

    def instrument(self, naif_id: int) -> Instrument:
        """The catalogued camera of `naif_id`, read from its IK once (Refusal if unusable)."""
        return read_once(self.instruments, naif_id, self._new_instrument)

    def instrument_row_id(self, naif_id: int | None) -> int | None:
        """The catalog id of a camera `instrument` gave, None for none."""
        found = None if naif_id is None else self.instruments.get(naif_id)
        return found.id if isinstance(found, Instrument) else None

    def _new_instrument(self, naif_id: int) -> Instrument:
        """The camera's row, inserted from its kernels unless another ingest has done so since
        this one read the catalog (or does so now): then that one's row."""
        camera = camera_from_kernel(naif_id)
        source, note = _focal_source(naif_id, camera.fx)
        with sp.no_found_check():
            name, found = sp.bodc2n(naif_id)
        return self._insert_instrument(naif_id, name=name if found else str(naif_id),
                                       frame_name=instrument_frame(naif_id), camera=camera, source=source, note=note)

    def cube_instrument(self, cube: Cube) -> Instrument:
        """The catalogued camera of a cube's instrument; a new one's row from the cube's label
        (its whole detector, from its NaifKeywords) where the catalog has none."""
        def from_cube(naif_id: int) -> Instrument:
            with sp.no_found_check():
                frame = sp.frmnam(naif_id) or str(naif_id)
            return self._insert_instrument(
                naif_id, name=cube.instrument_name[:64], frame_name=frame[:64], camera=cube.detector,
                source="ISIS NaifKeywords", note=f"INS{naif_id}_FOCAL_LENGTH (mm) over INS{naif_id}_PIXEL_SIZE "
                f"(microns) in {cube.path.name}'s label = {cube.detector.fx:.6g} px")
        return read_once(self.instruments, cube.instrument_id, from_cube)

    def _insert_instrument(self, naif_id: int, *, name: str, frame_name: str, camera: Camera, source: str,
                           note: str) -> Instrument:
        self.session.execute(insert_ignoring_conflict(
            self.session, Instrument, unique=[Instrument.naif_id], naif_id=naif_id, name=name,
            spacecraft_id=spacecraft_of(naif_id), frame_name=frame_name, width_px=camera.width,
            height_px=camera.height, fx_px=camera.fx, fy_px=camera.fy, cx_px=camera.cx,
            cy_px=camera.cy, focal_length_source=source, units_note=note))
        return self.session.scalars(select(Instrument).filter_by(naif_id=naif_id)
                                    .execution_options(populate_existing=True)).one()

    def ellipsoid(self, target: str) -> Ellipsoid:
        if target not in self.ellipsoids:
            self.ellipsoids[target] = ellipsoid_of(target)
        return self.ellipsoids[target]


def _focal_source(naif_id: int, fx: float) -> tuple[str, str]:
    """Which IK keywords gave the focal length, and the unit ratio they were read with."""
    length_name = f"INS{naif_id}_FOCAL_LENGTH"
    pixel_names = [f"INS{naif_id}_{k}" for k in ("PIXEL_SIZE", "PIXEL_PITCH")]
    pixel_name = next((n for n in pixel_names if sp.expool(n)), None)
    if not sp.expool(length_name) or pixel_name is None:
        return "FOV", "focal length from the FOV corners and the pixel count"
    length, pixel = sp.gdpool(length_name, 0, 1)[0], sp.gdpool(pixel_name, 0, 1)[0]
    ratio = fx / (length / pixel)
    return (f"FOCAL_LENGTH/{pixel_name.removeprefix(f'INS{naif_id}_')}",
            f"{length_name} = {length:g} over {pixel_name} = {pixel:g}, times {ratio:g} (the "
            f"unit ratio that agrees with the FOV) = {fx:.6g} px")


def _ingest_images(sessions: sessionmaker[Session], directory: Path, labels: list[Path], *,
                   downlink_id: int, report: IngestReport, shape: Surface | None,
                   limits: IngestLimits, manifest: Mapping[Path, _Listed], data_dir: Path,
                   progress: Progress | None) -> set[Path]:
    """Catalogue each label; the files the labels name."""
    named: set[Path] = set()
    with sessions() as session:
        kernels = accepted_kernels(session)
        missing = [k.path for k in kernels if not Path(k.path).is_file()]
        report.warnings += [f"catalogued kernel {p} is missing on disk" for p in missing]
        with kernel_pool(Path(k.path) for k in kernels if k.path not in missing):
            catalog = _Catalog(session, downlink_id, shape, directory, limits, manifest, data_dir)
            for n, label in enumerate(labels, 1):
                if _is_lidar(label, limits):
                    named |= _ingest_lidar(catalog, label, report)
                else:
                    named |= _ingest_product(catalog, label, report)
                if progress is not None:
                    progress("ingest", n, len(labels))
                if n % COMMIT_EVERY == 0:
                    _heartbeat(session, downlink_id)
                    session.commit()
            _heartbeat(session, downlink_id)
            session.commit()
    return named


def _is_lidar(label: Path, limits: IngestLimits) -> bool:
    """Whether a label is a laser altimetry product's: a PDS4 table of shots in a layout
    pwm.io.lidar knows, whole or broken (another table is judged as any product: not an
    image). A label too large to read is left to the image path, which says so."""
    if is_cube(label) or label.stat().st_size > limits.max_label_bytes:
        return False
    raw = label.read_bytes()
    # an image's label holds no table: it is parsed once, by _identify, not here too
    if b"Table_Binary" not in raw and b"Table_Character" not in raw:
        return False
    try:
        return is_lidar_label(ET.fromstring(raw))
    except ET.ParseError:
        return False


@dataclass(frozen=True)
class _LidarOutcome:
    """What judging one lidar product's copy gave: accepted with its rows' values, or rejected."""

    status: Acceptance
    code: str | None = None
    reason: str | None = None
    values: Mapping[str, Any] = field(default_factory=dict)
    tracks: tuple[LidarTrack, ...] = ()

    @property
    def verdict(self) -> tuple:
        return (self.status, self.code, self.reason, self.values.get("invalid_shots", {}),
                self.values.get("shots_artifact"))


def _lidar_provisional(row: LidarProduct) -> bool:
    """A catalogued lidar product whose outcome may change with the same content: rejected for
    its transfer or its kernels, or with shots whose time the kernels did not cover."""
    if row.status is Acceptance.REJECTED:
        return row.rejection_code in _PROVISIONAL_CODES | LIDAR_KERNEL_CODES
    return bool(row.invalid_shots.get(Invalid.OUTSIDE_KERNELS.name.lower()))


def _ingest_lidar(catalog: _Catalog, label: Path, report: IngestReport) -> frozenset[Path]:
    """Catalogue one lidar product (the module's docstring) in a savepoint and count it in
    `report`; the files its label names. Any exception in its checks is its rejection (code
    `unexpected`); a row of its LIDVID that a concurrent ingest inserted first is read, and the
    product judged once more against it."""
    try:
        identity = _identify(label, catalog.directory, catalog.limits, catalog.manifest)
    except OSError as exc:
        report.lidar.rejected += 1
        report.failures.append(Failure(str(label), "unreadable", str(exc)))
        return frozenset()
    outcome: _LidarOutcome | None
    try:
        try:
            outcome = _lidar_in_savepoint(catalog, label, identity)
        except IntegrityError:
            outcome = _lidar_in_savepoint(catalog, label, identity)
    except Exception as exc:
        log.exception("%s: rejected on an unexpected error", label)
        outcome = _LidarOutcome(Acceptance.REJECTED, UNEXPECTED, f"{type(exc).__name__}: {exc}")
        try:
            with catalog.session.begin_nested():
                _record_lidar(catalog, label, identity, outcome)
        except Exception:
            log.exception("%s: its rejection could not be stored", label)
    if outcome is None:
        report.lidar.unchanged += 1
    elif outcome.status is Acceptance.ACCEPTED:
        report.lidar.accepted += 1
        report.lidar_shots += outcome.values["shots"]
        report.lidar_valid_shots += outcome.values["valid_shots"]
    else:
        report.lidar.rejected += 1
        report.failures.append(Failure(str(label), outcome.code or "", outcome.reason or ""))
    return identity.files


def _lidar_in_savepoint(catalog: _Catalog, label: Path, identity: _Identity) -> _LidarOutcome | None:
    """Judge and record one lidar product's copy; None when the catalog already says what it
    would. A catalogued copy with other content stays, unless it arrived broken."""
    with catalog.session.begin_nested():
        row = catalog.session.scalars(select(LidarProduct).filter_by(lidvid=identity.lidvid)).one_or_none()
        if row is not None and row.sha256 == identity.sha256 and (
                identity.lidvid in catalog.lidar_seen or not _lidar_provisional(row)):
            return None
        if row is not None and row.sha256 != identity.sha256 and not (
                row.status is Acceptance.REJECTED and row.rejection_code in _PROVISIONAL_CODES):
            reason = (f"{identity.lidvid} is catalogued already with other content (sha256 {row.sha256}); "
                      f"this copy (sha256 {identity.sha256}) is not used")
            for path in [label, *identity.files]:
                if path.is_file():
                    record_file(catalog.session, downlink_id=catalog.downlink_id, path=path, code=CONFLICT,
                                reason=reason)
            return _LidarOutcome(Acceptance.REJECTED, CONFLICT, reason)
        outcome = _judge_lidar(catalog, label, identity)
        changed = _record_lidar(catalog, label, identity, outcome, row)
        catalog.session.flush()
    catalog.lidar_seen.add(identity.lidvid)
    return outcome if changed else None


def _record_lidar(catalog: _Catalog, label: Path, identity: _Identity, outcome: _LidarOutcome,
                  row: LidarProduct | None = None) -> bool:
    """Store the outcome on `row` (a new one for None), its tracks replaced; False where the
    row already said it."""
    if row is None:
        row = catalog.session.scalars(select(LidarProduct).filter_by(lidvid=identity.lidvid)).one_or_none()
    if row is None:
        row = LidarProduct(lidvid=identity.lidvid, lid=identity.lid, vid=identity.vid)
        catalog.session.add(row)
    elif (row.sha256 == identity.sha256 and (row.status, row.rejection_code, row.rejection_reason, row.invalid_shots,
                                               row.shots_artifact) == outcome.verdict):
        return False
    row.label_path, row.data_path = str(label), str(identity.data_path or "")
    row.sha256, row.size_bytes, row.downlink_id = identity.sha256, identity.size_bytes, catalog.downlink_id
    row.status, row.rejection_code, row.rejection_reason = outcome.status, outcome.code, outcome.reason
    blank: dict[str, Any] = {"layout": None, "instrument": None, "target": None, "body_frame": None,
                             "start_et": None, "stop_et": None, "start_utc": None, "stop_utc": None, "shots": 0,
                             "valid_shots": 0, "invalid_shots": {}, "shots_artifact": None}
    for name, value in (blank | dict(outcome.values)).items():
        setattr(row, name, value)
    row.ingested_at = utcnow()
    row.tracks = list(outcome.tracks)
    return True


def _judge_lidar(catalog: _Catalog, label: Path, identity: _Identity) -> _LidarOutcome:
    """Read a lidar product's table within the limits, resolve its target's frame, place its
    shots with the loaded kernels, group them into tracks and store them (the module's
    docstring); or its rejection."""
    if identity.rejection is not None:
        return _LidarOutcome(Acceptance.REJECTED, *identity.rejection)
    incomplete = _off_manifest(catalog, identity)
    if incomplete is not None:
        return _LidarOutcome(Acceptance.REJECTED, incomplete.code, incomplete.reason)
    try:
        table = read_lidar_table(label, root=catalog.directory, max_label_bytes=catalog.limits.max_label_bytes,
                                 max_shots=catalog.limits.max_lidar_shots)
    except ProductError as exc:
        return _LidarOutcome(Acceptance.REJECTED, exc.code, str(exc))
    except OSError as exc:
        return _LidarOutcome(Acceptance.REJECTED, "unreadable", str(exc))
    named = {"layout": table.layout, "instrument": (table.instrument or "")[:64] or None,
             "target": (table.target or "")[:64] or None, "shots": len(table.et)}
    if not len(table.et):
        return _LidarOutcome(Acceptance.REJECTED, "no_shots", f"{label.name}: its table holds no shots", named)
    target, frame = target_frame(table.target)
    if target is None or frame is None:
        said = "no target" if not table.target else f"target {table.target!r}"
        why = "SPICE knows no such body" if target is None else "the kernels give it no body-fixed frame"
        return _LidarOutcome(Acceptance.REJECTED, "unknown_target", f"{label.name} names {said}: {why}", named)
    try:
        shots = place_shots(table, target=body_name(target), body_frame=frame)
    except ProductError as exc:
        return _LidarOutcome(Acceptance.REJECTED, exc.code, str(exc), named)
    except sp.utils.exceptions.SpiceyError as exc:
        return _LidarOutcome(Acceptance.REJECTED, "geometry", spice_message(exc), named)
    codes, counts = np.unique(shots.invalid, return_counts=True)
    invalid = {Invalid(int(c)).name.lower(): int(n) for c, n in zip(codes, counts, strict=True)
               if c != Invalid.VALID}
    valid = int(shots.valid.sum())
    if not valid and invalid.get(Invalid.OUTSIDE_KERNELS.name.lower()):
        return _LidarOutcome(Acceptance.REJECTED, "outside_coverage", (
            f"{label.name}: none of its {len(shots)} shots is usable, {invalid['outside_kernels']} of them at "
            "times the kernels hold no pose for; judged again when kernels come"), named)
    track = track_ids(shots, LIDAR)
    with scratch_file(catalog.data_dir, ".npz") as scratch:
        write_shots(scratch, shots, track)
        artifact = store_artifact(catalog.data_dir, scratch)
    finite = table.et[np.isfinite(table.et)]
    span = (float(finite.min()), float(finite.max())) if len(finite) else (None, None)
    tracks = tuple(LidarTrack(
        track=e.track, start_et=e.start_et, stop_et=e.stop_et, shots=e.shots,
        cone_axis_x=float(e.axis[0]), cone_axis_y=float(e.axis[1]), cone_axis_z=float(e.axis[2]),
        cone_half_angle_rad=e.half_angle_rad, axis_lat_deg=float(np.degrees(np.arcsin(np.clip(e.axis[2], -1, 1)))),
        axis_lon_deg=float(np.degrees(np.arctan2(e.axis[1], e.axis[0])) % 360.0),
        min_x_km=float(e.box_min_km[0]), min_y_km=float(e.box_min_km[1]), min_z_km=float(e.box_min_km[2]),
        max_x_km=float(e.box_max_km[0]), max_y_km=float(e.box_max_km[1]), max_z_km=float(e.box_max_km[2]))
        for e in track_extents(shots.spots_km(), shots.et, track))
    return _LidarOutcome(Acceptance.ACCEPTED, values=named | {
        "body_frame": frame, "start_et": span[0], "stop_et": span[1], "start_utc": _utc(span[0]),
        "stop_utc": _utc(span[1]), "valid_shots": valid, "invalid_shots": invalid, "shots_artifact": artifact},
        tracks=tracks)


def _utc(et: float | None) -> datetime | None:
    """An ephemeris time as UTC (the pool's leapseconds), None where there is none."""
    if et is None:
        return None
    try:
        return sp.et2datetime(et).astimezone(UTC)
    except (sp.utils.exceptions.SpiceyError, ValueError, OverflowError):
        return None


def _ingest_product(catalog: _Catalog, label: Path, report: IngestReport) -> frozenset[Path]:
    """Catalogue one label and count what it did in `report`; the files it names.

    The product is judged on its own, in a savepoint: any exception in its checks is its
    rejection (code `unexpected`, with the exception), the products before it stay. A row of
    its LIDVID that another ingest inserted since this one read the catalog (the insert lost
    the race) is read, and the product judged once more against it."""
    try:
        identity = _identify(label, catalog.directory, catalog.limits, catalog.manifest)
    except OSError as exc:  # unreadable files cannot be keyed: reported, not catalogued
        report.images.rejected += 1
        report.failures.append(Failure(str(label), "unreadable", str(exc)))
        return frozenset()
    versions = catalog.known.setdefault((identity.lid, identity.vid), [])
    kept = _keep(catalog, versions)
    try:
        try:
            outcome = _catalogue_in_savepoint(catalog, label, identity, versions)
        except IntegrityError:
            _restore(catalog, versions, kept)
            versions[:] = catalog.reread(identity)
            kept = _keep(catalog, versions)
            outcome = _catalogue_in_savepoint(catalog, label, identity, versions)
    except Exception as exc:
        log.exception("%s: rejected on an unexpected error", label)
        _restore(catalog, versions, kept)
        outcome = _store_rejection(catalog, label, identity, _Outcome(
            ImageStatus.REJECTED, UNEXPECTED, f"{type(exc).__name__}: {exc}"))
    if outcome is None:
        report.images.unchanged += 1
    elif outcome.status is ImageStatus.ACCEPTED:
        report.images.accepted += 1
        report.geometry_unavailable += outcome.geometry_status is GeometryStatus.UNAVAILABLE
    else:
        report.images.rejected += 1
        report.failures.append(Failure(str(label), outcome.code or "", outcome.reason or ""))
    return identity.files


def _catalogue_in_savepoint(catalog: _Catalog, label: Path, identity: _Identity,
                            versions: list[_Known]) -> _Outcome | None:
    """_catalogue with its rows flushed in a savepoint: a failed insert rolls back this product
    only."""
    with catalog.session.begin_nested():
        outcome = _catalogue(catalog, label, identity, versions)
        catalog.session.flush()
    return outcome


def _store_rejection(catalog: _Catalog, label: Path, identity: _Identity, outcome: _Outcome
                     ) -> _Outcome | None:
    """Record a product's rejection under its LIDVID, else (that being what failed) under its
    label's sha256; None when the catalog already says so. If neither can be stored, the
    rejection is only reported."""
    unidentified = dataclasses.replace(identity, lid=_UNIDENTIFIED + _sha256([label]), vid="0")
    for key in (identity, unidentified):
        versions = catalog.known.setdefault((key.lid, key.vid), [])
        kept = _keep(catalog, versions)
        same = next((k for k in versions if k.sha256 == key.sha256), None)
        if same is not None and same.seen:
            return None
        try:
            with catalog.session.begin_nested():
                stored = _record(catalog, label, key, same, outcome)
                catalog.session.flush()
            return outcome if stored else None
        except Exception:
            log.exception("%s: its rejection could not be stored as %s", label, key.lidvid)
            _restore(catalog, versions, kept)
    return outcome


_Kept = tuple[list[tuple[_Known, dict[str, Any]]], set[int]]


def _keep(catalog: _Catalog, versions: list[_Known]) -> _Kept:
    """The catalog's in-memory view of a product's copies, to restore should it roll back."""
    return [(k, dict(vars(k))) for k in versions], set(catalog.instruments)


def _restore(catalog: _Catalog, versions: list[_Known], kept: _Kept) -> None:
    """Put the catalog's in-memory view back as it was before a product rolled back."""
    known, instruments = kept
    versions[:] = [k for k, _ in known]
    for k, fields in known:
        vars(k).update(fields)
    for naif_id in set(catalog.instruments) - instruments:
        del catalog.instruments[naif_id]


def _catalogue(catalog: _Catalog, label: Path, identity: _Identity, versions: list[_Known]
               ) -> _Outcome | None:
    """Judge and record one product; None when the catalog already says what it would. The
    copy holding the LIDVID is authoritative against other content unless it arrived broken."""
    same = next((k for k in versions if k.sha256 == identity.sha256), None)
    if same is not None and (same.seen or not same.provisional):
        return None
    holder = next((k for k in versions if k.status is not ImageStatus.CONFLICT), None)
    if same is None and holder is not None and not holder.broken:
        return _conflict(catalog, label, identity, catalogued=holder.sha256)
    outcome = _judge_copy(catalog, label, identity)
    if same is None and holder is not None:
        return _replace(catalog, label, identity, holder, outcome)
    return outcome if _record(catalog, label, identity, same, outcome) else None


def _judge_copy(catalog: _Catalog, label: Path, identity: _Identity) -> _Outcome:
    """The outcome of this copy: its rejection from keying it, else as incomplete where it is
    off the manifest (its content not what was sent), else as its label, array and geometry say."""
    if identity.rejection is not None:
        return _Outcome(ImageStatus.REJECTED, *identity.rejection)
    return _off_manifest(catalog, identity) or _judge(catalog, label)


def _off_manifest(catalog: _Catalog, identity: _Identity) -> _Outcome | None:
    """The product's rejection as incomplete when a file of it differs from the manifest (still
    arriving, or cut short): judged again on the next ingest."""
    for path, (digest, size) in sorted(identity.digests.items()):
        listed = catalog.manifest[path]
        if digest != listed.sha256:
            expected = "" if listed.size_bytes is None else f" ({listed.size_bytes} bytes)"
            return _Outcome(ImageStatus.REJECTED, INCOMPLETE, (
                f"{path.relative_to(catalog.directory).as_posix()} differs from the downlink's "
                f"manifest: it has sha256 {digest} ({size} bytes), the manifest lists sha256 "
                f"{listed.sha256}{expected}; judged again when it matches"))
    return None


def _record(catalog: _Catalog, label: Path, identity: _Identity, same: _Known | None,
            outcome: _Outcome) -> bool:
    """Store the outcome as a new row, or over `same`; False if `same` already says it."""
    versions = catalog.known[(identity.lid, identity.vid)]
    if same is not None:
        image = catalog.session.get_one(Image, same.id)
        same.seen = True
        if _verdict(image) == outcome.verdict:
            return False
        same.status, same.code = outcome.status, outcome.code
        same.geometry_status = outcome.geometry_status
    else:
        image = Image(lidvid=identity.lidvid, lid=identity.lid, vid=identity.vid,
                      downlink_id=catalog.downlink_id)
        catalog.session.add(image)
    _apply(image, identity, label, outcome)
    if same is None:
        catalog.session.flush()  # its id, should another copy of it come in this ingest
        versions.append(_Known(image.id, identity.sha256, outcome.status, outcome.code,
                               outcome.geometry_status, seen=True))
    return True


def _replace(catalog: _Catalog, label: Path, identity: _Identity, holder: _Known,
             outcome: _Outcome) -> _Outcome:
    """Record a copy of a product whose catalogued copy (`holder`) arrived broken. A copy not
    broken itself, or the same file again, takes the holder's row (its id kept) for this
    downlink; the broken copy, if it is still offered elsewhere (its label there), stays on as
    a copy not used. A broken copy of another file is itself a copy not used."""
    image = catalog.session.get_one(Image, holder.id)
    same_file = image.label_path == str(label)
    if not same_file and outcome.status is ImageStatus.REJECTED and outcome.code in _PROVISIONAL_CODES:
        return _conflict(catalog, label, identity, catalogued=holder.sha256,
                         detail=f"; it was rejected {outcome.code}: {outcome.reason}")
    if not same_file and Path(image.label_path).is_file():
        broken = _Identity(lid=image.lid, vid=image.vid, sha256=image.sha256,
                           data_path=Path(image.data_path) if image.data_path else None,
                           size_bytes=image.size_bytes)
        _conflict(catalog, Path(image.label_path), broken, catalogued=identity.sha256,
                  detail=f"; it was rejected {image.rejection_code}: {image.rejection_reason}",
                  downlink_id=image.downlink_id)
    holder.sha256, holder.status, holder.code = identity.sha256, outcome.status, outcome.code
    holder.geometry_status, holder.seen = outcome.geometry_status, True
    image.downlink_id = catalog.downlink_id
    _apply(image, identity, label, outcome)
    return outcome


def _conflict(catalog: _Catalog, label: Path, identity: _Identity, *, catalogued: str,
              detail: str = "", downlink_id: int | None = None) -> _Outcome:
    """Record a copy not used: the LIDVID is catalogued with other content (sha256
    `catalogued`), which stays. detail: what else to say of the copy; downlink_id: the
    downlink that offered it (default this ingest's)."""
    reason = (f"{identity.lidvid} is catalogued already with other content (sha256 "
              f"{catalogued}); this copy (sha256 {identity.sha256}) is not used{detail}")
    outcome = _Outcome(status=ImageStatus.CONFLICT, code="conflict", reason=reason)
    image = Image(lidvid=f"{identity.lidvid}#{identity.sha256[:16]}", lid=identity.lid,
                  vid=identity.vid, downlink_id=downlink_id or catalog.downlink_id)
    _apply(image, identity, label, outcome)
    catalog.session.add(image)
    catalog.known[(identity.lid, identity.vid)].append(
        _Known(None, identity.sha256, outcome.status, outcome.code, outcome.geometry_status,
               seen=True))
    return outcome


def _verdict(image: Image) -> tuple:
    return (image.status, image.rejection_code, image.rejection_reason, image.geometry_status,
            image.geometry_unavailable_reason)


def _apply(image: Image, identity: _Identity, label: Path, outcome: _Outcome) -> None:
    product = outcome.product
    image.label_path = str(label)
    image.data_path = str(product.data_path if product is not None else identity.data_path or "")
    image.sha256, image.size_bytes = identity.sha256, identity.size_bytes
    image.md5 = product.md5 if product is not None else None
    target = product.target_name if product else outcome.cube.target_name if outcome.cube else None
    image.target = target[:64] if target else None
    image.start_utc, image.stop_utc, image.start_et, image.stop_et = (
        outcome.times or (None, None, None, None))
    image.instrument_id = outcome.instrument_id
    if product is not None:
        image.window_first_line, image.window_first_sample = product.first_line, product.first_sample
        image.window_lines, image.window_samples = product.lines, product.samples
    elif outcome.cube is not None:
        (image.window_first_line, image.window_first_sample, image.window_lines,
         image.window_samples) = outcome.cube.window
    image.status, image.rejection_code = outcome.status, outcome.code
    image.rejection_reason = outcome.reason
    image.geometry_status = outcome.geometry_status
    image.geometry_unavailable_reason = outcome.geometry_reason
    image.geometry = outcome.geometry


def _judge(catalog: _Catalog, label: Path) -> _Outcome:
    """Read the product's label, work out its geometry from the loaded kernels, then read its
    array: the label's declared size is checked against the detector (and the pixel limit)
    before any array is read. A cube: `_judge_cube`."""
    if is_cube(label):
        return _judge_cube(catalog, label)
    try:
        product = read_image_label(label, root=catalog.directory,
                                   max_label_bytes=catalog.limits.max_label_bytes,
                                   max_pixels=catalog.limits.max_pixels,
                                   max_fits_header_bytes=catalog.limits.max_fits_header_bytes)
    except ProductError as exc:
        return _Outcome(ImageStatus.REJECTED, exc.code, str(exc))
    except OSError as exc:  # e.g. a file gone since it was hashed
        return _Outcome(ImageStatus.REJECTED, "unreadable", str(exc))
    try:
        times = exposure(product)
    except ProductError as exc:
        return _Outcome(ImageStatus.REJECTED, exc.code, str(exc), product=product)
    try:
        outcome = _geometry(catalog, product, times)
    except Refusal as exc:
        return _Outcome(ImageStatus.REJECTED, exc.code, str(exc), product=product, times=times,
                        instrument_id=catalog.instrument_row_id(exc.instrument_id))
    except sp.utils.exceptions.SpiceyError as exc:  # kernels that resolve names but lack data
        return _Outcome(ImageStatus.REJECTED, "geometry", spice_message(exc), product=product,
                        times=times)
    try:
        read_array(product)  # readable, as the refinement will read it
    except ProductError as exc:
        return _Outcome(ImageStatus.REJECTED, exc.code, str(exc), product=product, times=times,
                        instrument_id=outcome.instrument_id)
    return outcome


def _judge_cube(catalog: _Catalog, label: Path) -> _Outcome:
    """Read a cube's label and attached geometry (pwm.io.isis), its geometry on the current
    shape (else the ellipsoid its label gives), then its pixels, as the refinement reads them."""
    try:
        cube = read_cube(label, max_label_bytes=catalog.limits.max_label_bytes,
                         max_pixels=catalog.limits.max_pixels)
    except ProductError as exc:
        return _Outcome(ImageStatus.REJECTED, exc.code, str(exc))
    except OSError as exc:
        return _Outcome(ImageStatus.REJECTED, "unreadable", str(exc))
    half = 0.5 * cube.exposure_s
    times = Exposure(cube.start_utc, cube.stop_utc, cube.et - half, cube.et + half)
    try:
        instrument_id = catalog.instrument_row_id(catalog.cube_instrument(cube).naif_id)
        view = view_geometry(pose=cube.pose, sun=cube.sun, camera=cube.camera,
                             surface=catalog.shape or Ellipsoid(cube.radii_km))
        read_cube_pixels(cube)
    except (ProductError, OSError) as exc:
        return _Outcome(ImageStatus.REJECTED, getattr(exc, "code", "unreadable"), str(exc), times=times, cube=cube)
    return _Outcome(ImageStatus.ACCEPTED, geometry_status=GeometryStatus.COMPUTED, instrument_id=instrument_id,
                    times=times, geometry=_geometry_row(view, cube.body_frame), cube=cube)


def _geometry(catalog: _Catalog, product: ImageLabel, times: Exposure) -> _Outcome:
    """The product's geometry on the current shape (else the target's ellipsoid), its label
    resolved against the pool (pwm.io.resolve); accepted without geometry where the catalog has
    no kernels for its observer, Refusal where they do not resolve it."""
    try:
        image = resolve_label(product, times, windows=catalog.windows,
                              detector=lambda naif_id: _detector(catalog.instrument(naif_id)))
    except Refusal as exc:
        if exc.code != NO_KERNELS:
            raise
        return _Outcome(ImageStatus.ACCEPTED, geometry_reason=str(exc), product=product,
                        times=times)
    surface = catalog.shape or catalog.ellipsoid(str(image.target))
    pose, sun = pose_and_sun(image, windows=catalog.windows)
    view = view_geometry(pose=pose, sun=sun, camera=image.camera, surface=surface)
    return _Outcome(ImageStatus.ACCEPTED, geometry_status=GeometryStatus.COMPUTED,
                    product=product, instrument_id=catalog.instrument_row_id(image.instrument_id),
                    times=times, geometry=_geometry_row(view, image.body_frame))


def _detector(instrument: Instrument) -> Camera:
    """The camera of the instrument's whole detector, as the catalog holds it."""
    return Camera(width=instrument.width_px, height=instrument.height_px,
                  fx=instrument.fx_px, fy=instrument.fy_px, cx=instrument.cx_px,
                  cy=instrument.cy_px)


def _geometry_row(view: ViewGeometry, body_frame: str) -> ImageGeometry:
    x, y, z = (float(v) for v in view.position_km)
    sx, sy, sz = (float(v) for v in view.sun)
    return ImageGeometry(
        camera_x_km=x, camera_y_km=y, camera_z_km=z, camera_rotation=view.rotation.tolist(),
        sun_x=sx, sun_y=sy, sun_z=sz, range_km=view.range_km,
        intercept_range_km=view.intercept_range_km, pixel_scale_m=view.pixel_scale_m,
        phase_deg=view.phase_deg, incidence_deg=view.incidence_deg,
        emission_deg=view.emission_deg, intercept_lat_deg=view.intercept_lat_deg,
        intercept_lon_deg=view.intercept_lon_deg,
        footprint=[None if c is None else list(c) for c in view.footprint],
        cone_axis_x=float(view.cone_axis[0]), cone_axis_y=float(view.cone_axis[1]),
        cone_axis_z=float(view.cone_axis[2]), cone_half_angle_rad=view.cone_half_angle_rad,
        body_frame=body_frame, abcorr=ABCORR)
