"""The FastAPI app factory: routes exactly as in design.md, engine created in ``lifespan``.

Layers: routes (this module) -> :class:`selfcal_service.worker.RefitWorker` (calibrators) and
:class:`selfcal_service.storage.Storage` (all SQL in ``service/sqlite_store.py``). Routes hold
no numerics. ``create_app(settings, calibrator_factory=...)`` lets tests inject a fake
calibrator; ``app.state.store`` / ``app.state.worker`` exist while the app runs.
"""

from __future__ import annotations

import asyncio
import datetime as _dt
import gzip
import hashlib
import logging
import re
import sys
import time
from contextlib import asynccontextmanager
from typing import Annotated, Any, AsyncIterator

import orjson
from fastapi import Depends, FastAPI, Path, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.responses import PlainTextResponse, Response

from selfcal.blas_threads import one_blas_thread
from selfcal.errors import InputError
from selfcal_service.auth import AuthError, KeyRing
from selfcal_service.gc_policy import Refreezer
from selfcal_service.logs import device_id as device_id_var
from selfcal_service.logs import device_of_path, new_request_id
from selfcal_service.logs import request_id as request_id_var
from selfcal_service.metrics import Metrics
from selfcal_service.schemas import (
    BINARY_MEDIA_TYPE,
    DEVICE_ID_PATTERN,
    Batch,
    BatchAck,
    CalibrationOut,
    DeviceOut,
    DevicesOut,
    ErrorOut,
    FactoryCalibrationIn,
    FieldError,
    FleetDeviceOut,
    FleetOut,
    HealthOut,
    HistoryOut,
    PosesOut,
    ReadyOut,
    RefusalOut,
    RefusalsOut,
    RollbackIn,
    SampleBatchIn,
    VersionOut,
    WhoAmIOut,
    batch_request_openapi,
    canonical_binary,
    check_batch,
    decode_binary,
)
from selfcal_service.settings import Settings
from selfcal_service.group_commit import GroupCommitStore
from selfcal_service.sqlite_store import SQLiteStore
from selfcal_service.storage import (
    ConflictError,
    DeviceRecord,
    FleetRecord,
    NewVersion,
    RefusalRecord,
    SeqConflict,
    SeqJump,
    Storage,
    StorageUnavailable,
    VersionRecord,
)
from selfcal_service.worker import CalibratorFactory, LeaseConfig, RefitWorker

log = logging.getLogger("selfcal.service")

_ERRORS = {
    401: {"model": ErrorOut, "description": "missing or unknown API key"},
    403: {"model": ErrorOut, "description": "API key lacks the scope"},
    404: {"model": ErrorOut, "description": "unknown device or version"},
    422: {"model": ErrorOut, "description": "invalid input; `field` names it"},
}
_BODY_ERRORS = {
    **_ERRORS,
    413: {"model": ErrorOut, "description": "body larger than max_body_bytes"},
    415: {"model": ErrorOut, "description": "unsupported Content-Type"},
}
_INGEST_ERRORS = {
    **_BODY_ERRORS,
    409: {"model": ErrorOut, "description": "the seq is stored with other content (a resend must be identical)"},
    503: {"model": ErrorOut, "description": "nothing was stored (storage unavailable or busy); retry later"},
}


#: GET /fleet bodies from this size are gzipped for a client that accepts it.
FLEET_GZIP_MIN_BYTES = 8192


def _json(obj: Any, status: int = 200, headers: dict[str, str] | None = None) -> Response:
    return Response(orjson.dumps(obj), status_code=status, media_type="application/json", headers=headers)


async def _read(store: Storage, fn, *args):
    """Call a store read: directly for SQLite (a local file, microseconds), in a thread for
    a database server (PostgreSQL), so a slow or unreachable server never stalls the loop."""
    if getattr(store, "blocking_reads", False):
        return await run_in_threadpool(fn, *args)
    return fn(*args)


async def _current(store, device_id: str):
    """The device's (device row, served version), or None: read in the event loop where the
    store can (PostgreSQL's ``async_reads``, service/pg_async.py), else as :func:`_read`."""
    if getattr(store, "async_reads", False):
        return await store.current_async(device_id)
    return await _read(store, store.current, device_id)


async def _current_or_404(store, device_id: str):
    """The device's (device row, current version), or a 404 naming the device."""
    found = await _current(store, device_id)
    if found is None:
        raise FieldError("device_id", f"unknown device {device_id!r}", 404)
    return found


_DEVICE_ID_RE = re.compile(DEVICE_ID_PATTERN)


def _replay(chunks: list[bytes], finished: bool, last: dict | None, receive):
    """An ASGI ``receive`` that gives again what was received of a body: ``chunks`` in one
    message (``finished``: the whole body), then ``last`` (a message that was not body, as
    a disconnect), then ``receive``'s own messages."""
    pending = [{"type": "http.request", "body": b"".join(chunks), "more_body": not finished}]
    if last is not None:
        pending.append(last)
    pending.reverse()

    async def replayed():
        if pending:
            return pending.pop()
        return await receive()

    return replayed


def _model(obj: BaseModel, status: int = 200) -> Response:
    return Response(obj.model_dump_json(), status_code=status, media_type="application/json")


def _error(status: int, error: str, message: str, field: str | None = None, headers=None) -> Response:
    return _json({"error": error, "field": field, "message": message}, status, headers)


def _iso(ts: float | None) -> str | None:
    if ts is None:
        return None
    return _dt.datetime.fromtimestamp(ts, tz=_dt.timezone.utc).isoformat(timespec="milliseconds")


def _field_of(loc: tuple) -> str:
    parts = [p for p in loc if p not in ("body", "path", "query", "header")]
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "body"


