"""Request and response bodies of the HTTP API (pydantic). Units are in field names (km, m, deg);
positions are body-fixed; times are UTC (ISO 8601 with an offset)."""

from __future__ import annotations

import re
from datetime import datetime
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ConfigDict, Field, field_validator

from service.downlinks import Outcome
from service.jobs import JobState, error_reason, job_state
from service.queries import CoverageSummary, MapletCoverage, MapletImage, MapletInfo, RevisionInfo
from service.rows import Acceptance, DownlinkStatus, GeometryStatus, ImageStatus, Job, JobKind, ModelKind

Item = TypeVar("Item")

# A release tag: a letter first, so that it never reads as a version number; no `latest` or
# `released`, which name versions by their place.
TAG_PATTERN = r"^[A-Za-z][A-Za-z0-9._-]{0,63}$"
RESERVED_TAGS = frozenset({"latest", "released"})
# A version reference: a number, a tag, `latest` or `released`.
VERSION_REF_PATTERN = r"^([0-9]{1,9}|[A-Za-z][A-Za-z0-9._-]{0,63})$"
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
# The longest name of one directory entry, in bytes (Linux's NAME_MAX).
NAME_MAX_BYTES = 255


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid")


class _Out(BaseModel):
    model_config = ConfigDict(from_attributes=True)


class Page(_Out, Generic[Item]):
    """One page of a listing: `total` rows match, `items` are those from `offset` on."""

    items: list[Item]
    total: int
    limit: int
    offset: int


class ArtifactOut(_Out):
    sha256: str
    bytes: int


class TileOut(_Out):
    """One tile of a version stored in tiles: its key (`GET /versions/{ref}/export?tile=KEY`),
    face and vertex counts, bounding box (lowest and highest x, y, z; km, body-fixed) and its
    stored file's checksum and size."""

    key: str
    faces: int
    vertices: int
    box_min_km: list[float]
    box_max_km: list[float]
    sha256: str
    bytes: int


class VersionTiles(_Out):
    """The tiles a version's mesh is stored in (service.versions.store_mesh)."""

    version: int
    vertices: int
    faces: int
    tiles: list[TileOut]


class DownlinkRef(_Out):
    id: int
    name: str


class VersionSummary(_Out):
    version: int
    kind: ModelKind
    parent: int | None = Field(description="version number of the parent")
    created_at: datetime
    released: bool
    release_tag: str | None
    vertices: int | None
    faces: int | None


class Lineage(_Out):
    """Where a version comes from: its ancestors (parent first), children, the downlinks whose
    data it holds and the maplet revisions it was fused from."""

    ancestors: list[int]
    children: list[int]
    downlinks: list[DownlinkRef]
    maplet_revisions: int


class VersionDetail(VersionSummary):
    statistics: dict[str, Any]
    artifacts: dict[str, ArtifactOut]
    lineage: Lineage


class ReleaseRequest(_Body):
    tag: str = Field(pattern=TAG_PATTERN, description="set once; `latest` and `released` are "
                     "reserved")

    @field_validator("tag")
    @classmethod
    def _not_reserved(cls, tag: str) -> str:
        if tag.lower() in RESERVED_TAGS:
            raise ValueError(f"{tag!r} is reserved")
        return tag


class IngestRequest(_Body):
    path: str = Field(min_length=1, max_length=1024,
                      description="a directory, relative to the data directory's incoming area")

    @field_validator("path")
    @classmethod
    def _printable(cls, path: str) -> str:
        if _CONTROL.search(path):
            raise ValueError("the path holds control characters")
        # pydantic refuses lone surrogates, so every str here encodes
        if any(len(part.encode()) > NAME_MAX_BYTES for part in path.split("/")):
            raise ValueError(f"a component of the path is over {NAME_MAX_BYTES} bytes")
        return path


class JobSubmitted(_Out):
    key: str = Field(description="the job's idempotency key; GET /jobs?key= finds it")


