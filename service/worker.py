"""Background refits: feed committed batches to each device's calibrator, off the request path.

* Devices are sharded over ``worker_threads`` threads by a stable hash of the id, so one
  device is only ever handled by one thread: its refits never run concurrently.
* A cycle for a device reads *committed* raw batches above its ``processed_seq`` (in seq
  order), feeds them to the calibrator, and writes the calibrator state, the new
  ``processed_seq`` and every version the calibrator published in one transaction
  (:meth:`Storage.commit_progress`). A crash anywhere before that commit replays the same
  batches from the previous state on restart - nothing is lost or fed twice.
* Under load a device's batches pile up between cycles and are fed together, so the
  per-cycle cost (state serialisation, commit) is amortised.
* What is published is decided by the calibrator's guard: the worker only records the
  outcome of every refit (``published`` or the typed reason).
"""

from __future__ import annotations

import heapq
import importlib
import logging
import math
import threading
import time
import zlib
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from selfcal_service.logs import device_id as device_id_var
from selfcal_service.metrics import Metrics
from selfcal_service.schemas import Batch, decode_binary
from selfcal_service.storage import (
    ConflictError,
    DeviceRecord,
    LeaseLost,
    NewVersion,
    PendingBatch,
    Progress,
    RefusalRecord,
    Storage,
    StorageUnavailable,
    base_tag,
)

log = logging.getLogger("selfcal.service.worker")


#: Clock resets after its checkpoint whose offsets a device's feed state keeps, at most
#: (for replays after the checkpoint; the ones at or before it are dropped).
RESET_OFFSETS_KEPT = 256


class Calibrator(Protocol):
    """What the service needs from ``selfcal.calibrator.OnlineCalibrator`` (internals.md)."""

    status: str
    last_refit: dict[str, Any] | None

    def feed_samples(self, t_s, acc_g, temp_c=None, pressure_kpa=None) -> list[dict[str, Any]]: ...

    def calibration(self) -> dict[str, Any] | None: ...

    def to_json(self) -> str: ...


class CalibratorFactory:
    """Creates and restores calibrators: ``create()`` and ``restore(state_json)``.

    ``import_path`` is ``"module:Class"``; the class must provide ``Class(config=...,
    model=...)`` and ``Class.from_json(s)``. Tests pass a fake class.
    """

    def __init__(self, import_path_or_cls: str | type, config: dict | None = None, model: str = "affine9"):
        self._spec = import_path_or_cls
        self._cls: type | None = None if isinstance(import_path_or_cls, str) else import_path_or_cls
        self.config = config
        self.model = model

    @property
    def cls(self) -> type:
        if self._cls is None:
            module, _, name = str(self._spec).partition(":")
            self._cls = getattr(importlib.import_module(module), name)
        return self._cls

    def create(self) -> Calibrator:
        return self.cls(config=self.config, model=self.model)

    def restore(self, state_json: str) -> Calibrator:
        """A calibrator from its saved state. The service's current ``[selection]`` settings
        replace the saved ones (an operator who turns model selection off means every device)."""
        return self._configured(self.cls.from_json(state_json))

    def restore_checkpoint(self, base_json: str, patch_json: str | None) -> tuple[Calibrator, Any]:
        """A calibrator from a checkpoint: its base state and its latest patch (None: the
        base alone), and what a later patch is made against (None: the class writes no
        patches, ``from_checkpoint`` missing). As :meth:`restore` for the settings."""
        if hasattr(self.cls, "from_checkpoint"):
            cal, base = self.cls.from_checkpoint(base_json, patch_json)
            return self._configured(cal), base
        if patch_json is not None:
            raise ValueError(f"{self.cls.__name__} cannot apply a checkpoint patch (no from_checkpoint)")
        return self.restore(base_json), None

    def _configured(self, cal: Calibrator) -> Calibrator:
        if self.config is not None and hasattr(cal, "set_selection"):
            cal.set_selection((self.config or {}).get("selection"))
        return cal


