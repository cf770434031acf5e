"""Service settings, read from PWM_* environment variables."""

from __future__ import annotations

import dataclasses
import json
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, TypeVar

from pydantic import Field, SecretStr, ValidationError, ValidationInfo, field_validator, model_validator
from pydantic_core import ErrorDetails
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict, SettingsError
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError

from pwm.config import DEFAULTS, RefinementConfig
from pwm.io.lidar import MAX_SHOTS
from pwm.io.pds4 import FITS_BLOCK, MAX_FITS_HEADER_BYTES, MAX_LABEL_BYTES, MAX_PIXELS
from pwm.io.spice_kernels import MAX_METAKERNEL_ENTRIES
from pwm.knowledge import parse_knowledge_errors
from pwm.photoclinometry import Mode

CATALOG_FILENAME = "catalog.sqlite"
# An ingest that has not committed for this long (s) is taken for dead and its downlink taken
# over: well above the time one batch of products takes (service.ingest.COMMIT_EVERY).
INGEST_STALE_S = 900.0
# The most file references (file_name elements) one PDS4 label may hold: a product names its
# data file once, perhaps a few supplemental files (each is read to key the product).
MAX_LABEL_FILES = 64
# The database URL schemes the catalog runs on (service.db pins PostgreSQL to psycopg 3).
DATABASE_DRIVERS = frozenset({"sqlite", "sqlite+pysqlite", "postgresql", "postgres", "postgresql+psycopg"})
# Settings whose value is never repeated in an error: they may hold a password or a token.
_UNSHOWN = frozenset({"api_token", "broker_url", "database_url"})
# The settings that are fields of pwm.config.RefinementConfig, with those fields' names.
_REFINEMENT_FIELDS = {"refine_mode": "mode", "refine_passes": "passes", "refine_max_passes": "max_passes",
                      "maplet_nodes": "nodes", "tile_radius_km": "tile_radius_km"}


@dataclasses.dataclass(frozen=True)
class IngestLimits:
    """What ingest accepts from a downlink (service.ingest): kernel_library, a directory outside
    the downlinks whose kernels meta-kernels may name too (None: only the downlink's own);
    max_label_bytes, max_pixels and max_fits_header_bytes, the largest label, image array and
    FITS header read (pwm.io.pds4.read_image_label); max_metakernel_entries, the most kernels
    one meta-kernel may name (pwm.io.spice_kernels.metakernel_files); max_label_files, the most
    file references one label may hold (max_label_bytes bounds a downlink's manifest.json too);
    max_lidar_shots, the most shots one lidar product may hold (pwm.io.lidar.read_lidar_table);
    stale_s, how long an ingest may go without committing before another takes its downlink over."""

    kernel_library: Path | None = None
    max_label_bytes: int = MAX_LABEL_BYTES
    max_pixels: int = MAX_PIXELS
    max_fits_header_bytes: int = MAX_FITS_HEADER_BYTES
    max_metakernel_entries: int = MAX_METAKERNEL_ENTRIES
    max_label_files: int = MAX_LABEL_FILES
    max_lidar_shots: int = MAX_SHOTS
    stale_s: float = INGEST_STALE_S


