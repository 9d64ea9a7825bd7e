"""``selfcal worker --db postgresql://…``: a refit worker process for a shared database.

It leases devices that have stored batches not yet fed (``FOR UPDATE SKIP LOCKED``,
with an expiry), feeds them to each device's calibrator and commits the new state and
versions exactly as the in-process worker of ``selfcal serve`` does. Run as many as
the refits need, on any machines that reach the database; a killed worker's devices
are taken over by the others once its leases expire (``[service] lease_ttl_s``).
SIGTERM or Ctrl-C stops it after the current cycle and hands its leases back.
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--db", metavar="URL", required=True, help="postgresql://user@host:port/dbname")
    parser.add_argument("--threads", type=int, default=None,
                        help="refit threads (default: [service] worker_process_threads, 4); a cycle waits for its durable commit, so one thread leaves the process idle on the database")
    parser.add_argument("--nice", type=int, default=0, metavar="N",
                        help="lower this process's CPU priority by N (0-19): on a machine shared with API "
                             "processes, reads then go first and refits take what is left")
    parser.add_argument("--idle", action="store_true",
                        help="Linux: run the refits under SCHED_IDLE, i.e. only on CPU time that nothing "
                             "else wants (stronger than --nice 19; an API process on the same cores is "
                             "never kept waiting by a refit)")
    parser.add_argument("--status-every-s", type=float, default=10.0,
                        help="print a status line this often (0: never)")
    parser.add_argument("--log-format", default=None, choices=["text", "json"], help="json: structured logs")
    parser.add_argument(
        "--log-level", default=None, choices=["critical", "error", "warning", "info", "debug"], help="log level"
    )


def lower_priority(nice: int, idle: bool) -> None:
    """Lower this process's CPU priority before any thread starts (threads inherit it).

    nice : int, 0-19 — added to the process's nice value
    idle : bool — Linux SCHED_IDLE: scheduled only when no other task wants the CPU
    """
    import os

    from selfcal.errors import InputError

    if idle:
        if not hasattr(os, "SCHED_IDLE"):
            raise InputError("--idle: SCHED_IDLE is a Linux scheduling policy; this system has none (use --nice)")
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    if nice:
        os.nice(nice)


def run(args: argparse.Namespace) -> int:
    import logging
    import signal
    import threading
    import time

    from selfcal.config import load_config, section
    from selfcal.errors import InputError

    try:
        from selfcal_service.logs import redact_url
        from selfcal_service.main import make_worker, tune_gc
        from selfcal_service.metrics import Metrics
        from selfcal_service.pg_store import PostgresStore, is_postgres_url
        from selfcal_service.settings import load_settings
        from selfcal_service.worker import CalibratorFactory
    except ModuleNotFoundError as exc:  # pragma: no cover - depends on the install
        raise InputError(f"the worker needs the 'service' and 'postgres' extras: {exc}") from exc

    if args.threads is not None and not 1 <= args.threads <= 64:
        raise InputError(f"--threads {args.threads}: must be 1 to 64")
    if not 0 <= args.nice <= 19:
        raise InputError(f"--nice {args.nice}: must be 0 to 19")
    lower_priority(args.nice, args.idle)
    if not is_postgres_url(args.db):
        raise InputError(f"--db {args.db}: a refit worker needs a shared postgresql:// database "
                         "(with a SQLite file, `selfcal serve` runs the refits itself)")
    cfg = load_config(args.config)
    settings = load_settings(section(cfg, "service"), overrides={
        "db_path": args.db, "log_level": args.log_level, "log_format": args.log_format,
        "worker_process_threads": args.threads})
    settings = settings.model_copy(update={"worker_threads": settings.worker_process_threads})
    if settings.log_format == "json":
        import logging.config

        from selfcal_service.logs import uvicorn_log_config

        logging.config.dictConfig(uvicorn_log_config(settings.log_level, "json"))
    else:
        logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cal_config = {k: v for k, v in cfg.items() if k not in ("service", "gateway")}
    factory = CalibratorFactory(settings.calibrator, config=cal_config, model=settings.calibrator_model)
    # a reader connection for each refit thread, the lease thread and the status line, kept
    # between uses (8 idle at most by default: more threads would open and close them)
    store = PostgresStore(settings.db_path, group_commit_max_ops=settings.group_commit_max_ops,
                          max_idle_readers=max(8, settings.worker_threads + 4))
    try:
        store.open()
    except Exception as exc:  # noqa: BLE001 - unreachable database: one clear line
        raise InputError(f"--db: cannot open the database ({type(exc).__name__}: {exc})") from None
    metrics = Metrics(settings.metrics_dir or None)  # a shared folder: the API's /metrics adds our refits
    worker = make_worker(store, factory, metrics, settings)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    tune_gc(settings)
    metrics.track_gc(role="worker")  # its pauses apart from the API's in /metrics
    worker.start()
    print(f"selfcal worker {worker.lease.owner}: db={redact_url(settings.db_path)}, "
          f"threads={settings.worker_threads}, lease {settings.lease_ttl_s:g} s", file=sys.stderr, flush=True)
    t0 = time.monotonic()
    try:
        while not stop.wait(args.status_every_s if args.status_every_s > 0 else 3600):
            if args.status_every_s > 0:
                try:  # the database may be down for a moment: the worker waits it out
                    backlog = f"{store.backlog()} batches"
                except Exception as exc:  # noqa: BLE001
                    backlog = f"unknown ({type(exc).__name__})"
                print(f"selfcal worker: {time.monotonic() - t0:7.0f} s, {worker.cycles} cycles, "
                      f"{metrics.get('selfcal_worker_samples_total'):.0f} samples fed, "
                      f"{len(worker._leased)} devices leased, backlog {backlog}, "
                      f"{metrics.get('selfcal_worker_checkpoints_total'):.0f} checkpoints written "
                      f"({metrics.get('selfcal_worker_checkpoint_patches_total'):.0f} as patches, "
                      f"{metrics.get('selfcal_worker_checkpoint_bytes_total') / 1e6:.1f} MB), "
                      f"{worker.replays} restores replayed "
                      f"({metrics.get('selfcal_worker_replayed_samples_total'):.0f} samples), "
                      f"{worker.conflicts} conflicts", file=sys.stderr, flush=True)
    finally:
        worker.stop()
        store.close()
    return 0