def jsonable(obj: Any) -> Any:
    """Plain JSON types: numpy scalars/arrays converted, NaN/inf -> None."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if obj is None or isinstance(obj, str):
        return obj
    return str(obj)


#: Longest refusal message stored (the calibrator's messages are a line; a traceback is not).
REFUSAL_MESSAGE_CHARS = 300


def refusals_of(events: list[dict[str, Any]], rejected: list[tuple[int, int, str]]) -> list[RefusalRecord]:
    """The refusal log entries of one cycle: its refits that published nothing (the
    calibrator's reason and message, device time ``t_s``) and its rejected batches
    (reason ``late`` or ``calibrator``, the first word of the stored reason)."""
    def seconds(value: Any) -> float | None:
        value = jsonable(value)
        return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None

    out = [RefusalRecord(kind="refit", reason=None if ev.get("reason") is None else str(ev["reason"]),
                         message=str(ev.get("message") or "")[:REFUSAL_MESSAGE_CHARS], t_s=seconds(ev.get("t_s")))
           for ev in events if not ev.get("published")]
    out += [RefusalRecord(kind="batch", reason=reason.split(":", 1)[0], message=reason[:REFUSAL_MESSAGE_CHARS],
                          seq=int(seq)) for seq, _, reason in rejected]
    return out


#: The longest hold (s) before a device whose cycles keep failing is tried again.
FAILURE_HOLD_MAX_S = 60.0

#: The hold (s) before an embedded worker's cycle that met a concurrent change (an admin
#: seed or rollback of the device) is tried again: its batches are still pending, and no
#: new batch may come to have them fed.
CONFLICT_HOLD_S = 0.5


@dataclass(frozen=True)
class LeaseConfig:
    """How a worker leases devices from a shared database (PostgreSQL).

    ``owner``: this worker's unique id; ``ttl_s``: a lease not renewed for this long is
    free for another worker (so a killed worker's devices move on within it);
    ``poll_s``: how often to look for devices with pending batches; ``max_devices``:
    leases held at once; ``idle_s``: a device fed everything it had stays leased (and its
    calibrator cached) this long for its next batch, unless the room is needed (0: given
    up at once). Its state is written as a checkpoint when the lease is given up.
    """

    owner: str
    ttl_s: float = 10.0
    poll_s: float = 0.25
    max_devices: int = 8192
    idle_s: float = 60.0


def _tag_of(base: Any) -> str:
    """The store's tag (:func:`~selfcal_service.storage.base_tag`) of a calibrator's checkpoint base."""
    return base_tag(base.crc32, base.n_bytes)


def _shard(device_id: str, n: int) -> int:
    return zlib.crc32(device_id.encode()) % n


class _Shard:
    def __init__(self) -> None:
        self.pending: "OrderedDict[str, None]" = OrderedDict()
        self.cond = threading.Condition()
        self.thread: threading.Thread | None = None


class RefitWorker:
    """Owns the per-device calibrators and the worker threads."""

    def __init__(
        self,
        store: Storage,
        factory: CalibratorFactory,
        metrics: Metrics,
        *,
        threads: int = 1,
        max_batches_per_cycle: int = 256,
        time_reset_gap_s: float = 60.0,
        reorder_window_s: float = 10.0,
        min_cycle_interval_s: float = 0.0,
        checkpoint_samples: int = 0,
        checkpoint_patch_fraction: float = 0.25,
        cache_max_devices: int = 0,
        lease: "LeaseConfig | None" = None,
    ):
        self.store = store
        self.lease = lease  # shared database: work only on devices leased by this worker
        self.factory = factory
        self.metrics = metrics
        self.max_batches = max_batches_per_cycle
        self.time_reset_gap_s = time_reset_gap_s
        self._shards = [_Shard() for _ in range(threads)]
        # device -> ((processed_seq, state_rev) it stands at, calibrator), least recently used first
        self._cache: "OrderedDict[str, tuple[tuple[int | None, int | None], Calibrator]]" = OrderedDict()
        self._locks: dict[str, threading.Lock] = {}
        self._locks_guard = threading.Lock()
        self._stop = threading.Event()
        self._held: set[str] = set()  # devices waiting out the reorder window or the cycle interval
        self._held_lock = threading.Lock()
        # when each held device is looked at again: one thread for them all (a timer thread
        # per device would be a thread per insole with min_cycle_interval_s)
        self._wakes: list[tuple[float, str]] = []  # (monotonic s, device), a heap
        self._wake_cond = threading.Condition(self._held_lock)
        self._waker: threading.Thread | None = None
        self.reorder_window_s = reorder_window_s
        # a device fed everything it had is fed again at most this often (monotonic s of its last cycle)
        self.min_cycle_interval_s = min_cycle_interval_s
        self._last_cycle: dict[str, float] = {}
        self._failures: dict[str, int] = {}  # device -> cycles failed in a row (not storage faults)
        # the calibrator state is written (a checkpoint) once this many samples were fed
        # since the last one (0: every cycle); a restore replays the batches fed since
        self.checkpoint_samples = checkpoint_samples
        # a checkpoint is a patch against the base stored last while it is at most this
        # fraction of the base (0: always in full); the base of each cached device (what
        # the calibrator's ``checkpoint_patch`` needs) as this worker wrote or read it
        self.checkpoint_patch_fraction = checkpoint_patch_fraction
        self._bases: dict[str, Any] = {}
        # calibrators kept in memory (0: every device fed); the least recently used beyond
        # it is written as a checkpoint if it is ahead of one, then dropped
        self.cache_max_devices = cache_max_devices
        # devices whose cached calibrator is ahead of their checkpoint: (processed_seq, state_rev, feed_state)
        self._dirty: dict[str, tuple[int | None, int | None, dict[str, Any]]] = {}
        self.replays = 0
        self.busy = 0  # devices being processed right now
        self.cycles = 0
        self.conflicts = 0  # cycles dropped because another writer changed the device
        self._wanted: "OrderedDict[str, None]" = OrderedDict()  # ingested here: lease these first
        self._leasing = False  # the lease thread holds devices taken from _wanted, not yet queued
        self._lease_cond = threading.Condition()
        self._lease_thread: threading.Thread | None = None
        self._leased: set[str] = set()
        self._idle: dict[str, float] = {}  # leased devices fed everything they had: since (monotonic s)
        # devices a worker should hold: the fleet's leased and waiting devices per live worker
        self._share = lease.max_devices if lease is not None else 0
        self._waiting = 0  # devices with pending batches that no worker held (last heartbeat)
        self._workers = 1  # live refit workers (last heartbeat)

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        for i, shard in enumerate(self._shards):
            shard.thread = threading.Thread(target=self._loop, args=(shard,), name=f"selfcal-refit-{i}", daemon=True)
            shard.thread.start()
        if self.lease is not None:  # shared database: devices come from leases
            self._lease_thread = threading.Thread(target=self._lease_loop, name="selfcal-leases", daemon=True)
            self._lease_thread.start()
            return
        for device_id in self.store.pending_devices():  # resume after a restart
            self._enqueue(device_id)

    def stop(self) -> None:
        self._stop.set()
        with self._lease_cond:
            self._lease_cond.notify_all()
        with self._wake_cond:
            self._wake_cond.notify_all()
        if self._waker is not None:
            self._waker.join(timeout=30)
        for shard in self._shards:
            with shard.cond:
                shard.cond.notify_all()
        deadline = time.monotonic() + 60  # one wait for all the threads' current cycles, not 60 s each
        for shard in self._shards:
            if shard.thread is not None:
                shard.thread.join(timeout=max(0.0, deadline - time.monotonic()))
        if self._lease_thread is not None:
            self._lease_thread.join(timeout=30)
        # a restart then restores without a replay; with leases, only the devices still held
        # (the others were given up unwritten, and other workers may have fed them since)
        self.flush_checkpoints(only=None if self.lease is None else set(self._leased))
        if self.lease is not None:  # hand the devices over now rather than at lease expiry
            for device_id in list(self._leased):
                self._release(device_id, force=True)
            try:
                self.store.forget_worker(self.lease.owner)  # type: ignore[attr-defined]
            except Exception as exc:  # noqa: BLE001 - it ages out
                log.info("worker %s not unregistered (%s)", self.lease.owner, exc)

    def alive(self) -> int:
        return sum(1 for s in self._shards if s.thread is not None and s.thread.is_alive())

    def queue_depth(self) -> int:
        return sum(len(s.pending) for s in self._shards)

    def idle(self) -> bool:
        """Nothing this worker was given is left to do: no device waiting for its lease (or
        being leased), queued, in a cycle or held."""
        with self._lease_cond:  # read first: a device leased after this is queued before _leasing clears
            leasing = bool(self._wanted) or self._leasing
        return not leasing and self.queue_depth() == 0 and self.busy == 0 and not self._held

    def notify(self, device_id: str) -> None:
        """A device has new committed batches (cheap; called from the event loop)."""
        if self.lease is not None:  # lease it first (the lease thread), then work on it
            if self._lease_thread is None:  # an API-only process (--no-refit): workers elsewhere poll
                return
            with self._lease_cond:
                self._wanted[device_id] = None
                self._lease_cond.notify()
            return
        self._enqueue(device_id)

    def _enqueue(self, device_id: str) -> None:
        self._idle.pop(device_id, None)
        shard = self._shards[_shard(device_id, len(self._shards))]
        with shard.cond:
            if device_id not in shard.pending:
                shard.pending[device_id] = None
                shard.cond.notify()

    def device_lock(self, device_id: str) -> threading.Lock:
        with self._locks_guard:
            lock = self._locks.get(device_id)
            if lock is None:
                lock = self._locks[device_id] = threading.Lock()
            return lock

    # ------------------------------------------------------------ loop
    def _loop(self, shard: _Shard) -> None:
        backoff_s = 0.5
        while not self._stop.is_set():
            with shard.cond:
                while not shard.pending and not self._stop.is_set():
                    shard.cond.wait(timeout=1.0)
                if self._stop.is_set():
                    return
                device_id, _ = shard.pending.popitem(last=False)
                self.busy += 1
            failed_hold_s = None
            try:
                more = self.process(device_id)
                backoff_s = 0.5
                self._failures.pop(device_id, None)
            except ConflictError as exc:  # another writer changed the device (shared database)
                log.info("device %s: %s; cycle dropped", device_id, exc)
                self.conflicts += 1
                self.metrics.inc("selfcal_worker_conflicts_total")  # (_process dropped its calibrator)
                more = False
                if isinstance(exc, LeaseLost):  # not ours any more: no restore at its next batch
                    self._drop_lease(device_id)
                elif self.lease is None:  # the only writer of its batches: they are fed after a short hold
                    failed_hold_s = CONFLICT_HOLD_S
            except StorageUnavailable as exc:  # a storage fault: no traceback, wait it out
                if backoff_s == 0.5:
                    log.warning("refits paused: %s", exc)
                self.metrics.inc("selfcal_worker_errors_total")
                more = True
                self._stop.wait(backoff_s)
                backoff_s = min(5.0, 2 * backoff_s)
            except Exception:
                # this device's own fault (a corrupt checkpoint, a calibrator bug): it is
                # retried from the persisted state after a hold that doubles with each failure
                # in a row, while the thread goes on with the other devices (it slept 0.5 s
                # per failure: a few such devices starved their shard)
                failed_hold_s = self._failed(device_id)
                more = False
            finally:
                with shard.cond:
                    self.busy -= 1
            if failed_hold_s is not None:
                if self.lease is None or device_id in self._leased:  # (kept leased while it waits)
                    self._hold(device_id, failed_hold_s)
                continue
            if self.lease is None:
                if more:
                    self._enqueue(device_id)
            elif device_id not in self._leased:
                pass  # given up meanwhile
            elif more:
                if len(self._leased) > min(self._share, self.lease.max_devices):
                    self._release(device_id, force=True)  # more than its share: another worker takes it
                else:
                    self._enqueue(device_id)
            else:
                with self._held_lock:
                    held = device_id in self._held
                if held:
                    pass  # its hold timer looks at it again
                elif len(self._leased) > self._keep_cap():
                    # the room is needed: given up at once, and not written (the workers are
                    # behind). The leases' affinity gives it back to this worker, whose
                    # calibrator is in memory; another worker restores it (checkpoint + replay)
                    self._release(device_id, force=True, checkpoint=False)
                else:  # kept for its next batch; the lease thread gives it up when idle
                    self._idle[device_id] = time.monotonic()

    def _failed(self, device_id: str) -> float:
        """Count a failed cycle of a device; the hold (s) before its retry: 0.5 s doubled with
        each failure in a row, at most :data:`FAILURE_HOLD_MAX_S`. The traceback is logged at
        the first failure and then at every power of two (not at every retry)."""
        k = self._failures.get(device_id, 0) + 1
        self._failures[device_id] = k
        self.metrics.inc("selfcal_worker_errors_total")
        hold_s = min(FAILURE_HOLD_MAX_S, 0.5 * 2.0 ** (k - 1))
        if k & (k - 1) == 0:
            log.exception("refit cycle failed for device %s (%d in a row); retried in %g s", device_id, k, hold_s)
        else:
            log.warning("refit cycle failed for device %s (%d in a row); retried in %g s", device_id, k, hold_s)
        return hold_s

    def _keep(self, device_id: str, key: tuple[int | None, int | None], cal: Calibrator) -> None:
        """Cache a device's calibrator; beyond ``cache_max_devices`` the least recently used
        other devices are written as checkpoints (if ahead) and dropped."""
        self._cache[device_id] = (key, cal)
        self._cache.move_to_end(device_id)
        # (not bounded by default, with leases too: a worker behind its fleet takes every
        # device in turn, and a bound below the fleet would restore and replay at each turn)
        cap = self.cache_max_devices
        if cap <= 0:
            return
        for other in list(self._cache)[: max(0, len(self._cache) - cap)]:
            if other == device_id:
                continue
            lock = self.device_lock(other)
            if not lock.acquire(blocking=False):  # in a cycle on another thread: later
                continue
            try:
                self._checkpoint_now(other)
                self._forget(other)
                self.metrics.inc("selfcal_worker_evictions_total")
            finally:
                lock.release()

    def _forget(self, device_id: str) -> None:
        """Drop the cached calibrator: the next cycle restores it from the store."""
        self._cache.pop(device_id, None)
        self._dirty.pop(device_id, None)
        self._bases.pop(device_id, None)

    def _calibrator(self, rec: DeviceRecord) -> Calibrator:
        cached = self._cache.get(rec.device_id)
        if cached is not None and cached[0] == (rec.processed_seq, rec.state_rev):
            self._cache.move_to_end(rec.device_id)
            return cached[1]
        cal = self._restore(rec)
        # cached at once: a cycle that feeds it and then fails drops it (``_forget``)
        self._keep(rec.device_id, (rec.processed_seq, rec.state_rev), cal)
        return cal

    def _restore(self, rec: DeviceRecord) -> Calibrator:
        """The device's calibrator as of ``rec.processed_seq``: its checkpoint (or a fresh
        one), then the batches fed after the checkpoint fed again in seq order, up to
        ``max_batches`` a call. The calibrator gives the same state, bit for bit, however
        its samples are split into calls (tests/test_calibrator.py: the detector's windows
        do not depend on the chunks, and the pose store adds a cell's windows to it in
        order and appends new cells in the order they came), so the replay reproduces the
        state the last cycle had; its refit events were published then and are dropped
        now."""
        self._forget(rec.device_id)
        full = self.store.load_device(rec.device_id, with_state=True)
        if full is None or full.processed_seq != rec.processed_seq or full.state_rev != rec.state_rev:
            raise ConflictError(f"device {rec.device_id}: changed while its calibrator was restored")
        ckpt = full.checkpoint
        if ckpt is not None and full.calibrator_state:
            cal, base = self.factory.restore_checkpoint(full.calibrator_state, full.calibrator_patch)
            # patched later only if the row's tag is this base's (a row of an older schema has none)
            if base is not None and full.calibrator_base_tag == _tag_of(base):
                self._bases[rec.device_id] = base
        elif ckpt is not None and full.calibrator_patch is not None:
            raise ValueError(f"device {rec.device_id}: its checkpoint is a patch with no base")
        else:
            cal = self.factory.create()
        if rec.processed_seq is None or (ckpt is not None and ckpt.seq == rec.processed_seq):
            return cal  # nothing fed since the checkpoint
        feed = dict(ckpt.feed_state) if ckpt is not None else {}
        after = ckpt.seq if ckpt is not None else None
        samples = 0
        while True:
            rows = self.store.fed_batches(rec.device_id, after, rec.processed_seq, self.max_batches)
            if not rows:
                break
            _, n = self._feed(cal, [(r.seq, decode_binary(r.payload)) for r in rows], feed, rec, replay=True)
            samples += n
            after = rows[-1].seq
        if feed.get("last_t_s") != rec.feed_state.get("last_t_s"):
            log.warning("device %s: the replay ends at t = %s s, the last cycle at %s s", rec.device_id,
                        feed.get("last_t_s"), rec.feed_state.get("last_t_s"))
        self.replays += 1
        self.metrics.inc("selfcal_worker_replays_total")
        self.metrics.inc("selfcal_worker_replayed_samples_total", samples)
        return cal

    def _samples_since_checkpoint(self, rec: DeviceRecord, feed: dict[str, Any]) -> int:
        base = rec.checkpoint.feed_state.get("samples", 0) if rec.checkpoint is not None else 0
        return int(feed.get("samples", 0)) - int(base or 0)

    def flush_checkpoints(self, lock_timeout_s: float = 5.0, only: set[str] | None = None) -> int:
        """Write the cached calibrators that are ahead of their checkpoint (at a stop), of
        the devices in ``only`` if given; returns how many were written. A device whose
        cycle still runs is left to a replay."""
        written = 0
        for device_id in list(self._dirty):
            if only is not None and device_id not in only:
                continue
            lock = self.device_lock(device_id)
            if lock.acquire(timeout=lock_timeout_s):
                try:
                    written += self._checkpoint_now(device_id)
                finally:
                    lock.release()
        return written

    def _checkpoint_texts(self, device_id: str, cal: Calibrator) -> tuple[str | None, str | None, Any]:
        """A checkpoint of ``cal``: (full state or None, patch or None, the base once it is
        written). A patch against this worker's base of the device while it is at most
        ``checkpoint_patch_fraction`` of it; else the full state, the next base. The store
        writes a patch only onto its base (its tag), so a base another writer replaced
        makes the write a conflict, never a patch on the wrong base."""
        base = self._bases.get(device_id)
        if base is not None and self.checkpoint_patch_fraction > 0 and hasattr(cal, "checkpoint_patch"):
            patch = cal.checkpoint_patch(base)
            if len(patch) <= self.checkpoint_patch_fraction * base.n_bytes:
                return None, patch, base
        full = cal.to_json()
        return full, None, (cal.checkpoint_base(full) if hasattr(cal, "checkpoint_base") else None)

    def _based(self, device_id: str, state: str | None, patch: str | None, base: Any) -> None:
        """The checkpoint (full ``state`` or ``patch``) just committed for a device stands on
        ``base`` (None: unknown); counted."""
        if base is None:
            self._bases.pop(device_id, None)
        else:
            self._bases[device_id] = base
        if patch is not None:
            self.metrics.inc("selfcal_worker_checkpoint_patches_total")
        self.metrics.inc("selfcal_worker_checkpoint_bytes_total", len(patch if patch is not None else state or ""))

    def _checkpoint_now(self, device_id: str) -> bool:
        """Write the cached calibrator of a device (the caller holds its lock) if it is
        ahead of the checkpoint, and nothing was committed for the device since it was
        cached (the store checks the seq and, on PostgreSQL, the state revision)."""
        dirty = self._dirty.pop(device_id, None)
        cached = self._cache.get(device_id)
        if dirty is None or cached is None or cached[0] != (dirty[0], dirty[1]):
            return False
        try:
            state, patch, base = self._checkpoint_texts(device_id, cached[1])
            written = self.store.write_checkpoint(
                device_id, dirty[0], state, dirty[2], state_rev=dirty[1], patch=patch,
                patch_base=None if patch is None else _tag_of(base))
        except Exception as exc:  # noqa: BLE001 - the next restore replays instead
            log.warning("device %s: checkpoint not written (%s); a restore replays", device_id, exc)
            self._bases.pop(device_id, None)  # (it may have been written: the next one is in full)
            return False
        if written:
            self._based(device_id, state, patch, base)
        else:  # a newer cycle, or another writer's base: the next checkpoint is in full
            self._bases.pop(device_id, None)
        return written

    def _plan(self, rec: DeviceRecord, rows: list[PendingBatch], now: float):
        """Split pending batches into (to feed now in seq order, rejected late, held).

        The ordering contract: a device's batches are fed in seq order. A batch whose
        predecessor (seq - 1) has not arrived is held for up to ``reorder_window_s``
        (from the time the oldest held batch was stored); then the held batches are fed
        in seq order and the gap is given up. A batch that arrives after a later seq was
        fed is rejected as ``late`` (counted and reported with its reason, never lost
        silently). A new device's first batch is fed at once if its seq is 0. Batches
        the calibrator refused count as handled (``feed_state['handled_seq']``), so they
        leave no gap behind them.
        """
        handled = [q for q in (rec.processed_seq, rec.feed_state.get("handled_seq")) if q is not None]
        top = max(handled, default=None)
        late = [r for r in rows if top is not None and r.seq < top]
        fresh = [r for r in rows if top is None or r.seq > top]
        take: list[PendingBatch] = []
        expected = 0 if top is None else top + 1
        for i, r in enumerate(fresh):
            if r.seq == expected:
                take.append(r)
                expected += 1
                continue
            rest = fresh[i:]
            oldest = min(x.received_at for x in rest)
            if now - oldest >= self.reorder_window_s:
                take.extend(rest)  # give the gap up: later arrivals in it will be late
                return take, late, []
            return take, late, rest
        return take, late, []

    def process(self, device_id: str) -> bool:
        """One cycle for one device; returns True if batches remain."""
        token = device_id_var.set(device_id)  # the cycle's log lines carry the device
        try:
            return self._process(device_id)
        finally:
            device_id_var.reset(token)

    def _process(self, device_id: str) -> bool:
        with self.device_lock(device_id):
            try:
                return self._process_locked(device_id)
            except BaseException:
                # the cached calibrator may have been fed batches that were not committed:
                # dropped before any other thread can take the lock (and write or seed it)
                self._forget(device_id)
                raise

    def _process_locked(self, device_id: str) -> bool:
        if self.lease is not None and device_id not in self._leased:
            return False  # given up meanwhile (its share moved to another worker)
        if self.min_cycle_interval_s > 0:  # let batches gather: one commit for several
            last = self._last_cycle.get(device_id)
            wait = 0.0 if last is None else last + self.min_cycle_interval_s - time.monotonic()
            if wait > 0:
                self._hold(device_id, wait)
                return False
        rec, rows = self.store.load_cycle(device_id, self.max_batches)
        if rec is None or not rows:
            return False
        now = time.time()
        take, late, held = self._plan(rec, rows, now)
        if held:
            oldest = min(x.received_at for x in held)
            self._hold(device_id, max(0.05, oldest + self.reorder_window_s - now))
        if not take and not late:
            return False
        rejected = [(r.seq, r.n_samples, f"late: seq {r.seq} arrived after seq {rec.processed_seq} "
                     f"was fed (reorder window {self.reorder_window_s:g} s)") for r in late]
        cal = self._calibrator(rec)
        feed = dict(rec.feed_state)
        batches = [(r.seq, decode_binary(r.payload)) for r in take]
        try:
            events, samples = self._feed(cal, batches, feed, rec)
            fed = [q for q, _ in batches]
        except Exception:
            log.warning("device %s: calibrator raised; feeding batch by batch", device_id, exc_info=True)
            cal = self._restore(rec)
            feed = dict(rec.feed_state)
            events, samples, cal, fed, refused = self._feed_isolating(cal, batches, feed, rec)
            rejected += refused
        if take:
            feed["handled_seq"] = max(take[-1].seq, int(feed.get("handled_seq", -1)))
        versions = self._versions(cal, events, feed)
        last_refit = jsonable(getattr(cal, "last_refit", None))
        more = len(rows) >= self.max_batches
        checkpoint = self.checkpoint_samples <= 0 or \
            self._samples_since_checkpoint(rec, feed) >= self.checkpoint_samples
        state, patch, base = self._checkpoint_texts(device_id, cal) if checkpoint else (None, None, None)
        progress = Progress(
            device_id=device_id,
            expected_processed_seq=rec.processed_seq,
            processed_seq=max(fed, default=rec.processed_seq),  # fed seqs are all above it
            samples_added=samples,
            calibrator_state=state,
            calibrator_patch=patch,
            calibrator_patch_base=None if patch is None else _tag_of(base),
            calibrator_status=str(cal.status),
            last_refit=last_refit,
            feed_state=feed,
            new_versions=versions,
            fed_seqs=fed,
            rejected=rejected,
            refusals=refusals_of(events, rejected),
            expected_state_rev=rec.state_rev,
            lease_owner=self.lease.owner if self.lease is not None else None,
        )
        self.store.commit_progress(progress).result()  # durable before caching
        rev = None if rec.state_rev is None else rec.state_rev + 1
        self._keep(device_id, (progress.processed_seq, rev), cal)
        if checkpoint:
            self._dirty.pop(device_id, None)
            self._based(device_id, state, patch, base)
            self.metrics.inc("selfcal_worker_checkpoints_total")
        else:
            self._dirty[device_id] = (progress.processed_seq, rev, feed)
        self.cycles += 1
        if more:
            self._last_cycle.pop(device_id, None)  # a backlog is worked off without waiting
        else:
            self._last_cycle[device_id] = time.monotonic()
        self.metrics.inc("selfcal_worker_samples_total", samples)
        self.metrics.inc("selfcal_worker_cycles_total")
        for _, n, reason in rejected:
            kind = reason.split(":", 1)[0]
            self.metrics.inc("selfcal_rejected_batches_total", reason=kind)
            self.metrics.inc("selfcal_rejected_samples_total", n, reason=kind)
        for ev in events:
            outcome = "published" if ev.get("published") else str(ev.get("reason") or "unknown")
            self.metrics.inc("selfcal_refits_total", outcome=outcome)
        return more

    def _hold(self, device_id: str, delay_s: float) -> None:
        """Look at a device again after ``delay_s`` (batches held for the reorder window,
        or a device fed less than ``min_cycle_interval_s`` ago)."""
        with self._wake_cond:
            if device_id in self._held or self._stop.is_set():
                return
            self._held.add(device_id)
            heapq.heappush(self._wakes, (time.monotonic() + delay_s, device_id))
            if self._waker is None or not self._waker.is_alive():
                self._waker = threading.Thread(target=self._wake_loop, name="selfcal-holds", daemon=True)
                self._waker.start()
            elif self._wakes[0][1] == device_id:  # sooner than the waker's current wait
                self._wake_cond.notify()

    def _wake_loop(self) -> None:
        """Enqueue each held device when its time comes (the thread :meth:`_hold` starts)."""
        while True:
            with self._wake_cond:
                while not self._stop.is_set():
                    now = time.monotonic()
                    if self._wakes and self._wakes[0][0] <= now:
                        break
                    self._wake_cond.wait(timeout=min(self._wakes[0][0] - now, 1.0) if self._wakes else 1.0)
                if self._stop.is_set():  # nothing comes back after stop: nothing is held
                    self._held.clear()
                    self._wakes.clear()
                    return
                due = []
                while self._wakes and self._wakes[0][0] <= now:
                    due.append(heapq.heappop(self._wakes)[1])
                self._held.difference_update(due)
            for device_id in due:
                try:
                    self._enqueue(device_id)
                except Exception:  # noqa: BLE001 - one device's failure must not stop every device's wakes
                    log.exception("device %s: not enqueued after its hold", device_id)

    # ------------------------------------------------------------ feeding
    def _prepare(self, batch: Batch, seq: int, feed: dict[str, Any], count: bool = True,
                 fed_offsets: dict[int, float] | None = None, checkpoint_seq: int | None = None) -> np.ndarray:
        """Device time -> fed time: a clock going backwards (reboot) adds a gap, never a reversal.

        The offset a reset gives is kept in the feed state (``reset_offsets``: the resets
        after the device's checkpoint ``checkpoint_seq``, at most ``RESET_OFFSETS_KEPT``): a
        replay after the checkpoint (``fed_offsets``, from the device's latest feed state)
        feeds the batch at the time it was first fed, even if ``time_reset_gap_s`` changed
        since."""
        offset = float(feed.get("t_offset_s", 0.0))
        last = feed.get("last_t_s")
        t = batch.t_s + offset
        if last is not None and t[0] < last:
            first = (fed_offsets or {}).get(int(seq))
            if first is not None and batch.t_s[0] + first >= last:
                offset = first
            else:
                offset += (last - t[0]) + self.time_reset_gap_s
            t = batch.t_s + offset
            feed["clock_resets"] = int(feed.get("clock_resets", 0)) + 1
            kept = [r for r in feed.get("reset_offsets", [])
                    if int(r[0]) != int(seq) and (checkpoint_seq is None or int(r[0]) > checkpoint_seq)]
            feed["reset_offsets"] = (kept + [[int(seq), float(offset)]])[-RESET_OFFSETS_KEPT:]
            if count:
                self.metrics.inc("selfcal_clock_resets_total")
        feed["t_offset_s"] = offset
        return t

    def _account(self, batch: Batch, t: np.ndarray, seq: int, feed: dict[str, Any]) -> None:
        feed["last_t_s"] = float(t[-1])
        feed.setdefault("first_t_s", float(t[0]))
        feed.setdefault("first_seq", int(seq))
        feed["last_seq"] = int(seq)
        feed["samples"] = int(feed.get("samples", 0)) + batch.n
        if batch.temp_c is not None:
            lo, hi = float(batch.temp_c.min()), float(batch.temp_c.max())
            feed["temp_min_c"] = min(lo, feed.get("temp_min_c", lo))
            feed["temp_max_c"] = max(hi, feed.get("temp_max_c", hi))

    def _feed(self, cal: Calibrator, batches: list[tuple[int, Batch]], feed: dict[str, Any], rec,
              replay: bool = False) -> tuple[list, int]:
        """Feed runs of consecutive batches with the same columns in one call each
        (``replay``: batches fed before, after a checkpoint; the clock resets are not counted again)."""
        events: list[dict[str, Any]] = []
        samples = 0
        run: list[tuple[np.ndarray, Batch]] = []

        def shape(b: Batch) -> tuple[bool, int]:
            return (b.temp_c is not None, 0 if b.pressure_kpa is None else b.pressure_kpa.shape[1])

        def flush() -> None:
            if not run:
                return
            t = np.concatenate([r[0] for r in run])
            acc = np.concatenate([r[1].acc_g for r in run])
            temp = None if run[0][1].temp_c is None else np.concatenate([r[1].temp_c for r in run])
            pres = None if run[0][1].pressure_kpa is None else np.concatenate([r[1].pressure_kpa for r in run])
            out = cal.feed_samples(t, acc, temp_c=temp, pressure_kpa=pres)
            events.extend(self._stamp(out, feed))
            run.clear()

        fed_offsets = None
        if replay and rec is not None:  # the offsets the resets gave when these batches were first fed
            fed_offsets = {int(q): float(o) for q, o in (rec.feed_state or {}).get("reset_offsets", [])}
        checkpoint_seq = rec.checkpoint.seq if rec is not None and rec.checkpoint is not None else None
        for seq, batch in batches:
            if run and shape(run[-1][1]) != shape(batch):
                flush()
            t = self._prepare(batch, seq, feed, count=not replay, fed_offsets=fed_offsets,
                              checkpoint_seq=checkpoint_seq)
            self._account(batch, t, seq, feed)
            run.append((t, batch))
            samples += batch.n
        flush()
        return events, samples

    def _stamp(self, events: list[dict[str, Any]] | None, feed: dict[str, Any]) -> list[dict[str, Any]]:
        """Attach the feed bookkeeping at the time of each refit (for provenance)."""
        out = []
        for ev in events or []:
            ev = dict(ev)
            ev["_feed"] = {k: feed.get(k) for k in ("first_t_s", "first_seq", "last_seq", "samples", "temp_min_c", "temp_max_c")}
            out.append(ev)
        return out

    def _feed_isolating(self, cal: Calibrator, batches, feed, rec):
        """Slow path: feed one batch at a time; a batch the calibrator refuses is rejected.

        Returns (events, samples fed, calibrator, fed seqs, [(seq, n, reason)] rejected).
        """
        events: list[dict[str, Any]] = []
        samples = 0
        fed: list[int] = []
        refused: list[tuple[int, int, str]] = []
        for seq, batch in batches:
            snapshot, feed_before = cal.to_json(), dict(feed)
            try:
                ev, n = self._feed(cal, [(seq, batch)], feed, rec)
            except Exception as exc:
                cal = self.factory.restore(snapshot)
                feed.clear()
                feed.update(feed_before)
                refused.append((int(seq), batch.n, f"calibrator: {type(exc).__name__}: {exc}"[:300]))
                continue
            events.extend(ev)
            samples += n
            fed.append(int(seq))
        return events, samples, cal, fed, refused

    def _versions(self, cal: Calibrator, events: list[dict[str, Any]], feed: dict[str, Any]) -> list[NewVersion]:
        published = [ev for ev in events if ev.get("published")]
        out = []
        for i, ev in enumerate(published):
            calib = ev.get("calibration")
            if calib is None and i == len(published) - 1:
                calib = cal.calibration()
            if calib is None:
                continue
            calib = jsonable(calib)
            calibrator_version = calib.pop("version", None)  # the service numbers versions
            status = calib.get("status")
            if status not in ("provisional", "calibrated"):
                status = str(cal.status) if i == len(published) - 1 else "provisional"
                if status == "uncalibrated":
                    status = "provisional"
            f = ev.get("_feed", {})
            prov: dict[str, Any] = {
                "n_poses": calib.get("n_poses"),
                "coverage": calib.get("coverage"),
                "temp_range_c": (
                    [f["temp_min_c"], f["temp_max_c"]] if f.get("temp_min_c") is not None else None
                ),
                "time_span_s": [f.get("first_t_s"), jsonable(ev.get("t_s"))],
                "seq_range": [f.get("first_seq"), f.get("last_seq")],
                "samples": f.get("samples"),
                "refit": {k: jsonable(v) for k, v in ev.items() if k not in ("calibration", "_feed")},
            }
            if isinstance(calib.get("provenance"), dict):
                prov["poses"] = calib["provenance"]
                prov["coverage"] = prov["coverage"] or calib["provenance"].get("cube_coverage")
            prov["calibrator_version"] = calibrator_version
            out.append(NewVersion(status=status, source="refit", calibration=calib, provenance=jsonable(prov)))
        return out

    # ------------------------------------------------------------ leases (shared database)
    def _lease_loop(self) -> None:
        """Lease devices with pending batches (ingested here first), renew what we hold."""
        lease = self.lease
        assert lease is not None
        last_renew = 0.0
        deferred: list[str] = []  # ingested here, not leased for want of room: preferred next time
        while not self._stop.is_set():
            with self._lease_cond:
                if not self._wanted:
                    self._lease_cond.wait(timeout=lease.poll_s)
                wanted = list(dict.fromkeys([*deferred, *self._wanted]))
                self._leasing = bool(self._wanted)  # (deferred ones wait for room: not counted)
                self._wanted.clear()
            try:
                if self._stop.is_set():
                    return
                try:
                    now = time.monotonic()
                    if now - last_renew >= lease.ttl_s / 3:
                        # the heartbeat renews every lease this worker holds
                        before = set(self._leased)
                        workers, leased, waiting = self.store.heartbeat(lease.owner, lease.ttl_s)  # type: ignore[attr-defined]
                        self._share = max(1, math.ceil((leased + waiting) / max(1, workers)))
                        self._waiting = waiting
                        self._workers = workers
                        last_renew = now
                        self._reconcile_leases(before, set(self.store.held_leases(lease.owner)))  # type: ignore[attr-defined]
                    room = min(lease.max_devices, self._share) - len(self._leased)
                    if room <= 0:
                        room = 0 if self._leased else 1  # (a worker holding nothing always takes one)
                    got = [] if room == 0 else self.store.acquire_leases(  # type: ignore[attr-defined]
                        lease.owner, lease.ttl_s, room, prefer=wanted, workers=self._workers)
                    # no room now: the devices ingested here stay preferred at the next pass
                    deferred = [d for d in wanted if d not in self._leased][-lease.max_devices:] if room == 0 else []
                except Exception as exc:  # noqa: BLE001 - storage down: wait and retry
                    log.warning("leases: %s", exc)
                    self._stop.wait(lease.poll_s)
                    continue
                for device_id in got:
                    self._leased.add(device_id)
                    self._enqueue(device_id)
                for device_id in wanted:  # new batches for a device we already hold: look again
                    if device_id in self._leased and device_id not in got:
                        self._enqueue(device_id)
                try:
                    self._keep_or_release_idle(lease)
                except Exception as exc:  # noqa: BLE001 - storage down: wait and retry
                    log.warning("leases: %s", exc)
                    self._stop.wait(lease.poll_s)
            finally:
                with self._lease_cond:
                    self._leasing = False  # what it leased is queued by now

    def _drop_lease(self, device_id: str) -> None:
        """Forget a lease the database no longer gives this worker (it lapsed, or went to
        another worker): not fed here again unless leased anew."""
        self._leased.discard(device_id)
        self._idle.pop(device_id, None)

    def _reconcile_leases(self, before: set[str], held: set[str]) -> None:
        """Make the leases this worker believes it holds those the database says it holds.

        ``before``: ``_leased`` just before the database was read; ``held``: the devices whose
        lease row names this worker. Only this (the lease) thread takes leases, so a device
        in ``held`` but in neither ``before`` nor ``_leased`` was leased by a statement whose
        reply was lost (a connection that broke after the commit, or a read retried on a new
        connection): renewed by every heartbeat, it was held for ever and fed by no one. It
        is released (this worker may take it again by affinity). A device in ``before`` and
        still in ``_leased`` but not in ``held`` was taken by another worker after this one's
        lease lapsed: forgotten (a refit thread may be releasing it right now; forgetting it
        twice is harmless)."""
        owner = self.lease.owner  # type: ignore[union-attr]
        for device_id in held - before - self._leased:
            log.warning("device %s: leased in the database but unknown to this worker; released", device_id)
            self.metrics.inc("selfcal_worker_lease_repairs_total", kind="orphan")
            try:
                self.store.release_lease(owner, device_id)  # type: ignore[attr-defined]
            except Exception as exc:  # noqa: BLE001 - the next heartbeat tries again
                log.info("device %s: orphan lease not released (%s)", device_id, exc)
        for device_id in (before & self._leased) - held:
            log.info("device %s: lease lost to another worker; forgotten", device_id)
            self.metrics.inc("selfcal_worker_lease_repairs_total", kind="lost")
            self._drop_lease(device_id)

    def _keep_cap(self) -> int:
        """Devices this worker may keep leased between batches: its share of the fleet's
        active devices, less a slack of an eighth of ``max_devices`` for devices waiting;
        none while more devices than that wait for a worker (the fleet outgrew the
        workers' leases: each device is given up once fed, as a fair queue)."""
        lease = self.lease
        assert lease is not None
        slack = max(1, lease.max_devices // 8)
        if self._waiting > slack:  # devices wait for a worker: none is kept idle (the workers are behind)
            return 0
        return min(self._share, lease.max_devices - slack)

    def _keep_or_release_idle(self, lease: "LeaseConfig") -> None:
        """Feed held devices that got batches through another process; give up the leases
        of devices idle for ``idle_s``, or the longest idle when the room is needed."""
        if self._idle:
            for device_id in self.store.leased_with_pending(lease.owner):  # type: ignore[attr-defined]
                if device_id in self._idle:
                    self._enqueue(device_id)
        now = time.monotonic()
        idle = sorted(self._idle.items(), key=lambda kv: kv[1])
        # beyond the share of the fleet's active devices per live worker, or when the room
        # is needed, idle devices go first: other workers take them with their next batch.
        # A pass stops after a sixth of the lease time (checkpoint writes can be slow), so
        # that the renewals are never late
        spare = len(self._leased) - self._keep_cap()
        for device_id, since in idle:
            if time.monotonic() - now > lease.ttl_s / 6:
                break
            if spare > 0 or now - since >= lease.idle_s:
                if self._release(device_id, wait=False):
                    spare -= 1

    def _release(self, device_id: str, force: bool = False, checkpoint: bool = True, wait: bool = True) -> bool:
        """Give a lease up (``force``: whether idle or not) unless the device has work
        again; with ``checkpoint`` its calibrator is written first if it is ahead of its
        checkpoint. The cached calibrator stays: it is used again if this worker is the
        next to take the device (the state revision tells)."""
        lock = self.device_lock(device_id)
        if not lock.acquire(blocking=wait):
            return False  # in a cycle (or an admin write) right now: looked at again later
        try:
            was_idle = self._idle.pop(device_id, None) is not None
            if not force and not was_idle:
                return False  # enqueued again meanwhile
            if checkpoint:
                self._checkpoint_now(device_id)  # the next holder restores it without a replay
            try:
                self.store.release_lease(self.lease.owner, device_id)  # type: ignore[union-attr, attr-defined]
            except Exception as exc:  # noqa: BLE001
                if not self._stop.is_set():  # still renewed: kept, and given up at a later pass
                    log.info("device %s: lease not released (%s); tried again", device_id, exc)
                    self._idle[device_id] = 0.0
                    return False
                log.info("device %s: lease not released (%s); it expires", device_id, exc)
            self._leased.discard(device_id)
            return True
        finally:
            lock.release()

    # ------------------------------------------------------------ admin
    def publish_admin(
        self, device_id: str, version: NewVersion, seed: dict[str, Any] | None = None, timeout_s: float = 30.0
    ) -> int:
        """Seed/rollback: append a served version under the device lock (no refit races).

        ``seed`` (``{"params", "std", "matrix", "offset"}``) is installed in the
        calibrator with ``seed_calibration`` when the calibrator has it, so later refits
        use it as their prior; the calibrator state and the version are written in one
        transaction. A factory seed is then served as the calibrator describes it.
        """
        for attempt in range(5):  # on a shared database a worker elsewhere may commit first
            try:
                return self._publish_admin_once(device_id, version, seed, timeout_s)
            except ConflictError:  # (the calibrator was dropped under the device lock)
                if attempt == 4:
                    raise
                time.sleep(0.05 * (attempt + 1))
        raise AssertionError("unreachable")  # pragma: no cover

    def _publish_admin_once(
        self, device_id: str, version: NewVersion, seed: dict[str, Any] | None, timeout_s: float
    ) -> int:
        with self.device_lock(device_id):
            try:
                return self._publish_admin_locked(device_id, version, seed, timeout_s)
            except BaseException:
                self._forget(device_id)  # the seed may be in the cached calibrator, uncommitted
                raise

    def _publish_admin_locked(
        self, device_id: str, version: NewVersion, seed: dict[str, Any] | None, timeout_s: float
    ) -> int:
        rec = self.store.load_device(device_id, with_state=False)
        expected = rec.processed_seq if rec else None
        cal: Calibrator | None = None
        if seed is not None and hasattr(self.factory.cls, "seed_calibration"):
            cal = self._calibrator(rec) if rec else self.factory.create()
            params = seed.get("params")
            std = {k: v for k, v in (seed.get("std") or {}).items() if v is not None}
            if seed.get("model") not in (None, cal.model.name):
                # a version published under another model (the calibrator switched since, e.g. it
                # dropped an effect): its parameters do not fit this model, its correction does;
                # the calibrator's prior is then its linear part (the version is served as it was)
                params, std = None, {}
            if not params:
                theta = cal.model.from_linear(np.asarray(seed["matrix"]), np.asarray(seed["offset"]))
                params = cal.model.to_dict(theta)
            t_s = float((rec.feed_state.get("last_t_s") if rec else None) or 0.0)
            cal.seed_calibration(params, std or None, t_s=t_s)
            if version.source == "factory":
                calib = jsonable(cal.calibration())
                calib.pop("version", None)
                calib["source"] = "factory"
                status = str(cal.status) if cal.status != "uncalibrated" else "provisional"
                version = NewVersion(status, version.source, calib, version.provenance)
        # an admin write is rare: always a full state (a new base)
        state = cal.to_json() if cal is not None else None
        progress = Progress(
            device_id=device_id,
            expected_processed_seq=expected,
            processed_seq=expected,
            samples_added=0,
            calibrator_state=state,  # None: the checkpoint stays
            calibrator_status=str(cal.status) if cal is not None else (rec.calibrator_status if rec else None),
            last_refit=rec.last_refit if rec else None,
            feed_state=rec.feed_state if rec else {},
            new_versions=[version],
            expected_state_rev=rec.state_rev if rec else None,
        )
        numbers = self.store.commit_progress(progress).result(timeout=timeout_s)
        rev = rec.state_rev + 1 if rec is not None and rec.state_rev is not None else None
        if cal is not None:
            self._keep(device_id, (expected, rev), cal)
            self._dirty.pop(device_id, None)
            self._based(device_id, state, None, cal.checkpoint_base(state) if hasattr(cal, "checkpoint_base") else None)
        else:  # the calibrator did not change: what is cached stays valid
            cached = self._cache.get(device_id)
            if cached is not None and rec is not None and cached[0] == (expected, rec.state_rev):
                self._keep(device_id, (expected, rev), cached[1])
                dirty = self._dirty.get(device_id)
                if dirty is not None and (dirty[0], dirty[1]) == (expected, rec.state_rev):
                    # still ahead of its checkpoint, now at the new revision: written later
                    self._dirty[device_id] = (expected, rev, dirty[2])
        return numbers[-1]