class PoseSigmaOut(_Out):
    """1-sigma figures of a pose (pwm.spg.uncertainty.PoseSigma): lateral position and position
    along the boresight (m), pointing (microradians), line of sight (pixels)."""

    lateral_m: float
    along_m: float
    pointing_urad: float
    los_px: float


class PoseCorrectionOut(_Out):
    """An image's pose correction from bundle adjustment (service.spg), applied on top of its
    kernels' pose: the camera's offset (body-fixed, m) and a small rotation (microradians); the
    latest adjustment's 1-sigma figures before (the navigation knowledge) and after it, and which
    of them the images determined (the posterior under half the prior)."""

    position_m: list[float]
    rotation_urad: list[float]
    corrected_at: datetime
    sigma_prior: PoseSigmaOut | None = None
    sigma_posterior: PoseSigmaOut | None = None
    determined: list[str] = []


class GeometryOut(_Out):
    camera_km: list[float]
    sun_direction: list[float]
    range_km: float
    intercept_range_km: float | None
    pixel_scale_m: float | None
    phase_deg: float | None
    incidence_deg: float | None
    emission_deg: float | None
    intercept_lat_deg: float | None
    intercept_lon_deg: float | None
    footprint: list[Any] | None
    body_frame: str
    computed_at: datetime


class ImageOut(_Out):
    id: int
    lidvid: str
    status: ImageStatus
    rejection_code: str | None
    rejection_reason: str | None
    downlink_id: int | None
    instrument: str | None
    target: str | None
    start_utc: datetime | None
    stop_utc: datetime | None
    geometry_status: GeometryStatus
    geometry: GeometryOut | None
    pose_corrected: bool
    pose_correction: PoseCorrectionOut | None = None


class ImageDetail(ImageOut):
    maplets: list[MapletCoverage]


class DownlinkOut(_Out):
    """A downlink and what its ingest made of it (service.downlinks): outcome rejected when
    every product failed; unused_files, the files it offered that are neither kernels nor
    products (each with its reason in the catalog); repeat_count, its deliveries after the
    first."""

    id: int
    name: str
    received_at: datetime
    status: DownlinkStatus
    outcome: Outcome
    kernels: int
    images: dict[ImageStatus, int]
    accepted: int
    rejected: int
    conflict: int
    unused_files: int
    lidar: dict[Acceptance, int] = Field(description="its lidar products by status")
    lidar_shots: int = Field(description="the shots of its accepted lidar products")
    lidar_valid_shots: int = Field(description="those of them usable (a valid return, placed)")
    repeat_count: int
    last_seen_at: datetime | None
    model_note: str | None = Field(description="set when the downlink came to a catalog without "
                                               "a model: the version its images made, or why none "
                                               "could be made yet")
    pose_adjustment: dict[str, Any] | None = Field(
        default=None, description="what the adjustment of the downlink's poses did: the pose knowledge taken "
        "(knowledge, source), the median line of sight before and after (los_prior_px, los_posterior_px, "
        "1 sigma), the pose model's unknowns with their values and sigmas, or why none ran (note)")


class JobOut(_Out):
    """A job; `error` is why its latest attempt failed, the full `traceback` goes only to
    callers with the API token (it names the server's files)."""

    id: int
    kind: JobKind
    key: str
    status: JobState = Field(description="`lost`: running, but its attempt's heartbeat stopped "
                             "(its worker died); it is taken over after the grace")
    attempts: int
    progress: float
    message: str | None
    error: str | None = Field(description="why the latest attempt failed: the exception's last "
                              "line, with paths reduced to file names")
    traceback: str | None = Field(None, description="the failed attempt's full traceback; only "
                                  "with the API token")
    worker: str | None = Field(description="the worker (node:pid) of the latest attempt")
    heartbeat_at: datetime | None = Field(description="the latest attempt's latest heartbeat")
    enqueued_at: datetime | None = Field(description="when the job was last handed to the broker")
    enqueue_error: str | None = Field(description="why the last hand-over to the broker failed; "
                                      "the reconciler tries again")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    downlink_id: int | None
    maplet_id: int | None

    @classmethod
    def shown(cls, job: Job, *, with_traceback: bool, grace_s: float) -> JobOut:
        """The job as shown to a caller: lost when its heartbeat is older than grace_s (s), the
        reason for anyone, the traceback only `with_traceback` (a caller with the token)."""
        return cls.model_validate(job).model_copy(update={
            "status": job_state(job, grace_s=grace_s),
            "error": error_reason(job.error),
            "traceback": job.error if with_traceback else None})