class Settings(BaseSettings):
    """Where the catalog and its artifacts live, and how workers and clients reach the service.

    data_dir: PWM_DATA_DIR, made absolute at load time.
    database_url: PWM_DATABASE_URL, sqlite:///FILE or postgresql://USER@HOST/DATABASE; empty
        means the SQLite file `catalog.sqlite` in data_dir.
    database_pool_timeout_s: PWM_DATABASE_POOL_TIMEOUT_S, how long a request waits for a free
        PostgreSQL connection of the process's pool before it is answered 503.
    broker_url: PWM_BROKER_URL; None runs jobs in-process instead of through a broker.
    api_token: PWM_API_TOKEN, the bearer token of the API's changing calls; None refuses them all.
    export_cache_bytes: PWM_EXPORT_CACHE_BYTES, how many bytes of made exports (decimated
        meshes, DSK, ICQ, site products, difference maps) the data directory keeps; the least
        recently served go first.
    cors_origins: PWM_CORS_ORIGINS, the origins (a JSON list) whose pages may call the API from
        a browser; empty: none (no CORS headers).
    kernel_library, max_label_bytes, max_image_pixels, max_fits_header_bytes,
    max_metakernel_entries, max_label_files, max_lidar_shots, ingest_stale_s:
        PWM_KERNEL_LIBRARY, PWM_MAX_LABEL_BYTES, PWM_MAX_IMAGE_PIXELS,
        PWM_MAX_FITS_HEADER_BYTES (at least one 2880-byte block), PWM_MAX_METAKERNEL_ENTRIES,
        PWM_MAX_LABEL_FILES, PWM_MAX_LIDAR_SHOTS and PWM_INGEST_STALE_S, what ingest accepts
        (`ingest_limits`).
    heartbeat_s: PWM_HEARTBEAT_S, how often a running job's attempt records that it is alive.
    heartbeat_grace_s: PWM_HEARTBEAT_GRACE_S, how long after its latest heartbeat an attempt is
        lost (shown so, and taken over by the next delivery); several heartbeats, so that a
        loaded database or a paused process is not taken for a dead one.
    refine_mode, refine_passes, refine_max_passes, maplet_nodes, tile_radius_km:
        PWM_REFINE_MODE, PWM_REFINE_PASSES, PWM_REFINE_MAX_PASSES, PWM_MAPLET_NODES and
        PWM_TILE_RADIUS_KM, the catalog's refinement settings (`refinement`); their defaults and
        every other setting are pwm.config.DEFAULTS.
    refine_on_config_change: PWM_REFINE_ON_CONFIG_CHANGE, whether a downlink's plan and the
        passes after it also refine the maplets whose current revision was made with another
        refinement configuration (another pwm.config.RefinementConfig.digest; the whole catalog,
        after a change of a setting it names); false: only those whose images changed, the rest
        left to `pwm refine-catalog --because-config-changed` (service.refinement.stale_maplets).
    lidar_residual_shots: PWM_LIDAR_RESIDUAL_SHOTS, at most how many of the catalog's usable
        lidar shots each published version is checked against (a uniform sample; its lidar
        statistics, service.publish.lidar_statistics): enough for a per-track figure and a
        10-degree map, cheap to ray-cast (0: none checked).
    mesh_tile_faces: PWM_MESH_TILE_FACES, the most faces a version's mesh is stored and exported
        as one file with: a larger one is stored in tiles of at most this many faces
        (pwm.mesh_tiles, service.versions.store_mesh), exported tile by tile and drawn by the
        console at full resolution a tile at a time; at most 32,000,000, the plates a SPICE DSK
        type 2 segment holds (DSK02's MAXPLT), since a DSK has a segment per tile.
    pose_knowledge: PWM_POSE_KNOWLEDGE, the 1-sigma pose knowledge of kernels that state none
        (`POS_M,POINT_RAD` or `nav:ALONG_M,CROSS_M,MISALIGN_URAD,DRIFT_URAD`, as
        pwm.knowledge.parse_knowledge_errors reads it); unset: none to adjust.
    """

    model_config = SettingsConfigDict(env_prefix="PWM_", allow_inf_nan=False)

    data_dir: Path = Path("pwm-data")
    database_url: str = ""
    database_pool_timeout_s: float = Field(30.0, gt=0)
    broker_url: str | None = None
    api_token: SecretStr | None = None
    export_cache_bytes: int = Field(2 * 1024**3, ge=0)
    cors_origins: Annotated[list[str], NoDecode] = []
    kernel_library: Path | None = None
    max_label_bytes: int = Field(MAX_LABEL_BYTES, ge=1)
    max_image_pixels: int = Field(MAX_PIXELS, ge=1)
    max_fits_header_bytes: int = Field(MAX_FITS_HEADER_BYTES, ge=FITS_BLOCK)
    max_metakernel_entries: int = Field(MAX_METAKERNEL_ENTRIES, ge=1)
    max_label_files: int = Field(MAX_LABEL_FILES, ge=1)
    max_lidar_shots: int = Field(MAX_SHOTS, ge=1)
    ingest_stale_s: float = Field(INGEST_STALE_S, gt=0)
    heartbeat_s: float = Field(10.0, gt=0)
    heartbeat_grace_s: float = Field(60.0, gt=0)
    refine_mode: Mode = DEFAULTS.mode
    refine_passes: int = DEFAULTS.passes
    refine_max_passes: int = DEFAULTS.max_passes
    maplet_nodes: int = DEFAULTS.nodes
    tile_radius_km: float | None = DEFAULTS.tile_radius_km
    refine_on_config_change: bool = False
    lidar_residual_shots: int = Field(200_000, ge=0)
    mesh_tile_faces: int = Field(4_000_000, ge=100, le=32_000_000)
    pose_knowledge: str | None = None

    @field_validator("database_url")
    @classmethod
    def _supported_database(cls, url: str) -> str:
        try:
            supported = not url or make_url(url).drivername in DATABASE_DRIVERS
        except ArgumentError:
            supported = False
        if not supported:
            raise ValueError("expected sqlite:///FILE or postgresql://USER@HOST/DATABASE")
        return url

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _origins_from_json(cls, value: Any) -> Any:
        if not isinstance(value, str):
            return value
        try:
            return json.loads(value) if value.strip() else []
        except ValueError:
            raise ValueError('expected a JSON list of origins, e.g. ["https://console.example"]') from None

    @field_validator(*_REFINEMENT_FIELDS)
    @classmethod
    def _refinement_checks(cls, value: Any, info: ValidationInfo) -> Any:
        # RefinementConfig's own checks, each setting alone, so that an error names its variable
        assert info.field_name is not None
        dataclasses.replace(DEFAULTS, **{_REFINEMENT_FIELDS[info.field_name]: value})
        return value

    @field_validator("pose_knowledge")
    @classmethod
    def _knowledge_checks(cls, value: str | None) -> str | None:
        if value:
            parse_knowledge_errors(value)
        return value

    @model_validator(mode="after")
    def _resolve_paths(self) -> Settings:
        # Absolute paths, so a later change of working directory cannot move the catalog.
        self.data_dir = self.data_dir.resolve()
        if self.kernel_library is not None:
            self.kernel_library = self.kernel_library.resolve()
        if not self.database_url:
            self.database_url = f"sqlite:///{self.data_dir / CATALOG_FILENAME}"
        if self.heartbeat_grace_s < 2 * self.heartbeat_s:
            raise ValueError(f"PWM_HEARTBEAT_GRACE_S ({self.heartbeat_grace_s:g} s) must be at "
                             f"least twice PWM_HEARTBEAT_S ({self.heartbeat_s:g} s), or one late "
                             "beat shows a live job as lost")
        return self

    def ingest_limits(self) -> IngestLimits:
        """What ingest accepts from a downlink, as these settings say."""
        return IngestLimits(kernel_library=self.kernel_library,
                            max_label_bytes=self.max_label_bytes, max_pixels=self.max_image_pixels,
                            max_fits_header_bytes=self.max_fits_header_bytes,
                            max_metakernel_entries=self.max_metakernel_entries,
                            max_label_files=self.max_label_files, max_lidar_shots=self.max_lidar_shots,
                            stale_s=self.ingest_stale_s)

    def refinement(self) -> RefinementConfig:
        """How the catalog tiles and refines maplets: pwm.config.DEFAULTS with these settings."""
        knowledge = None if not self.pose_knowledge else parse_knowledge_errors(self.pose_knowledge)
        return dataclasses.replace(DEFAULTS, mode=self.refine_mode, passes=self.refine_passes,
                                   max_passes=self.refine_max_passes, nodes=self.maplet_nodes,
                                   tile_radius_km=self.tile_radius_km, knowledge=knowledge)


S = TypeVar("S", bound=Settings)


class BadEnvironment(Exception):
    """PWM_* environment variables that make no valid settings: `problems`, one line each,
    naming the variable and what it accepts (the value too, unless it may be a secret)."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("; ".join(problems))
        self.problems = problems


def from_environment(cls: type[S]) -> S:
    """`cls` (Settings or a subclass) read from the environment; BadEnvironment if it cannot
    be."""
    try:
        return cls()
    except ValidationError as exc:
        raise BadEnvironment([_problem(cls, error) for error in exc.errors()]) from None
    except SettingsError as exc:  # a value pydantic-settings could not decode
        raise BadEnvironment([str(exc)]) from None


def _problem(cls: type[Settings], error: ErrorDetails) -> str:
    message = error["msg"].removeprefix("Value error, ")
    if not error["loc"]:  # a check across settings: its message names the variables
        return message
    field, *inner = error["loc"]
    variable = f"{cls.model_config.get('env_prefix', '')}{field}".upper()
    where = variable + "".join(f"[{part}]" for part in inner)
    if field in _UNSHOWN:
        return f"{where}: {message}"
    return f"{where}={error['input']!r}: {message}"


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, read from the environment once (BadEnvironment if they
    cannot be)."""
    return from_environment(Settings)
