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
  feed bookkeeping and any newly published versions in **one** transaction, and only
  if the stored ``processed_seq`` still equals the one the worker started from (and,
  on a shared database, the state revision and the worker's lease); otherwise it
  raises :class:`ConflictError` and writes nothing.
* Version numbers of a device are 1, 2, 3, ... in publication order; ``current_version``
  points at the version served by ``GET /devices/{id}/calibration``.
"""

from __future__ import annotations

import abc
import json
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any


class ConflictError(Exception):
    """The device changed under a worker (another writer advanced processed_seq)."""


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


@dataclass
class NewVersion:
    status: str
    source: str  # "refit" | "factory" | "rollback"
    calibration: dict[str, Any]
    provenance: dict[str, Any]


@dataclass
class Progress:
    """What one worker cycle writes for one device (one transaction)."""

    device_id: str
    expected_processed_seq: int | None
    processed_seq: int | None
    samples_added: int
    calibrator_state: str | None
    calibrator_status: str | None
    last_refit: dict[str, Any] | None
    feed_state: dict[str, Any]
    new_versions: list[NewVersion] = field(default_factory=list)
    fed_seqs: list[int] = field(default_factory=list)
    rejected: list[tuple[int, int, str]] = field(default_factory=list)  # (seq, n_samples, reason)
    # optimistic checks of a shared database (PostgreSQL): the state this cycle started
    # from, and the lease the writing worker must still hold (None: not checked)
    expected_state_rev: int | None = None
    lease_owner: str | None = None


@dataclass
class VersionRecord:
    version: int
    status: str
    source: str
    created_at: float
    calibration: dict[str, Any]
    provenance: dict[str, Any]


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
    def load_device(self, device_id: str) -> DeviceRecord | None: ...

    @abc.abstractmethod
    def pending_batches(self, device_id: str, limit: int) -> list[PendingBatch]:
        """Pending batches of a device in seq order."""

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
    def ping(self) -> bool: ...

    @abc.abstractmethod
    def backlog(self) -> int:
        """Stored batches that are neither fed nor rejected yet (all devices)."""

    @abc.abstractmethod
    def probe_write(self, timeout_s: float = 2.0) -> str | None:
        """Commit a tiny write through the writer; None if it worked, else the reason."""
