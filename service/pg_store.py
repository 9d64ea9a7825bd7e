"""PostgreSQL implementation of :class:`selfcal_service.storage.Storage` (psycopg 3). All its SQL is here.

Selected by a URL: ``selfcal serve --db postgresql://user@host:port/dbname``. Many API
processes and refit workers share one database:

* **Writes** go through the same group-committing writer as SQLite
  (:mod:`selfcal_service.group_commit`), one writer connection per process. PostgreSQL's
  default ``synchronous_commit=on`` makes each COMMIT durable before a batch is
  acknowledged. Every write locks its device row first, and ops of a group run in
  device-id order, so two processes' groups take row locks in the same order.
* **Idempotent seq across processes.** ``INSERT … ON CONFLICT DO NOTHING`` waits for a
  concurrent insert of the same ``(device_id, seq)`` and then compares the content
  hash: duplicate or 409, never a 500.
* **Leases.** A refit worker owns a device while ``lease_owner`` is its id and
  ``lease_expires`` (set when taken) or the worker's heartbeat (``workers.until``, which
  renews all its leases in one write) is in the future (:meth:`acquire_leases`, ``FOR
  UPDATE SKIP LOCKED``).
  A killed worker's leases expire and another worker takes its devices.
  :meth:`commit_progress` writes only if the lease is still held *and* the device's
  ``processed_seq`` and ``state_rev`` are those the cycle started from, so a worker that
  lost its lease cannot feed a batch twice or overwrite newer state.
* **Schema** versions are in ``meta``; ordered migrations run at start under an
  advisory lock (several processes may start at once).
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import Future
from typing import Any

from selfcal_service.group_commit import GroupCommitStore
from selfcal_service.pg_async import AsyncReaders, storage_errors
from selfcal_service.storage import (
    DEVICE_COLUMNS,
    REFUSAL_COLUMNS,
    REFUSALS_KEPT_PER_DEVICE,
    VERSION_COLUMNS,
    ConflictError,
    DeviceRecord,
    FleetRecord,
    IngestResult,
    LeaseLost,
    PendingBatch,
    Progress,
    SeqConflict,
    SeqJump,
    VersionRecord,
    RefusalRecord,
    device_from_row,
    base_tag_of,
    upsert_checkpoint,
    upsert_checkpoint_sql,
    with_checkpoint,
    dumps_json,
    fleet_from_row,
    fleet_select,
    refusal_from_row,
    version_from_row,
)

log = logging.getLogger("selfcal.service.postgres")

SCHEMA_VERSION = 6
# acquire_leases looks at this many more of the longest-waiting devices than it takes, and
# takes the worker's own (last fed by it) among them first
AFFINITY_SLACK = 32
#: A session idle inside a transaction this long (s) is ended by the server (its client froze
#: or vanished mid-group): its row locks go, instead of stalling every write to those devices.
IDLE_IN_TRANSACTION_S = 10.0
_SCHEMA_LOCK = 815_372_001  # pg_advisory_lock key while the schema is created or migrated

_REFUSALS_SCHEMA = [
    """CREATE TABLE IF NOT EXISTS refusals (
        id        BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
        device_id TEXT NOT NULL,
        recorded_at DOUBLE PRECISION NOT NULL,
        kind      TEXT NOT NULL,
        reason    TEXT,
        message   TEXT,
        t_s       DOUBLE PRECISION,
        seq       BIGINT
    )""",
    "CREATE INDEX IF NOT EXISTS refusals_device ON refusals (device_id, id)",
]

# An ingest in one round trip: lock the device row (the same lock order as every writer),
# then a duplicate, a conflicting resend or a seq jump is told apart from a new batch, which
# is stored. Six statements from the client cost the API process ~6 round trips of psycopg
# per batch; this is one. Returns ('stored' | 'duplicate' | 'conflict' | 'jump' | 'error',
# highest seq, error text). Its EXCEPTION block is a savepoint on the server: an error
# other than a lock conflict (which fails the writer's group, as a storage error does)
# undoes this batch only and comes back as 'error', so the client needs no savepoint.
_INGEST_FUNCTION = """CREATE OR REPLACE FUNCTION selfcal_ingest(
        p_device TEXT, p_seq BIGINT, p_n INTEGER, p_at DOUBLE PRECISION, p_payload BYTEA, p_digest BYTEA,
        p_max_jump BIGINT, OUT status TEXT, OUT top BIGINT, OUT error TEXT)
    LANGUAGE plpgsql AS $fn$
    DECLARE
        old_digest BYTEA;
    BEGIN
      BEGIN
        INSERT INTO devices(device_id, created_at) VALUES (p_device, p_at) ON CONFLICT DO NOTHING;
        PERFORM 1 FROM devices WHERE device_id = p_device FOR UPDATE;
        SELECT digest INTO old_digest FROM batches WHERE device_id = p_device AND seq = p_seq;
        IF FOUND THEN
            status := CASE WHEN old_digest IS NOT NULL AND old_digest <> p_digest
                           THEN 'conflict' ELSE 'duplicate' END;
            RETURN;
        END IF;
        SELECT MAX(seq) INTO top FROM batches WHERE device_id = p_device;
        IF top IS NOT NULL AND p_seq > top + p_max_jump THEN
            status := 'jump';
            RETURN;
        END IF;
        INSERT INTO batches(device_id, seq, n_samples, received_at, payload, digest, state)
            VALUES (p_device, p_seq, p_n, p_at, p_payload, p_digest, 0) ON CONFLICT (device_id, seq) DO NOTHING;
        IF NOT FOUND THEN  -- another process stored this seq meanwhile (now committed)
            SELECT digest INTO old_digest FROM batches WHERE device_id = p_device AND seq = p_seq;
            status := CASE WHEN FOUND AND old_digest IS NOT NULL AND old_digest <> p_digest
                           THEN 'conflict' ELSE 'duplicate' END;
            RETURN;
        END IF;
        UPDATE devices SET batches_stored = batches_stored + 1 WHERE device_id = p_device;
        status := 'stored';
      EXCEPTION
        WHEN deadlock_detected OR serialization_failure OR lock_not_available THEN
            RAISE;
        WHEN OTHERS THEN
            status := 'error';
            error := SQLSTATE || ': ' || SQLERRM;
      END;
    END
    $fn$"""

# A worker cycle's commit in one round trip (v5), for the cycles with no rejected batch and
# no refusal (nearly all; those take the statement-by-statement path): lock the device row,
# check that nobody changed it since the cycle read it and that the lease is still held,
# number and insert the new versions, update the device, write the checkpoint if given
# (never an older seq over a newer one) and mark the fed batches. The seven statements and
# the savepoint cost the worker ~9 round trips of psycopg a cycle; this is one. Returns
# (conflict text or NULL, the new version numbers). A conflict is found before anything is
# written (a device row is created only when the checks pass); its EXCEPTION block is a
# savepoint on the server: an error other than a lock conflict undoes this cycle only and
# comes back as ``error``.
_PROGRESS_FUNCTION = """CREATE OR REPLACE FUNCTION selfcal_progress(
        p_device TEXT, p_expected_seq BIGINT, p_expected_rev BIGINT, p_owner TEXT, p_seq BIGINT,
        p_samples BIGINT, p_status TEXT, p_last_refit TEXT, p_feed TEXT, p_at DOUBLE PRECISION,
        p_state TEXT, p_patch TEXT, p_base_tag TEXT, p_fed BIGINT[], p_v_status TEXT[], p_v_source TEXT[], p_v_calibration TEXT[],
        p_v_provenance TEXT[], OUT conflict TEXT, OUT numbers INTEGER[], OUT error TEXT)
    LANGUAGE plpgsql AS $fn$
    DECLARE
        v_seq BIGINT; v_rev BIGINT; v_owner TEXT; v_until DOUBLE PRECISION; v_found BOOLEAN;
        v_db_now DOUBLE PRECISION; v_n INTEGER; i INTEGER;
    BEGIN
      BEGIN
        LOOP  -- at most twice: the row is created (if missing) only once the checks pass
            SELECT processed_seq, state_rev, lease_owner, lease_expires INTO v_seq, v_rev, v_owner, v_until
                FROM devices WHERE device_id = p_device FOR UPDATE;
            v_found := FOUND;
            IF NOT v_found THEN
                v_seq := NULL; v_rev := 0; v_owner := NULL; v_until := NULL;
            END IF;
            v_db_now := extract(epoch from clock_timestamp());
            IF v_seq IS DISTINCT FROM p_expected_seq
               OR (p_expected_rev IS NOT NULL AND v_rev IS DISTINCT FROM p_expected_rev) THEN
                conflict := format('device %s: changed under the worker (processed_seq %s, state_rev %s)',
                                   p_device, COALESCE(v_seq::text, 'None'), v_rev);
                RETURN;
            END IF;
            IF p_owner IS NOT NULL AND (v_owner IS DISTINCT FROM p_owner OR NOT (COALESCE(v_until, 0) >= v_db_now
                    OR EXISTS (SELECT 1 FROM workers w WHERE w.owner = v_owner AND w.until >= v_db_now))) THEN
                conflict := format('device %s: lease of %s lost (owner %s)', p_device, p_owner,
                                   COALESCE(v_owner, 'None'));
                RETURN;
            END IF;
            EXIT WHEN v_found;
            INSERT INTO devices(device_id, created_at) VALUES (p_device, p_at) ON CONFLICT DO NOTHING;
        END LOOP;
        numbers := '{}';
        IF p_state IS NOT NULL OR p_patch IS NOT NULL THEN  -- first: a checkpoint not written is a conflict
            IF p_state IS NOT NULL AND p_patch IS NOT NULL THEN
                error := 'a checkpoint is a full state or a patch, not both';
                RETURN;
            END IF;
            UPSERT_CHECKPOINT;
            IF NOT FOUND THEN
                conflict := format('device %s: its checkpoint changed under the worker', p_device);
                numbers := NULL;
                RETURN;
            END IF;
        END IF;
        IF COALESCE(cardinality(p_v_status), 0) > 0 THEN
            SELECT COALESCE(MAX(version), 0) INTO v_n FROM versions WHERE device_id = p_device;
            FOR i IN 1 .. cardinality(p_v_status) LOOP
                v_n := v_n + 1;
                INSERT INTO versions(device_id, version, status, source, created_at, calibration, provenance)
                    VALUES (p_device, v_n, p_v_status[i], p_v_source[i], p_at, p_v_calibration[i], p_v_provenance[i]);
                numbers := numbers || v_n;
            END LOOP;
        END IF;
        UPDATE devices SET processed_seq = p_seq, samples_processed = samples_processed + p_samples,
            calibrator_status = p_status, last_refit = p_last_refit, feed_state = p_feed,
            current_version = COALESCE(numbers[cardinality(numbers)], current_version),
            updated_at = extract(epoch from clock_timestamp()),
            state_rev = state_rev + 1
            WHERE device_id = p_device;
        IF COALESCE(cardinality(p_fed), 0) > 0 THEN
            UPDATE batches SET state = 1 WHERE device_id = p_device AND seq = ANY(p_fed) AND state = 0;
        END IF;
      EXCEPTION
        WHEN deadlock_detected OR serialization_failure OR lock_not_available THEN
            RAISE;
        WHEN OTHERS THEN
            conflict := NULL;
            numbers := NULL;
            error := SQLSTATE || ': ' || SQLERRM;
      END;
    END
    $fn$""".replace("UPSERT_CHECKPOINT", upsert_checkpoint_sql(
    "p_device", "p_seq", "p_state", "p_base_tag", "p_patch", "p_feed", "p_at"))

# the calibrator state in its own table, written every checkpoint_samples rather than every
# cycle (devices.calibrator_state stays, always NULL since v4)
_CHECKPOINTS_SCHEMA = """CREATE TABLE IF NOT EXISTS checkpoints (
        device_id  TEXT PRIMARY KEY,
        seq        BIGINT,
        state      TEXT NOT NULL,
        feed_state TEXT NOT NULL,
        written_at DOUBLE PRECISION NOT NULL
    )"""

# v6: a checkpoint is a base (``state`` renamed ``base``) and its latest patch
# (``selfcal.checkpoint``); a patch write leaves the base's TOAST chunks as they are. The
# cycle's function takes the patch and its schema-5 signature is dropped, and the column
# renamed: a schema-5 worker still running fails its commits and checkpoint writes
# rather than write a base under another worker's patch
_CHECKPOINT_PATCH = ["ALTER TABLE checkpoints RENAME COLUMN state TO base",
                     "ALTER TABLE checkpoints ADD COLUMN base_tag TEXT",
                     "ALTER TABLE checkpoints ADD COLUMN patch TEXT"]
_PROGRESS_FUNCTION_V5 = ("DROP FUNCTION IF EXISTS selfcal_progress(TEXT, BIGINT, BIGINT, TEXT, BIGINT, BIGINT, TEXT, "
                         "TEXT, TEXT, DOUBLE PRECISION, TEXT, BIGINT[], TEXT[], TEXT[], TEXT[], TEXT[])")

# live refit workers (a heartbeat with the lease renewal): each holds about its share of
# the fleet's active devices
_WORKERS_SCHEMA = [
    "CREATE TABLE IF NOT EXISTS workers (owner TEXT PRIMARY KEY, seen_at DOUBLE PRECISION NOT NULL)",
    "CREATE INDEX IF NOT EXISTS devices_leased ON devices (lease_owner) WHERE lease_owner IS NOT NULL",
]
# v5: a worker's heartbeat renews all its leases at once (workers.until); a device's lease
# is live while its lease_expires (set when taken) or its owner's heartbeat is ahead of now.
# Renewing every device row every lease_ttl_s/3 wrote ~1.8 KB of log per lease held.
# lease_until, which schema-4 workers renew row by row and trust alone, stays NULL: such a
# worker left running would take live leases from schema-5 workers, so its lease writes
# fail instead (a rolling upgrade stops the old workers)
_WORKER_UNTIL = "ALTER TABLE workers ADD COLUMN IF NOT EXISTS until DOUBLE PRECISION"
_LEASE_EXPIRES = [
    "ALTER TABLE devices ADD COLUMN IF NOT EXISTS lease_expires DOUBLE PRECISION",
    "UPDATE devices SET lease_expires = lease_until, lease_until = NULL WHERE lease_until IS NOT NULL",
    "ALTER TABLE devices ADD CONSTRAINT devices_leases_by_heartbeat CHECK (lease_until IS NULL)",
]

# a process of schema 3 still running against a migrated database (a rolling upgrade)
# would read no state and publish from a fresh calibrator: its write fails instead
_STATE_MOVED = ("ALTER TABLE devices ADD CONSTRAINT devices_state_in_checkpoints "
                "CHECK (calibrator_state IS NULL)")

# The large values (a batch's payload, a checkpoint's base and patch) are compressed with
# lz4 where the server has it (PostgreSQL 14+ built with lz4, as Debian's packages and the
# official images are) instead of pglz: pglz took ~0.3 ms of the server's CPU of each
# 400-sample batch's ~0.5-ms insert (a quarter of the server's CPU a sample at fleet
# scale); lz4 stores the insole's quantised samples ~2.5x smaller than raw against pglz's
# ~4.8x. A physical setting, not a schema version: set at every start where missing, with
# a short lock timeout (ALTER TABLE takes an exclusive lock, and must not queue every
# ingest behind a long reader), and skipped, to be tried at the next start, if the lock
# cannot be had. Only values written after it are lz4; those before stay pglz (both read).
_LZ4_COLUMNS = (("batches", "payload"), ("checkpoints", "base"), ("checkpoints", "patch"))
_LZ4_LOCK_TIMEOUT = "1s"
_HAS_LZ4 = ("SELECT EXISTS (SELECT 1 FROM pg_settings WHERE name = 'default_toast_compression' "
            "AND 'lz4' = ANY(enumvals))")

_SCHEMA = [
    "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    """CREATE TABLE IF NOT EXISTS devices (
        device_id         TEXT PRIMARY KEY,
        created_at        DOUBLE PRECISION NOT NULL,
        batches_stored    BIGINT NOT NULL DEFAULT 0,
        processed_seq     BIGINT,
        samples_processed BIGINT NOT NULL DEFAULT 0,
        calibrator_state  TEXT,
        calibrator_status TEXT,
        last_refit        TEXT,
        feed_state        TEXT,
        current_version   INTEGER,
        updated_at        DOUBLE PRECISION,
        rejected_batches  BIGINT NOT NULL DEFAULT 0,
        rejected_samples  BIGINT NOT NULL DEFAULT 0,
        last_rejection    TEXT,
        state_rev         BIGINT NOT NULL DEFAULT 0,
        lease_owner       TEXT,
        lease_until       DOUBLE PRECISION,
        last_owner        TEXT
    )""",
    """CREATE TABLE IF NOT EXISTS batches (
        device_id   TEXT NOT NULL,
        seq         BIGINT NOT NULL,
        n_samples   INTEGER NOT NULL,
        received_at DOUBLE PRECISION NOT NULL,
        payload     BYTEA NOT NULL,
        digest      BYTEA,
        state       SMALLINT NOT NULL DEFAULT 0,
        reason      TEXT,
        PRIMARY KEY (device_id, seq)
    )""",
    "CREATE INDEX IF NOT EXISTS batches_pending ON batches (device_id, seq) WHERE state = 0",
    """CREATE TABLE IF NOT EXISTS versions (
        device_id   TEXT NOT NULL,
        version     INTEGER NOT NULL,
        status      TEXT NOT NULL,
        source      TEXT NOT NULL,
        created_at  DOUBLE PRECISION NOT NULL,
        calibration TEXT NOT NULL,
        provenance  TEXT NOT NULL,
        PRIMARY KEY (device_id, version)
    )""",
    *_REFUSALS_SCHEMA,
    _INGEST_FUNCTION,
    _CHECKPOINTS_SCHEMA,
    *_WORKERS_SCHEMA,
    _STATE_MOVED,
    *_CHECKPOINT_PATCH,
    _PROGRESS_FUNCTION,
    _WORKER_UNTIL,
    *_LEASE_EXPIRES,
]

#: Ordered migrations: ``MIGRATIONS[v]`` takes a database from schema v to v + 1.
MIGRATIONS: dict[int, list[str]] = {
    1: list(_REFUSALS_SCHEMA),  # v2: the refusal log of the dashboard (starts empty)
    2: [_INGEST_FUNCTION],  # v3: an ingest in one round trip
    3: [  # v4: checkpoints, the worker registry
        _CHECKPOINTS_SCHEMA,
        *_WORKERS_SCHEMA,
        "INSERT INTO checkpoints(device_id, seq, state, feed_state, written_at) SELECT device_id, processed_seq, "
        "calibrator_state, COALESCE(feed_state, '{}'), COALESCE(updated_at, created_at) FROM devices "
        "WHERE calibrator_state IS NOT NULL",
        "UPDATE devices SET calibrator_state = NULL WHERE calibrator_state IS NOT NULL",
        _STATE_MOVED,
    ],
    4: [  # v5: a worker cycle's commit in one round trip; lease affinity
        # (the function is created by v6, whose signature it has; a body is checked when run)
        "ALTER TABLE devices ADD COLUMN IF NOT EXISTS last_owner TEXT",
        _WORKER_UNTIL,
        *_LEASE_EXPIRES,
    ],
    5: [_PROGRESS_FUNCTION_V5, *_CHECKPOINT_PATCH, _PROGRESS_FUNCTION],  # v6: checkpoint patches
}

_COLS = [*DEVICE_COLUMNS, "state_rev"]
_DEVICE_READ_COLS = ", ".join("NULL" if c == "calibrator_state" else f"d.{c}" for c in _COLS)  # no state
# what the worker loads: the state comes from the checkpoint (devices.calibrator_state is unused since v4)
_LOAD_COLS_STATE = ", ".join("c.base" if c == "calibrator_state" else f"d.{c}" for c in _COLS)
_CKPT_SQL = ", c.device_id IS NOT NULL, c.seq, c.feed_state{} FROM devices d LEFT JOIN checkpoints c " \
            "ON c.device_id = d.device_id WHERE d.device_id = %s"
_N = len(_COLS)
# the read routes' device row and served version, one round trip
_CURRENT_SQL = (f"SELECT {_DEVICE_READ_COLS}, v.version, v.status, v.source, v.created_at, v.calibration, "
                "v.provenance FROM devices d LEFT JOIN versions v "
                "ON v.device_id = d.device_id AND v.version = d.current_version WHERE d.device_id = %s")


def _current_from_rows(rows: list[tuple]) -> tuple[DeviceRecord, VersionRecord | None] | None:
    if not rows:
        return None
    row = rows[0]
    return device_from_row(row[:_N]), (version_from_row(row[_N:]) if row[_N] is not None else None)


# a worker cycle's read: the device row (no state) and its first pending batches, one row
# a batch (at least one row); the device's columns are NULL after the first row
_CYCLE_SQL = (
    "SELECT " + ", ".join(f"CASE WHEN b.first IS NOT FALSE THEN {c} END" for c in _DEVICE_READ_COLS.split(", "))
    + ", CASE WHEN b.first IS NOT FALSE THEN c.device_id IS NOT NULL END,"
    " CASE WHEN b.first IS NOT FALSE THEN c.seq END, CASE WHEN b.first IS NOT FALSE THEN c.feed_state END,"
    " b.seq, b.n_samples, b.received_at, b.payload FROM devices d"
    " LEFT JOIN checkpoints c ON c.device_id = d.device_id"
    " LEFT JOIN LATERAL (SELECT seq, n_samples, received_at, payload, row_number() OVER (ORDER BY seq) = 1 AS first"
    " FROM batches WHERE device_id = d.device_id AND state = 0 ORDER BY seq LIMIT %s) b ON true"
    " WHERE d.device_id = %s ORDER BY b.seq")

_NOW = "extract(epoch from clock_timestamp())"


def _worker_live(owner: str) -> str:
    """SQL: the worker named by the expression ``owner`` has a heartbeat ahead of now."""
    return f"EXISTS (SELECT 1 FROM workers w WHERE w.owner = {owner} AND w.until >= {_NOW})"


def _lease_live(d: str) -> str:
    """SQL: the lease of the device row aliased ``d`` is held now (taken less than a lease
    time ago, or its owner's heartbeat is still ahead of now)."""
    return f"({d}.lease_expires >= {_NOW} OR {_worker_live(f'{d}.lease_owner')})"


# the dashboard's page of devices: the served calibration's figures read with jsonb operators
_FLEET_SQL = fleet_select(lambda key: f"((v.calibration::jsonb) ->> '{key}')::double precision",
                          lambda key: f"((v.calibration::jsonb) ->> '{key}')")  # the database's clock, seconds since the epoch


def _close_in_loop(loop: Any, readers: AsyncReaders) -> None:
    """Close an event loop's readers from any thread: in the loop itself while it can
    still run (a statement running there closes its own connection when it ends; asyncio's
    shutdown runs the callback), at once once it is closed (nothing runs on them any more)."""
    import asyncio

    try:
        running = asyncio.get_running_loop()
    except RuntimeError:
        running = None
    if loop.is_closed():
        readers.close_all()
    elif running is loop:
        readers.close()
    else:  # running in another thread, or between two runs (asyncio.run's shutdown)
        readers.refuse()  # from now on (a flag); the idle connections are closed in the loop
        try:
            loop.call_soon_threadsafe(readers.close)
        except RuntimeError:  # it closed meanwhile
            readers.close_all()


def is_postgres_url(db: str) -> bool:
    """True for ``postgresql://…`` / ``postgres://…`` (anything else is a SQLite path)."""
    return db.startswith(("postgresql://", "postgres://"))


class PostgresStore(GroupCommitStore):
    """PostgreSQL storage: group-committing writer, a small pool of reader connections, leases."""

    blocking_reads = True  # reads wait on a server: the routes call them in a thread
    # ... except :meth:`current_async`, which waits on its socket in the event loop
    # (``async_reads``; service/pg_async.py)

    def __init__(self, url: str, *, group_commit_max_ops: int = 512, connect_timeout_s: float = 5.0,
                 statement_timeout_s: float = 30.0, max_idle_readers: int = 8, async_reads: bool = True):
        super().__init__(group_commit_max_ops)
        self.url = url
        self.connect_timeout_s = connect_timeout_s
        self.statement_timeout_s = statement_timeout_s
        self.max_idle_readers = max_idle_readers
        self.async_reads = async_reads
        self._idle: list[Any] = []  # reader connections not in use (a small pool)
        self._conns: list[Any] = []
        self._conns_lock = threading.Lock()
        self._busy: set[Any] = set()  # reader connections running a statement (close() leaves them to it)
        self._aio: dict[int, tuple[Any, AsyncReaders]] = {}  # id(event loop) -> (loop, its readers)
        self._reads_closed = False

    # ------------------------------------------------------------ connections
    def _connect_kwargs(self) -> dict[str, Any]:
        """psycopg's ``connect`` arguments for a reader or the writer (sync or async)."""
        # keepalives and tcp_user_timeout: a partitioned database host fails a call in
        # seconds, not after the kernel's 15-minute TCP timeout; statement_timeout bounds
        # any one statement (a lock wait included). The server's side: a session whose
        # client froze or vanished inside a transaction (a worker host partitioned mid-
        # group) is ended after IDLE_IN_TRANSACTION_S, and a dead peer is found by the
        # server's own keepalives; else it kept its device-row locks for the kernel's ~2 h,
        # and every write to those devices waited out statement_timeout and failed
        options = (f"-c statement_timeout={int(1000 * self.statement_timeout_s)}"
                   f" -c idle_in_transaction_session_timeout={int(1000 * IDLE_IN_TRANSACTION_S)}"
                   " -c tcp_keepalives_idle=5 -c tcp_keepalives_interval=2 -c tcp_keepalives_count=3")
        return dict(conninfo=self.url, autocommit=True, connect_timeout=int(max(1, self.connect_timeout_s)),
                    keepalives=1, keepalives_idle=5, keepalives_interval=2, keepalives_count=3,
                    tcp_user_timeout=int(1000 * max(1.0, self.connect_timeout_s)), options=options)

    def _connect(self) -> Any:
        import psycopg

        conn = psycopg.connect(**self._connect_kwargs())
        with self._conns_lock:
            self._conns.append(conn)
        return conn

    def _drop(self, conn: Any) -> None:
        try:
            conn.close()
        except Exception:  # noqa: BLE001 - closing a broken connection
            pass
        with self._conns_lock:
            self._busy.discard(conn)
            if conn in self._conns:
                self._conns.remove(conn)

    def _reader(self, pooled: bool) -> Any:
        """A reader connection for this thread's statement, marked busy: an idle one
        (``pooled``; None if there is none) or a new one. StorageUnavailable once closed."""
        from selfcal_service.storage import StorageUnavailable

        with self._conns_lock:
            if self._reads_closed:
                raise StorageUnavailable("the store is closed")
            if pooled:
                conn = self._idle.pop() if self._idle else None
                if conn is not None:
                    self._busy.add(conn)
                return conn
        conn = self._connect()
        with self._conns_lock:
            self._busy.add(conn)
            closed = self._reads_closed
        if closed:  # closed while connecting
            self._drop(conn)
            raise StorageUnavailable("the store is closed")
        return conn

    def _read(self, sql: str, params: tuple | dict = ()) -> list[tuple]:
        """Run one statement on a pooled reader connection; a broken one is replaced once, by
        a new connection (a restarted server broke the idle ones too)."""
        from selfcal_service.storage import StorageUnavailable

        errors = storage_errors()
        for attempt in (0, 1):
            conn = self._reader(pooled=True) if not attempt else None
            pooled = conn is not None
            try:
                if conn is None:  # a new one, in here: a failed connect is a 503 like the rest
                    conn = self._reader(pooled=False)
                rows = conn.execute(sql, params).fetchall()
            except errors as exc:
                broken = conn is not None and (conn.broken or conn.closed)  # before closing it
                if conn is not None:
                    self._drop(conn)  # never back into the pool
                if not (pooled and broken):  # a failed connect, a timeout or a deadlock is not retried
                    raise StorageUnavailable(f"database read failed: {type(exc).__name__}: {exc}") from None
                with self._conns_lock:  # a restarted server broke them all: retry on a new one
                    stale, self._idle = self._idle, []
                for c in stale:
                    self._drop(c)
                continue
            except BaseException:
                if conn is not None:
                    self._drop(conn)
                raise
            with self._conns_lock:
                self._busy.discard(conn)
                if not self._reads_closed and len(self._idle) < self.max_idle_readers:
                    self._idle.append(conn)
                    conn = None
            if conn is not None:
                self._drop(conn)
            return rows
        return []  # pragma: no cover

    _writer_connect = _connect

    def _close_writer(self, conn: Any) -> None:
        self._drop(conn)

    def _is_storage_error(self, exc: BaseException) -> bool:
        return isinstance(exc, storage_errors())

    def _transaction_aborted(self, conn: Any) -> bool:
        # a refusal raised in Python, or by the driver before sending (e.g. a NUL byte in a
        # text value), leaves the transaction open: only that op fails
        from psycopg.pq import TransactionStatus

        return conn.info.transaction_status != TransactionStatus.INTRANS

    def _probe_op(self, conn: Any) -> None:
        conn.execute("INSERT INTO meta(key, value) VALUES ('ready_probe', %s) "
                     "ON CONFLICT (key) DO UPDATE SET value = EXCLUDED.value", (repr(time.time()),))

    def open(self) -> None:
        self._reads_closed = False
        conn = self._connect()
        try:
            conn.execute("SELECT pg_advisory_lock(%s)", (_SCHEMA_LOCK,))
            try:
                has_meta = conn.execute("SELECT to_regclass('meta') IS NOT NULL").fetchone()[0]
                row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone() \
                    if has_meta else None
                if row is None:
                    with conn.transaction():
                        for stmt in _SCHEMA:
                            conn.execute(stmt)
                        conn.execute("INSERT INTO meta(key, value) VALUES ('schema_version', %s) "
                                     "ON CONFLICT (key) DO NOTHING", (str(SCHEMA_VERSION),))
                else:
                    version = int(row[0])
                    if version > SCHEMA_VERSION:
                        raise RuntimeError(f"database schema version {version} is newer than this service's "
                                           f"{SCHEMA_VERSION}; upgrade selfcal")
                    while version < SCHEMA_VERSION:
                        with conn.transaction():
                            conn.execute("SET LOCAL statement_timeout = 0")  # a fleet's states may be moved
                            for stmt in MIGRATIONS[version]:
                                conn.execute(stmt)
                            version += 1
                            conn.execute("UPDATE meta SET value = %s WHERE key = 'schema_version'", (str(version),))
                        log.warning("database migrated to schema version %d", version)
                self._compress_with_lz4(conn)
            finally:
                conn.execute("SELECT pg_advisory_unlock(%s)", (_SCHEMA_LOCK,))
        finally:
            self._close_writer(conn)
        self._start_writer("selfcal-postgres-writer")

    @staticmethod
    def _compress_with_lz4(conn: Any) -> None:
        """lz4 for the large columns where the server has it and they lack it (see
        ``_LZ4_COLUMNS``); a lock not had within ``_LZ4_LOCK_TIMEOUT`` leaves them as they
        are until the next start."""
        import psycopg

        if not conn.execute(_HAS_LZ4).fetchone()[0]:
            return
        todo = [(t, c) for t, c in _LZ4_COLUMNS if conn.execute(
            "SELECT attcompression FROM pg_attribute WHERE attrelid = %s::regclass AND attname = %s",
            (t, c)).fetchone()[0] != "l"]
        if not todo:
            return
        try:
            with conn.transaction():
                conn.execute(f"SET LOCAL lock_timeout = '{_LZ4_LOCK_TIMEOUT}'")
                for table, column in todo:
                    conn.execute(f"ALTER TABLE {table} ALTER COLUMN {column} SET COMPRESSION lz4")
            log.info("lz4 compression set for %s", ", ".join(f"{t}.{c}" for t, c in todo))
        except psycopg.errors.LockNotAvailable:
            log.warning("lz4 compression not set for %s: another session holds a lock on the table "
                        "(tried again at the next start)", ", ".join(f"{t}.{c}" for t, c in todo))

    def close(self) -> None:
        self._stop_writer()
        with self._conns_lock:
            self._reads_closed = True
            pools, self._aio = list(self._aio.values()), {}
        for loop, readers in pools:
            _close_in_loop(loop, readers)
        with self._conns_lock:  # a connection running a read is closed by that read when it ends
            free = [c for c in self._conns if c not in self._busy]
            self._conns = [c for c in self._conns if c in self._busy]
            self._idle.clear()
        for conn in free:
            try:
                conn.close()
            except Exception:  # noqa: BLE001 - closing anyway
                pass

    def _take_group(self, first: Any) -> tuple[list, bool]:
        ops, stop = super()._take_group(first)
        ops.sort(key=lambda item: getattr(item[0], "device_id", ""))  # one lock order for every process
        return ops, stop

    # ------------------------------------------------------------ ingest
    def submit_batch(self, device_id: str, seq: int, n_samples: int, payload: bytes, received_at: float,
                     digest: bytes, max_seq_jump: int) -> Future:
        def op(conn: Any) -> IngestResult:
            status, top, error = conn.execute(
                "SELECT status, top, error FROM selfcal_ingest(%s, %s, %s, %s, %s, %s, %s)",
                (device_id, seq, n_samples, received_at, payload, digest, max_seq_jump)).fetchone()
            if status == "error":  # undone on the server; its neighbours in the group stand
                raise RuntimeError(f"the database refused batch {seq} of device {device_id!r}: {error}")
            if status == "conflict":
                raise SeqConflict(
                    f"seq {seq} of device {device_id!r} is stored with other content; a resent "
                    "batch must be identical (a new batch needs a new seq)")
            if status == "jump":
                raise SeqJump(
                    f"seq {seq} is more than {max_seq_jump} above the highest stored seq {top} of device "
                    f"{device_id!r} (a corrupt seq would strand every later batch)")
            return IngestResult(duplicate=status == "duplicate")

        op.one_statement = True  # type: ignore[attr-defined]  # a server-side savepoint; refusals raise in Python
        op.device_id = device_id  # type: ignore[attr-defined]
        return self._submit(op)

    # ------------------------------------------------------------ worker
    def pending_devices(self) -> list[str]:
        return [r[0] for r in self._read("SELECT DISTINCT device_id FROM batches WHERE state = 0 ORDER BY 1")]

    def load_device(self, device_id: str, with_state: bool = True) -> DeviceRecord | None:
        cols = _LOAD_COLS_STATE if with_state else _DEVICE_READ_COLS
        rows = self._read(f"SELECT {cols}{_CKPT_SQL.format(', c.patch, c.base_tag' if with_state else '')}",
                          (device_id,))
        return with_checkpoint(device_from_row(rows[0][:_N]), rows[0][_N:]) if rows else None

    def fed_batches(self, device_id: str, after_seq: int | None, upto_seq: int | None,
                    limit: int) -> list[PendingBatch]:
        rows = self._read(
            "SELECT seq, n_samples, received_at, payload FROM batches WHERE device_id = %s AND state = 1 "
            "AND seq > %s AND seq <= %s ORDER BY seq LIMIT %s",
            (device_id, -1 if after_seq is None else after_seq, -1 if upto_seq is None else upto_seq, limit))
        return [PendingBatch(r[0], r[1], r[2], bytes(r[3])) for r in rows]

    def write_checkpoint(self, device_id: str, seq: int | None, state: str | None, feed_state: dict[str, Any],
                         state_rev: int | None = None, patch: str | None = None,
                         patch_base: str | None = None) -> bool:
        def op(conn: Any) -> bool:
            row = conn.execute("SELECT processed_seq, state_rev FROM devices WHERE device_id = %s FOR UPDATE",
                               (device_id,)).fetchone()
            if row is None or row[0] != seq or (state_rev is not None and row[1] != state_rev):
                return False
            return upsert_checkpoint(conn, "%s", device_id, seq, state, feed_state, time.time(), patch, patch_base)

        op.device_id = device_id  # type: ignore[attr-defined]
        return self._submit(op).result()

    def pending_batches(self, device_id: str, limit: int) -> list[PendingBatch]:
        rows = self._read(
            "SELECT seq, n_samples, received_at, payload FROM batches WHERE device_id = %s AND state = 0 "
            "ORDER BY seq LIMIT %s", (device_id, limit))
        return [PendingBatch(r[0], r[1], r[2], bytes(r[3])) for r in rows]

    def load_cycle(self, device_id: str, limit: int) -> tuple[DeviceRecord | None, list[PendingBatch]]:
        # one round trip; the device's columns come with the first batch's row only
        rows = self._read(_CYCLE_SQL, (limit, device_id))
        if not rows:
            return None, []
        rec = with_checkpoint(device_from_row(rows[0][:_N]), rows[0][_N:_N + 3])
        return rec, [PendingBatch(r[-4], r[-3], r[-2], bytes(r[-1])) for r in rows if r[-4] is not None]

    def commit_progress(self, p: Progress) -> Future:
        if not p.rejected and not p.refusals:  # nearly every cycle: one round trip
            return self._commit_progress_function(p)
        return self._commit_progress_statements(p)

    def _commit_progress_statements(self, p: Progress) -> Future:
        """:meth:`commit_progress` statement by statement (any cycle; the one with
        rejected batches or refusals)."""

        def op(conn: Any) -> list[int]:
            now = time.time()
            conn.execute("INSERT INTO devices(device_id, created_at) VALUES (%s, %s) ON CONFLICT DO NOTHING",
                         (p.device_id, now))
            row = conn.execute(  # the device row lock serialises publishers of this device
                f"SELECT processed_seq, state_rev, lease_owner, {_lease_live('d')} FROM devices d "
                "WHERE device_id = %s FOR UPDATE", (p.device_id,)).fetchone()
            processed, rev, owner, live = row
            if processed != p.expected_processed_seq or (p.expected_state_rev is not None
                                                         and rev != p.expected_state_rev):
                raise ConflictError(f"device {p.device_id}: changed under the worker "
                                    f"(processed_seq {processed}, state_rev {rev})")
            if p.lease_owner is not None and (owner != p.lease_owner or not live):
                raise LeaseLost(f"device {p.device_id}: lease of {p.lease_owner} lost (owner {owner})")
            numbers = []
            for v in p.new_versions:
                (number,) = conn.execute(
                    "SELECT COALESCE(MAX(version), 0) + 1 FROM versions WHERE device_id = %s", (p.device_id,)
                ).fetchone()
                conn.execute(
                    "INSERT INTO versions(device_id, version, status, source, created_at, calibration, provenance) "
                    "VALUES (%s, %s, %s, %s, %s, %s, %s)",
                    (p.device_id, number, v.status, v.source, now, dumps_json(v.calibration), dumps_json(v.provenance)))
                numbers.append(number)
            conn.execute(
                "UPDATE devices SET processed_seq = %s, samples_processed = samples_processed + %s, "
                "calibrator_status = %s, last_refit = %s, feed_state = %s, "
                f"current_version = COALESCE(%s, current_version), updated_at = {_NOW}, state_rev = state_rev + 1 "
                "WHERE device_id = %s",
                (p.processed_seq, p.samples_added, p.calibrator_status,
                 None if p.last_refit is None else dumps_json(p.last_refit), dumps_json(p.feed_state),
                 numbers[-1] if numbers else None, p.device_id))
            if (p.calibrator_state is not None or p.calibrator_patch is not None) and not upsert_checkpoint(
                    conn, "%s", p.device_id, p.processed_seq, p.calibrator_state, p.feed_state, now,
                    p.calibrator_patch, p.calibrator_patch_base):
                raise ConflictError(f"device {p.device_id}: its checkpoint changed under the worker")
            if p.fed_seqs:
                conn.execute("UPDATE batches SET state = 1 WHERE device_id = %s AND seq = ANY(%s) AND state = 0",
                             (p.device_id, list(p.fed_seqs)))
            if p.rejected:
                with conn.cursor() as cur:
                    cur.executemany(
                        "UPDATE batches SET state = 2, reason = %s WHERE device_id = %s AND seq = %s AND state = 0",
                        [(reason, p.device_id, q) for q, _, reason in p.rejected])
                q, _, reason = p.rejected[-1]
                conn.execute(
                    "UPDATE devices SET rejected_batches = rejected_batches + %s, "
                    "rejected_samples = rejected_samples + %s, last_rejection = %s WHERE device_id = %s",
                    (len(p.rejected), sum(r[1] for r in p.rejected),
                     dumps_json({"seq": q, "reason": reason, "at": now}), p.device_id))
            if p.refusals:
                with conn.cursor() as cur:
                    cur.executemany(
                        f"INSERT INTO refusals(device_id, {REFUSAL_COLUMNS}) VALUES (%s, %s, %s, %s, %s, %s, %s)",
                        [(p.device_id, r.at if r.at is not None else now, r.kind, r.reason, r.message, r.t_s, r.seq)
                         for r in p.refusals])
                conn.execute(  # keep the device's newest REFUSALS_KEPT_PER_DEVICE
                    "DELETE FROM refusals WHERE device_id = %s AND id < (SELECT id FROM refusals "
                    "WHERE device_id = %s ORDER BY id DESC LIMIT 1 OFFSET %s)",
                    (p.device_id, p.device_id, REFUSALS_KEPT_PER_DEVICE - 1))
            return numbers

        op.device_id = p.device_id  # type: ignore[attr-defined]
        return self._submit(op)

    def _commit_progress_function(self, p: Progress) -> Future:
        """:meth:`commit_progress` by ``selfcal_progress()`` (same checks, same writes)."""
        vs = p.new_versions

        def op(conn: Any) -> list[int]:
            now = time.time()
            conflict, numbers, error = conn.execute(
                "SELECT conflict, numbers, error FROM selfcal_progress(%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, "
                "%s, %s, %s, %s::bigint[], %s::text[], %s::text[], %s::text[], %s::text[])",
                (p.device_id, p.expected_processed_seq, p.expected_state_rev, p.lease_owner, p.processed_seq,
                 p.samples_added, p.calibrator_status, None if p.last_refit is None else dumps_json(p.last_refit),
                 dumps_json(p.feed_state), now, p.calibrator_state, p.calibrator_patch,
                 base_tag_of(p.calibrator_state) if p.calibrator_state is not None else p.calibrator_patch_base,
                 list(p.fed_seqs),
                 [v.status for v in vs],
                 [v.source for v in vs], [dumps_json(v.calibration) for v in vs],
                 [dumps_json(v.provenance) for v in vs])).fetchone()
            if error is not None:  # undone on the server; its neighbours in the group stand
                raise RuntimeError(f"the database refused the cycle of device {p.device_id!r}: {error}")
            if conflict is not None:  # (the function's two kinds: "changed under the worker", "lease of ... lost")
                raise (LeaseLost if " lease of " in conflict and " lost (owner " in conflict else ConflictError)(conflict)
            return [int(n) for n in numbers]

        op.one_statement = True  # type: ignore[attr-defined]  # a server-side savepoint; refusals raise in Python
        op.device_id = p.device_id  # type: ignore[attr-defined]
        return self._submit(op)

    # ------------------------------------------------------------ leases
    def acquire_leases(self, owner: str, ttl_s: float, limit: int, prefer: list[str] | None = None,
                       workers: int = 1) -> list[str]:
        """Lease up to ``limit`` devices with pending batches whose lease is free or expired.

        ``prefer`` (devices just ingested here) go first; devices this owner already holds
        are not returned again (renewal keeps them). Lease times are the database's clock,
        so hosts with skewed clocks cannot steal each other's live leases.

        Affinity: of the ``limit * workers + 32`` candidates that waited longest (``workers``:
        the live workers, so that about ``limit`` of them are this one's), the devices
        this owner gave up last (``last_owner``) and those whose last owner is no live
        worker (new devices, a stopped worker's) are taken first, then the others, oldest
        first. A worker that is behind its fleet gives every device up once fed; it then
        takes its own back, whose calibrators it still has in memory, rather than another
        worker's (a restore: the checkpoint and a replay of the batches fed since).
        Nothing waits for ever: a device is its last owner's while that worker lives, and
        everyone's after; it moves to the front of the queue as the devices before it
        are fed, and a worker whose own devices fall behind finds its oldest in the other
        workers' windows, which take them when they hold fewer than ``limit`` of their own.
        """
        rows = self._read(
            # the window, read without locks (locking it would write a lock for every row)
            "WITH w AS MATERIALIZED (SELECT d.device_id, d.updated_at, d.last_owner,"
            " d.device_id = ANY(%(prefer)s) AS preferred FROM devices d"
            f" WHERE (d.lease_owner IS NULL OR NOT {_lease_live('d')})"
            " AND EXISTS (SELECT 1 FROM batches b WHERE b.device_id = d.device_id AND b.state = 0)"
            " ORDER BY preferred DESC, d.updated_at NULLS FIRST LIMIT %(window)s),"
            # the devices taken: preferred, then this worker's own (and those no live worker
            # fed last: new devices, a stopped worker's), then the others; oldest first
            " r AS (SELECT *, (last_owner IS NULL OR last_owner = %(me)s"
            f" OR NOT {_worker_live('r0.last_owner')}) AS own FROM w AS r0),"
            " c AS (SELECT device_id FROM r ORDER BY preferred DESC, own DESC, updated_at NULLS FIRST"
            " LIMIT %(limit)s),"
            # only those are locked, and taken if still free (another worker may have been first)
            " l AS MATERIALIZED (SELECT d.device_id FROM devices d JOIN c ON c.device_id = d.device_id"
            f" WHERE d.lease_owner IS NULL OR NOT {_lease_live('d')} FOR UPDATE OF d SKIP LOCKED)"
            f" UPDATE devices SET lease_owner = %(me)s, lease_expires = {_NOW} + %(ttl)s"
            " FROM l WHERE devices.device_id = l.device_id RETURNING devices.device_id",
            {"me": owner, "ttl": ttl_s, "prefer": list(prefer or []), "limit": limit,
             "window": limit * max(1, workers) + AFFINITY_SLACK})
        return [r[0] for r in rows]

    def renew_leases(self, owner: str, ttl_s: float) -> int:
        """Extend every lease ``owner`` holds, by one write of its heartbeat (``workers.until``,
        the database's clock); return the number of devices it holds."""
        self._beat(owner, ttl_s)
        return int(self._read("SELECT COUNT(*) FROM devices WHERE lease_owner = %s", (owner,))[0][0])

    def _beat(self, owner: str, ttl_s: float) -> None:
        self._read(f"INSERT INTO workers(owner, seen_at, until) VALUES (%(me)s, {_NOW}, {_NOW} + %(ttl)s) "
                   "ON CONFLICT (owner) DO UPDATE SET seen_at = excluded.seen_at, until = excluded.until RETURNING 1",
                   {"me": owner, "ttl": ttl_s})

    def held_leases(self, owner: str) -> list[str]:
        """Every device whose lease row names ``owner`` (what the database says it holds)."""
        return [r[0] for r in self._read("SELECT device_id FROM devices WHERE lease_owner = %s", (owner,))]

    def leased_with_pending(self, owner: str) -> list[str]:
        """Devices ``owner`` holds that have pending batches (ingested by other processes)."""
        rows = self._read("SELECT DISTINCT b.device_id FROM batches b JOIN devices d ON d.device_id = b.device_id "
                          "WHERE b.state = 0 AND d.lease_owner = %s", (owner,))
        return [r[0] for r in rows]

    def heartbeat(self, owner: str, ttl_s: float) -> tuple[int, int, int]:
        """Record ``owner`` as live; return (live workers, devices leased now, devices with
        pending batches that no live lease holds). Workers not seen for ten lease times
        are deleted."""
        self._beat(owner, ttl_s)  # (this renews its leases too)
        self._read(f"DELETE FROM workers WHERE seen_at < {_NOW} - %(old)s RETURNING 1", {"old": 10 * ttl_s})
        rows = self._read(
            f"SELECT (SELECT COUNT(*) FROM workers WHERE seen_at >= {_NOW} - %(ttl)s),"
            f" (SELECT COUNT(*) FROM devices d WHERE d.lease_owner IS NOT NULL AND {_lease_live('d')}),"
            " (SELECT COUNT(DISTINCT b.device_id) FROM batches b JOIN devices d ON d.device_id = b.device_id"
            f" WHERE b.state = 0 AND (d.lease_owner IS NULL OR NOT {_lease_live('d')}))", {"ttl": ttl_s})
        return int(rows[0][0]), int(rows[0][1]), int(rows[0][2])

    def forget_worker(self, owner: str) -> None:
        """``owner`` stops (its share goes to the others at once; a lease it still holds
        lapses within a lease time of being taken)."""
        self._read("DELETE FROM workers WHERE owner = %s RETURNING 1", (owner,))

    def release_lease(self, owner: str, device_id: str) -> None:
        """Give a device's lease up (it had nothing left to feed)."""
        self._read("UPDATE devices SET lease_owner = NULL, lease_expires = NULL, last_owner = lease_owner "
                   "WHERE device_id = %s AND lease_owner = %s RETURNING 1", (device_id, owner))

    def lease_counts(self) -> dict[str, int]:
        """Leases held now, by owner (for metrics)."""
        rows = self._read("SELECT d.lease_owner, COUNT(*) FROM devices d WHERE d.lease_owner IS NOT NULL "
                          f"AND {_lease_live('d')} GROUP BY 1")
        return {r[0]: int(r[1]) for r in rows}

    # ------------------------------------------------------------ reads
    def current(self, device_id: str) -> tuple[DeviceRecord, VersionRecord | None] | None:
        return _current_from_rows(self._read(_CURRENT_SQL, (device_id,)))

    async def current_async(self, device_id: str) -> tuple[DeviceRecord, VersionRecord | None] | None:
        """:meth:`current`, waiting on the database in the running event loop (no thread)."""
        return _current_from_rows(await self._async_readers().read(_CURRENT_SQL, (device_id,)))

    def _async_readers(self) -> AsyncReaders:
        """The running event loop's readers (made at its first read; a closed loop's go)."""
        import asyncio

        from selfcal_service.storage import StorageUnavailable

        loop = asyncio.get_running_loop()
        entry = self._aio.get(id(loop))  # the loop is held there: its id is not reused
        if entry is None:
            with self._conns_lock:
                if self._reads_closed:
                    raise StorageUnavailable("the store is closed")
                ended = [k for k, (lp, _) in self._aio.items() if lp.is_closed()]
                for key in ended:  # loops that ended (a test's client): nothing runs on theirs
                    self._aio.pop(key)[1].close_all()
                entry = self._aio[id(loop)] = (loop, AsyncReaders(self._connect_kwargs, self.max_idle_readers))
        return entry[1]

    def history(self, device_id: str) -> list[VersionRecord]:
        rows = self._read(f"SELECT {VERSION_COLUMNS} FROM versions WHERE device_id = %s ORDER BY version",
                          (device_id,))
        return [version_from_row(r) for r in rows]

    def get_version(self, device_id: str, version: int) -> VersionRecord | None:
        rows = self._read(f"SELECT {VERSION_COLUMNS} FROM versions WHERE device_id = %s AND version = %s",
                          (device_id, version))
        return version_from_row(rows[0]) if rows else None

    def list_devices(self, after: str | None, limit: int) -> list[tuple[DeviceRecord, str]]:
        rows = self._read(
            f"SELECT {_DEVICE_READ_COLS}, COALESCE(v.status, 'uncalibrated') FROM devices d "
            "LEFT JOIN versions v ON v.device_id = d.device_id AND v.version = d.current_version "
            "WHERE d.device_id > %s ORDER BY d.device_id LIMIT %s", (after or "", limit))
        return [(device_from_row(r[:_N]), r[_N]) for r in rows]

    def fleet(self, after: str | None, limit: int, device_id: str | None = None) -> list[FleetRecord]:
        if device_id is not None:
            rows = self._read(_FLEET_SQL + " WHERE d.device_id = %s", (device_id,))
        else:
            rows = self._read(_FLEET_SQL + " WHERE d.device_id > %s ORDER BY d.device_id LIMIT %s",
                              (after or "", limit))
        return [fleet_from_row(r) for r in rows]

    def refusals(self, device_id: str, limit: int) -> list[RefusalRecord]:
        rows = self._read(
            f"SELECT {REFUSAL_COLUMNS} FROM (SELECT id, {REFUSAL_COLUMNS} FROM refusals WHERE device_id = %s "
            "ORDER BY id DESC LIMIT %s) AS newest ORDER BY id", (device_id, limit))
        return [refusal_from_row(r) for r in rows]

    def backlog(self) -> int:
        return int(self._read("SELECT COUNT(*) FROM batches WHERE state = 0")[0][0])

    def oldest_pending_age_s(self) -> float:
        """Age of the oldest stored batch not yet fed nor rejected (0 if none), seconds."""
        (oldest,) = self._read("SELECT MIN(received_at) FROM batches WHERE state = 0")[0]
        return 0.0 if oldest is None else max(0.0, time.time() - oldest)

    def ping(self) -> bool:
        try:
            self._read("SELECT 1")
        except Exception:  # noqa: BLE001 - any failure is "not ok"
            return False
        return self.writer_alive()
