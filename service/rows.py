"""The catalog schema: downlinks, kernels, instruments, images and their geometry, lidar
products and their tracks, maplets, maplet revisions, model versions and jobs (SQLAlchemy 2.0
declarative, SQLite and PostgreSQL).

Units are in column names (km, m, deg, px); positions are body-fixed (e.g. IAU_BENNU). Times
are timezone-aware UTC datetimes, and ephemeris times (ET) are TDB seconds past J2000 as SPICE
gives them. Enumerations are stored as VARCHAR with a CHECK constraint on both databases.
"""

from __future__ import annotations

import enum
import math
from datetime import UTC, datetime
from typing import Any

import numpy as np
from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    CheckConstraint,
    Column,
    DateTime,
    Dialect,
    Double,
    Enum as SAEnum,
    ForeignKey,
    Index,
    MetaData,
    String,
    Table,
    Text,
    TypeDecorator,
    UniqueConstraint,
    event,
    inspect,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, relationship

from pwm.camera import PoseCorrection
from pwm.frames import LocalFrame, stored_frame, unit_to_latlon
from pwm.lidar.strips import Correction
from pwm.maplets import MapletGrid, flat_grid
from pwm.spg.uncertainty import PoseSigma
from pwm.tiling import level_of

# Explicit constraint names keep migrations identical on both databases and let Alembic's
# SQLite batch mode find constraints again.
NAMING_CONVENTION = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s",
    "pk": "pk_%(table_name)s",
}

ENUM_LENGTH = 16


def utcnow() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC datetimes on both databases; naive datetimes are refused.

    SQLite keeps no zone, so values are converted to UTC before storage and marked UTC on load.
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError(f"naive datetime {value!r}: give a timezone (UTC)")
        return value.astimezone(UTC)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value.astimezone(UTC)


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    # float pinned to Double (64-bit on both databases), not left to the SQLAlchemy release.
    type_annotation_map = {
        float: Double(),
        datetime: UTCDateTime(),
        dict[str, Any]: JSON,
        list[Any]: JSON,
    }


def _enum(cls: type[enum.StrEnum], name: str) -> SAEnum:
    """A portable enumeration column type storing the members' values, checked by the database."""
    return SAEnum(
        cls,
        name=name,
        native_enum=False,
        create_constraint=True,
        length=ENUM_LENGTH,
        validate_strings=True,
        values_callable=lambda members: [m.value for m in members],
    )


class Acceptance(enum.StrEnum):
    ACCEPTED = "accepted"
    REJECTED = "rejected"


class DownlinkStatus(enum.StrEnum):
    RECEIVED = "received"
    INGESTING = "ingesting"
    INGESTED = "ingested"
    FAILED = "failed"


class KernelKind(enum.StrEnum):
    LSK = "lsk"
    PCK = "pck"
    FK = "fk"
    IK = "ik"
    SCLK = "sclk"
    SPK = "spk"
    CK = "ck"
    MK = "mk"
    DSK = "dsk"


class ImageStatus(enum.StrEnum):
    ACCEPTED = "accepted"
    REJECTED = "rejected"
    # Same LIDVID delivered again with different content; the first copy stays authoritative.
    CONFLICT = "conflict"


class GeometryStatus(enum.StrEnum):
    PENDING = "pending"
    COMPUTED = "computed"
    UNAVAILABLE = "unavailable"


class CoverageRole(enum.StrEnum):
    """The part an image plays in a maplet's image set (nadir plus four azimuths)."""

    NADIR = "nadir"
    EAST = "east"
    WEST = "west"
    NORTH = "north"
    SOUTH = "south"


class ModelKind(enum.StrEnum):
    START = "start"
    PHOTOGRAMMETRIC = "photogrammetric"
    REFINED = "refined"
    IMPORTED = "imported"
    # Made from the lidar alone, where a catalog had no model (service.lidar.start_from_lidar).
    LIDAR = "lidar"


class JobKind(enum.StrEnum):
    INGEST = "ingest"
    REFINE = "refine"
    FUSE = "fuse"