def _validation_response(errors: list[dict[str, Any]]) -> Response:
    err = errors[0]
    field = _field_of(tuple(err.get("loc", ())))
    msg = err.get("msg", "invalid value")
    if err.get("type") == "json_invalid":
        field = "body"
    return _error(422, "validation_error", f"{field}: {msg}", field)


def _versions_out(v: VersionRecord) -> VersionOut:
    return VersionOut(
        version=v.version,
        status=v.status,
        source=v.source,
        created_at=_iso(v.created_at),
        calibration=v.calibration,
        provenance=v.provenance,
    )


def refusal_out(r: RefusalRecord) -> RefusalOut:
    """A stored refusal as the API shows it (ISO time beside the Unix seconds)."""
    return RefusalOut(kind=r.kind, reason=r.reason, message=r.message, at=_iso(r.at), at_unix_s=r.at,
                      t_s=r.t_s, seq=r.seq)


def fleet_device_out(f: FleetRecord) -> FleetDeviceOut:
    """A fleet row as the API shows it (ISO times, the last refusal typed)."""
    status = f.status if f.status in ("uncalibrated", "provisional", "calibrated") else "uncalibrated"
    return FleetDeviceOut(
        device_id=f.device_id, status=status, version=f.version, source=f.source, model=f.model,
        predicted_sphere_rms_mg=f.predicted_sphere_rms_mg, residual_rms_mg=f.residual_rms_mg, n_poses=f.n_poses,
        backlog_batches=f.backlog_batches, batches_stored=f.batches_stored, samples_processed=f.samples_processed,
        rejected_batches=f.rejected_batches, last_seen=_iso(f.last_seen), updated_at=_iso(f.updated_at),
        last_refusal=None if f.last_refusal is None else refusal_out(f.last_refusal))


def _split_determined(calib: dict[str, Any]) -> tuple[list[str], list[str]]:
    det = calib.get("determined", calib.get("determined_params"))
    und = calib.get("undetermined", calib.get("undetermined_params"))
    if det is not None or und is not None:
        return list(det or []), list(und or [])
    std = calib.get("std") or {}
    params = calib.get("params") or {}
    det = [k for k in params if std.get(k) is not None]
    und = [k for k in params if std.get(k) is None]
    return det, und


def calibration_out(device_id: str, dev: DeviceRecord, ver: VersionRecord | None) -> CalibrationOut:
    calib = ver.calibration if ver else {}
    det, und = _split_determined(calib) if ver else ([], [])
    cstatus = dev.calibrator_status if dev.calibrator_status in ("uncalibrated", "provisional", "calibrated") else None
    return CalibrationOut(
        device_id=device_id,
        version=ver.version if ver else None,
        status=ver.status if ver else "uncalibrated",
        status_reason=calib.get("status_reason"),
        source=ver.source if ver else None,
        model=calib.get("model"),
        params=calib.get("params"),
        std=calib.get("std"),
        matrix=calib.get("matrix"),
        offset=calib.get("offset"),
        n_poses=calib.get("n_poses"),
        residual_rms_mg=calib.get("residual_rms_mg"),
        predicted_sphere_rms_mg=calib.get("predicted_sphere_rms_mg"),
        predicted_sphere_rms_mg_model=calib.get("predicted_sphere_rms_mg_model"),
        unmodelled=calib.get("unmodelled"),
        updated_at=_iso(ver.created_at) if ver else None,
        determined=det,
        undetermined=und,
        last_refit=dev.last_refit,
        calibrator_status=cstatus,
        samples_processed=dev.samples_processed,
        batches_stored=dev.batches_stored,
        processed_seq=dev.processed_seq,
        rejected_batches=dev.rejected_batches,
        rejected_samples=dev.rejected_samples,
        last_rejection=dev.last_rejection,
    )


async def _read_body(request: Request, limit: int) -> bytes:
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            if int(declared) > limit:
                raise FieldError("body", f"{declared} bytes exceed the limit of {limit}", 413)
        except ValueError:
            raise FieldError("Content-Length", "not an integer", 400) from None
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise FieldError("body", f"body exceeds the limit of {limit} bytes", 413)
        chunks.append(chunk)
    return b"".join(chunks)


def _accepts_gzip(accept_encoding: str) -> bool:
    """Whether an ``Accept-Encoding`` value accepts gzip (named, or ``*``, with q > 0)."""
    accepted = {}
    for part in accept_encoding.split(","):
        name, _, params = part.strip().partition(";")
        q = 1.0
        for p in params.split(";"):
            key, _, value = p.strip().partition("=")
            if key.strip().lower() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        if name.strip():
            accepted[name.strip().lower()] = q
    return accepted.get("gzip", accepted.get("x-gzip", accepted.get("*", 0.0))) > 0


def _media_type(content_type: str) -> str:
    """The media type of a Content-Type value, parameters left out, lower case."""
    return content_type.split(";")[0].strip().lower()


def _content_type(request: Request) -> str:
    """The request's media type; a compressed body (any Content-Encoding but identity) is a
    415: it was decoded as if plain (stored as is when its bytes happened to parse)."""
    encoding = request.headers.get("content-encoding", "identity").strip().lower()
    if encoding not in ("", "identity"):
        raise FieldError("Content-Encoding", f"{encoding!r} is not accepted: send the body uncompressed", 415)
    return _media_type(request.headers.get("content-type", "application/json"))


def _header(scope, name: bytes) -> bytes | None:
    """The first value of the header ``name`` (lower case) of an ASGI ``scope``, as a
    Request's ``headers.get`` gives it (undecoded), or None."""
    return next((v for k, v in scope["headers"] if k == name), None)


