"""``selfcal serve``: start the calibration service (FastAPI + uvicorn; SQLite or PostgreSQL).

Settings: defaults < ``[service]`` of the config < ``SELFCAL_*`` env < these flags.
API keys come from ``SELFCAL_API_KEYS`` (or ``[service] api_keys``), never from a flag
(command lines are visible to every user of the machine).

* ``--db PATH`` (or ``sqlite:///PATH``): the embedded default. One process that also
  runs the refits.
* ``--db postgresql://…``: a shared database. ``--workers N`` runs N API processes
  (uvicorn workers). Each also runs refits on the devices it leases, unless
  ``--no-refit``; then ``selfcal worker --db URL`` processes do the refits.
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--db", metavar="PATH|URL", required=True,
                        help="SQLite database file (created if missing), or postgresql://user@host:port/dbname")
    parser.add_argument("--host", default=None, help="bind address (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None, help="TCP port (default 8000; 0 = any free port)")
    parser.add_argument("--workers", type=int, default=1,
                        help="API processes (default 1; more than 1 needs PostgreSQL)")
    parser.add_argument("--refit-threads", type=int, default=None, help="refit threads per process (default 1)")
    parser.add_argument("--no-refit", action="store_true",
                        help="PostgreSQL: API only, refits by `selfcal worker` processes")
    parser.add_argument("--log-format", default=None, choices=["text", "json"],
                        help="json: structured logs, one object a line, with request and device ids")
    parser.add_argument(
        "--log-level", default=None, choices=["critical", "error", "warning", "info", "debug"], help="log level"
    )


def run(args: argparse.Namespace) -> int:
    import json
    import os
    from pathlib import Path

    from selfcal.config import load_config, section
    from selfcal.errors import InputError

    try:
        import uvicorn

        from selfcal_service.http_protocol import protocol_class
        from selfcal_service.logs import uvicorn_log_config
        from selfcal_service.main import SERVE_ENV, create_app
        from selfcal_service.pg_store import is_postgres_url
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
            "worker_threads": args.refit_threads,
            "log_level": args.log_level,
            "log_format": args.log_format,
            "refit_in_process": False if args.no_refit else None,
        },
    )
    postgres = is_postgres_url(settings.db_path)
    try:
        http_protocol = protocol_class(settings.http_parser)
    except ValueError as exc:
        raise InputError(f"service setting http_parser: {exc}") from None
    if args.workers < 1:
        raise InputError(f"--workers {args.workers}: must be 1 or more")
    if not postgres and (args.workers > 1 or not settings.refit_in_process):
        raise InputError("--workers > 1 and --no-refit need a PostgreSQL database (--db postgresql://...): "
                         "a SQLite file has one writer process, which also runs the refits")
    if not postgres:  # a folder that is not there: one line here, not a traceback from the app's startup
        db_file = Path(settings.db_path.removeprefix("sqlite:///"))
        if not db_file.parent.is_dir():
            raise InputError(f"--db {settings.db_path}: the folder {db_file.parent} does not exist (create it first)")
        if db_file.is_dir():
            raise InputError(f"--db {settings.db_path}: is a folder; give a database file in it")
        if not os.access(db_file.parent, os.W_OK):
            raise InputError(f"--db {settings.db_path}: cannot write in {db_file.parent}")
    if postgres:
        try:
            import psycopg  # noqa: F401
        except ModuleNotFoundError as exc:
            raise InputError("a postgresql:// database needs the 'postgres' extra "
                             "(pip install 'selfcal[postgres]')") from exc
    from selfcal_service.logs import redact_url

    shown = redact_url(settings.db_path) if postgres else settings.db_path  # no credentials in logs
    print(
        f"selfcal serve: http://{settings.host}:{settings.port} db={shown} "
        f"({'postgresql' if postgres else 'sqlite, synchronous=' + settings.sqlite_synchronous}, "
        f"api processes={args.workers}, refits={'in process' if settings.refit_in_process else 'selfcal worker'})",
        file=sys.stderr,
        flush=True,
    )
    common = dict(
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        access_log=settings.access_log,
        timeout_graceful_shutdown=10,
        timeout_keep_alive=settings.keep_alive_timeout_s,
        http=http_protocol,
    )
    log_config = uvicorn_log_config(settings.log_level, settings.log_format)
    if log_config is not None:
        common["log_config"] = log_config
    if args.workers == 1:
        uvicorn.run(create_app(settings, config=cfg), **common)
        return 0
    # N processes: each builds its app from the same settings (handed over in the environment);
    # their metrics meet in a shared folder, so a scrape of any process counts them all
    import shutil
    import tempfile

    shared = settings.metrics_dir or tempfile.mkdtemp(prefix="selfcal-metrics-")
    for old in Path(shared).glob("*.json"):  # counters start at zero with each start, as in one process
        old.unlink(missing_ok=True)
    spec = {"settings": {**settings.model_dump(), "metrics_dir": shared}, "config": cfg}
    os.environ[SERVE_ENV] = json.dumps(spec)
    try:
        uvicorn.run("selfcal_service.main:app_from_env", factory=True, workers=args.workers, **common)
    finally:
        if not settings.metrics_dir:
            shutil.rmtree(shared, ignore_errors=True)
    return 0
