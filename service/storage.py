"""The storage interface of the service (SQLite today, PostgreSQL next).

Everything the routes and the worker need from a database goes through
:class:`Storage`; every SQL statement lives in one implementation module
(``service/sqlite_store.py``). Writes return a ``concurrent.futures.Future`` that
resolves only after the transaction holding them is committed, which is what lets the
HTTP layer acknowledge a batch after a durable commit and lets an implementation group
many writes into one commit.

Invariants every implementation keeps:

* ``(device_id, seq)`` is unique in the raw-batch table. A resent seq with the same
  content (SHA-256 of the canonical batch bytes) is a duplicate; with other content it
  is refused (:class:`SeqConflict`, HTTP 409) and nothing changes.
* A seq more than ``max_seq_jump`` above the device's highest stored seq is refused
  (:class:`SeqJump`, HTTP 422): one corrupt seq cannot strand the device's later
  batches behind it.
* Every stored batch is *pending*, then either *fed* to the calibrator exactly once or
  *rejected* with a reason (for example ``late``); never both, never neither for long.
  ``processed_seq`` is the highest fed seq.
* ``commit_progress`` writes the calibrator state, the fed and rejected batches, the
  feed bookkeeping, any newly published versions and the cycle's refusals (refits that
  published nothing, rejected batches; the last ``REFUSALS_KEPT_PER_DEVICE`` per device are
  kept) in **one** transaction, and only
  if the stored ``processed_seq`` still equals the one the worker started from (and,
  on a shared database, the state revision and the worker's lease); otherwise it
  raises :class:`ConflictError` and writes nothing.
* Version numbers of a device are 1, 2, 3, ... in publication order; ``current_version``
  points at the version served by ``GET /devices/{id}/calibration``.
"""

from __future__ import annotations

import abc
import json
import zlib
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any


class ConflictError(Exception):
    """The device changed under a worker (another writer advanced processed_seq)."""


class LeaseLost(ConflictError):
    """The worker's lease of the device lapsed or went to another worker (shared database):
    the device is no longer this worker's to feed."""


class SeqConflict(Exception):
    """A resent seq whose content differs from the stored batch (HTTP 409)."""


class SeqJump(Exception):
    """A seq too far above the device's highest stored seq (HTTP 422)."""


class StorageUnavailable(Exception):
    """The database cannot take writes now (read-only, full, replaced); HTTP 503."""


@dataclass(frozen=True)
class IngestResult:
    duplicate: bool


@dataclass(frozen=True)
class PendingBatch:
    """A stored batch not yet fed nor rejected."""

    seq: int
    n_samples: int
    received_at: float
    payload: bytes


@dataclass(frozen=True)
class Checkpoint:
    """The last written calibrator state of a device: the state after feeding every fed
    batch up to ``seq`` (None: before any), and the feed bookkeeping at that point. A
    worker restores it and feeds the stored batches after ``seq`` again (replay)."""

    seq: int | None
    feed_state: dict[str, Any]


@dataclass
class DeviceRecord:
    device_id: str
    batches_stored: int
    processed_seq: int | None
    samples_processed: int
    calibrator_state: str | None
    calibrator_status: str | None
    last_refit: dict[str, Any] | None
    feed_state: dict[str, Any]
    current_version: int | None
    updated_at: float | None
    rejected_batches: int = 0
    rejected_samples: int = 0
    last_rejection: dict[str, Any] | None = None
    state_rev: int | None = None  # bumped by every commit_progress (PostgreSQL; None on SQLite)
    # where ``calibrator_state`` stands (None: no checkpoint, a fresh calibrator). The state
    # text itself is read only by ``load_device(..., with_state=True)``.
    checkpoint: Checkpoint | None = None
    # the checkpoint's latest patch against ``calibrator_state`` (its base), or None: the
    # base alone is the checkpoint (``selfcal.checkpoint``; read with the state only)
    calibrator_patch: str | None = None
    # the stored base's tag (:func:`base_tag`; None before schema 6/5 wrote one)
    calibrator_base_tag: str | None = None


@dataclass
class NewVersion:
    status: str
    source: str  # "refit" | "factory" | "rollback"
    calibration: dict[str, Any]
    provenance: dict[str, Any]


