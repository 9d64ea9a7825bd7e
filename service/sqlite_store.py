"""SQLite (WAL) implementation of :class:`selfcal_service.storage.Storage`. All SQL is here.

One writer thread owns the only writing connection and applies queued writes in
*group commits*: it takes every write queued so far (up to ``group_commit_max_ops``),
runs each inside its own SAVEPOINT (a failing write does not sink its neighbours), then
COMMITs once and only then resolves the futures. With ``synchronous=FULL`` that
commit is fsynced, so an acknowledged batch survives ``kill -9`` *and* power loss;
``NORMAL`` in WAL mode survives ``kill -9`` (the WAL is in the OS page cache) but may
lose the last commits on power loss, which would break the ack promise - hence FULL
by default; group commit makes the fsync cost per request small.

Reads use one connection per thread (WAL readers never wait for the writer).
"""

from __future__ import annotations

import json
import logging
import queue
import sqlite3
import threading
import time
from concurrent.futures import Future
from typing import Any, Callable

from selfcal_service.storage import (
    ConflictError,
    DeviceRecord,
    IngestResult,
    NewVersion,
    Progress,
    Storage,
    VersionRecord,
)

log = logging.getLogger("selfcal.service.sqlite")

SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS devices (
    device_id         TEXT PRIMARY KEY,
    created_at        REAL NOT NULL,
    batches_stored    INTEGER NOT NULL DEFAULT 0,
    processed_seq     INTEGER,
    samples_processed INTEGER NOT NULL DEFAULT 0,
    calibrator_state  TEXT,
    calibrator_status TEXT,
    last_refit        TEXT,
    feed_state        TEXT,
    current_version   INTEGER,
    updated_at        REAL
);
CREATE TABLE IF NOT EXISTS batches (
    device_id   TEXT NOT NULL,
    seq         INTEGER NOT NULL,
    n_samples   INTEGER NOT NULL,
    received_at REAL NOT NULL,
    payload     BLOB NOT NULL,
    PRIMARY KEY (device_id, seq)
);
CREATE TABLE IF NOT EXISTS versions (
    device_id   TEXT NOT NULL,
    version     INTEGER NOT NULL,
    status      TEXT NOT NULL,
    source      TEXT NOT NULL,
    created_at  REAL NOT NULL,
    calibration TEXT NOT NULL,
    provenance  TEXT NOT NULL,
    PRIMARY KEY (device_id, version)
);
"""

_DEVICE_COLS = (
    "device_id, batches_stored, processed_seq, samples_processed, calibrator_state, "
    "calibrator_status, last_refit, feed_state, current_version, updated_at"
)

_STOP = object()


def _device(row: tuple) -> DeviceRecord:
    return DeviceRecord(
        device_id=row[0],
        batches_stored=row[1],
        processed_seq=row[2],
        samples_processed=row[3],
        calibrator_state=row[4],
        calibrator_status=row[5],
        last_refit=json.loads(row[6]) if row[6] else None,
        feed_state=json.loads(row[7]) if row[7] else {},
        current_version=row[8],
        updated_at=row[9],
    )


def _version(row: tuple) -> VersionRecord:
    return VersionRecord(
        version=row[0],
        status=row[1],
        source=row[2],
        created_at=row[3],
        calibration=json.loads(row[4]),
        provenance=json.loads(row[5]),
    )


def _dumps(obj: Any) -> str:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


class SQLiteStore(Storage):
    """SQLite WAL storage with a group-committing writer thread."""

    def __init__(self, path: str, *, synchronous: str = "FULL", group_commit_max_ops: int = 512):
        self.path = path
        self.synchronous = synchronous
        self.group_commit_max_ops = group_commit_max_ops
        self._queue: "queue.SimpleQueue[Any]" = queue.SimpleQueue()
        self._local = threading.local()
        self._writer: threading.Thread | None = None
        self._conns: list[sqlite3.Connection] = []
        self._conns_lock = threading.Lock()
        self.commits = 0  # transactions committed (for metrics)
        self.ops_committed = 0

    # ------------------------------------------------------------ connections
    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=30.0)
        conn.execute("PRAGMA busy_timeout=30000")
        conn.execute(f"PRAGMA synchronous={self.synchronous}")
        with self._conns_lock:
            self._conns.append(conn)
        return conn

    def _reader(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._local.conn = self._connect()
        return conn

    def open(self) -> None:
        conn = sqlite3.connect(self.path, isolation_level=None, timeout=30.0)
        mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if mode.lower() != "wal":
            raise RuntimeError(f"db_path {self.path}: could not enable WAL (got {mode})")
        conn.executescript(_SCHEMA)
        row = conn.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
        if row is None:
            conn.execute("INSERT INTO meta(key, value) VALUES('schema_version', ?)", (str(SCHEMA_VERSION),))
        elif int(row[0]) != SCHEMA_VERSION:
            raise RuntimeError(f"db_path {self.path}: schema version {row[0]}, expected {SCHEMA_VERSION}")
        conn.close()
        self._writer = threading.Thread(target=self._write_loop, name="selfcal-sqlite-writer", daemon=True)
        self._writer.start()

    def close(self) -> None:
        if self._writer is not None:
            self._queue.put(_STOP)
            self._writer.join(timeout=30)
            self._writer = None
        with self._conns_lock:
            for conn in self._conns:
                try:
                    conn.close()
                except sqlite3.Error:  # pragma: no cover - closing anyway
                    pass
            self._conns.clear()

    # ------------------------------------------------------------ writer
    def _submit(self, fn: Callable[[sqlite3.Connection], Any]) -> Future:
        fut: Future = Future()
        if self._writer is None:
            fut.set_exception(RuntimeError("storage is closed"))
            return fut
        self._queue.put((fn, fut))
        return fut

    def queue_depth(self) -> int:
        return self._queue.qsize()

    def _write_loop(self) -> None:
        conn = self._connect()
        stop = False
        while not stop:
            item = self._queue.get()
            if item is _STOP:
                break
            ops = [item]
            while len(ops) < self.group_commit_max_ops:
                try:
                    nxt = self._queue.get_nowait()
                except queue.Empty:
                    break
                if nxt is _STOP:
                    stop = True
                    break
                ops.append(nxt)
            results: list[tuple[Future, bool, Any]] = []
            try:
                conn.execute("BEGIN IMMEDIATE")
                for fn, fut in ops:
                    conn.execute("SAVEPOINT op")
                    try:
                        value = fn(conn)
                    except Exception as exc:  # one bad write must not sink the group
                        conn.execute("ROLLBACK TO op")
                        conn.execute("RELEASE op")
                        results.append((fut, False, exc))
                    else:
                        conn.execute("RELEASE op")
                        results.append((fut, True, value))
                conn.execute("COMMIT")
            except Exception as exc:
                log.exception("group commit failed")
                try:
                    conn.execute("ROLLBACK")
                except sqlite3.Error:
                    pass
                for _, fut in ops:
                    if not fut.done():
                        fut.set_exception(exc)
                continue
            self.commits += 1
            self.ops_committed += len(ops)
            for fut, ok, value in results:  # only now: the commit is durable
                if ok:
                    fut.set_result(value)
                else:
                    fut.set_exception(value)

    # ------------------------------------------------------------ ingest
    def submit_batch(self, device_id: str, seq: int, n_samples: int, payload: bytes, received_at: float) -> Future:
        def op(conn: sqlite3.Connection) -> IngestResult:
            cur = conn.execute(
                "INSERT OR IGNORE INTO batches(device_id, seq, n_samples, received_at, payload) "
                "VALUES (?, ?, ?, ?, ?)",
                (device_id, seq, n_samples, received_at, payload),
            )
            if cur.rowcount == 0:
                return IngestResult(duplicate=True, late=False)
            row = conn.execute(
                "INSERT INTO devices(device_id, created_at, batches_stored) VALUES (?, ?, 1) "
                "ON CONFLICT(device_id) DO UPDATE SET batches_stored = batches_stored + 1 "
                "RETURNING processed_seq",
                (device_id, received_at),
            ).fetchone()
            processed = row[0] if row else None
            return IngestResult(duplicate=False, late=processed is not None and seq <= processed)

        return self._submit(op)

    # ------------------------------------------------------------ worker
    def pending_devices(self) -> list[str]:
        rows = self._reader().execute(
            "SELECT d.device_id FROM devices d WHERE EXISTS ("
            " SELECT 1 FROM batches b WHERE b.device_id = d.device_id"
            " AND b.seq > COALESCE(d.processed_seq, -1)) ORDER BY d.device_id"
        ).fetchall()
        return [r[0] for r in rows]

    def load_device(self, device_id: str) -> DeviceRecord | None:
        row = self._reader().execute(
            f"SELECT {_DEVICE_COLS} FROM devices WHERE device_id = ?", (device_id,)
        ).fetchone()
        return _device(row) if row else None

    def pending_batches(self, device_id: str, after_seq: int | None, limit: int) -> list[tuple[int, bytes]]:
        return self._reader().execute(
            "SELECT seq, payload FROM batches WHERE device_id = ? AND seq > ? ORDER BY seq LIMIT ?",
            (device_id, -1 if after_seq is None else after_seq, limit),
        ).fetchall()

    @staticmethod
    def _insert_version(conn: sqlite3.Connection, device_id: str, v: NewVersion, now: float) -> int:
        (number,) = conn.execute(
            "SELECT COALESCE(MAX(version), 0) + 1 FROM versions WHERE device_id = ?", (device_id,)
        ).fetchone()
        conn.execute(
            "INSERT INTO versions(device_id, version, status, source, created_at, calibration, provenance) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            (device_id, number, v.status, v.source, now, _dumps(v.calibration), _dumps(v.provenance)),
        )
        return number

    def commit_progress(self, p: Progress) -> Future:
        def op(conn: sqlite3.Connection) -> list[int]:
            now = time.time()
            conn.execute("INSERT OR IGNORE INTO devices(device_id, created_at) VALUES (?, ?)", (p.device_id, now))
            numbers = [self._insert_version(conn, p.device_id, v, now) for v in p.new_versions]
            cur = conn.execute(
                "UPDATE devices SET processed_seq = ?, samples_processed = samples_processed + ?, "
                "calibrator_state = ?, calibrator_status = ?, last_refit = ?, feed_state = ?, "
                "current_version = COALESCE(?, current_version), updated_at = ? "
                "WHERE device_id = ? AND processed_seq IS ?",
                (
                    p.processed_seq,
                    p.samples_added,
                    p.calibrator_state,
                    p.calibrator_status,
                    None if p.last_refit is None else _dumps(p.last_refit),
                    _dumps(p.feed_state),
                    numbers[-1] if numbers else None,
                    now,
                    p.device_id,
                    p.expected_processed_seq,
                ),
            )
            if cur.rowcount != 1:
                raise ConflictError(f"device {p.device_id}: processed_seq changed under the worker")
            return numbers

        return self._submit(op)

    # ------------------------------------------------------------ reads
    def current(self, device_id: str) -> tuple[DeviceRecord, VersionRecord | None] | None:
        conn = self._reader()
        row = conn.execute(
            f"SELECT d.{_DEVICE_COLS}, v.version, v.status, v.source, v.created_at, v.calibration, "
            "v.provenance FROM devices d LEFT JOIN versions v "
            "ON v.device_id = d.device_id AND v.version = d.current_version "
            "WHERE d.device_id = ?",
            (device_id,),
        ).fetchone()
        if row is None:
            return None
        dev = _device(row[:10])
        ver = _version(row[10:]) if row[10] is not None else None
        return dev, ver

    def history(self, device_id: str) -> list[VersionRecord]:
        rows = self._reader().execute(
            "SELECT version, status, source, created_at, calibration, provenance FROM versions "
            "WHERE device_id = ? ORDER BY version",
            (device_id,),
        ).fetchall()
        return [_version(r) for r in rows]

    def get_version(self, device_id: str, version: int) -> VersionRecord | None:
        row = self._reader().execute(
            "SELECT version, status, source, created_at, calibration, provenance FROM versions "
            "WHERE device_id = ? AND version = ?",
            (device_id, version),
        ).fetchone()
        return _version(row) if row else None

    def list_devices(self, after: str | None, limit: int) -> list[tuple[DeviceRecord, str]]:
        rows = self._reader().execute(
            f"SELECT d.{_DEVICE_COLS}, COALESCE(v.status, 'uncalibrated') FROM devices d "
            "LEFT JOIN versions v ON v.device_id = d.device_id AND v.version = d.current_version "
            "WHERE d.device_id > ? ORDER BY d.device_id LIMIT ?",
            (after or "", limit),
        ).fetchall()
        return [(_device(r[:10]), r[10]) for r in rows]

    def ping(self) -> bool:
        try:
            self._reader().execute("SELECT 1").fetchone()
        except sqlite3.Error:
            return False
        return self._writer is not None and self._writer.is_alive()