class JobStatus(enum.StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


class Downlink(Base):
    """One delivery of PDS4 products and SPICE kernels."""

    __tablename__ = "downlinks"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(255), unique=True)
    path: Mapped[str] = mapped_column(Text)
    received_at: Mapped[datetime] = mapped_column(default=utcnow)
    status: Mapped[DownlinkStatus] = mapped_column(
        _enum(DownlinkStatus, "downlink_status"), default=DownlinkStatus.RECEIVED
    )
    manifest_sha256: Mapped[str | None] = mapped_column(String(64))
    # Deliveries of this downlink after the first (the same path, or the same manifest at
    # another path), and when it was last delivered.
    repeat_count: Mapped[int] = mapped_column(default=0, server_default="0")
    last_seen_at: Mapped[datetime | None]
    # Who is ingesting it while the status is ingesting ("host:pid"), and when that ingest last
    # committed: an ingest whose owner died or stopped committing is stale and is taken over.
    ingest_owner: Mapped[str | None] = mapped_column(String(255))
    ingest_heartbeat_at: Mapped[datetime | None]
    # Set when the downlink arrived at a catalog without a model version: the version made from
    # the images by photogrammetry (service.spg.start_from_images), or why none could be made.
    model_note: Mapped[str | None] = mapped_column(Text)
    # What the adjustment of the downlink's poses did (service.spg.adjust_downlink): the
    # knowledge taken and where from, the line of sight before and after, the pose model's
    # unknowns; or the reason none ran. Null where no pose knowledge was stated.
    pose_adjustment: Mapped[dict[str, Any] | None]

    kernels: Mapped[list[Kernel]] = relationship(back_populates="downlink")
    images: Mapped[list[Image]] = relationship(back_populates="downlink")
    files: Mapped[list[DownlinkFile]] = relationship(back_populates="downlink",
                                                     cascade="all, delete-orphan")


class DownlinkFile(Base):
    """A file of a downlink that is neither a catalogued kernel nor a product's label or data
    file, with why it is not used: of no type ingest knows, a symbolic link out of the downlink,
    a kernel a meta-kernel names outside it, or one refused before it was read. With the kernels
    and images, every file a downlink offers is accounted for."""

    __tablename__ = "downlink_files"

    id: Mapped[int] = mapped_column(primary_key=True)
    downlink_id: Mapped[int] = mapped_column(ForeignKey("downlinks.id", ondelete="CASCADE"))
    path: Mapped[str] = mapped_column(Text)
    code: Mapped[str] = mapped_column(String(32))
    reason: Mapped[str] = mapped_column(Text)
    seen_at: Mapped[datetime] = mapped_column(default=utcnow)

    downlink: Mapped[Downlink] = relationship(back_populates="files")

    __table_args__ = (UniqueConstraint("downlink_id", "path"),)


class Kernel(Base):
    """A SPICE kernel file, catalogued once per content (sha256)."""

    __tablename__ = "kernels"

    id: Mapped[int] = mapped_column(primary_key=True)
    path: Mapped[str] = mapped_column(Text)
    kind: Mapped[KernelKind] = mapped_column(_enum(KernelKind, "kernel_kind"))
    sha256: Mapped[str] = mapped_column(String(64), unique=True)
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    status: Mapped[Acceptance] = mapped_column(_enum(Acceptance, "kernel_status"))
    # How and why a rejected kernel was refused (kernel: SPICE refused it; kernel_truncated,
    # kernel_constants, kernel_redefines: pwm.io.kernel_checks).
    rejection_code: Mapped[str | None] = mapped_column(String(32))
    rejection_reason: Mapped[str | None] = mapped_column(Text)
    # The first downlink that delivered it (KernelDelivery lists them all).
    downlink_id: Mapped[int | None] = mapped_column(
        ForeignKey("downlinks.id", ondelete="SET NULL"), index=True
    )
    # Retired by an operator (`pwm kernels retire`): never loaded again, nor judged again when
    # delivered again, whatever its status.
    retired_at: Mapped[datetime | None]
    retirement_reason: Mapped[str | None] = mapped_column(Text)

    downlink: Mapped[Downlink | None] = relationship(back_populates="kernels")
    coverage: Mapped[list[KernelCoverage]] = relationship(
        back_populates="kernel", cascade="all, delete-orphan"
    )


class KernelDelivery(Base):
    """A downlink that delivered a kernel's content, at which path (the first and each later
    one)."""

    __tablename__ = "kernel_deliveries"

    id: Mapped[int] = mapped_column(primary_key=True)
    kernel_id: Mapped[int] = mapped_column(ForeignKey("kernels.id", ondelete="CASCADE"))
    downlink_id: Mapped[int] = mapped_column(ForeignKey("downlinks.id", ondelete="CASCADE"),
                                             index=True)
    path: Mapped[str] = mapped_column(Text)

    __table_args__ = (UniqueConstraint("kernel_id", "downlink_id"),)