#: Refusals kept per device (the oldest are deleted beyond this); a refit runs at most every
#: few minutes of worn data, so this is days to weeks of a device's history.
REFUSALS_KEPT_PER_DEVICE = 1000


@dataclass
class RefusalRecord:
    """A refit that published nothing, or a stored batch that was never fed, with its reason.

    ``kind``: ``"refit"`` (``reason`` is the calibrator's: ``no_significant_change``,
    ``worse_than_current``, ``insufficient_coverage``, ...) or ``"batch"`` (``late``,
    ``calibrator``). ``at``: Unix time (s) the service recorded it (None when written:
    the commit's time, the clock of the versions' ``created_at``). ``t_s``: the device's
    (calibrator's) time of a refit, s. ``seq``: the rejected batch's seq.
    """

    kind: str
    reason: str | None
    message: str = ""
    at: float | None = None
    t_s: float | None = None
    seq: int | None = None


@dataclass
class Progress:
    """What one worker cycle writes for one device (one transaction)."""

    device_id: str
    expected_processed_seq: int | None
    processed_seq: int | None
    samples_added: int
    # the calibrator state after this cycle, written as the device's checkpoint at
    # ``processed_seq`` with ``feed_state``; None keeps the stored checkpoint (the batches
    # fed since are replayed on restore)
    calibrator_state: str | None
    calibrator_status: str | None
    last_refit: dict[str, Any] | None
    feed_state: dict[str, Any]
    new_versions: list[NewVersion] = field(default_factory=list)
    fed_seqs: list[int] = field(default_factory=list)
    rejected: list[tuple[int, int, str]] = field(default_factory=list)  # (seq, n_samples, reason)
    refusals: list[RefusalRecord] = field(default_factory=list)  # appended to the device's refusal log
    # optimistic checks of a shared database (PostgreSQL): the state this cycle started
    # from, and the lease the writing worker must still hold (None: not checked)
    expected_state_rev: int | None = None
    lease_owner: str | None = None
    # the calibrator state after this cycle as a patch against the stored base (with
    # ``calibrator_state`` None): the checkpoint's patch is replaced and its base kept. A
    # full ``calibrator_state`` replaces the base and clears the patch.
    calibrator_patch: str | None = None
    # the tag (:func:`base_tag`) of the base the patch was made against: the patch is
    # written only onto that base, and the commit is a ConflictError otherwise
    calibrator_patch_base: str | None = None


@dataclass
class VersionRecord:
    version: int
    status: str
    source: str
    created_at: float
    calibration: dict[str, Any]
    provenance: dict[str, Any]


@dataclass
class FleetRecord:
    """One device as the fleet dashboard lists it (the served version's figures, the backlog).

    ``last_seen``: Unix time (s) the device's highest-seq batch was received;
    ``updated_at``: Unix time (s) of the last refit cycle or admin write.
    ``predicted_sphere_rms_mg``, ``residual_rms_mg``, ``n_poses`` and ``model`` come from the
    served version's calibration (None before the first). ``backlog_batches``: stored
    batches of this device neither fed nor rejected yet.
    """

    device_id: str
    status: str
    version: int | None
    source: str | None
    model: str | None
    predicted_sphere_rms_mg: float | None
    residual_rms_mg: float | None
    n_poses: int | None
    backlog_batches: int
    batches_stored: int
    samples_processed: int
    rejected_batches: int
    last_seen: float | None
    updated_at: float | None
    last_refusal: RefusalRecord | None


def fleet_from_row(row: tuple) -> FleetRecord:
    """A :class:`FleetRecord` from a row of the stores' fleet query (see ``FLEET_COLUMNS``)."""
    (device_id, status, version, source, model, predicted, residual, n_poses, backlog, stored, samples,
     rejected, last_seen, updated_at, r_at, r_kind, r_reason, r_message, r_t_s, r_seq) = row
    refusal = None if r_kind is None else RefusalRecord(
        kind=r_kind, reason=r_reason, message=r_message or "", at=r_at, t_s=r_t_s, seq=r_seq)
    return FleetRecord(
        device_id=device_id, status=status, version=version, source=source, model=model,
        predicted_sphere_rms_mg=None if predicted is None else float(predicted),
        residual_rms_mg=None if residual is None else float(residual),
        n_poses=None if n_poses is None else int(n_poses),
        backlog_batches=int(backlog or 0), batches_stored=int(stored or 0), samples_processed=int(samples or 0),
        rejected_batches=int(rejected or 0), last_seen=last_seen, updated_at=updated_at, last_refusal=refusal)


