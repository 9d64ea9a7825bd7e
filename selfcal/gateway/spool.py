"""The gateway's SQLite spool: an outbox of batches plus per-device state.

Every closed batch is written here *before* it is posted (outbox pattern), with
its batch ``seq`` already assigned; it is deleted only after the service
acknowledged it (200, ``duplicate`` or not). So:

* a service outage only makes the spool grow; batches are forwarded in
  ``seq`` order per device when it returns;
* the samples of the still-open batches are journalled (``open_samples``) every
  ``journal_every_s``: a gateway crash (``kill -9``, a power cut) loses at most the
  samples received since the last journal write, and the next start spools the
  journalled ones as a batch. A batch's commit deletes the journal rows it covers and
  records the last sample count stored (``stored_count``), so no sample is spooled
  twice. A batch that was sent but not yet deleted is resent with the *same* ``seq``
  and body, and the service recognises it (``duplicate: true``);
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

import numpy as np

from selfcal.gateway.errors import GatewayError

_SCHEMA = """
CREATE TABLE IF NOT EXISTS devices (
    device_id       TEXT PRIMARY KEY,
    next_batch_seq  INTEGER NOT NULL,
    last_count      INTEGER,
    count_offset    INTEGER NOT NULL DEFAULT 0,
    stored_count    INTEGER
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
CREATE TABLE IF NOT EXISTS open_samples (
    id              INTEGER PRIMARY KEY AUTOINCREMENT,
    device_id       TEXT NOT NULL,
    sample_rate_hz  REAL NOT NULL,
    first_count     INTEGER NOT NULL,
    last_count      INTEGER NOT NULL,
    counts          BLOB NOT NULL,
    acc_g           BLOB NOT NULL,
    pressure_kpa    BLOB NOT NULL,
    temp_c          BLOB NOT NULL,
    tracker_last    INTEGER NOT NULL,
    tracker_offset  INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS open_samples_device ON open_samples (device_id, last_count);
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
class OpenSamples:
    """Samples of a device's open batch, as journalled (or to journal).

    Attributes
    ----------
    device_id : str
    sample_rate_hz : float
    counts : ndarray, shape (n,), int64 — unwrapped sample counts (increasing)
    acc_g : ndarray, shape (n, 3), g
    pressure_kpa : ndarray, shape (n, 4), kPa
    temp_c : ndarray, shape (n,), degC
    tracker_last, tracker_offset : int
        The device's sample-index unwrapping state after these samples.
    """

    device_id: str
    sample_rate_hz: float
    counts: np.ndarray
    acc_g: np.ndarray
    pressure_kpa: np.ndarray
    temp_c: np.ndarray
    tracker_last: int
    tracker_offset: int


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
    stored_count : int or None
        The last sample count in the batches stored (None: none yet).
    """

    next_batch_seq: int
    last_count: int | None
    count_offset: int
    stored_count: int | None = None


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
            columns = {row[1] for row in self._db.execute("PRAGMA table_info(devices)")}
            if "stored_count" not in columns:  # a spool of an earlier release
                self._db.execute("ALTER TABLE devices ADD COLUMN stored_count INTEGER")
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
            "SELECT next_batch_seq, last_count, count_offset, stored_count FROM devices WHERE device_id = ?",
            (device_id,),
        ).fetchone()
        if row is None:
            return DeviceState(next_batch_seq=0, last_count=None, count_offset=0)
        return DeviceState(next_batch_seq=row[0], last_count=row[1], count_offset=row[2], stored_count=row[3])

    def put_batch(
        self,
        device_id: str,
        n_samples: int,
        make_body: Callable[[int], bytes],
        last_count: int | None,
        count_offset: int,
        stored_count: int | None = None,
    ) -> int:
        """Allocate the device's next batch seq and store the batch, atomically; with
        ``stored_count``, the journal rows of the open samples it covers go in the same
        transaction.

        Parameters
        ----------
        device_id : str
        n_samples : int
            Samples in the batch.
        make_body : callable
            ``make_body(seq) -> bytes``: the JSON body for the allocated seq.
        last_count, count_offset : int
            The device's unwrapping state after this batch (persisted with it).
        stored_count : int, optional
            The batch's last sample count: journalled samples up to it are stored now.

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
                "INSERT INTO devices (device_id, next_batch_seq, last_count, count_offset, stored_count) "
                "VALUES (?, ?, ?, ?, ?) ON CONFLICT(device_id) DO UPDATE SET "
                "next_batch_seq = excluded.next_batch_seq, last_count = excluded.last_count, "
                "count_offset = excluded.count_offset, "
                "stored_count = COALESCE(excluded.stored_count, devices.stored_count)",
                (device_id, seq + 1, last_count, count_offset, stored_count),
            )
            if stored_count is not None:
                db.execute("DELETE FROM open_samples WHERE device_id = ? AND last_count <= ?",
                           (device_id, stored_count))
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise
        return seq

    # -- journal of the open batches -----------------------------------------
    def journal(self, parts: list[OpenSamples]) -> None:
        """Write open samples to the journal, all ``parts`` in one transaction."""
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            db.executemany(
                "INSERT INTO open_samples (device_id, sample_rate_hz, first_count, last_count, counts, acc_g, "
                "pressure_kpa, temp_c, tracker_last, tracker_offset) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [(p.device_id, float(p.sample_rate_hz), int(p.counts[0]), int(p.counts[-1]),
                  np.ascontiguousarray(p.counts, dtype="<i8").tobytes(),
                  np.ascontiguousarray(p.acc_g, dtype="<f8").tobytes(),
                  np.ascontiguousarray(p.pressure_kpa, dtype="<f8").tobytes(),
                  np.ascontiguousarray(p.temp_c, dtype="<f8").tobytes(), int(p.tracker_last), int(p.tracker_offset))
                 for p in parts if len(p.counts)],
            )
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise

    def journalled(self) -> dict[str, list[OpenSamples]]:
        """The journalled open samples per device, in journal order, without the samples
        a stored batch holds already (a journal row a batch covered only in part)."""
        stored = dict(self._db.execute("SELECT device_id, stored_count FROM devices"))
        out: dict[str, list[OpenSamples]] = {}
        for (device_id, rate, counts, acc, pressure, temp, last, offset) in self._db.execute(
                "SELECT device_id, sample_rate_hz, counts, acc_g, pressure_kpa, temp_c, tracker_last, "
                "tracker_offset FROM open_samples ORDER BY id"):
            c = np.frombuffer(counts, dtype="<i8")
            part = OpenSamples(device_id, rate, c, np.frombuffer(acc, dtype="<f8").reshape(len(c), 3),
                               np.frombuffer(pressure, dtype="<f8").reshape(len(c), -1),
                               np.frombuffer(temp, dtype="<f8"), last, offset)
            done = stored.get(device_id)
            if done is not None and c[0] <= done:
                keep = c > done
                part = OpenSamples(device_id, rate, c[keep], part.acc_g[keep], part.pressure_kpa[keep],
                                   part.temp_c[keep], last, offset)
            out.setdefault(device_id, []).append(part)
        return out

    def drop_journal(self, device_id: str) -> None:
        """Delete the device's journal rows (what they held is stored, or was refused)."""
        self._db.execute("DELETE FROM open_samples WHERE device_id = ?", (device_id,))

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