class KernelCoverage(Base):
    """A time window an SPK (body NAIF id) or CK (frame/instrument NAIF id) covers."""

    __tablename__ = "kernel_coverage"

    id: Mapped[int] = mapped_column(primary_key=True)
    kernel_id: Mapped[int] = mapped_column(ForeignKey("kernels.id", ondelete="CASCADE"), index=True)
    naif_id: Mapped[int] = mapped_column(index=True)
    start_et: Mapped[float]
    stop_et: Mapped[float]
    start_utc: Mapped[datetime]
    stop_utc: Mapped[datetime]

    kernel: Mapped[Kernel] = relationship(back_populates="coverage")

    __table_args__ = (CheckConstraint("stop_et >= start_et", name="window_order"),)


class Instrument(Base):
    """A camera: pinhole intrinsics in pixels (pwm.camera.Camera) as derived from its kernels."""

    __tablename__ = "instruments"

    id: Mapped[int] = mapped_column(primary_key=True)
    naif_id: Mapped[int] = mapped_column(unique=True)
    name: Mapped[str] = mapped_column(String(64))
    spacecraft_id: Mapped[int]
    frame_name: Mapped[str] = mapped_column(String(64))
    width_px: Mapped[int]
    height_px: Mapped[int]
    fx_px: Mapped[float]
    fy_px: Mapped[float]
    cx_px: Mapped[float]
    cy_px: Mapped[float]
    # Which kernel keywords gave the focal length, and the units they were found in.
    focal_length_source: Mapped[str] = mapped_column(String(64))
    units_note: Mapped[str | None] = mapped_column(Text)

    images: Mapped[list[Image]] = relationship(back_populates="instrument")


class Image(Base):
    """A PDS4 image product (label + data file) and its place in the pipeline."""

    __tablename__ = "images"

    id: Mapped[int] = mapped_column(primary_key=True)
    # A conflicting copy (status conflict) is stored as lidvid + "#" + its sha256's first 16 hex
    # digits: the authoritative copy holds the LIDVID itself.
    lidvid: Mapped[str] = mapped_column(String(255), unique=True)
    lid: Mapped[str] = mapped_column(String(255), index=True)
    vid: Mapped[str] = mapped_column(String(32))
    label_path: Mapped[str] = mapped_column(Text)
    data_path: Mapped[str] = mapped_column(Text)
    md5: Mapped[str | None] = mapped_column(String(32))
    sha256: Mapped[str] = mapped_column(String(64))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    instrument_id: Mapped[int | None] = mapped_column(ForeignKey("instruments.id"), index=True)
    target: Mapped[str | None] = mapped_column(String(64))
    start_utc: Mapped[datetime | None] = mapped_column(index=True)
    stop_utc: Mapped[datetime | None]
    start_et: Mapped[float | None]
    stop_et: Mapped[float | None]
    status: Mapped[ImageStatus] = mapped_column(_enum(ImageStatus, "image_status"), index=True)
    # Short machine-friendly cause of a rejection (a pwm.io.pds4.ProductError code, or an ingest
    # code such as unknown_instrument or outside_coverage); rejection_reason gives the detail.
    rejection_code: Mapped[str | None] = mapped_column(String(32))
    rejection_reason: Mapped[str | None] = mapped_column(Text)
    geometry_status: Mapped[GeometryStatus] = mapped_column(
        _enum(GeometryStatus, "geometry_status"), default=GeometryStatus.PENDING
    )
    geometry_unavailable_reason: Mapped[str | None] = mapped_column(Text)
    downlink_id: Mapped[int | None] = mapped_column(
        ForeignKey("downlinks.id", ondelete="SET NULL"), index=True
    )
    # Pose correction from bundle adjustment: camera position offset (body-fixed, km) and a
    # small rotation vector (rad) applied on top of the SPICE body -> camera rotation.
    pose_dx_km: Mapped[float | None]
    pose_dy_km: Mapped[float | None]
    pose_dz_km: Mapped[float | None]
    pose_rx_rad: Mapped[float | None]
    pose_ry_rad: Mapped[float | None]
    pose_rz_rad: Mapped[float | None]
    pose_corrected_at: Mapped[datetime | None]
    # The latest adjustment's 1-sigma figures of the pose, {"prior": {...}, "posterior": {...}},
    # each pwm.spg.uncertainty.PoseSigma's fields (m, urad, px), and "knowledge": the stated pose
    # knowledge its priors came from (pwm.knowledge's text; absent where they were assumed, as
    # the start from nothing assumes them).
    pose_sigma: Mapped[dict[str, Any] | None]

    def pose_correction(self) -> PoseCorrection | None:
        """The stored pose correction (a component not set counts as 0), or None when no
        component is set."""
        position = (self.pose_dx_km, self.pose_dy_km, self.pose_dz_km)
        rotation = (self.pose_rx_rad, self.pose_ry_rad, self.pose_rz_rad)
        if all(v is None for v in position + rotation):
            return None
        dx, dy, dz = (v or 0.0 for v in position)
        rx, ry, rz = (v or 0.0 for v in rotation)
        return PoseCorrection(position_km=(dx, dy, dz), rotation_rad=(rx, ry, rz))

    def pose_sigmas(self) -> tuple[PoseSigma, PoseSigma] | None:
        """The latest adjustment's prior and posterior 1-sigma figures, or None before any."""
        if not self.pose_sigma:
            return None
        return PoseSigma(**self.pose_sigma["prior"]), PoseSigma(**self.pose_sigma["posterior"])

    def los_sigma_px(self) -> float:
        """1 sigma per image axis of how far the image may be off its (corrected) pose (px): the
        latest adjustment's posterior line of sight under a stated knowledge, else 0."""
        if not self.pose_sigma or not self.pose_sigma.get("knowledge"):
            return 0.0
        return float(self.pose_sigma["posterior"]["los_px"]) / math.sqrt(2)

    # The detector window of the array (zero-based first line and sample, size), as the label
    # gives it; null for images catalogued before it was kept (their label is read instead).
    window_first_line: Mapped[int | None]
    window_first_sample: Mapped[int | None]
    window_lines: Mapped[int | None]
    window_samples: Mapped[int | None]

    def window(self) -> tuple[int, int, int, int] | None:
        """(first_line, first_sample, lines, samples) of the array, or None when not kept."""
        values = (self.window_first_line, self.window_first_sample, self.window_lines, self.window_samples)
        if any(v is None for v in values):
            return None
        first_line, first_sample, lines, samples = (int(v) for v in values if v is not None)
        return first_line, first_sample, lines, samples

    # When the image was weighed into the coverage rows of the maplets it sees (null: not yet).
    # An ingest with a shape weighs the images not yet weighed; clear it to have one weighed again.
    coverage_computed_at: Mapped[datetime | None]

    instrument: Mapped[Instrument | None] = relationship(back_populates="images")
    downlink: Mapped[Downlink | None] = relationship(back_populates="images")
    geometry: Mapped[ImageGeometry | None] = relationship(
        back_populates="image", cascade="all, delete-orphan"
    )
    coverage: Mapped[list[Coverage]] = relationship(
        back_populates="image", cascade="all, delete-orphan"
    )


