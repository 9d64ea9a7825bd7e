"""Service settings: one validated pydantic model, merged from four layers.

Precedence (lowest first): the defaults below < the ``[service]`` section of the
TOML config (``selfcal/configs/default.toml`` overridden by ``--config FILE``) < ``SELFCAL_*``
environment variables (``SELFCAL_API_KEYS``, ``SELFCAL_DB_PATH`` …) < command-line
flags of ``selfcal serve``.

We do not use ``pydantic-settings`` (style.md principle 12) to avoid one more runtime
dependency: the merge is :func:`load_settings`, a dozen lines, and the model itself is
the same validated ``Settings`` object the template passes around.
"""

from __future__ import annotations

import os
from typing import Any, Literal, Mapping

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

ENV_PREFIX = "SELFCAL_"


class Settings(BaseModel):
    """Validated settings of the HTTP service (all units in the names)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    db_path: str = Field(
        "selfcal.db", description="SQLite database file (WAL mode), or a postgresql://user@host:port/db URL"
    )
    host: str = Field("127.0.0.1", description="bind address")
    port: int = Field(8000, ge=0, le=65535, description="TCP port (0 = any free port)")
    api_keys: str = Field(
        "",
        description="comma-separated KEY=SCOPE[+SCOPE...]; scopes: ingest, read, admin",
        repr=False,
    )
    max_body_bytes: int = Field(1_048_576, ge=1024, description="larger bodies get 413")
    max_batch_samples: int = Field(2000, ge=1, le=100_000, description="samples per batch")
    max_pressure_channels: int = Field(16, ge=1, le=256)
    sqlite_synchronous: Literal["FULL", "NORMAL"] = Field(
        "FULL", description="FULL: an acknowledged batch survives power loss, not only kill -9"
    )
    group_commit_max_ops: int = Field(512, ge=1, description="writes per SQLite transaction")
    worker_threads: int = Field(1, ge=1, le=64, description="refit workers (devices sharded)")
    hot_routes: bool = Field(
        True, description="answer a binary batch POST and a calibration GET without FastAPI's routing layers "
                          "(the same answers, about half the CPU); false: every request through the app's routes")
    worker_process_threads: int = Field(
        4, ge=1, le=64,
        description="refit threads of each `selfcal worker` process (PostgreSQL; `--threads`): a cycle waits for its "
                    "durable commit, and several threads keep several cycles' commits in flight")
    worker_max_batches_per_cycle: int = Field(256, ge=1)
    time_reset_gap_s: float = Field(
        60.0, gt=0, description="gap inserted when a device clock goes backwards (reboot)"
    )
    min_cycle_interval_s: float = Field(
        0.0, ge=0, le=3600,
        description="a device's batches are fed at most once per this many seconds (0: as they come): one commit "
                    "for the batches that arrive meanwhile (the state itself is written per checkpoint_samples); "
                    "a device with a backlog is not held",
    )
    checkpoint_samples: int = Field(
        12_000, ge=0, le=10_000_000,
        description="a device's whole calibrator state (up to ~1.5 MB after a week) is written once this many samples "
                    "were fed since it was last written (0: every cycle); a restore (restart, lease takeover) feeds "
                    "the stored batches since then again. 12 000 = 10 min of a 20-Hz insole",
    )
    checkpoint_patch_fraction: float = Field(
        0.25, ge=0, le=1,
        description="a checkpoint is written as a patch against the last full state written (its base: the changed "
                    "pose cells and the rest of the state, 3-7 % of it for a worn insole) while the patch is at most "
                    "this fraction of the base's size; past it, a new full base. 0: every checkpoint in full",
    )
    cache_max_devices: int = Field(
        0, ge=0, le=10_000_000,
        description="calibrators a refit process keeps in memory (~1.5 MB each after a week of wear); beyond it the "
                    "least recently fed is written as a checkpoint and dropped, and restored (with a replay) when its "
                    "next batch comes; 0: every device it feeds",
    )
    reorder_window_s: float = Field(
        10.0, ge=0, le=3600,
        description="a batch whose predecessor seq is missing waits this long for it before being fed",
    )
    max_seq_jump: int = Field(
        100_000, ge=1, description="a seq this far above the device's highest stored seq gets 422",
    )
    max_backlog_batches: int = Field(
        100_000, ge=1, description="/readyz fails above this many stored batches not yet fed",
    )
    write_timeout_s: float = Field(
        30.0, gt=0, le=600, description="an ingest not committed within this gets 503 (a resend is a duplicate)"
    )
    refit_in_process: bool = Field(
        True, description="run refits in this process (SQLite: always; PostgreSQL: off for pure API processes)"
    )
    lease_ttl_s: float = Field(
        10.0, gt=0.5, le=600, description="PostgreSQL: a refit worker's lease on a device lasts this long unless renewed"
    )
    lease_poll_s: float = Field(0.25, gt=0, le=60, description="PostgreSQL: how often a worker looks for work")
    lease_max_devices: int = Field(
        8192, ge=1, le=1_000_000,
        description="PostgreSQL: devices a refit worker leases at once, at most (it holds about its share of the "
                    "active devices: active / live workers); beyond it a worker gives each device up once fed. "
                    "The calibrators it keeps in memory are bounded by cache_max_devices",
    )
    lease_idle_s: float = Field(
        60.0, ge=0, le=3600,
        description="PostgreSQL: a worker keeps the lease (and the cached calibrator) of a device that was fed "
                    "everything it had this long for its next batch, unless it needs the room; 0: gives it up at once",
    )
    calibrator: str = Field(
        "selfcal.calibrator:OnlineCalibrator",
        description="import path module:Class of the calibrator (tests inject a fake)",
    )
    calibrator_model: str = Field("affine9", description="error model passed to the calibrator")
    gil_switch_interval_s: float = Field(
        0.001, gt=0, le=0.1, description="sys.setswitchinterval: refit threads yield the GIL to requests sooner"
    )
    pg_async_reads: bool = Field(
        True, description="PostgreSQL: GET /devices/{id}/calibration (and the routes that read the served "
                          "version) waits on the database in the event loop, not in a thread (service/pg_async.py)"
    )
    gc_freeze: bool = Field(
        True, description="gc.freeze() once the app is up: what was imported and built at start leaves the cyclic "
                          "collector's full scans (each stalls every request; docs/service.md)"
    )
    gc_unfreeze_every_s: float = Field(
        600.0, ge=0, le=86400,
        description="with gc_freeze: what survives each full collection is frozen too (the next one scans only "
                    "what arrived since), and everything is unfrozen once per this many seconds so that cyclic "
                    "garbage among frozen objects is freed (one full scan per period; service/gc_policy.py); "
                    "0: only what exists at start is frozen"
    )
    gc_gen0_threshold: int = Field(
        700, ge=100, le=1_000_000, description="gc.set_threshold's first value: allocations between young collections"
    )
    header_timeout_s: float = Field(
        10.0, gt=0, le=600, description="a request's line and headers must arrive within this (slow clients)"
    )
    body_timeout_s: float = Field(30.0, gt=0, le=3600, description="a request's body must arrive within this")
    http_parser: Literal["auto", "httptools", "h11"] = Field(
        "auto", description="uvicorn's HTTP parser: httptools (C; auto picks it when installed) or h11 (pure Python)"
    )
    keep_alive_timeout_s: int = Field(5, ge=1, le=600, description="an idle keep-alive connection is closed after this")
    metrics_dir: str = Field(
        "", description="a folder shared by this machine's API processes: /metrics adds up all of them "
        "(serve --workers N sets one)"
    )
    log_level: Literal["critical", "error", "warning", "info", "debug"] = "info"
    access_log: bool = False
    log_format: Literal["text", "json"] = Field(
        "text", description="json: one JSON object a line, with request_id and device_id"
    )

    @field_validator("api_keys")
    @classmethod
    def _keys_parse(cls, value: str) -> str:
        from selfcal_service.auth import parse_api_keys

        parse_api_keys(value)  # raises ValueError naming the bad entry
        return value


def load_settings(
    config_section: Mapping[str, Any] | None = None,
    overrides: Mapping[str, Any] | None = None,
    environ: Mapping[str, str] | None = None,
) -> Settings:
    """Merge defaults < ``[service]`` config < ``SELFCAL_*`` env < ``overrides``.

    Raises ``selfcal.errors.InputError`` naming the bad key.
    """
    from selfcal.errors import InputError

    environ = os.environ if environ is None else environ
    merged: dict[str, Any] = {}
    for key, value in (config_section or {}).items():
        if key not in Settings.model_fields:
            raise InputError(f"config [service].{key}: unknown key")
        merged[key] = value
    for name in Settings.model_fields:
        env_name = ENV_PREFIX + name.upper()
        if env_name in environ:
            merged[name] = environ[env_name]
    for key, value in (overrides or {}).items():
        if value is not None:
            merged[key] = value
    try:
        return Settings.model_validate(merged)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = ".".join(str(p) for p in err["loc"]) or "settings"
        raise InputError(f"service setting {field}: {err['msg']}") from None
