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

import hashlib
import logging
import os
import sqlite3
import threading
import time
from concurrent.futures import Future
from pathlib import Path
from typing import Any

from selfcal_service.group_commit import GroupCommitStore
from selfcal_service.storage import (
    DEVICE_COLUMNS,
    REFUSAL_COLUMNS,
    REFUSALS_KEPT_PER_DEVICE,
    VERSION_COLUMNS,
    ConflictError,
    DeviceRecord,
    FleetRecord,
    IngestResult,
    NewVersion,
    PendingBatch,
    Progress,
    SeqConflict,
    SeqJump,
    VersionRecord,
    RefusalRecord,
    base_tag_of,
    check_checkpoint,
    device_from_row,
    with_checkpoint,
    dumps_json,
    fleet_from_row,
    fleet_select,
    refusal_from_row,
    version_from_row,
)

log = logging.getLogger("selfcal.service.sqlite")

SCHEMA_VERSION = 5

# the calibrator state, written every checkpoint_samples rather than every cycle (v4)
_CHECKPOINTS_DDL = """CREATE TABLE IF NOT EXISTS checkpoints (
    device_id  TEXT PRIMARY KEY,
    seq        INTEGER,
    state      TEXT NOT NULL,
    feed_state TEXT NOT NULL,
    written_at REAL NOT NULL
)"""

# v5: a checkpoint is a base (``state`` renamed ``base``) and its latest patch (``selfcal.checkpoint``)
# SQLite keeps a row in one record: updating a column beside a megabyte base rewrites the
# record (unless the new one has the very same size), so the latest patch, with the seq
# and feed bookkeeping it stands at, has a table of its own (PostgreSQL: a column)
_CHECKPOINT_PATCH_DDL = ["ALTER TABLE checkpoints RENAME COLUMN state TO base",
                         "ALTER TABLE checkpoints ADD COLUMN base_tag TEXT",
                         "CREATE TABLE IF NOT EXISTS checkpoint_patches (device_id TEXT PRIMARY KEY, seq INTEGER, "
                         "patch TEXT NOT NULL, feed_state TEXT NOT NULL, written_at REAL NOT NULL)"]
# a device's checkpoint as read: its latest patch's seq and bookkeeping when it has one
_CKPT_COLS = ("c.device_id IS NOT NULL, CASE WHEN p.device_id IS NULL THEN c.seq ELSE p.seq END, "
              "CASE WHEN p.device_id IS NULL THEN c.feed_state ELSE p.feed_state END")
_CKPT_JOIN = ("LEFT JOIN checkpoints c ON c.device_id = d.device_id "
              "LEFT JOIN checkpoint_patches p ON p.device_id = d.device_id")