class ImageGeometry(Base):
    """Viewing geometry of one image at mid-exposure, from SPICE, in the body-fixed frame."""

    __tablename__ = "image_geometry"

    image_id: Mapped[int] = mapped_column(
        ForeignKey("images.id", ondelete="CASCADE"), primary_key=True
    )
    camera_x_km: Mapped[float]
    camera_y_km: Mapped[float]
    camera_z_km: Mapped[float]
    # 3x3 body-fixed -> image frame (+X sample, +Y line, +Z boresight), row-major, as
    # pwm.camera.Pose.rotation; a mirror of the SPICE instrument frame for OCAMS.
    camera_rotation: Mapped[list[Any]]
    sun_x: Mapped[float]
    sun_y: Mapped[float]
    sun_z: Mapped[float]
    # Camera to the body centre.
    range_km: Mapped[float]
    # Boresight quantities are null when the boresight misses the body.
    intercept_range_km: Mapped[float | None]
    pixel_scale_m: Mapped[float | None]
    phase_deg: Mapped[float | None]
    incidence_deg: Mapped[float | None]
    emission_deg: Mapped[float | None]
    intercept_lat_deg: Mapped[float | None]
    intercept_lon_deg: Mapped[float | None]
    # [lat_deg, lon_deg] of the four image corners (outer corners of the first and last pixels:
    # first line first sample, first line last sample, last line last sample, last line first
    # sample); null for a corner whose ray misses the body.
    footprint: Mapped[list[Any] | None]
    # The cone that holds what the array can see (pwm.views.Cones): unit body-fixed axis through
    # the array's centre and half-angle to its farthest corner, apex at the camera; null before
    # it was kept (such an image may see anything).
    cone_axis_x: Mapped[float | None]
    cone_axis_y: Mapped[float | None]
    cone_axis_z: Mapped[float | None]
    cone_half_angle_rad: Mapped[float | None]
    body_frame: Mapped[str] = mapped_column(String(64))
    abcorr: Mapped[str] = mapped_column(String(16))
    computed_at: Mapped[datetime] = mapped_column(default=utcnow)

    image: Mapped[Image] = relationship(back_populates="geometry")


