"""Service settings, read from PWM_* environment variables."""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from pathlib import Path

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from pwm.config import DEFAULTS, RefinementConfig
from pwm.photoclinometry import Mode

CATALOG_FILENAME = "catalog.sqlite"


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
    heartbeat_s: PWM_HEARTBEAT_S, how often a running job's attempt records that it is alive.
    heartbeat_grace_s: PWM_HEARTBEAT_GRACE_S, how long after its latest heartbeat an attempt is
        lost (shown so, and taken over by the next delivery); several heartbeats, so that a
        loaded database or a paused process is not taken for a dead one.
    refine_mode, maplet_nodes, tile_radius_km: PWM_REFINE_MODE, PWM_MAPLET_NODES and
        PWM_TILE_RADIUS_KM, the catalog's refinement settings (`refinement`); their defaults and
        every other setting are pwm.config.DEFAULTS.
    """

    model_config = SettingsConfigDict(env_prefix="PWM_")

    data_dir: Path = Path("pwm-data")
    database_url: str = ""
    broker_url: str | None = None
    api_token: SecretStr | None = None
    export_cache_bytes: int = Field(2 * 1024**3, ge=0)
    cors_origins: list[str] = []
    heartbeat_s: float = Field(10.0, gt=0)
    heartbeat_grace_s: float = Field(60.0, gt=0)
    refine_mode: Mode = DEFAULTS.mode
    maplet_nodes: int = DEFAULTS.nodes
    tile_radius_km: float | None = DEFAULTS.tile_radius_km

    @model_validator(mode="after")
    def _resolve_paths(self) -> Settings:
        # Absolute paths, so a later change of working directory cannot move the catalog.
        self.data_dir = self.data_dir.resolve()
        if not self.database_url:
            self.database_url = f"sqlite:///{self.data_dir / CATALOG_FILENAME}"
        self.refinement()  # its checks, at load time
        if self.heartbeat_grace_s < 2 * self.heartbeat_s:
            raise ValueError(f"heartbeat_grace_s ({self.heartbeat_grace_s:g} s) must be at least "
                             f"twice heartbeat_s ({self.heartbeat_s:g} s), or one late beat "
                             "shows a live job as lost")
        return self

    def refinement(self) -> RefinementConfig:
        """How the catalog tiles and refines maplets: pwm.config.DEFAULTS with these settings."""
        return dataclasses.replace(DEFAULTS, mode=self.refine_mode, nodes=self.maplet_nodes,
                                   tile_radius_km=self.tile_radius_km)


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, read from the environment once."""
    return Settings()
