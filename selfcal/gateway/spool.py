"""The gateway's SQLite spool: an outbox of batches plus per-device state.

Every closed batch is written here *before* it is posted (outbox pattern), with
its batch ``seq`` already assigned; it is deleted only after the service
acknowledged it (200, ``duplicate`` or not). So:

* a service outage only makes the spool grow; batches are forwarded in
  ``seq`` order per device when it returns;
* a gateway crash loses at most the samples of the still-open batches; a batch
  that was sent but not yet deleted is resent with the *same* ``seq`` and body,
  and the service recognises it (``duplicate: true``);
* batch ``seq`` and the sample-index unwrapping state survive restarts
  (``devices`` table), so seq numbers are never reused for different data.

SQLite runs in WAL mode with ``synchronous=FULL``: every committed batch survives a
power cut too (one fsync per batch, one every few seconds per insole). With NORMAL a
power cut could roll back the last commits after their batches had been posted, and the
next, different batches were then given the same seqs (the service answers 409 to those:
:meth:`Spool.renumber` moves them on).
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from selfcal.gateway.errors import GatewayError

_SCHEMA = """
CREATE TABLE IF NOT EXISTS devices (
    device_id       TEXT PRIMARY KEY,
    next_batch_seq  INTEGER NOT NULL,
    last_count      INTEGER,
    count_offset    INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS batches (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    device_id   TEXT NOT NULL,
    seq         INTEGER NOT NULL,
    n_samples   INTEGER NOT NULL,
    body        BLOB NOT NULL,
    created_s   REAL NOT NULL,
    attempts    INTEGER NOT NULL DEFAULT 0,
    UNIQUE (device_id, seq)
);
CREATE INDEX IF NOT EXISTS batches_device ON batches (device_id, seq);
CREATE TABLE IF NOT EXISTS rejected (
    id          INTEGER PRIMARY KEY,
    device_id   TEXT NOT NULL,
    seq         INTEGER NOT NULL,
    n_samples   INTEGER NOT NULL,
    body        BLOB NOT NULL,
    status      INTEGER NOT NULL,
    reason      TEXT NOT NULL,
    rejected_s  REAL NOT NULL
);
"""


@dataclass(frozen=True)
class SpooledBatch:
    """One batch waiting in the spool.

    Attributes
    ----------
    id : int
        Spool row id (insertion order).
    device_id : str
    seq : int
        Batch sequence number (per device, persisted, never reused).
    n_samples : int
    body : bytes
        The exact JSON body to POST (resends are byte-identical).
    attempts : int
        Failed POST attempts so far.
    """

    id: int
    device_id: str
    seq: int
    n_samples: int
    body: bytes
    attempts: int


@dataclass(frozen=True)
class DeviceState:
    """Persisted per-device state.

    Attributes
    ----------
    next_batch_seq : int
        Seq the next batch of this device gets.
    last_count : int or None
        Last unwrapped sample count seen (see :class:`~selfcal.gateway.codec.SeqTracker`).
    count_offset : int
        Offset of the sample-index unwrapping.
    """

    next_batch_seq: int
    last_count: int | None
    count_offset: int


class Spool:
    """SQLite outbox of batches and per-device counters.

    Parameters
    ----------
    path : str or Path
        SQLite file (created if missing). ``":memory:"`` for a throw-away spool.
    """

    def __init__(self, path: str | Path):
        self.path = str(path)
        if self.path != ":memory:":
            Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        try:
            self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.executescript(_SCHEMA)
        except sqlite3.DatabaseError as exc:
            raise GatewayError(f"spool {self.path}: cannot open SQLite database: {exc}") from exc

    def close(self) -> None:
        """Close the database (idempotent)."""
        if self._db is not None:
            self._db.close()
            self._db = None  # type: ignore[assignment]

    # -- device state --------------------------------------------------------
    def device_state(self, device_id: str) -> DeviceState:
        """The persisted state of ``device_id`` (fresh state if unknown)."""
        row = self._db.execute(
            "SELECT next_batch_seq, last_count, count_offset FROM devices WHERE device_id = ?",
            (device_id,),
        ).fetchone()
        if row is None:
            return DeviceState(next_batch_seq=0, last_count=None, count_offset=0)
        return DeviceState(next_batch_seq=row[0], last_count=row[1], count_offset=row[2])

    def put_batch(
        self,
        device_id: str,
        n_samples: int,
        make_body: Callable[[int], bytes],
        last_count: int | None,
        count_offset: int,
    ) -> int:
        """Allocate the device's next batch seq and store the batch, atomically.

        Parameters
        ----------
        device_id : str
        n_samples : int
            Samples in the batch.
        make_body : callable
            ``make_body(seq) -> bytes``: the JSON body for the allocated seq.
        last_count, count_offset : int
            The device's unwrapping state after this batch (persisted with it).

        Returns
        -------
        int
            The batch seq.
        """
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            row = db.execute(
                "SELECT next_batch_seq FROM devices WHERE device_id = ?", (device_id,)
            ).fetchone()
            seq = 0 if row is None else row[0]
            db.execute(
                "INSERT INTO batches (device_id, seq, n_samples, body, created_s) VALUES (?, ?, ?, ?, ?)",
                (device_id, seq, n_samples, make_body(seq), time.time()),
            )
            db.execute(
                "INSERT INTO devices (device_id, next_batch_seq, last_count, count_offset) "
                "VALUES (?, ?, ?, ?) ON CONFLICT(device_id) DO UPDATE SET "
                "next_batch_seq = excluded.next_batch_seq, last_count = excluded.last_count, "
                "count_offset = excluded.count_offset",
                (device_id, seq + 1, last_count, count_offset),
            )
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise
        return seq

    # -- outbox --------------------------------------------------------------
    def heads(self, limit: int = 1000) -> list[SpooledBatch]:
        """The oldest pending batch of each device (at most ``limit`` devices)."""
        rows = self._db.execute(
            "SELECT b.id, b.device_id, b.seq, b.n_samples, b.body, b.attempts FROM batches b "
            "JOIN (SELECT device_id, MIN(seq) AS seq FROM batches GROUP BY device_id) h "
            "ON b.device_id = h.device_id AND b.seq = h.seq ORDER BY b.id LIMIT ?",
            (limit,),
        ).fetchall()
        return [SpooledBatch(*row) for row in rows]

    def ack(self, batch: SpooledBatch) -> None:
        """Delete a batch the service acknowledged."""
        self._db.execute("DELETE FROM batches WHERE id = ?", (batch.id,))

    def failed_attempt(self, batch: SpooledBatch) -> None:
        """Count a failed POST of ``batch``."""
        self._db.execute("UPDATE batches SET attempts = attempts + 1 WHERE id = ?", (batch.id,))

    def reject(self, batch: SpooledBatch, status: int, reason: str) -> None:
        """Move a batch the service refused for good (4xx) to the ``rejected`` table."""
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            db.execute(
                "INSERT INTO rejected (id, device_id, seq, n_samples, body, status, reason, rejected_s) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (batch.id, batch.device_id, batch.seq, batch.n_samples, batch.body, status, reason, time.time()),
            )
            db.execute("DELETE FROM batches WHERE id = ?", (batch.id,))
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise

    def renumber(self, device_id: str, start_seq: int) -> int:
        """Give the device's pending batches new seqs from ``start_seq`` on, in their order,
        and the device's next batch the seq after them, atomically (the service holds their
        seqs with other content: a lost or replaced spool, two gateways, a power cut under
        an older release). Each body is rewritten with its new seq. ``start_seq`` must be
        above every pending seq of the device. Returns the batches renumbered."""
        import json

        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            rows = db.execute("SELECT id, seq, body FROM batches WHERE device_id = ? ORDER BY seq",
                              (device_id,)).fetchall()
            if rows and start_seq <= rows[-1][1]:
                raise GatewayError(f"renumber {device_id}: start seq {start_seq} is not above the pending "
                                   f"seqs (up to {rows[-1][1]})")
            for i, (row_id, _, body) in enumerate(rows):  # each new seq is above every old one: no clash
                payload = json.loads(body)
                payload["seq"] = start_seq + i
                db.execute("UPDATE batches SET seq = ?, body = ? WHERE id = ?",
                           (start_seq + i, json.dumps(payload, separators=(",", ":")).encode(), row_id))
            db.execute("UPDATE devices SET next_batch_seq = MAX(next_batch_seq, ?) WHERE device_id = ?",
                       (start_seq + len(rows), device_id))
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise
        return len(rows)

    def next_seq(self, device_id: str) -> int:
        """The seq the device's next batch gets."""
        return self.device_state(device_id).next_batch_seq

    def depth(self) -> dict[str, tuple[int, int]]:
        """Pending ``(batches, samples)`` per device."""
        rows = self._db.execute(
            "SELECT device_id, COUNT(*), COALESCE(SUM(n_samples), 0) FROM batches GROUP BY device_id"
        ).fetchall()
        return {device_id: (n, s) for device_id, n, s in rows}

    def rejected_count(self) -> int:
        """Batches the service refused for good."""
        return int(self._db.execute("SELECT COUNT(*) FROM rejected").fetchone()[0])