async def _json_body(request: Request, model: type[BaseModel], limit: int) -> BaseModel:
    body = await _read_body(request, limit)
    if _content_type(request) != "application/json":
        raise FieldError("Content-Type", "expected application/json", 415)
    try:
        return model.model_validate_json(body or b"{}")
    except ValidationError as exc:
        raise RequestValidationError(exc.errors()) from None


async def _admin_publish(worker: RefitWorker, device_id: str, version: NewVersion, seed: dict) -> int:
    """Run the (locking, blocking) admin publication off the event loop; bad params -> 422."""
    try:
        return await run_in_threadpool(worker.publish_admin, device_id, version, seed)
    except (InputError, ValueError, KeyError, TypeError) as exc:
        field = str(exc).split(":", 1)[0] if str(exc).split(":", 1)[0] in ("params", "std", "matrix", "offset") else "params"
        raise FieldError(field, f"cannot install this calibration: {exc}") from None


def _allowed_methods(app: FastAPI, path: str) -> list[str]:
    """Methods of the routes that match ``path`` (for a 405's ``Allow`` header)."""
    methods: set[str] = set()
    for route in app.routes:
        match = getattr(route, "path_regex", None)
        if match is not None and match.match(path) and getattr(route, "methods", None):
            methods |= set(route.methods)
    return sorted(methods)  # (HEAD is not served: not listed)


def check_admin_calibration(model_name: str, matrix, offset, params: dict | None, guard) -> None:
    """The plausibility rules of the refit guard, for an admin write; FieldError if not.

    ``a_cal_g = matrix @ (raw_g - offset_g)``: the matrix must be finite, well
    conditioned (singular values within 10x of each other) with a positive
    determinant, and the parameters it implies (or the given ``params``) within the
    guard's plausible ranges ([guard] max_bias_g, max_scale_dev, ...).
    """
    import numpy as np

    from selfcal.fit import implausible
    from selfcal.models import ErrorModel

    m = np.asarray(matrix, dtype=float)
    o = np.asarray(offset, dtype=float)
    if not (np.isfinite(m).all() and np.isfinite(o).all()):
        raise FieldError("matrix", "matrix and offset must be finite")
    sv = np.linalg.svd(m, compute_uv=False)
    det = float(np.linalg.det(m))
    if not (sv[-1] > 0 and sv[0] / sv[-1] <= 10.0 and det > 0):
        raise FieldError("matrix", f"not a plausible correction: singular values {np.round(sv, 4).tolist()}, "
                         f"determinant {det:.4g} (needs det > 0 and a condition number <= 10)")
    try:
        model = ErrorModel(model_name)
        theta = model.from_linear(m, o)
        where = "matrix"
        if params:
            given = model.from_dict(params)
            # the params are served (and the matrix and offset they imply): they must be the
            # given matrix and offset's, or one of the two was silently ignored
            implied = model.from_linear(*model.linear(given))
            off = float(np.max(np.abs(implied[:9] - theta[:9])))  # (theta: the matrix and offset's)
            if off > 1e-6:
                raise FieldError("params", f"params and matrix/offset describe different corrections (their "
                                           f"base parameters differ by up to {off:.3g}); give the same calibration "
                                           "in both")
            theta, where = given, "params"
    except (InputError, ValueError, np.linalg.LinAlgError) as exc:
        raise FieldError("params", str(exc)) from None
    reason = implausible(model, theta, guard)
    if reason:
        raise FieldError(where, f"implausible calibration: {reason}")


def open_store(settings: Settings) -> Storage:
    """The store named by ``settings.db_path``: a ``postgresql://`` URL, or a SQLite file path."""
    from selfcal_service.pg_store import PostgresStore, is_postgres_url

    if is_postgres_url(settings.db_path):
        return PostgresStore(settings.db_path, group_commit_max_ops=settings.group_commit_max_ops,
                             async_reads=settings.pg_async_reads)
    path = settings.db_path.removeprefix("sqlite:///") if settings.db_path.startswith("sqlite:///") else settings.db_path
    return SQLiteStore(path, synchronous=settings.sqlite_synchronous,
                       group_commit_max_ops=settings.group_commit_max_ops)


def expected_refit_threads(settings: Settings) -> int:
    """Refit threads a healthy process runs: none in an API-only process (``--no-refit``)."""
    return settings.worker_threads if settings.refit_in_process else 0


def worker_owner_id() -> str:
    """A unique lease owner id for this process: host, pid and a random suffix."""
    import os
    import socket
    import uuid

    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


def make_worker(store: Storage, factory: CalibratorFactory, metrics: Metrics, settings: Settings) -> RefitWorker:
    """The refit worker for ``store``: leasing devices when the database is shared (PostgreSQL)."""
    from selfcal_service.pg_store import PostgresStore

    lease = None
    if isinstance(store, PostgresStore):
        lease = LeaseConfig(owner=worker_owner_id(), ttl_s=settings.lease_ttl_s, poll_s=settings.lease_poll_s,
                            idle_s=settings.lease_idle_s, max_devices=settings.lease_max_devices)
        metrics.gauge("selfcal_worker_leases", lambda: len(worker._leased))
    worker = RefitWorker(
        store,
        factory,
        metrics,
        threads=settings.worker_threads,
        max_batches_per_cycle=settings.worker_max_batches_per_cycle,
        time_reset_gap_s=settings.time_reset_gap_s,
        reorder_window_s=settings.reorder_window_s,
        min_cycle_interval_s=settings.min_cycle_interval_s,
        checkpoint_samples=settings.checkpoint_samples,
        checkpoint_patch_fraction=settings.checkpoint_patch_fraction,
        cache_max_devices=settings.cache_max_devices,
        lease=lease,
    )
    return worker


