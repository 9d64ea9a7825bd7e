"""Structured logs: one JSON object a line, with the request id and the device id.

``selfcal serve --log-format json`` (or ``[service] log_format = "json"``) sends every
log record (the service's, the worker's and uvicorn's) through :class:`JsonFormatter`:

    {"ts": "2026-11-23T16:51:13.123Z", "level": "warning", "logger": "selfcal.service.worker",
     "msg": "...", "pid": 4242, "request_id": "9f2c...", "device_id": "insole-L-0001"}

``request_id`` is the client's ``X-Request-ID`` header when it sends one (checked: at
most 64 characters of ``[A-Za-z0-9._-]``), else a new random id; the response echoes
it. ``device_id`` is set for requests under ``/devices/{id}/`` and for refit cycles.
Both live in context variables, so they follow a request or a worker cycle.
"""

from __future__ import annotations

import contextvars
import datetime as _dt
import json
import logging
import os
import re
import uuid
from typing import Any

request_id: contextvars.ContextVar[str | None] = contextvars.ContextVar("selfcal_request_id", default=None)
device_id: contextvars.ContextVar[str | None] = contextvars.ContextVar("selfcal_device_id", default=None)

_REQUEST_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
_DEVICE_PATH = re.compile(r"^/devices/([^/]+)")


def new_request_id(header: str | None) -> str:
    """The client's request id if it is a plain token, else a fresh random one."""
    if header and _REQUEST_ID.match(header):
        return header
    return uuid.uuid4().hex[:16]


def device_of_path(path: str) -> str | None:
    """``insole-1`` for ``/devices/insole-1/...``, else None."""
    m = _DEVICE_PATH.match(path)
    return m.group(1) if m else None


class JsonFormatter(logging.Formatter):
    """A log record as one JSON line (UTC time, level, logger, message, pid, ids, exception)."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "ts": _dt.datetime.fromtimestamp(record.created, _dt.timezone.utc).isoformat(timespec="milliseconds")
            .replace("+00:00", "Z"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
            "pid": os.getpid(),
        }
        rid = getattr(record, "request_id", None) or request_id.get()
        did = getattr(record, "device_id", None) or device_id.get()
        if rid:
            out["request_id"] = rid
        if did:
            out["device_id"] = did
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, ensure_ascii=False)


def uvicorn_log_config(level: str, fmt: str) -> dict[str, Any] | None:
    """A ``logging.config`` dict for uvicorn and the service: JSON lines, or None (uvicorn's own)."""
    if fmt != "json":
        return None
    handler = {"class": "logging.StreamHandler", "formatter": "json", "stream": "ext://sys.stderr"}
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "formatters": {"json": {"()": "selfcal_service.logs.JsonFormatter"}},
        "handlers": {"default": handler},
        "loggers": {
            "uvicorn": {"handlers": ["default"], "level": level.upper(), "propagate": False},
            "uvicorn.error": {"level": level.upper()},
            "uvicorn.access": {"handlers": ["default"], "level": level.upper(), "propagate": False},
            "selfcal": {"handlers": ["default"], "level": level.upper(), "propagate": False},
        },
        "root": {"handlers": ["default"], "level": "WARNING"},  # psycopg, asyncio, the rest: JSON too
    }


def redact_url(url: str) -> str:
    """A database URL fit for logs: no user, no password, no query (``host:port/db``)."""
    from urllib.parse import urlsplit

    parts = urlsplit(url)
    if not parts.scheme or not parts.hostname:
        return url
    port = f":{parts.port}" if parts.port else ""
    return f"{parts.scheme}://{parts.hostname}{port}{parts.path}"