class LidarProduct(Base):
    """A PDS4 laser altimetry product (a table of shots, pwm.io.lidar), catalogued once per
    LIDVID: its shots placed with SPICE at ingest, stored in the artifact store as one
    compressed array file (`shots`: service.lidar's record), never one row per shot; its
    counts here, its tracks in LidarTrack. A copy of a LIDVID with other content is not a row
    but a DownlinkFile (code conflict); a copy that arrived broken holds the LIDVID until a
    whole one takes its row, as images do (service.ingest)."""

    __tablename__ = "lidar_products"

    id: Mapped[int] = mapped_column(primary_key=True)
    lidvid: Mapped[str] = mapped_column(String(255), unique=True)
    lid: Mapped[str] = mapped_column(String(255))
    vid: Mapped[str] = mapped_column(String(32))
    label_path: Mapped[str] = mapped_column(Text)
    data_path: Mapped[str] = mapped_column(Text)
    # of the label and the data files it names, one after another, as an image's
    sha256: Mapped[str] = mapped_column(String(64))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    downlink_id: Mapped[int | None] = mapped_column(ForeignKey("downlinks.id", ondelete="SET NULL"), index=True)
    status: Mapped[Acceptance] = mapped_column(_enum(Acceptance, "lidar_status"), index=True)
    rejection_code: Mapped[str | None] = mapped_column(String(32))
    rejection_reason: Mapped[str | None] = mapped_column(Text)
    # the record layout (pwm.io.lidar.LAYOUTS), the instrument and target as the label names
    # them, the body-fixed frame the shots are placed in
    layout: Mapped[str | None] = mapped_column(String(16))
    instrument: Mapped[str | None] = mapped_column(String(64))
    target: Mapped[str | None] = mapped_column(String(64))
    body_frame: Mapped[str | None] = mapped_column(String(64))
    # the finite shot times' span
    start_et: Mapped[float | None]
    stop_et: Mapped[float | None]
    start_utc: Mapped[datetime | None] = mapped_column(index=True)
    stop_utc: Mapped[datetime | None]
    shots: Mapped[int] = mapped_column(BigInteger, default=0)
    valid_shots: Mapped[int] = mapped_column(BigInteger, default=0)
    # {reason: count} of the invalid shots, by pwm.lidar.shots.Invalid's lower-case names
    invalid_shots: Mapped[dict[str, Any]] = mapped_column(default=dict)
    # the shots' array file: an artifact record (service.artifacts), null for a rejected product
    shots_artifact: Mapped[dict[str, Any] | None]
    ingested_at: Mapped[datetime] = mapped_column(default=utcnow)

    tracks: Mapped[list[LidarTrack]] = relationship(back_populates="product", cascade="all, delete-orphan",
                                                    order_by="LidarTrack.track")

    __table_args__ = (CheckConstraint("valid_shots >= 0 AND valid_shots <= shots", name="shot_counts"),)