# Dependencies are ``async def``: FastAPI runs a plain ``def`` dependency in its thread
# pool, a thread hop per dependency per request (about a fifth of a GET's CPU, measured
# with bench/request_cost.py). None of them blocks.
async def get_store(request: Request) -> Storage:
    return request.app.state.store


async def get_worker(request: Request) -> RefitWorker:
    return request.app.state.worker


StoreDep = Annotated[Storage, Depends(get_store)]
WorkerDep = Annotated[RefitWorker, Depends(get_worker)]
DeviceId = Annotated[
    str, Path(pattern=DEVICE_ID_PATTERN, description="letter/digit, then up to 63 of [A-Za-z0-9._:-]")
]


def tune_gc(settings: Settings) -> "Refreezer | None":
    """The cyclic garbage collector, set for a long-running server process: one full
    collection, then ``gc.freeze()`` (``settings.gc_freeze``), so that the objects that
    exist now (modules, the app, the store) are never scanned again; and the young
    generation's threshold (``settings.gc_gen0_threshold``). A full collection of an
    unfrozen API process took up to 186 ms under load, and every request waited.

    With ``gc_unfreeze_every_s`` > 0, what survives each later full collection is frozen
    too (the calibrators the embedded service builds per device), and all is unfrozen
    once per period (:class:`selfcal_service.gc_policy.Refreezer`, returned installed:
    call its ``remove()`` at shutdown); else None."""
    import gc

    _, t1, t2 = gc.get_threshold()
    gc.set_threshold(settings.gc_gen0_threshold, t1, t2)
    if settings.gc_freeze:
        gc.collect()
        gc.freeze()
        if settings.gc_unfreeze_every_s > 0:
            return Refreezer(settings.gc_unfreeze_every_s).install()
    return None