def refusal_from_row(row: tuple) -> RefusalRecord:
    """A :class:`RefusalRecord` from a row in ``REFUSAL_COLUMNS`` order."""
    return RefusalRecord(kind=row[1], reason=row[2], message=row[3] or "", at=row[0], t_s=row[4], seq=row[5])


def fleet_select(json_number, json_text) -> str:
    """The fleet query of both stores, up to its WHERE clause (rows for :func:`fleet_from_row`).

    ``json_number(key)`` / ``json_text(key)``: this database's SQL for one key of the
    served version's calibration (a JSON text column) as a number / a text. The backlog
    counts the device's pending batches (the partial index ``batches_pending``); last seen
    is the receipt time of its highest seq (the primary key); the last refusal is its
    newest row in ``refusals`` (index ``refusals_device``).
    """
    return (
        "SELECT d.device_id, COALESCE(v.status, 'uncalibrated'), d.current_version, v.source, "
        f"{json_text('model')}, {json_number('predicted_sphere_rms_mg')}, {json_number('residual_rms_mg')}, "
        f"{json_number('n_poses')}, "
        "(SELECT COUNT(*) FROM batches b WHERE b.device_id = d.device_id AND b.state = 0), "
        "d.batches_stored, d.samples_processed, d.rejected_batches, "
        "(SELECT b.received_at FROM batches b WHERE b.device_id = d.device_id ORDER BY b.seq DESC LIMIT 1), "
        "d.updated_at, r.recorded_at, r.kind, r.reason, r.message, r.t_s, r.seq "
        "FROM devices d "
        "LEFT JOIN versions v ON v.device_id = d.device_id AND v.version = d.current_version "
        "LEFT JOIN refusals r ON r.id = (SELECT MAX(r2.id) FROM refusals r2 WHERE r2.device_id = d.device_id)"
    )


#: The refusal columns in the order :func:`refusal_from_row` reads them.
REFUSAL_COLUMNS = "recorded_at, kind, reason, message, t_s, seq"


#: The device columns in the order :func:`device_from_row` reads them; a store may select
#: ``state_rev`` after them (PostgreSQL) or not (SQLite).
DEVICE_COLUMNS = (
    "device_id", "batches_stored", "processed_seq", "samples_processed", "calibrator_state",
    "calibrator_status", "last_refit", "feed_state", "current_version", "updated_at",
    "rejected_batches", "rejected_samples", "last_rejection",
)
#: The version columns in the order :func:`version_from_row` reads them.
VERSION_COLUMNS = "version, status, source, created_at, calibration, provenance"


def device_from_row(row: tuple) -> DeviceRecord:
    """A :class:`DeviceRecord` from a row in ``DEVICE_COLUMNS`` order (JSON columns as text),
    optionally followed by ``state_rev``."""
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
        rejected_batches=row[10] or 0,
        rejected_samples=row[11] or 0,
        last_rejection=json.loads(row[12]) if row[12] else None,
        state_rev=row[13] if len(row) > len(DEVICE_COLUMNS) else None,
    )


def base_tag(crc32: int, n_bytes: int) -> str:
    """The tag of a checkpoint base: its text's CRC-32 and length in bytes (UTF-8)."""
    return f"{crc32 & 0xFFFFFFFF:08x}-{n_bytes}"


def base_tag_of(text: str) -> str:
    """:func:`base_tag` of a state text."""
    raw = text.encode()
    return base_tag(zlib.crc32(raw), len(raw))