class LidarTrack(Base):
    """One track of a lidar product (pwm.lidar.tracks.track_ids: a time window one rigid
    correction serves): its span, its valid shots, the cone about the body centre that holds
    its spots (unit body-fixed axis and half-angle, as an image's cone, queried against the
    maplets' centres by service.queries.maplets_crossed) and their bounding box (body-fixed,
    km); once adjusted, its strip correction (pwm.lidar.strips.Correction: rotation vector
    rad, translation km, about the point about_km) and its 1 sigma (6: rotation rad,
    translation km; null where unconstrained), and its spots' residuals to the model
    (km) and crossovers with other tracks, with the version they were measured on."""

    __tablename__ = "lidar_tracks"

    id: Mapped[int] = mapped_column(primary_key=True)
    product_id: Mapped[int] = mapped_column(ForeignKey("lidar_products.id", ondelete="CASCADE"))
    track: Mapped[int]
    start_et: Mapped[float]
    stop_et: Mapped[float]
    shots: Mapped[int]
    cone_axis_x: Mapped[float]
    cone_axis_y: Mapped[float]
    cone_axis_z: Mapped[float]
    cone_half_angle_rad: Mapped[float]
    # the cone's axis as latitude and east longitude (deg): the prefilter's index
    axis_lat_deg: Mapped[float]
    axis_lon_deg: Mapped[float]
    min_x_km: Mapped[float]
    min_y_km: Mapped[float]
    min_z_km: Mapped[float]
    max_x_km: Mapped[float]
    max_y_km: Mapped[float]
    max_z_km: Mapped[float]
    rotation_x_rad: Mapped[float | None]
    rotation_y_rad: Mapped[float | None]
    rotation_z_rad: Mapped[float | None]
    translation_x_km: Mapped[float | None]
    translation_y_km: Mapped[float | None]
    translation_z_km: Mapped[float | None]
    about_x_km: Mapped[float | None]
    about_y_km: Mapped[float | None]
    about_z_km: Mapped[float | None]
    correction_sigma: Mapped[list[Any] | None]
    adjusted_at: Mapped[datetime | None]
    residual_mean_km: Mapped[float | None]
    residual_rms_km: Mapped[float | None]
    residual_p95_km: Mapped[float | None]
    residual_version: Mapped[int | None]
    # Its spots' crossovers with other tracks' (corrections applied; measured with the
    # residuals) and the RMS of their height differences (km; null with none).
    crossovers: Mapped[int | None]
    crossover_rms_km: Mapped[float | None]

    product: Mapped[LidarProduct] = relationship(back_populates="tracks")

    def strip_correction(self) -> Correction | None:
        """The stored strip correction (an unconstrained part's sigma infinite; no covariance,
        residual or extent kept), None where the track was not adjusted."""
        if self.adjusted_at is None:
            return None
        sigma = np.array([np.inf if s is None else s for s in self.correction_sigma or [None] * 6], dtype=float)
        return Correction(track=self.track,
                          rotation_rad=np.array([self.rotation_x_rad, self.rotation_y_rad, self.rotation_z_rad],
                                                dtype=float),
                          translation_km=np.array([self.translation_x_km, self.translation_y_km,
                                                   self.translation_z_km], dtype=float),
                          about_km=np.array([self.about_x_km, self.about_y_km, self.about_z_km], dtype=float),
                          sigma=sigma, covariance=np.zeros((6, 6)), shots=self.shots, rms_km=float("nan"),
                          extent_km=0.0)

    def store_strip_correction(self, correction: Correction) -> None:
        """Store a strip correction and its sigma (an unconstrained part's null), adjusted now."""
        self.rotation_x_rad, self.rotation_y_rad, self.rotation_z_rad = map(float, correction.rotation_rad)
        self.translation_x_km, self.translation_y_km, self.translation_z_km = map(float, correction.translation_km)
        self.about_x_km, self.about_y_km, self.about_z_km = map(float, correction.about_km)
        self.correction_sigma = [float(s) if np.isfinite(s) else None for s in correction.sigma]
        self.adjusted_at = utcnow()

    __table_args__ = (
        UniqueConstraint("product_id", "track"),
        CheckConstraint("cone_half_angle_rad >= 0", name="cone_half_angle_nonnegative"),
        Index(None, "axis_lat_deg", "axis_lon_deg"),
    )


def _level(gsd_m: float) -> int:
    return int(level_of(gsd_m * 1e-3))


class Maplet(Base):
    """A square surface patch with its local frame: Pl = rotation (P - origin), z along the
    regional normal, x parallel to the equator."""

    __tablename__ = "maplets"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    center_lat_deg: Mapped[float]
    center_lon_deg: Mapped[float]
    origin_x_km: Mapped[float]
    origin_y_km: Mapped[float]
    origin_z_km: Mapped[float]
    # 3x3 rotation body-fixed -> local, row-major (rows x, y, z).
    rotation: Mapped[list[Any]]
    size_km: Mapped[float]
    gsd_m: Mapped[float]
    # pwm.tiling.level_of the spacing, by default from gsd_m
    level: Mapped[int] = mapped_column(default=lambda context: _level(context.get_current_parameters()["gsd_m"]))
    nodes_per_side: Mapped[int]
    # w_PWM: lower for a weak image set, which holds the maplet closer to the starting shape.
    region_weight: Mapped[float] = mapped_column(default=1.0)
    # use_alter: maplets and maplet_revisions reference each other.
    current_revision_id: Mapped[int | None] = mapped_column(
        ForeignKey("maplet_revisions.id", ondelete="SET NULL", use_alter=True)
    )

    revisions: Mapped[list[MapletRevision]] = relationship(
        back_populates="maplet",
        foreign_keys="MapletRevision.maplet_id",
        cascade="all, delete-orphan",
        order_by="MapletRevision.revision",
    )
    current_revision: Mapped[MapletRevision | None] = relationship(
        foreign_keys=[current_revision_id], post_update=True
    )
    coverage: Mapped[list[Coverage]] = relationship(
        back_populates="maplet", cascade="all, delete-orphan"
    )

    __table_args__ = (
        CheckConstraint("region_weight > 0", name="region_weight_positive"),
        # The spatial prefilter of service.queries: a latitude range scan, longitude checked in
        # the index.
        Index(None, "center_lat_deg", "center_lon_deg"),
    )

    @classmethod
    def of(cls, grid: MapletGrid) -> Maplet:
        """The catalog row of a tiled maplet: its frame, extent and spacing (no revision yet)."""
        lat, lon = unit_to_latlon(grid.frame.origin)
        x, y, z = (float(v) for v in grid.frame.origin)
        return cls(name=grid.name, center_lat_deg=float(lat), center_lon_deg=float(lon), origin_x_km=x,
                   origin_y_km=y, origin_z_km=z, rotation=grid.frame.rotation.tolist(),
                   size_km=(grid.n - 1) * grid.spacing_km, gsd_m=grid.spacing_km * 1e3, nodes_per_side=grid.n)

    @staticmethod
    def frame_of(row: Any) -> LocalFrame:
        """The local frame of a maplet, or of a query's row holding its origin and rotation."""
        return stored_frame((row.origin_x_km, row.origin_y_km, row.origin_z_km), row.rotation)

    def grid(self, *, nodes: int | None = None) -> MapletGrid:
        """Its grid, flat (heights still to sample), on `nodes` a side over its square (its own
        count if None)."""
        return flat_grid(self.name, Maplet.frame_of(self), size_km=self.size_km,
                         nodes=self.nodes_per_side if nodes is None else nodes)