def create_app(
    settings: Settings,
    calibrator_factory: CalibratorFactory | None = None,
    config: dict[str, Any] | None = None,
    store: Storage | None = None,
) -> FastAPI:
    """Build the app. ``calibrator_factory`` defaults to ``settings.calibrator``."""
    # the calibrator persists its config in every state: never hand it [service] (keys)
    cal_config = {k: v for k, v in (config or {}).items() if k not in ("service", "gateway")}
    factory = calibrator_factory or CalibratorFactory(
        settings.calibrator, config=cal_config, model=settings.calibrator_model
    )
    keys = KeyRing(settings.api_keys)
    metrics = Metrics(settings.metrics_dir or None)
    from selfcal_service import http_protocol

    http_protocol.configure(settings.header_timeout_s, settings.body_timeout_s,
                            lambda kind: metrics.inc("selfcal_http_timeouts_total", kind=kind))
    from selfcal.fit import GuardConfig

    guard = GuardConfig.from_section((config or {}).get("guard"))
    if len(keys) == 0:
        log.warning("no API keys configured (SELFCAL_API_KEYS): every request but /healthz gets 401")

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # CPU-bound refit threads hold the GIL for up to the switch interval (5 ms by
        # default) before the event loop can answer a GET: shorten it (process-wide).
        sys.setswitchinterval(settings.gil_switch_interval_s)
        # the refits' matrices are small: OpenBLAS's extra threads would only busy-wait
        # beside the request threads (process-wide; a count set in the environment is kept)
        one_blas_thread()
        st = store or open_store(settings)
        if not settings.refit_in_process and isinstance(st, SQLiteStore):
            raise InputError("refit_in_process = false needs a PostgreSQL database (SQLite has one process, "
                             "which must run the refits)")
        st.open()
        worker = make_worker(st, factory, metrics, settings)
        if settings.refit_in_process:
            worker.start()
        app.state.store, app.state.worker = st, worker
        metrics.gauge("selfcal_worker_queue_depth", worker.queue_depth)
        metrics.gauge("selfcal_backlog_batches", st.backlog, per_process=False)
        if hasattr(st, "oldest_pending_age_s"):
            metrics.gauge("selfcal_backlog_oldest_age_seconds", st.oldest_pending_age_s, per_process=False)
        if isinstance(st, GroupCommitStore):
            metrics.gauge("selfcal_db_write_queue_depth", st.queue_depth)
            metrics.counter_from("selfcal_db_commits_total", lambda: st.commits)
            metrics.counter_from("selfcal_db_writes_total", lambda: st.ops_committed)
        refreezer = tune_gc(settings)
        metrics.track_gc()
        try:
            yield
        finally:
            metrics.untrack_gc()
            if refreezer is not None:
                refreezer.remove()
            if settings.gc_freeze:
                import gc

                gc.unfreeze()  # back to the collector (tests run many apps in one process)
            if settings.refit_in_process:
                worker.stop()
            st.close()  # in this loop: its event-loop readers are closed here too

    app = FastAPI(
        title="selfcal",
        version="1",
        summary="Online self-calibration of wearable accelerometers: ingest, refit, model registry",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.metrics = metrics

    # ------------------------------------------------------------ dependencies
    def need(scope: str):
        async def check(request: Request) -> None:  # a digest and a compare: never blocks
            keys.check(request.headers.get("authorization"), scope)

        return Depends(check)


    # ------------------------------------------------------------ errors
    @app.exception_handler(AuthError)
    async def _auth(request: Request, exc: AuthError) -> Response:
        headers = {"WWW-Authenticate": "Bearer"} if exc.status == 401 else None
        return _error(exc.status, "unauthorized" if exc.status == 401 else "forbidden", exc.message, "Authorization", headers)

    @app.exception_handler(FieldError)
    async def _field(request: Request, exc: FieldError) -> Response:
        if request.url.path.endswith("/samples"):
            metrics.inc("selfcal_ingest_rejected_total", status=str(exc.status))
        kind = {404: "not_found", 409: "conflict", 413: "too_large",
                415: "unsupported_media_type"}.get(exc.status, "validation_error")
        return _error(exc.status, kind, f"{exc.field}: {exc.message}", exc.field)

    @app.exception_handler(ConflictError)
    async def _busy(request: Request, exc: ConflictError) -> Response:
        return _error(503, "busy", f"{exc} (another process kept changing the device; retry later)", None,
                      {"Retry-After": "1"})

    @app.exception_handler(StorageUnavailable)
    async def _unavailable(request: Request, exc: StorageUnavailable) -> Response:
        metrics.inc("selfcal_storage_unavailable_total")
        return _error(503, "storage_unavailable", f"{exc} (nothing was stored; retry later)", None,
                      {"Retry-After": "5"})

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> Response:
        if request.url.path.endswith("/samples"):
            metrics.inc("selfcal_ingest_rejected_total", status="422")
        return _validation_response(list(exc.errors()))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        headers = dict(exc.headers or {})
        kind = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        if exc.status_code == 405:
            headers["Allow"] = ", ".join(_allowed_methods(request.app, request.url.path))
        return _error(exc.status_code, kind, str(exc.detail), None, headers or None)

    @app.exception_handler(Exception)
    async def _crash(request: Request, exc: Exception) -> Response:  # pragma: no cover - defensive
        log.exception("unhandled error on %s", request.url.path)
        return _error(500, "internal_error", "internal error (see the server log)")

    # ------------------------------------------------------------ latency metrics
    class _Timing:
        """Pure ASGI middleware (cheaper than BaseHTTPMiddleware): latency by route.

        It also answers an unexpected exception with a JSON 500 *and returns normally*,
        so the keep-alive connection stays open. (Starlette's outermost error
        middleware re-raises after its 500, and uvicorn then closes the connection.)
        Only an exception after the response started still closes it: nothing else
        can be sent on that connection.
        """

        def __init__(self, inner):
            self.inner = inner

        async def __call__(self, scope, receive, send):
            if scope["type"] != "http":
                return await self.inner(scope, receive, send)
            t0 = time.perf_counter()
            status = [500]
            started = [False]
            rid = new_request_id(next((v.decode("latin-1") for k, v in scope.get("headers", ())
                                       if k == b"x-request-id"), None))
            request_id_var.set(rid)  # this request's task only: the logs carry both ids
            device_id_var.set(device_of_path(scope.get("path", "")))

            async def send_wrapped(message):
                if message["type"] == "http.response.start":
                    status[0] = message["status"]
                    started[0] = True
                    message = dict(message, headers=[*message.get("headers", []),
                                                     (b"x-request-id", rid.encode("latin-1"))])
                await send(message)

            try:
                await self.inner(scope, receive, send_wrapped)
            except ClientDisconnect:  # the client left mid-body (or missed body_timeout_s): not our error
                if not started[0]:
                    status[0] = 499  # (nginx's code: recorded, never sent)
            except Exception:
                if started[0]:
                    raise
                log.exception("unhandled error on %s %s", scope.get("method", ""), scope.get("path", ""))
                metrics.inc("selfcal_http_internal_errors_total")
                status[0] = 500
                await _error(500, "internal_error", f"internal error (request id {rid}; see the server log)")(
                    scope, receive, send_wrapped)
            finally:
                route = scope.get("route")
                metrics.observe(
                    "selfcal_http_request_duration_seconds",
                    time.perf_counter() - t0,
                    route=getattr(route, "path", "unmatched"),
                    method=scope.get("method", ""),
                    code=f"{status[0] // 100}xx",
                )

    hot_routes: dict[str, Any] = {}  # method -> the APIRoute it stands for (filled once the routes exist)

    class _HotRoutes:
        """The two requests a fleet sends all day, answered without FastAPI's routing,
        dependency solving and parameter validation, which were ~45 % of an API process's
        CPU at fleet load (py-spy under bench/request_cost.py): ``POST
        /devices/{id}/samples`` with a binary batch and ``GET /devices/{id}/calibration``.

        Only the plain case is answered here, by the route's own code (:func:`ingest`,
        :func:`_current_or_404`, :func:`calibration_out`, the same Response): a request it
        would not answer exactly as the route does (no key or a key without the scope, an
        id the pattern refuses, a body over the limit or that does not decode, JSON, a
        client gone) is handed to the app unchanged, what it read of the body replayed in
        one message, so every such answer is the route's. An exception from the store (an
        unknown device's 404 included) is answered by the app's own handler for it, as
        the route's would be, or left to the timing middleware's 500 if it has none.
        """

        def __init__(self, inner):
            self.inner = inner

        async def __call__(self, scope, receive, send):
            if scope["type"] == "http" and hot_routes:
                method, path = scope["method"], scope["path"]
                if method == "GET" and path.endswith("/calibration"):
                    if await self._get(scope, receive, send):
                        return
                elif method == "POST" and path.endswith("/samples"):
                    done, receive = await self._post(scope, receive, send)
                    if done:
                        return
            await self.inner(scope, receive, send)

        @staticmethod
        def _device(path: str, suffix: str) -> str | None:
            """The device id of ``/devices/{id}{suffix}`` when the route's pattern takes it."""
            if not path.startswith("/devices/"):
                return None
            device_id = path[len("/devices/"): -len(suffix)]
            return device_id if _DEVICE_ID_RE.fullmatch(device_id) else None

        @staticmethod
        def _authorized(scope, scope_name: str) -> bool:
            authorization = _header(scope, b"authorization")
            try:
                keys.check(None if authorization is None else authorization.decode("latin-1"), scope_name)
            except AuthError:
                return False
            return True

        async def _answer_error(self, exc: Exception, scope, receive, send) -> bool:
            """The app's handler's answer to ``exc`` (False: none for its type)."""
            for cls in type(exc).__mro__:
                handler = app.exception_handlers.get(cls)
                if handler is not None and cls is not Exception:
                    response = await handler(Request(scope, receive), exc)
                    await response(scope, receive, send)
                    return True
            return False

        async def _get(self, scope, receive, send) -> bool:
            device_id = self._device(scope["path"], "/calibration")
            if device_id is None or not self._authorized(scope, "read"):
                return False
            scope["route"] = hot_routes["GET"]
            try:
                found = await _current_or_404(app.state.store, device_id)
            except Exception as exc:  # noqa: BLE001 - the app's handler's answer (an unknown device's 404 too)
                if not await self._answer_error(exc, scope, receive, send):
                    raise  # no handler: the 500 of the timing middleware, as from the route
                return True
            await _model(calibration_out(device_id, *found))(scope, receive, send)
            return True

        async def _post(self, scope, receive, send):
            device_id = self._device(scope["path"], "/samples")
            if device_id is None:
                return False, receive
            ctype = _header(scope, b"content-type")
            ctype = "application/json" if ctype is None else ctype.decode("latin-1")
            if (_media_type(ctype) != BINARY_MEDIA_TYPE or not self._authorized(scope, "ingest")
                    or _header(scope, b"content-encoding") not in (None, b"identity")):
                return False, receive  # (an encoded body: the route's 415)
            limit = settings.max_body_bytes
            declared = _header(scope, b"content-length")
            if declared is not None and (not declared.isdigit() or len(declared) > 18 or int(declared) > limit):
                return False, receive
            chunks, size = [], 0
            while True:
                message = await receive()
                if message["type"] != "http.request":
                    return False, _replay(chunks, False, message, receive)  # a client gone: the route's answer
                chunk = message.get("body", b"")
                size += len(chunk)
                chunks.append(chunk)
                if size > limit:
                    return False, _replay(chunks, not message.get("more_body", False), None, receive)
                if not message.get("more_body", False):
                    break
            body = b"".join(chunks)
            try:
                batch = decode_binary(body)
            except FieldError:
                return False, _replay([body], True, None, receive)
            scope["route"] = hot_routes["POST"]
            try:
                response = await ingest(device_id, batch, canonical_binary(body), app.state.store, app.state.worker)
            except Exception as exc:  # noqa: BLE001 - answered as the route's would be
                if not await self._answer_error(exc, scope, receive, send):
                    raise
                return True, receive
            await response(scope, receive, send)
            return True, receive

    app.add_middleware(_HotRoutes)
    app.add_middleware(_Timing)

    # ------------------------------------------------------------ routes
    @app.post(
        "/devices/{device_id}/samples",
        response_model=BatchAck,
        responses=_INGEST_ERRORS,
        dependencies=[need("ingest")],
        openapi_extra=batch_request_openapi(settings.max_batch_samples),
        summary="ingest one batch of samples (acknowledged after a durable commit)",
        tags=["ingest"],
    )
    async def post_samples(device_id: DeviceId, request: Request, store: StoreDep, worker: WorkerDep) -> Response:
        body = await _read_body(request, settings.max_body_bytes)
        ctype = _content_type(request)
        if ctype == BINARY_MEDIA_TYPE:
            batch = decode_binary(body)
            payload = canonical_binary(body)
        elif ctype == "application/json":
            try:
                parsed = SampleBatchIn.model_validate_json(body)
            except ValidationError as exc:
                raise RequestValidationError(exc.errors()) from None
            batch = parsed.to_batch()
            payload = batch.to_bytes()
        else:
            raise FieldError("Content-Type", f"expected application/json or {BINARY_MEDIA_TYPE}", 415)
        return await ingest(device_id, batch, payload, store, worker)

    async def ingest(device_id: str, batch: Batch, payload: bytes, store: Storage, worker: RefitWorker) -> Response:
        """A decoded batch checked, stored (durably) and acknowledged: the route's work after
        the body, shared with the hot path (:class:`_HotRoutes`)."""
        check_batch(
            batch,
            max_samples=settings.max_batch_samples,
            max_pressure_channels=settings.max_pressure_channels,
        )
        digest = hashlib.sha256(payload).digest()  # canonical bytes: the same samples, the same digest
        try:
            result = await asyncio.wait_for(asyncio.wrap_future(store.submit_batch(
                device_id, batch.seq, batch.n, payload, time.time(), digest, settings.max_seq_jump)),
                timeout=settings.write_timeout_s)
        except asyncio.TimeoutError:  # the database did not answer: maybe stored later (a resend is a duplicate)
            raise StorageUnavailable(f"no commit within {settings.write_timeout_s:g} s") from None
        except SeqConflict as exc:
            metrics.inc("selfcal_ingest_conflicts_total")
            raise FieldError("seq", str(exc), 409) from None
        except SeqJump as exc:
            raise FieldError("seq", str(exc), 422) from None
        if result.duplicate:
            metrics.inc("selfcal_ingest_duplicates_total")
        else:
            metrics.inc("selfcal_ingest_batches_total")
            metrics.inc("selfcal_ingest_samples_total", batch.n)
        # a duplicate too: its first send may have been stored after its request timed out
        # (503), so no one told the worker; a cycle with nothing pending costs one read
        worker.notify(device_id)
        return _json({"device_id": device_id, "seq": batch.seq, "accepted": batch.n, "duplicate": result.duplicate})

    @app.get(
        "/devices/{device_id}/calibration",
        response_model=CalibrationOut,
        responses=_ERRORS,
        dependencies=[need("read")],
        summary="the current model of a device, its status and the last refit's outcome",
        tags=["calibration"],
    )
    async def get_calibration(device_id: DeviceId, store: StoreDep) -> Response:
        found = await _current_or_404(store, device_id)
        return _model(calibration_out(device_id, *found))

    @app.put(
        "/devices/{device_id}/calibration",
        response_model=CalibrationOut,
        responses=_BODY_ERRORS,
        dependencies=[need("admin")],
        openapi_extra={
            "requestBody": {
                "required": True,
                "content": {"application/json": {"schema": FactoryCalibrationIn.model_json_schema()}},
            }
        },
        summary="seed a device with a factory calibration (becomes the served version)",
        tags=["admin"],
    )
    async def put_calibration(device_id: DeviceId, request: Request, store: StoreDep, worker: WorkerDep) -> Response:
        body = await _json_body(request, FactoryCalibrationIn, settings.max_body_bytes)
        assert isinstance(body, FactoryCalibrationIn)
        if body.model != settings.calibrator_model:
            raise FieldError("model", f"this service runs model {settings.calibrator_model!r}, got {body.model!r}")
        check_admin_calibration(body.model, body.matrix, body.offset, body.params, guard)
        calib = body.model_dump(exclude_none=True, exclude={"note"})
        calib.setdefault("params", {})
        calib.setdefault("std", {})
        calib["source"] = "factory"
        version = NewVersion(
            status="calibrated",
            source="factory",
            calibration=calib,
            provenance={"note": body.note, "seeded_at": time.time()},
        )
        seed = {"params": body.params, "std": body.std, "matrix": body.matrix, "offset": body.offset}
        await _admin_publish(worker, device_id, version, seed)
        dev, ver = await _current(store, device_id)
        return _model(calibration_out(device_id, dev, ver))

    @app.get(
        "/devices/{device_id}/calibration/history",
        response_model=HistoryOut,
        responses=_ERRORS,
        dependencies=[need("read")],
        summary="every published version with its provenance",
        tags=["calibration"],
    )
    async def get_history(device_id: DeviceId, store: StoreDep) -> Response:
        found = await _current_or_404(store, device_id)
        versions = [_versions_out(v) for v in await _read(store, store.history, device_id)]
        return _model(HistoryOut(device_id=device_id, current_version=found[0].current_version, versions=versions))

    @app.post(
        "/devices/{device_id}/calibration/rollback",
        response_model=CalibrationOut,
        responses=_BODY_ERRORS,
        dependencies=[need("admin")],
        openapi_extra={
            "requestBody": {
                "required": False,
                "content": {"application/json": {"schema": RollbackIn.model_json_schema()}},
            }
        },
        summary="serve an earlier version again (recorded as a new version)",
        tags=["admin"],
    )
    async def post_rollback(device_id: DeviceId, request: Request, store: StoreDep, worker: WorkerDep) -> Response:
        body = await _json_body(request, RollbackIn, settings.max_body_bytes)
        assert isinstance(body, RollbackIn)
        found = await _current_or_404(store, device_id)
        current = found[0].current_version
        target = body.to_version
        if target is None:
            if not current or current < 2:
                raise FieldError("to_version", "no earlier version to roll back to", 422)
            target = current - 1
        old = await _read(store, store.get_version, device_id, target)
        if old is None:
            raise FieldError("to_version", f"device {device_id!r} has no version {target}", 404)
        version = NewVersion(
            status=old.status,
            source="rollback",
            calibration=old.calibration,
            provenance={**old.provenance, "rollback_of": old.version, "replaced": current},
        )
        seed = {"params": old.calibration.get("params"), "std": old.calibration.get("std"),
                "matrix": old.calibration.get("matrix"), "offset": old.calibration.get("offset"),
                "model": old.calibration.get("model")}
        await _admin_publish(worker, device_id, version, seed)
        dev, ver = await _current(store, device_id)
        return _model(calibration_out(device_id, dev, ver))

    @app.get(
        "/devices",
        response_model=DevicesOut,
        responses=_ERRORS,
        dependencies=[need("read")],
        summary="devices in id order (paged)",
        tags=["calibration"],
    )
    async def get_devices(
        store: StoreDep,
        after: Annotated[str | None, Query(max_length=64, description="last device_id of the previous page")] = None,
        limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    ) -> Response:
        rows = await _read(store, store.list_devices, after, limit)
        devices = [
            DeviceOut(
                device_id=d.device_id,
                status=status,
                version=d.current_version,
                samples_processed=d.samples_processed,
                batches_stored=d.batches_stored,
                updated_at=_iso(d.updated_at),
            )
            for d, status in rows
        ]
        nxt = devices[-1].device_id if len(devices) == limit else None
        return _model(DevicesOut(devices=devices, next_after=nxt))

    @app.get(
        "/fleet",
        response_model=FleetOut,
        responses=_ERRORS,
        dependencies=[need("read")],
        summary="devices in id order with the served version's figures, backlog and last refusal (paged)",
        tags=["dashboard"],
    )
    async def get_fleet(
        request: Request,
        store: StoreDep,
        after: Annotated[str | None, Query(max_length=64, description="last device_id of the previous page")] = None,
        limit: Annotated[int, Query(ge=1, le=1000)] = 1000,
        device_id: Annotated[str | None, Query(pattern=DEVICE_ID_PATTERN, description="only this device")] = None,
    ) -> Response:
        rows = await _read(store, store.fleet, after, limit, device_id)
        devices = [fleet_device_out(f) for f in rows]
        nxt = devices[-1].device_id if len(devices) == limit and device_id is None else None
        body = FleetOut(devices=devices, next_after=nxt).model_dump_json().encode()
        if len(body) < FLEET_GZIP_MIN_BYTES or not _accepts_gzip(request.headers.get("accept-encoding", "")):
            return Response(body, media_type="application/json", headers={"Vary": "Accept-Encoding"})
        # a dashboard polls this every 5 s: 1000 devices are ~425 KiB of JSON, ~10x less gzipped
        packed = await run_in_threadpool(gzip.compress, body, 5)
        return Response(packed, media_type="application/json",
                        headers={"Content-Encoding": "gzip", "Vary": "Accept-Encoding"})

    @app.get(
        "/devices/{device_id}/refusals",
        response_model=RefusalsOut,
        responses=_ERRORS,
        dependencies=[need("read")],
        summary="the device's refits that published nothing and batches never fed, with reasons (oldest first)",
        tags=["dashboard"],
    )
    async def get_refusals(
        device_id: DeviceId, store: StoreDep,
        limit: Annotated[int, Query(ge=1, le=1000, description="the newest this many")] = 500,
    ) -> Response:
        await _current_or_404(store, device_id)
        rows = await _read(store, store.refusals, device_id, limit)
        return _model(RefusalsOut(device_id=device_id, refusals=[refusal_out(r) for r in rows]))

    @app.get(
        "/devices/{device_id}/poses",
        response_model=PosesOut,
        responses=_ERRORS,
        dependencies=[need("read")],
        summary="the stored still poses (direction, degC, residual in mg) and the undetermined directions",
        tags=["dashboard"],
    )
    async def get_poses(device_id: DeviceId, store: StoreDep) -> Response:
        from selfcal_service.coverage import pose_coverage

        _, ver = await _current_or_404(store, device_id)
        # the one read that carries the calibrator state (up to megabytes): off the event loop on any store
        rec = await run_in_threadpool(store.load_device, device_id)
        state = rec.calibrator_state if rec is not None else None
        found = await run_in_threadpool(pose_coverage, state, ver.calibration if ver else None,
                                        ver.version if ver else None,
                                        patch_json=rec.calibrator_patch if rec is not None else None)
        return _model(PosesOut(device_id=device_id, **found))

    @app.get(
        "/whoami",
        response_model=WhoAmIOut,
        responses={401: _ERRORS[401]},
        summary="the scopes of the presented key (any valid key)",
        tags=["dashboard"],
    )
    async def whoami(request: Request) -> Response:
        scopes = keys.scopes_of(request.headers.get("authorization"))
        return _model(WhoAmIOut(scopes=sorted(scopes)))

    @app.get(
        "/healthz",
        response_model=HealthOut,
        responses={503: {"model": HealthOut, "description": "a thread of the service died: restart it"}},
        summary="liveness (no key needed)", tags=["ops"])
    async def healthz(request: Request) -> Response:
        store: Storage = request.app.state.store
        worker: RefitWorker = request.app.state.worker
        db = await _read(store, store.ping)
        alive = worker.alive()
        expected = expected_refit_threads(settings)
        ok = db and alive == expected
        return _json(
            {"status": "ok" if ok else "degraded", "db": db, "workers_alive": alive, "pending_devices": worker.queue_depth()},
            200 if ok else 503,
        )

    @app.get(
        "/readyz",
        response_model=ReadyOut,
        responses={503: {"model": ReadyOut, "description": "storage not writable, a worker down, or backlog too large"}},
        summary="readiness (no key needed): a write probe, the workers, the backlog", tags=["ops"])
    async def readyz(request: Request) -> Response:
        store: Storage = request.app.state.store
        worker: RefitWorker = request.app.state.worker
        problem = await run_in_threadpool(store.probe_write, 2.0)  # the writer checks the file's identity
        alive = worker.alive()
        try:
            backlog = await run_in_threadpool(store.backlog)
        except Exception as exc:  # noqa: BLE001 - readiness reports, never raises
            backlog = -1
            problem = problem or f"cannot read the backlog: {exc}"
        expected = expected_refit_threads(settings)
        ready = (problem is None and alive == expected
                 and 0 <= backlog <= settings.max_backlog_batches)
        return _json({"ready": ready, "storage_writable": problem is None, "storage_problem": problem,
                      "workers_alive": alive, "backlog_batches": backlog,
                      "max_backlog_batches": settings.max_backlog_batches}, 200 if ready else 503)

    @app.get(
        "/metrics",
        response_class=PlainTextResponse,
        responses={401: _ERRORS[401], 403: _ERRORS[403]},
        dependencies=[need("read")],
        summary="Prometheus text format",
        tags=["ops"],
    )
    async def get_metrics(request: Request) -> Response:
        # render reads the backlog gauges from the store, and the other processes' files
        text = await _read(request.app.state.store, metrics.render)
        return PlainTextResponse(text, media_type="text/plain; version=0.0.4")

    from selfcal_service.dashboard import add_dashboard_routes

    add_dashboard_routes(app)
    from fastapi.routing import APIRoute

    for route in app.routes:
        if isinstance(route, APIRoute) and route.path == "/devices/{device_id}/samples" and "POST" in route.methods:
            hot_routes["POST"] = route
        if isinstance(route, APIRoute) and route.path == "/devices/{device_id}/calibration" and "GET" in route.methods:
            hot_routes["GET"] = route
    if not settings.hot_routes or len(hot_routes) != 2:
        hot_routes.clear()  # every request through the app's routing
    return app


#: Environment variable through which ``selfcal serve --workers N`` hands the settings
#: and config to its API processes (JSON: ``{"settings": {...}, "config": {...}}``).
SERVE_ENV = "SELFCAL_SERVE_SPEC"


def app_from_env() -> FastAPI:
    """App factory for uvicorn's worker processes: settings and config from ``SELFCAL_SERVE_SPEC``."""
    import json
    import os

    spec = json.loads(os.environ[SERVE_ENV])
    return create_app(Settings.model_validate(spec["settings"]), config=spec["config"])
