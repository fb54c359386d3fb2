"""Service settings: environment variables ``NARF_*`` (or keyword arguments), validated once at start."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from narf_core.threads import available_cores

REPO_MODELS_DIR = Path(__file__).resolve().parent.parent / "models"


class Settings(BaseSettings):
    """Everything the service can be told; ``NARF_<FIELD>`` in the environment sets ``<field>``.

    ``workers``, ``queue_size`` and ``torch_threads`` default to values sized to the machine:
    one worker per core, a queue of four requests per worker, and the cores that other processes
    leave free at start shared out among the workers (so two concurrent renders on two cores use one
    thread each instead of fighting, and a server started beside a busy process takes one thread).
    """

    model_config = SettingsConfigDict(env_prefix="NARF_", extra="forbid")

    models_dir: Path = Field(REPO_MODELS_DIR, description="Folder whose *.narf bundles are served.")
    device: str = Field("cpu", description="torch device the models are loaded on, e.g. 'cpu' or 'cuda'.")
    token: SecretStr | None = Field(None, description="Bearer token required on /v1 routes; unset = no auth.")
    max_body_bytes: int = Field(32 * 2**20, gt=0, description="Largest accepted request body (413 above).")
    max_image_pixels: int = Field(2048 * 2048, gt=0, description="Largest image, uploaded or rendered (413 above).")
    max_iterations: int = Field(1000, gt=0, description="Largest number of refinement iterations per request.")
    workers: int = Field(0, ge=0, description="Compute threads; 0 = one per available core.")
    queue_size: int = Field(-1, ge=-1, description="Requests waiting beyond the running ones; -1 = 4 per worker.")
    torch_threads: int = Field(0, ge=0, description="torch intra-op threads; 0 = free cores at start / workers.")
    retry_after_max_s: int = Field(30, gt=0, description="Cap on the Retry-After hint sent with a 503.")

    @field_validator("token", mode="before")
    @classmethod
    def _blank_token_is_none(cls, token: object) -> object:
        """``NARF_TOKEN=`` (set but empty, as compose files leave it) means no authentication."""
        return None if isinstance(token, str) and not token.strip() else token

    @model_validator(mode="after")
    def _size_to_machine(self) -> Settings:
        cores = available_cores()
        if self.workers == 0:
            self.workers = cores
        if self.queue_size == -1:
            self.queue_size = 4 * self.workers
        return self