class Coverage(Base):
    """How one image sees one maplet, and its weight in that maplet's refinement."""

    __tablename__ = "coverage"

    id: Mapped[int] = mapped_column(primary_key=True)
    # The (image_id, maplet_id) unique index also serves lookups by image.
    image_id: Mapped[int] = mapped_column(ForeignKey("images.id", ondelete="CASCADE"))
    maplet_id: Mapped[int] = mapped_column(
        ForeignKey("maplets.id", ondelete="CASCADE"), index=True
    )
    visible_fraction: Mapped[float]
    shadowed_fraction: Mapped[float]
    incidence_deg: Mapped[float]
    emission_deg: Mapped[float]
    phase_deg: Mapped[float]
    sun_azimuth_deg: Mapped[float]
    # null in rows weighed before migration 0010: their image is traced again (service.coverage)
    camera_azimuth_deg: Mapped[float | None]
    resolution_m_per_px: Mapped[float]
    weight: Mapped[float]
    role: Mapped[CoverageRole | None] = mapped_column(_enum(CoverageRole, "coverage_role"))

    image: Mapped[Image] = relationship(back_populates="coverage")
    maplet: Mapped[Maplet] = relationship(back_populates="coverage")

    __table_args__ = (
        UniqueConstraint("image_id", "maplet_id"),
        CheckConstraint("visible_fraction BETWEEN 0 AND 1", name="visible_fraction_range"),
        CheckConstraint("shadowed_fraction BETWEEN 0 AND 1", name="shadowed_fraction_range"),
        CheckConstraint("weight >= 0", name="weight_nonnegative"),
    )


class MapletRevision(Base):
    """One solved state of a maplet. input_hash identifies the image set and parameters, so the
    same inputs are never solved twice; config_digest is the digest of the refinement
    configuration it was made with (pwm.config.RefinementConfig.digest; None: made before it was
    recorded), so that a changed configuration re-refines only when asked
    (service.refinement.stale_maplets)."""

    __tablename__ = "maplet_revisions"

    id: Mapped[int] = mapped_column(primary_key=True)
    maplet_id: Mapped[int] = mapped_column(ForeignKey("maplets.id", ondelete="CASCADE"))
    revision: Mapped[int]
    input_hash: Mapped[str] = mapped_column(String(64))
    mode: Mapped[str] = mapped_column(String(32))
    config_digest: Mapped[str | None] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    statistics: Mapped[dict[str, Any]] = mapped_column(default=dict)
    artifact_path: Mapped[str] = mapped_column(Text)
    sha256: Mapped[str] = mapped_column(String(64))

    maplet: Mapped[Maplet] = relationship(back_populates="revisions", foreign_keys=[maplet_id])

    __table_args__ = (
        UniqueConstraint("maplet_id", "revision"),
        UniqueConstraint("maplet_id", "input_hash"),
    )


# Lineage of a model version: the maplet revisions it was fused from and the downlinks whose
# data it contains.
model_version_maplet_revisions = Table(
    "model_version_maplet_revisions",
    Base.metadata,
    Column(
        "model_version_id",
        ForeignKey("model_versions.id", ondelete="CASCADE"),
        primary_key=True,
    ),
    Column(
        "maplet_revision_id",
        ForeignKey("maplet_revisions.id", ondelete="RESTRICT"),
        primary_key=True,
    ),
)

model_version_downlinks = Table(
    "model_version_downlinks",
    Base.metadata,
    Column(
        "model_version_id",
        ForeignKey("model_versions.id", ondelete="CASCADE"),
        primary_key=True,
    ),
    Column("downlink_id", ForeignKey("downlinks.id", ondelete="RESTRICT"), primary_key=True),
)


