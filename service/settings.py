"""Service settings, read from PWM_* environment variables."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

CATALOG_FILENAME = "catalog.sqlite"


class Settings(BaseSettings):
    """Where the catalog and its artifacts live, and how workers and clients reach the service.

    data_dir: PWM_DATA_DIR, made absolute at load time.
    database_url: PWM_DATABASE_URL; empty means the SQLite file `catalog.sqlite` in data_dir.
    broker_url: PWM_BROKER_URL; None runs jobs in-process instead of through a broker.
    api_token: PWM_API_TOKEN, the bearer token of the API's changing calls; None refuses them all.
    export_cache_bytes: PWM_EXPORT_CACHE_BYTES, how many bytes of made exports (decimated meshes,
    DSK, ICQ, site products, difference maps) the data directory keeps; the least recently
    served go first.
    cors_origins: PWM_CORS_ORIGINS, the origins (a JSON list) whose pages may call the API from
    a browser; empty: none (no CORS headers).
    """

    model_config = SettingsConfigDict(env_prefix="PWM_")

    data_dir: Path = Path("pwm-data")
    database_url: str = ""
    broker_url: str | None = None
    api_token: SecretStr | None = None
    export_cache_bytes: int = Field(2 * 1024**3, ge=0)
    cors_origins: list[str] = []

    @model_validator(mode="after")
    def _resolve_paths(self) -> Settings:
        # Absolute paths, so a later change of working directory cannot move the catalog.
        self.data_dir = self.data_dir.resolve()
        if not self.database_url:
            self.database_url = f"sqlite:///{self.data_dir / CATALOG_FILENAME}"
        return self


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, read from the environment once."""
    return Settings()
