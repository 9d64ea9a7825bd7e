"""``selfcal serve``: start the calibration service (FastAPI + uvicorn + SQLite WAL).

Settings: defaults < ``[service]`` of the config < ``SELFCAL_*`` env < these flags.
API keys come from ``SELFCAL_API_KEYS`` (or ``[service] api_keys``), never from a flag
(command lines are visible to every user of the machine).
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--db", metavar="PATH", required=True, help="SQLite database file (created if missing)")
    parser.add_argument("--host", default=None, help="bind address (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None, help="TCP port (default 8000; 0 = any free port)")
    parser.add_argument("--workers", type=int, default=None, help="refit worker threads (default 1)")
    parser.add_argument(
        "--log-level", default=None, choices=["critical", "error", "warning", "info", "debug"], help="log level"
    )


def run(args: argparse.Namespace) -> int:
    from selfcal.config import load_config, section
    from selfcal.errors import InputError

    try:
        import uvicorn

        from selfcal_service.main import create_app
        from selfcal_service.settings import load_settings
    except ModuleNotFoundError as exc:  # pragma: no cover - depends on the install
        raise InputError(f"the service needs the 'service' extra (pip install 'selfcal[service]'): {exc}") from exc

    cfg = load_config(args.config)
    settings = load_settings(
        section(cfg, "service"),
        overrides={
            "db_path": args.db,
            "host": args.host,
            "port": args.port,
            "worker_threads": args.workers,
            "log_level": args.log_level,
        },
    )
    from selfcal_service.http_protocol import make_protocol

    app = create_app(settings, config=cfg)
    metrics = app.state.metrics
    protocol = make_protocol(settings.header_timeout_s, settings.body_timeout_s,
                             on_timeout=lambda kind: metrics.inc("selfcal_http_timeouts_total", kind=kind))
    print(
        f"selfcal serve: http://{settings.host}:{settings.port} db={settings.db_path} "
        f"(synchronous={settings.sqlite_synchronous}, workers={settings.worker_threads})",
        file=sys.stderr,
        flush=True,
    )
    uvicorn.run(
        app,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        access_log=settings.access_log,
        timeout_graceful_shutdown=10,
        timeout_keep_alive=settings.keep_alive_timeout_s,
        http=protocol,
    )
    return 0