class ModelVersion(Base):
    """A published global shape model. Its content and lineage never change after it is
    written; only the release flag and tag may be set later."""

    __tablename__ = "model_versions"

    id: Mapped[int] = mapped_column(primary_key=True)
    version: Mapped[int] = mapped_column(unique=True)
    kind: Mapped[ModelKind] = mapped_column(_enum(ModelKind, "model_kind"))
    parent_id: Mapped[int | None] = mapped_column(
        ForeignKey("model_versions.id", ondelete="RESTRICT"), index=True
    )
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    statistics: Mapped[dict[str, Any]] = mapped_column(default=dict)
    # {name: {"path": ..., "sha256": ...}} for the mesh and its companions.
    artifacts: Mapped[dict[str, Any]] = mapped_column(default=dict)
    released: Mapped[bool] = mapped_column(Boolean, default=False)
    release_tag: Mapped[str | None] = mapped_column(String(64), unique=True)

    parent: Mapped[ModelVersion | None] = relationship(
        back_populates="children", remote_side=[id]
    )
    children: Mapped[list[ModelVersion]] = relationship(back_populates="parent")
    maplet_revisions: Mapped[list[MapletRevision]] = relationship(
        secondary=model_version_maplet_revisions
    )
    downlinks: Mapped[list[Downlink]] = relationship(secondary=model_version_downlinks)

    @property
    def mesh_artifact(self) -> dict[str, Any]:
        """The record of the file that holds the version's mesh: its PLY, or for a mesh stored
        in tiles (service.versions.store_mesh) the tiles' index; either reads back with
        service.artifacts.artifact_mesh, and its checksum names the mesh."""
        return dict(self.artifacts["tiles"] if "tiles" in self.artifacts else self.artifacts["ply"])


MUTABLE_MODEL_VERSION_FIELDS = frozenset({"released", "release_tag", "children"})


@event.listens_for(Session, "before_flush")
def _refuse_model_version_edits(session: Session, _context: Any, _instances: Any) -> None:
    """Refuse changes to a stored model version's content or lineage (the release flag and tag
    may be set once), and the deletion of a released version."""
    for obj in session.deleted:
        if isinstance(obj, ModelVersion) and obj.released:
            raise ValueError(f"model version {obj.version} is released; it cannot be deleted")
    for obj in session.dirty:
        if not isinstance(obj, ModelVersion):
            continue
        state = inspect(obj)
        changed = {a.key for a in state.attrs if a.history.has_changes()}
        frozen = changed - MUTABLE_MODEL_VERSION_FIELDS
        if frozen:
            raise ValueError(
                f"model version {obj.version} is immutable; refused changes to {sorted(frozen)}"
            )
        # The values this flush replaces: a release (True, or a tag) may not be replaced.
        if any(state.attrs.released.history.deleted) or any(
                tag is not None for tag in state.attrs.release_tag.history.deleted):
            raise ValueError(f"model version {obj.version} is released; its release cannot "
                             "be changed")


class Job(Base):
    """A unit of background work; `key` makes submission idempotent."""

    __tablename__ = "jobs"

    id: Mapped[int] = mapped_column(primary_key=True)
    kind: Mapped[JobKind] = mapped_column(_enum(JobKind, "job_kind"))
    key: Mapped[str] = mapped_column(String(255), unique=True)
    status: Mapped[JobStatus] = mapped_column(
        _enum(JobStatus, "job_status"), default=JobStatus.QUEUED, index=True
    )
    attempts: Mapped[int] = mapped_column(default=0)
    progress: Mapped[float] = mapped_column(default=0.0)
    message: Mapped[str | None] = mapped_column(Text)
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    # The running attempt's worker and its latest sign of life (service.jobs); when the job was
    # last handed to the broker, and why that failed if it did.
    worker: Mapped[str | None] = mapped_column(String(255))
    heartbeat_at: Mapped[datetime | None]
    enqueued_at: Mapped[datetime | None]
    enqueue_error: Mapped[str | None] = mapped_column(Text)
    downlink_id: Mapped[int | None] = mapped_column(
        ForeignKey("downlinks.id", ondelete="SET NULL"), index=True
    )
    maplet_id: Mapped[int | None] = mapped_column(
        ForeignKey("maplets.id", ondelete="SET NULL"), index=True
    )

    downlink: Mapped[Downlink | None] = relationship()
    maplet: Mapped[Maplet | None] = relationship()

    __table_args__ = (
        CheckConstraint("progress BETWEEN 0 AND 1", name="progress_range"),
        CheckConstraint("attempts >= 0", name="attempts_nonnegative"),
    )