def upsert_checkpoint_sql(device_id: str, seq: str, state: str, tag: str, patch: str, feed_state: str,
                          written_at: str) -> str:
    """SQL that writes a device's checkpoint from seven value expressions (placeholders,
    or a PL/pgSQL function's parameters), never an older state over a newer one, and a
    patch only onto the base it was made against (``tag``: the full state's tag, or the
    patch's base's); a row it must not write is left as it is (no row counted).

    A full ``state`` (``patch`` NULL) replaces the base (column ``base``) and clears the
    patch; a ``patch`` (``state`` NULL) replaces the patch and keeps the base, whose text
    is not written again (PostgreSQL keeps its TOAST chunks). A patch with no checkpoint
    row to patch stores an empty base, which no patch applies to: its restore fails,
    loudly. (The column was ``state`` before patches: a process of that release fails
    its checkpoint writes and reads instead of writing a base under a patch.)"""
    return (f"INSERT INTO checkpoints(device_id, seq, base, base_tag, patch, feed_state, written_at) "
            f"VALUES ({device_id}, {seq}, COALESCE({state}, ''), {tag}, {patch}, {feed_state}, {written_at}) "
            "ON CONFLICT (device_id) DO UPDATE SET seq = excluded.seq, "
            "base = CASE WHEN excluded.patch IS NULL THEN excluded.base ELSE checkpoints.base END, "
            "base_tag = CASE WHEN excluded.patch IS NULL THEN excluded.base_tag ELSE checkpoints.base_tag END, "
            "patch = excluded.patch, feed_state = excluded.feed_state, written_at = excluded.written_at "
            "WHERE (checkpoints.seq IS NULL OR excluded.seq >= checkpoints.seq) "
            "AND (excluded.patch IS NULL OR checkpoints.base_tag = excluded.base_tag)")


def check_checkpoint(state: str | None, patch: str | None, patch_base: str | None) -> None:
    """ValueError unless a checkpoint write is exactly one of a full ``state`` or a
    ``patch`` with the tag of the base it was made against (both stores)."""
    if (state is None) == (patch is None) or (patch is not None and patch_base is None):
        raise ValueError("a checkpoint is a full state or a patch with its base's tag, exactly one of them")


def upsert_checkpoint(conn: Any, placeholder: str, device_id: str, seq: int | None, state: str | None,
                      feed_state: dict[str, Any], now: float, patch: str | None = None,
                      patch_base: str | None = None) -> bool:
    """Write a device's checkpoint (a full ``state``, or a ``patch`` made against the base
    tagged ``patch_base``) on a psycopg connection (``placeholder`` ``%s``; SQLite keeps
    its patches in a table of their own, ``sqlite_store.write_checkpoint_sqlite``), in
    the caller's transaction. False if the row was left as it was (a newer checkpoint,
    or another base than the patch's)."""
    check_checkpoint(state, patch, patch_base)
    cur = conn.execute(upsert_checkpoint_sql(*[placeholder] * 7),
                       (device_id, seq, state, base_tag_of(state) if patch is None else patch_base, patch,
                        dumps_json(feed_state), now))
    return cur.rowcount == 1


def with_checkpoint(rec: DeviceRecord, cols: tuple) -> DeviceRecord:
    """``rec`` with its checkpoint from the columns (exists, seq, feed_state JSON[, patch,
    base tag])."""
    exists, seq, feed = cols[:3]
    if exists:
        rec.checkpoint = Checkpoint(seq=seq, feed_state=json.loads(feed) if feed else {})
        rec.calibrator_patch = cols[3] if len(cols) > 3 else None
        rec.calibrator_base_tag = cols[4] if len(cols) > 4 else None
    return rec


def version_from_row(row: tuple) -> VersionRecord:
    """A :class:`VersionRecord` from a row in ``VERSION_COLUMNS`` order."""
    return VersionRecord(version=row[0], status=row[1], source=row[2], created_at=row[3],
                         calibration=json.loads(row[4]), provenance=json.loads(row[5]))


