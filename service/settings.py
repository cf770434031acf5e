"""Service settings, read from PWM_* environment variables."""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from pathlib import Path

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from pwm.config import DEFAULTS, RefinementConfig
from pwm.io.pds4 import MAX_LABEL_BYTES, MAX_PIXELS
from pwm.io.spice_kernels import MAX_METAKERNEL_ENTRIES
from pwm.knowledge import parse_knowledge_errors
from pwm.photoclinometry import Mode

CATALOG_FILENAME = "catalog.sqlite"
# An ingest that has not committed for this long (s) is taken for dead and its downlink taken
# over: well above the time one batch of products takes (service.ingest.COMMIT_EVERY).
INGEST_STALE_S = 900.0


@dataclasses.dataclass(frozen=True)
class IngestLimits:
    """What ingest accepts from a downlink (service.ingest): kernel_library, a directory outside
    the downlinks whose kernels meta-kernels may name too (None: only the downlink's own);
    max_label_bytes and max_pixels, the largest label and image array read
    (pwm.io.pds4.read_image_label); max_metakernel_entries, the most kernels one meta-kernel
    may name (pwm.io.spice_kernels.metakernel_files); stale_s, how long an ingest may go
    without committing before another takes its downlink over."""

    kernel_library: Path | None = None
    max_label_bytes: int = MAX_LABEL_BYTES
    max_pixels: int = MAX_PIXELS
    max_metakernel_entries: int = MAX_METAKERNEL_ENTRIES
    stale_s: float = INGEST_STALE_S


class Settings(BaseSettings):
    """Where the catalog and its artifacts live, and how workers and clients reach the service.

    data_dir: PWM_DATA_DIR, made absolute at load time.
    database_url: PWM_DATABASE_URL; empty means the SQLite file `catalog.sqlite` in data_dir.
    broker_url: PWM_BROKER_URL; None runs jobs in-process instead of through a broker.
    api_token: PWM_API_TOKEN, the bearer token of the API's changing calls; None refuses them all.
    export_cache_bytes: PWM_EXPORT_CACHE_BYTES, how many bytes of made exports (decimated
        meshes, DSK, ICQ, site products, difference maps) the data directory keeps; the least
        recently served go first.
    cors_origins: PWM_CORS_ORIGINS, the origins (a JSON list) whose pages may call the API from
        a browser; empty: none (no CORS headers).
    kernel_library, max_label_bytes, max_image_pixels, max_metakernel_entries, ingest_stale_s:
        PWM_KERNEL_LIBRARY, PWM_MAX_LABEL_BYTES, PWM_MAX_IMAGE_PIXELS,
        PWM_MAX_METAKERNEL_ENTRIES and PWM_INGEST_STALE_S, what ingest accepts (`ingest_limits`).
    heartbeat_s: PWM_HEARTBEAT_S, how often a running job's attempt records that it is alive.
    heartbeat_grace_s: PWM_HEARTBEAT_GRACE_S, how long after its latest heartbeat an attempt is
        lost (shown so, and taken over by the next delivery); several heartbeats, so that a
        loaded database or a paused process is not taken for a dead one.
    refine_mode, refine_passes, maplet_nodes, tile_radius_km: PWM_REFINE_MODE,
        PWM_REFINE_PASSES, PWM_MAPLET_NODES and PWM_TILE_RADIUS_KM, the catalog's refinement
        settings (`refinement`); their defaults and every other setting are pwm.config.DEFAULTS.
    pose_knowledge: PWM_POSE_KNOWLEDGE, the 1-sigma pose knowledge of kernels that state none
        (`POS_M,POINT_RAD` or `nav:ALONG_M,CROSS_M,MISALIGN_URAD,DRIFT_URAD`, as
        pwm.knowledge.parse_knowledge_errors reads it); unset: none to adjust.
    """

    model_config = SettingsConfigDict(env_prefix="PWM_")

    data_dir: Path = Path("pwm-data")
    database_url: str = ""
    broker_url: str | None = None
    api_token: SecretStr | None = None
    export_cache_bytes: int = Field(2 * 1024**3, ge=0)
    cors_origins: list[str] = []
    kernel_library: Path | None = None
    max_label_bytes: int = Field(MAX_LABEL_BYTES, ge=1)
    max_image_pixels: int = Field(MAX_PIXELS, ge=1)
    max_metakernel_entries: int = Field(MAX_METAKERNEL_ENTRIES, ge=1)
    ingest_stale_s: float = Field(INGEST_STALE_S, gt=0)
    heartbeat_s: float = Field(10.0, gt=0)
    heartbeat_grace_s: float = Field(60.0, gt=0)
    refine_mode: Mode = DEFAULTS.mode
    refine_passes: int = DEFAULTS.passes
    maplet_nodes: int = DEFAULTS.nodes
    tile_radius_km: float | None = DEFAULTS.tile_radius_km
    pose_knowledge: str | None = None

    @model_validator(mode="after")
    def _resolve_paths(self) -> Settings:
        # Absolute paths, so a later change of working directory cannot move the catalog.
        self.data_dir = self.data_dir.resolve()
        if self.kernel_library is not None:
            self.kernel_library = self.kernel_library.resolve()
        if not self.database_url:
            self.database_url = f"sqlite:///{self.data_dir / CATALOG_FILENAME}"
        self.refinement()  # its checks, at load time
        if self.heartbeat_grace_s < 2 * self.heartbeat_s:
            raise ValueError(f"heartbeat_grace_s ({self.heartbeat_grace_s:g} s) must be at least "
                             f"twice heartbeat_s ({self.heartbeat_s:g} s), or one late beat "
                             "shows a live job as lost")
        return self

    def ingest_limits(self) -> IngestLimits:
        """What ingest accepts from a downlink, as these settings say."""
        return IngestLimits(kernel_library=self.kernel_library,
                            max_label_bytes=self.max_label_bytes, max_pixels=self.max_image_pixels,
                            max_metakernel_entries=self.max_metakernel_entries,
                            stale_s=self.ingest_stale_s)

    def refinement(self) -> RefinementConfig:
        """How the catalog tiles and refines maplets: pwm.config.DEFAULTS with these settings."""
        knowledge = None if not self.pose_knowledge else parse_knowledge_errors(self.pose_knowledge)
        return dataclasses.replace(DEFAULTS, mode=self.refine_mode, passes=self.refine_passes,
                                   nodes=self.maplet_nodes, tile_radius_km=self.tile_radius_km, knowledge=knowledge)


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, read from the environment once."""
    return Settings()