class MapletDetail(_Out):
    maplet: MapletInfo
    origin_km: list[float]
    rotation: list[Any]
    coverage: CoverageSummary
    images: list[MapletImage]
    revisions: list[RevisionInfo]


class LidarFiguresOut(_Out):
    """Signed distances of lidar spots to a model (km, positive outside): mean, RMS and 95th
    percentile of their magnitudes; None where no spot was measured."""

    shots: int = Field(description="spots measured")
    mean_km: float | None
    rms_km: float | None
    p95_km: float | None
    crossovers: int | None = Field(None, description="crossovers with other tracks (per track; in all: the "
                                   "version's figure)")
    crossover_rms_km: float | None = Field(None, description="RMS of their height differences")
    disagreement_sigmas: float | None = Field(
        None, description="per track: |mean| in the track's own sigmas (its placement's and its spots' scatter over "
                          "their number); null where the track is not placed")


class LidarMapOut(_Out):
    lon_cells: int
    lat_cells: int
    rms_km: list[list[float | None]] = Field(
        description="RMS distance per cell (km): rows from the south pole up in planetocentric latitude, "
                    "columns east from longitude 0; null where no spot fell")


class LidarResidualsOut(_Out):
    """A version checked against the catalog's lidar when it was published
    (service.publish.lidar_statistics): a uniform sample of the usable shots, each track's strip
    correction applied where it had one."""

    version: int
    products: int
    usable_shots: int = Field(description="the catalog's usable shots, of which `shots` were sampled")
    shots: int
    measured: int
    missed: int = Field(description="sampled spots that met no surface near them")
    mean_km: float | None
    rms_km: float | None
    p95_km: float | None
    crossovers: int | None = Field(None, description="crossovers between the sampled spots of different tracks")
    tracks: dict[int, LidarFiguresOut] = Field(description="per track, by its catalog id (GET /lidar/tracks)")
    map: LidarMapOut
    disagree_sigmas: float | None = Field(None, description="how many of its sigmas a track's mean may lie off")
    disagreeing_tracks: list[int] = Field(
        default_factory=list, description="tracks (catalog ids) whose mean lies further off the version than "
                                          "`disagree_sigmas`: flagged, not averaged in")


class LidarCorrectionOut(_Out):
    """A track's strip correction (pwm.lidar.strips): a rotation vector (rad) about `about_km`
    and a translation (km), body-fixed, applied to its spots; 1 sigma of the six (rotation rad,
    then translation km; null where the track did not constrain it)."""

    rotation_rad: list[float]
    translation_km: list[float]
    about_km: list[float]
    sigma: list[float | None]
    adjusted_at: datetime


class LidarTrackOut(_Out):
    """A catalogued lidar track: its span (TDB seconds past J2000), usable shots, the cone about
    the body's centre holding its spots, its strip correction once adjusted, and its spots'
    residuals on the version they were last measured on."""

    id: int
    product: str = Field(description="the LIDVID of its product")
    track: int = Field(description="its number in the product")
    start_et: float
    stop_et: float
    shots: int
    axis_lat_deg: float
    axis_lon_deg: float
    cone_half_angle_deg: float
    correction: LidarCorrectionOut | None
    residual_version: int | None = Field(description="the version its residuals were measured on")
    residual_mean_km: float | None
    residual_rms_km: float | None
    residual_p95_km: float | None
    crossovers: int | None = Field(description="its spots' crossovers with other tracks' (corrections applied)")
    crossover_rms_km: float | None = Field(description="RMS of those crossovers' height differences")


class Problem(_Out):
    """An error: what went wrong, in words."""

    detail: str