def dumps_json(obj: Any) -> str:
    """Compact JSON for a stored column (NaN refused)."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


class Storage(abc.ABC):
    """Durable store of raw batches, calibrator states and model versions."""

    @abc.abstractmethod
    def open(self) -> None:
        """Create the schema if needed and start any background writer."""

    @abc.abstractmethod
    def close(self) -> None:
        """Finish queued writes and release connections."""

    # -- ingest
    @abc.abstractmethod
    def submit_batch(
        self, device_id: str, seq: int, n_samples: int, payload: bytes, received_at: float,
        digest: bytes, max_seq_jump: int,
    ) -> "Future[IngestResult]":
        """Store a raw batch; the future resolves after the commit (durable ack).

        ``digest`` is the SHA-256 of the canonical batch bytes (duplicate vs conflict).
        The future raises :class:`SeqConflict`, :class:`SeqJump` or
        :class:`StorageUnavailable`; nothing is stored then.
        """

    # -- worker
    @abc.abstractmethod
    def pending_devices(self) -> list[str]:
        """Devices with pending (neither fed nor rejected) batches, for restart."""

    @abc.abstractmethod
    def load_device(self, device_id: str, with_state: bool = True) -> DeviceRecord | None:
        """The device row with its checkpoint's position; the checkpoint's state text
        (``calibrator_state``, up to megabytes, and ``calibrator_patch``) only ``with_state``."""

    @abc.abstractmethod
    def fed_batches(self, device_id: str, after_seq: int | None, upto_seq: int | None,
                    limit: int) -> list[PendingBatch]:
        """Batches fed to the calibrator with ``after_seq < seq <= upto_seq`` (None: no
        bound below) in seq order, at most ``limit``: the replay after a checkpoint."""

    @abc.abstractmethod
    def write_checkpoint(self, device_id: str, seq: int | None, state: str | None,
                         feed_state: dict[str, Any], state_rev: int | None = None,
                         patch: str | None = None, patch_base: str | None = None) -> bool:
        """Write a calibrator state (full ``state``, or a ``patch`` made against the stored
        base tagged ``patch_base``, with ``state`` None; not written if the stored base is
        another) as the device's checkpoint at ``seq`` if the device's
        ``processed_seq`` is still ``seq`` and (when given; PostgreSQL) its ``state_rev``
        is still ``state_rev`` (else nothing: a newer cycle or an admin seed was
        committed); True if written. Durable on return."""

    @abc.abstractmethod
    def pending_batches(self, device_id: str, limit: int) -> list[PendingBatch]:
        """Pending batches of a device in seq order."""

    def load_cycle(self, device_id: str, limit: int) -> tuple[DeviceRecord | None, list[PendingBatch]]:
        """What a worker cycle reads: the device row as ``load_device(device_id,
        with_state=False)`` gives it (None: no such device) and its first ``limit`` pending
        batches in seq order. A store may read both in one statement."""
        rec = self.load_device(device_id, with_state=False)
        if rec is None:
            return None, []
        return rec, self.pending_batches(device_id, limit)

    @abc.abstractmethod
    def commit_progress(self, progress: Progress) -> "Future[list[int]]":
        """Write one worker cycle atomically; resolves to the new version numbers."""

    # -- reads
    @abc.abstractmethod
    def current(self, device_id: str) -> tuple[DeviceRecord, VersionRecord | None] | None:
        """(device row, served version) for the read routes: ``calibrator_state`` is None
        (it can be megabytes and no read needs it; ``load_device`` has it)."""

    @abc.abstractmethod
    def history(self, device_id: str) -> list[VersionRecord]: ...

    @abc.abstractmethod
    def get_version(self, device_id: str, version: int) -> VersionRecord | None: ...

    @abc.abstractmethod
    def list_devices(self, after: str | None, limit: int) -> list[tuple[DeviceRecord, str]]:
        """Devices ordered by id (after ``after``), each with its served status
        (``calibrator_state`` is None, as in :meth:`current`)."""

    @abc.abstractmethod
    def fleet(self, after: str | None, limit: int, device_id: str | None = None) -> list[FleetRecord]:
        """Devices ordered by id (after ``after``) with the served version's figures, the
        backlog and the last refusal: one query for a page of the dashboard. With
        ``device_id``: that device's row only (or none)."""

    @abc.abstractmethod
    def refusals(self, device_id: str, limit: int) -> list[RefusalRecord]:
        """The device's last ``limit`` refusals, oldest first."""

    @abc.abstractmethod
    def ping(self) -> bool: ...

    @abc.abstractmethod
    def backlog(self) -> int:
        """Stored batches that are neither fed nor rejected yet (all devices)."""

    @abc.abstractmethod
    def probe_write(self, timeout_s: float = 2.0) -> str | None:
        """Commit a tiny write through the writer; None if it worked, else the reason."""