def write_checkpoint_sqlite(conn: sqlite3.Connection, device_id: str, seq: int | None, state: str | None,
                            feed_state: dict[str, Any], now: float, patch: str | None = None,
                            patch_base: str | None = None) -> bool:
    """Write a device's checkpoint in the caller's transaction: a full ``state`` (the base;
    its patch is deleted) or a ``patch`` made against the base tagged ``patch_base`` (in
    ``checkpoint_patches``; the base's record is not touched). Never an older checkpoint
    over a newer one, nor a patch onto another base: False then, and nothing written."""
    check_checkpoint(state, patch, patch_base)
    row = conn.execute(f"SELECT c.base_tag, {_CKPT_COLS} FROM (SELECT ? AS device_id) d {_CKPT_JOIN}",
                       (device_id,)).fetchone()
    tag, exists, stored_seq = row[0], row[1], row[2]
    if exists and stored_seq is not None and (seq is None or seq < stored_seq):
        return False
    if patch is not None:
        if not exists or tag != patch_base:
            return False
        conn.execute("INSERT OR REPLACE INTO checkpoint_patches(device_id, seq, patch, feed_state, written_at) "
                     "VALUES (?, ?, ?, ?, ?)", (device_id, seq, patch, dumps_json(feed_state), now))
        return True
    conn.execute("INSERT INTO checkpoints(device_id, seq, base, base_tag, feed_state, written_at) "
                 "VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT (device_id) DO UPDATE SET seq = excluded.seq, "
                 "base = excluded.base, base_tag = excluded.base_tag, feed_state = excluded.feed_state, "
                 "written_at = excluded.written_at",
                 (device_id, seq, state, base_tag_of(state), dumps_json(feed_state), now))
    conn.execute("DELETE FROM checkpoint_patches WHERE device_id = ?", (device_id,))
    return True

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
    updated_at        REAL,
    rejected_batches  INTEGER NOT NULL DEFAULT 0,
    rejected_samples  INTEGER NOT NULL DEFAULT 0,
    last_rejection    TEXT
);
CREATE TABLE IF NOT EXISTS batches (
    device_id   TEXT NOT NULL,
    seq         INTEGER NOT NULL,
    n_samples   INTEGER NOT NULL,
    received_at REAL NOT NULL,
    payload     BLOB NOT NULL,
    digest      BLOB,
    state       INTEGER NOT NULL DEFAULT 0,
    reason      TEXT,
    PRIMARY KEY (device_id, seq)
);
CREATE INDEX IF NOT EXISTS batches_pending ON batches (device_id, seq) WHERE state = 0;
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
CREATE TABLE IF NOT EXISTS refusals (
    id        INTEGER PRIMARY KEY,
    device_id TEXT NOT NULL,
    recorded_at REAL NOT NULL,
    kind      TEXT NOT NULL,
    reason    TEXT,
    message   TEXT,
    t_s       REAL,
    seq       INTEGER
);
CREATE INDEX IF NOT EXISTS refusals_device ON refusals (device_id, id);
""" + _CHECKPOINTS_DDL + ";\n" + "".join(f"{x};\n" for x in _CHECKPOINT_PATCH_DDL)

#: Batch states: pending, fed to the calibrator once, rejected with a reason.
PENDING, FED, REJECTED = 0, 1, 2

#: Ordered migrations: ``MIGRATIONS[v]`` takes a database from schema v to v + 1.
MIGRATIONS = {
    1: [
        # v1 had no per-batch state: a batch at or below processed_seq was handled then
        # (fed, or skipped as late without a record); it is marked fed.
        "ALTER TABLE batches ADD COLUMN digest BLOB",
        # v1 stored every batch in its canonical bytes already: hash them, so that a
        # resend with other content is a conflict for old batches too
        "UPDATE batches SET digest = sha256(payload)",
        "ALTER TABLE batches ADD COLUMN state INTEGER NOT NULL DEFAULT 0",
        "ALTER TABLE batches ADD COLUMN reason TEXT",
        "UPDATE batches SET state = 1 WHERE seq <= COALESCE((SELECT d.processed_seq FROM devices d "
        "WHERE d.device_id = batches.device_id), -1)",
        "CREATE INDEX IF NOT EXISTS batches_pending ON batches (device_id, seq) WHERE state = 0",
        "ALTER TABLE devices ADD COLUMN rejected_batches INTEGER NOT NULL DEFAULT 0",
        "ALTER TABLE devices ADD COLUMN rejected_samples INTEGER NOT NULL DEFAULT 0",
        "ALTER TABLE devices ADD COLUMN last_rejection TEXT",
    ],
    # v3: the refusal log (refits that published nothing, rejected batches) for the dashboard;
    # a v2 database starts with an empty log
    2: [
        "CREATE TABLE IF NOT EXISTS refusals (id INTEGER PRIMARY KEY, device_id TEXT NOT NULL, recorded_at REAL NOT NULL, "
        "kind TEXT NOT NULL, reason TEXT, message TEXT, t_s REAL, seq INTEGER)",
        "CREATE INDEX IF NOT EXISTS refusals_device ON refusals (device_id, id)",
    ],
    # v4: the calibrator state moves to its own table, written every checkpoint_samples
    # rather than every cycle (devices.calibrator_state stays, always NULL: a row update
    # would rewrite the megabyte of state with it)
    3: [
        _CHECKPOINTS_DDL,
        "INSERT INTO checkpoints(device_id, seq, state, feed_state, written_at) SELECT device_id, processed_seq, "
        "calibrator_state, COALESCE(feed_state, '{}'), COALESCE(updated_at, created_at) FROM devices "
        "WHERE calibrator_state IS NOT NULL",
        "UPDATE devices SET calibrator_state = NULL",
    ],
    4: list(_CHECKPOINT_PATCH_DDL),  # v5: checkpoint patches (every checkpoint so far is a base)
}

_N_DEVICE_COLS = len(DEVICE_COLUMNS)
# what the read routes select: every device column but the calibrator state, which can be
# a megabyte for a device worn for weeks (thousands of pose cells) and no read needs
_DEVICE_READ_COLS = ", ".join("NULL" if c == "calibrator_state" else f"d.{c}" for c in DEVICE_COLUMNS)
# what the worker loads: the state comes from the checkpoint (devices.calibrator_state is unused since v4)
_LOAD_COLS_STATE = ", ".join("c.base" if c == "calibrator_state" else f"d.{c}" for c in DEVICE_COLUMNS)
# the dashboard's page of devices: JSON1's json_extract reads the served calibration's figures
_FLEET_SQL = fleet_select(lambda key: f"json_extract(v.calibration, '$.{key}')",
                          lambda key: f"json_extract(v.calibration, '$.{key}')")


class SQLiteStore(GroupCommitStore):
    """SQLite WAL storage with a group-committing writer thread."""

    begin_sql = "BEGIN IMMEDIATE"

    def __init__(self, path: str, *, synchronous: str = "FULL", group_commit_max_ops: int = 512):
        super().__init__(group_commit_max_ops)
        self.path = path
        self.synchronous = synchronous
        self._local = threading.local()
        self._conns: list[sqlite3.Connection] = []
        self._conns_lock = threading.Lock()
        self._identity: tuple[int, int] | None = None

    # ------------------------------------------------------------ connections
    def _connect(self) -> sqlite3.Connection:
        # mode=rw: never create a file here (a deleted database must not come back empty)
        uri = Path(self.path).resolve().as_uri() + "?mode=rw"
        conn = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False, timeout=30.0)
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

    # the writer's hooks (service/group_commit.py)
    _writer_connect = _connect

    def _close_writer(self, conn: sqlite3.Connection) -> None:
        try:
            conn.close()
        except sqlite3.Error:
            pass
        with self._conns_lock:
            if conn in self._conns:
                self._conns.remove(conn)

    def _is_storage_error(self, exc: BaseException) -> bool:
        return isinstance(exc, sqlite3.DatabaseError) and not isinstance(exc, sqlite3.IntegrityError)

    def _probe_op(self, conn: sqlite3.Connection) -> None:
        conn.execute("INSERT OR REPLACE INTO meta(key, value) VALUES('ready_probe', ?)", (repr(time.time()),))

    def open(self) -> None:
        conn = sqlite3.connect(self.path, isolation_level=None, timeout=30.0)
        conn.create_function("sha256", 1, lambda b: hashlib.sha256(b).digest(), deterministic=True)
        mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if mode.lower() != "wal":
            raise RuntimeError(f"db_path {self.path}: could not enable WAL (got {mode})")
        has_meta = conn.execute("SELECT 1 FROM sqlite_master WHERE name = 'meta'").fetchone()
        row = conn.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone() if has_meta else None
        if row is None:  # the schema and its version in one transaction: a first start that dies
            # between them had left tables without a version, which the next start migrated
            # again and failed on (the service then never started on that file)
            try:
                conn.executescript(f"BEGIN IMMEDIATE;\n{_SCHEMA}\nINSERT OR REPLACE INTO meta(key, value) "
                                   f"VALUES('schema_version', '{SCHEMA_VERSION}');\nCOMMIT;")
            except BaseException:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                raise
        else:
            version = int(row[0])
            if version > SCHEMA_VERSION:
                raise RuntimeError(f"db_path {self.path}: schema version {version} is newer than this "
                                   f"service's {SCHEMA_VERSION}; upgrade selfcal")
            while version < SCHEMA_VERSION:  # versioned migrations, each in one transaction
                conn.execute("BEGIN IMMEDIATE")
                for stmt in MIGRATIONS[version]:
                    conn.execute(stmt)
                version += 1
                conn.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(version),))
                conn.execute("COMMIT")
                log.warning("db_path %s: migrated to schema version %d", self.path, version)
        conn.close()
        self._identity = self._file_identity()
        self._start_writer("selfcal-sqlite-writer")

    def _file_identity(self) -> tuple[int, int] | None:
        try:
            st = os.stat(self.path)
        except OSError:
            return None
        return (st.st_dev, st.st_ino)

    def identity_problem(self) -> str | None:
        """Why the database file is no longer the one opened (deleted, replaced), or None."""
        now = self._file_identity()
        if now is None:
            return f"database file {self.path} was deleted while the service runs"
        if now != self._identity:
            return f"database file {self.path} was replaced while the service runs"
        return None

    def close(self) -> None:
        self._stop_writer()
        with self._conns_lock:
            for conn in self._conns:
                try:
                    conn.close()
                except sqlite3.Error:  # pragma: no cover - closing anyway
                    pass
            self._conns.clear()

    # ------------------------------------------------------------ ingest
    def submit_batch(self, device_id: str, seq: int, n_samples: int, payload: bytes, received_at: float,
                     digest: bytes, max_seq_jump: int) -> Future:
        def op(conn: sqlite3.Connection) -> IngestResult:
            old = conn.execute(
                "SELECT digest FROM batches WHERE device_id = ? AND seq = ?", (device_id, seq)
            ).fetchone()
            if old is not None:
                if old[0] is not None and old[0] != digest:
                    raise SeqConflict(
                        f"seq {seq} of device {device_id!r} is stored with other content; a resent "
                        "batch must be identical (a new batch needs a new seq)")
                return IngestResult(duplicate=True)
            (top,) = conn.execute("SELECT MAX(seq) FROM batches WHERE device_id = ?", (device_id,)).fetchone()
            if top is not None and seq > top + max_seq_jump:
                raise SeqJump(
                    f"seq {seq} is more than {max_seq_jump} above the highest stored seq {top} of device "
                    f"{device_id!r} (a corrupt seq would strand every later batch)")
            conn.execute(
                "INSERT INTO batches(device_id, seq, n_samples, received_at, payload, digest, state) "
                "VALUES (?, ?, ?, ?, ?, ?, 0)",
                (device_id, seq, n_samples, received_at, payload, digest),
            )
            conn.execute(
                "INSERT INTO devices(device_id, created_at, batches_stored) VALUES (?, ?, 1) "
                "ON CONFLICT(device_id) DO UPDATE SET batches_stored = batches_stored + 1",
                (device_id, received_at),
            )
            return IngestResult(duplicate=False)

        return self._submit(op)

    # ------------------------------------------------------------ worker
    def pending_devices(self) -> list[str]:
        rows = self._reader().execute(
            "SELECT DISTINCT device_id FROM batches WHERE state = 0 ORDER BY device_id"
        ).fetchall()
        return [r[0] for r in rows]

    def load_device(self, device_id: str, with_state: bool = True) -> DeviceRecord | None:
        row = self._reader().execute(
            f"SELECT {_LOAD_COLS_STATE if with_state else _DEVICE_READ_COLS}, {_CKPT_COLS}"
            f"{', p.patch, c.base_tag' if with_state else ''} FROM devices d {_CKPT_JOIN} WHERE d.device_id = ?",
            (device_id,),
        ).fetchone()
        return with_checkpoint(device_from_row(row[:_N_DEVICE_COLS]), row[_N_DEVICE_COLS:]) if row else None

    def fed_batches(self, device_id: str, after_seq: int | None, upto_seq: int | None,
                    limit: int) -> list[PendingBatch]:
        rows = self._reader().execute(
            "SELECT seq, n_samples, received_at, payload FROM batches WHERE device_id = ? AND state = 1 "
            "AND seq > ? AND seq <= ? ORDER BY seq LIMIT ?",
            (device_id, -1 if after_seq is None else after_seq, -1 if upto_seq is None else upto_seq, limit),
        ).fetchall()
        return [PendingBatch(*r) for r in rows]

    def write_checkpoint(self, device_id: str, seq: int | None, state: str | None, feed_state: dict[str, Any],
                         state_rev: int | None = None, patch: str | None = None,
                         patch_base: str | None = None) -> bool:
        # (one process: no revision to check)
        def op(conn: sqlite3.Connection) -> bool:
            row = conn.execute("SELECT processed_seq FROM devices WHERE device_id = ?", (device_id,)).fetchone()
            if row is None or row[0] != seq:
                return False
            return write_checkpoint_sqlite(conn, device_id, seq, state, feed_state, time.time(), patch, patch_base)

        return self._submit(op).result()

    def pending_batches(self, device_id: str, limit: int) -> list[PendingBatch]:
        rows = self._reader().execute(
            "SELECT seq, n_samples, received_at, payload FROM batches WHERE device_id = ? AND state = 0 "
            "ORDER BY seq LIMIT ?",
            (device_id, limit),
        ).fetchall()
        return [PendingBatch(*r) for r in rows]

    @staticmethod
    def _insert_version(conn: sqlite3.Connection, device_id: str, v: NewVersion, now: float) -> int:
        (number,) = conn.execute(
            "SELECT COALESCE(MAX(version), 0) + 1 FROM versions WHERE device_id = ?", (device_id,)
        ).fetchone()
        conn.execute(
            "INSERT INTO versions(device_id, version, status, source, created_at, calibration, provenance) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            (device_id, number, v.status, v.source, now, dumps_json(v.calibration), dumps_json(v.provenance)),
        )
        return number

    def commit_progress(self, p: Progress) -> Future:
        def op(conn: sqlite3.Connection) -> list[int]:
            now = time.time()
            conn.execute("INSERT OR IGNORE INTO devices(device_id, created_at) VALUES (?, ?)", (p.device_id, now))
            numbers = [self._insert_version(conn, p.device_id, v, now) for v in p.new_versions]
            cur = conn.execute(
                "UPDATE devices SET processed_seq = ?, samples_processed = samples_processed + ?, "
                "calibrator_status = ?, last_refit = ?, feed_state = ?, "
                "current_version = COALESCE(?, current_version), updated_at = ? "
                "WHERE device_id = ? AND processed_seq IS ?",
                (
                    p.processed_seq,
                    p.samples_added,
                    p.calibrator_status,
                    None if p.last_refit is None else dumps_json(p.last_refit),
                    dumps_json(p.feed_state),
                    numbers[-1] if numbers else None,
                    now,
                    p.device_id,
                    p.expected_processed_seq,
                ),
            )
            if cur.rowcount != 1:
                raise ConflictError(f"device {p.device_id}: processed_seq changed under the worker")
            if (p.calibrator_state is not None or p.calibrator_patch is not None) and not write_checkpoint_sqlite(
                    conn, p.device_id, p.processed_seq, p.calibrator_state, p.feed_state, now,
                    p.calibrator_patch, p.calibrator_patch_base):
                raise ConflictError(f"device {p.device_id}: its checkpoint changed under the worker")
            if p.fed_seqs:
                conn.executemany(
                    "UPDATE batches SET state = 1 WHERE device_id = ? AND seq = ? AND state = 0",
                    [(p.device_id, q) for q in p.fed_seqs])
            if p.rejected:
                conn.executemany(
                    "UPDATE batches SET state = 2, reason = ? WHERE device_id = ? AND seq = ? AND state = 0",
                    [(reason, p.device_id, q) for q, _, reason in p.rejected])
                q, _, reason = p.rejected[-1]
                conn.execute(
                    "UPDATE devices SET rejected_batches = rejected_batches + ?, "
                    "rejected_samples = rejected_samples + ?, last_rejection = ? WHERE device_id = ?",
                    (len(p.rejected), sum(r[1] for r in p.rejected),
                     dumps_json({"seq": q, "reason": reason, "at": now}), p.device_id))
            if p.refusals:
                conn.executemany(
                    f"INSERT INTO refusals(device_id, {REFUSAL_COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?)",
                    [(p.device_id, r.at if r.at is not None else now, r.kind, r.reason, r.message, r.t_s, r.seq)
                     for r in p.refusals])
                conn.execute(  # keep the device's newest REFUSALS_KEPT_PER_DEVICE
                    "DELETE FROM refusals WHERE device_id = ? AND id < (SELECT id FROM refusals WHERE device_id = ? "
                    "ORDER BY id DESC LIMIT 1 OFFSET ?)", (p.device_id, p.device_id, REFUSALS_KEPT_PER_DEVICE - 1))
            return numbers

        return self._submit(op)

    # ------------------------------------------------------------ reads
    def current(self, device_id: str) -> tuple[DeviceRecord, VersionRecord | None] | None:
        conn = self._reader()
        row = conn.execute(
            f"SELECT {_DEVICE_READ_COLS}, v.version, v.status, v.source, v.created_at, v.calibration, "
            "v.provenance FROM devices d LEFT JOIN versions v "
            "ON v.device_id = d.device_id AND v.version = d.current_version "
            "WHERE d.device_id = ?",
            (device_id,),
        ).fetchone()
        if row is None:
            return None
        dev = device_from_row(row[:_N_DEVICE_COLS])
        ver = version_from_row(row[_N_DEVICE_COLS:]) if row[_N_DEVICE_COLS] is not None else None
        return dev, ver

    def history(self, device_id: str) -> list[VersionRecord]:
        rows = self._reader().execute(
            f"SELECT {VERSION_COLUMNS} FROM versions "
            "WHERE device_id = ? ORDER BY version",
            (device_id,),
        ).fetchall()
        return [version_from_row(r) for r in rows]

    def get_version(self, device_id: str, version: int) -> VersionRecord | None:
        row = self._reader().execute(
            f"SELECT {VERSION_COLUMNS} FROM versions "
            "WHERE device_id = ? AND version = ?",
            (device_id, version),
        ).fetchone()
        return version_from_row(row) if row else None

    def list_devices(self, after: str | None, limit: int) -> list[tuple[DeviceRecord, str]]:
        rows = self._reader().execute(
            f"SELECT {_DEVICE_READ_COLS}, COALESCE(v.status, 'uncalibrated') FROM devices d "
            "LEFT JOIN versions v ON v.device_id = d.device_id AND v.version = d.current_version "
            "WHERE d.device_id > ? ORDER BY d.device_id LIMIT ?",
            (after or "", limit),
        ).fetchall()
        return [(device_from_row(r[:_N_DEVICE_COLS]), r[_N_DEVICE_COLS]) for r in rows]

    def fleet(self, after: str | None, limit: int, device_id: str | None = None) -> list[FleetRecord]:
        if device_id is not None:
            rows = self._reader().execute(_FLEET_SQL + " WHERE d.device_id = ?", (device_id,)).fetchall()
        else:
            rows = self._reader().execute(
                _FLEET_SQL + " WHERE d.device_id > ? ORDER BY d.device_id LIMIT ?", (after or "", limit)).fetchall()
        return [fleet_from_row(r) for r in rows]

    def refusals(self, device_id: str, limit: int) -> list[RefusalRecord]:
        rows = self._reader().execute(
            f"SELECT {REFUSAL_COLUMNS} FROM (SELECT id, {REFUSAL_COLUMNS} FROM refusals WHERE device_id = ? "
            "ORDER BY id DESC LIMIT ?) ORDER BY id", (device_id, limit)).fetchall()
        return [refusal_from_row(r) for r in rows]

    def backlog(self) -> int:
        return int(self._reader().execute("SELECT COUNT(*) FROM batches WHERE state = 0").fetchone()[0])

    def oldest_pending_age_s(self) -> float:
        """Age of the oldest stored batch not yet fed nor rejected (0 if none), seconds."""
        (oldest,) = self._reader().execute("SELECT MIN(received_at) FROM batches WHERE state = 0").fetchone()
        return 0.0 if oldest is None else max(0.0, time.time() - oldest)

    def ping(self) -> bool:
        try:
            self._reader().execute("SELECT 1").fetchone()
        except sqlite3.Error:
            return False
        return self.writer_alive()
