"""Service settings: environment variables ``NARF_*`` (or keyword arguments), validated once at start."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

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
    token: SecretStr | None = Field(None, description="Bearer token required on every non-public route; unset = none.")
    token_file: Path | None = Field(None, description="File whose content (stripped) is the token, not NARF_TOKEN.")
    public_routes: Annotated[list[str], NoDecode] = Field(
        ["/healthz", "/readyz"],
        description="Path prefixes answered without the token (comma-separated or a JSON list); every other "
        "route, present or future, needs it. /readyz gives why a bundle was refused only with the token.",
    )
    max_body_bytes: int = Field(32 * 2**20, gt=0, description="Largest accepted request body (413 above).")
    max_image_pixels: int = Field(2048 * 2048, gt=0, description="Largest image, uploaded or rendered (413 above).")
    max_iterations: int = Field(1000, gt=0, description="Largest number of refinement iterations per request.")
    workers: int = Field(0, ge=0, description="Compute threads; 0 = one per available core.")
    queue_size: int = Field(-1, ge=-1, description="Requests waiting beyond the running ones; -1 = 4 per worker.")
    torch_threads: int = Field(0, ge=0, description="torch intra-op threads; 0 = free cores at start / workers.")
    track_processes: bool = Field(
        True, description="Run /v1/track frames in child processes, one per worker, each with its own copy of the "
        "models (started on the first frame), so concurrent tracks are not serialised on one interpreter's lock; "
        "false: on the worker threads like the other routes."
    )
    retry_after_max_s: int = Field(30, gt=0, description="Cap on the Retry-After hint sent with a 503.")
    max_json_bytes: int = Field(
        64 * 2**10, gt=0, description="Largest JSON document: a JSON body or the estimate's 'request' part (413 above)."
    )
    max_seconds: float = Field(
        60.0, gt=0, description="Work budget per job: an estimate still running after this long stops with "
        "status 'budget_exceeded' and returns its best estimate so far."
    )
    max_work_rays: int = Field(
        10_000_000, gt=0, description="Largest estimate, in rays traced: iterations x rays_per_iteration x box scale x "
        "starts x refinements (without a depth image: the RGB-only ones and the polish), with the choices and the covariance "
        "(EstimateOptions.max_rays; 422 above, before any work)."
    )
    header_timeout_s: float = Field(
        10.0, gt=0, description="A connection that has not sent a request's full headers within this long "
        "(from connecting, or from the previous response) is closed (408 if it had started one)."
    )
    body_timeout_s: float = Field(60.0, gt=0, description="A body not fully received within this long is answered 408.")
    keep_alive_timeout_s: float = Field(5.0, gt=0, description="An idle keep-alive connection closes after this long.")
    state_key: SecretStr | None = Field(
        None, description="Key (at least 16 characters) that signs /v1/track state tokens; every replica behind one "
        "address needs the same. Unset: a random key per process (tokens then only work with this replica)."
    )
    state_key_file: Path | None = Field(None, description="File whose content (stripped) is the state key, instead of NARF_STATE_KEY.")

    @field_validator("token", mode="before")
    @classmethod
    def _blank_token_is_none(cls, token: object) -> object:
        """``NARF_TOKEN=`` (set but empty, as compose files leave it) means no authentication."""
        return None if isinstance(token, str) and not token.strip() else token

    @field_validator("device")
    @classmethod
    def _usable_device(cls, device: str) -> str:
        """A device this machine has (narf_core.bundle.resolve_device), refused at start rather than per bundle."""
        from narf_core.bundle import resolve_device

        return str(resolve_device(device))

    @field_validator("public_routes", mode="before")
    @classmethod
    def _split_routes(cls, routes: object) -> object:
        """``NARF_PUBLIC_ROUTES=/healthz,/readyz`` or a JSON list; an empty string makes every route private."""
        if isinstance(routes, str):
            text = routes.strip()
            return json.loads(text) if text.startswith("[") else [r.strip() for r in text.split(",") if r.strip()]
        return routes

    @field_validator("public_routes")
    @classmethod
    def _absolute_routes(cls, routes: list[str]) -> list[str]:
        for route in routes:
            if not route.startswith("/") or "?" in route:
                raise ValueError(f"a public route is a path prefix starting with '/', got {route!r}")
        return [route.rstrip("/") or "/" for route in routes]

    @model_validator(mode="after")
    def _read_token_file(self) -> Settings:
        if self.token_file is None:
            return self
        if self.token is not None:
            raise ValueError("set the token once: NARF_TOKEN or NARF_TOKEN_FILE (--token-file), not both")
        try:
            token = self.token_file.read_text().strip()
        except (OSError, UnicodeDecodeError) as e:
            raise ValueError(f"cannot read the token file {self.token_file}: {e}") from None
        if not token:
            raise ValueError(f"the token file {self.token_file} is empty")
        self.token = SecretStr(token)
        return self

    @model_validator(mode="after")
    def _read_state_key(self) -> Settings:
        if self.state_key_file is not None:
            if self.state_key is not None:
                raise ValueError("set the state key once: NARF_STATE_KEY or NARF_STATE_KEY_FILE, not both")
            try:
                self.state_key = SecretStr(self.state_key_file.read_text().strip())
            except (OSError, UnicodeDecodeError) as e:
                raise ValueError(f"cannot read the state key file {self.state_key_file}: {e}") from None
        if self.state_key is not None and len(self.state_key.get_secret_value()) < 16:
            raise ValueError("the state key must be at least 16 characters")
        return self

    def is_public(self, path: str) -> bool:
        """Whether ``path`` is answered without the token: it is a public route or lies below one
        (a path with ``.`` or ``..`` segments never is)."""
        if any(segment in (".", "..") for segment in path.split("/")):
            return False
        return any(path == route or path.startswith(route.rstrip("/") + "/") for route in self.public_routes)

    @model_validator(mode="after")
    def _size_to_machine(self) -> Settings:
        cores = available_cores()
        if self.workers == 0:
            self.workers = cores
        if self.queue_size == -1:
            self.queue_size = 4 * self.workers
        return self
