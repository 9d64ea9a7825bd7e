"""Checkpoint and replay: the calibrator state is written every ``checkpoint_samples``, and
a worker that restores a device (after a crash, on another host) feeds the batches fed
since the checkpoint again. The calibration it then publishes must be the one a worker
that never stopped publishes (runs on SQLite and on PostgreSQL)."""

from __future__ import annotations

import hashlib
import json
import time

import numpy as np
import pytest
from service_helpers import backend_db

N = 8000  # samples a batch
CKPT = 40_000  # a checkpoint every 5 batches


@pytest.fixture(scope="module")
def stream():
    """Hours 3.3 to 10 of a simulated 20-Hz insole's day (seeded), as 60 batches of 8 000
    samples (the calibrator's first versions come in these hours)."""
    from selfcal.config import load_config, section
    from selfcal.sim.config import SimConfig
    from selfcal.sim.simulator import Simulation

    cfg = load_config()
    sim = Simulation(SimConfig.from_section(section(cfg, "sim")), np.random.default_rng(11), days=0.45)
    ch = sim.samples()
    n, i0 = N, int(np.searchsorted(ch.t_s, 12_000.0))
    assert len(ch.t_s) >= i0 + 60 * n
    return cfg, [(k, *(x[i0 + k * n:i0 + (k + 1) * n] for x in (ch.t_s, ch.acc_g, ch.temp_c, ch.pressure_kpa)))
                 for k in range(60)]


def _open(db: str):
    from selfcal_service.main import open_store
    from selfcal_service.settings import load_settings

    store = open_store(load_settings({}, overrides={"db_path": db}, environ={}))
    store.open()
    return store


def _worker(store, cfg, checkpoint_samples: int, time_reset_gap_s: float = 60.0):
    from selfcal_service.metrics import Metrics
    from selfcal_service.settings import load_settings
    from selfcal_service.worker import CalibratorFactory, RefitWorker

    factory = CalibratorFactory(load_settings({}, environ={}).calibrator,
                                config={k: v for k, v in cfg.items() if k not in ("service", "gateway")})
    return RefitWorker(store, factory, Metrics(), max_batches_per_cycle=1, checkpoint_samples=checkpoint_samples,
                       time_reset_gap_s=time_reset_gap_s)


def _wait_for(pred, what: str, timeout_s: float = 30.0) -> None:
    """Wait until ``pred()`` holds (fail naming ``what`` after ``timeout_s``)."""
    t_end = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < t_end, what
        time.sleep(0.02)


def _ingest(store, batches, device: str = "ins") -> None:
    from selfcal_service.schemas import Batch

    for k, t, acc, temp, pres in batches:
        payload = Batch(seq=k, t_s=t, acc_g=acc, temp_c=temp, pressure_kpa=pres).to_bytes()
        store.submit_batch(device, k, len(t), payload, time.time(), hashlib.sha256(payload).digest(), 10**6).result()


def _drain(worker) -> int:
    cycles = 0
    while worker.process("ins"):
        cycles += 1
    return cycles + 1


def _fed(db_path, stream, n_batches: int):
    """A store with the first ``n_batches`` fed by a worker that writes no checkpoint yet:
    (store, worker, the device's record)."""
    cfg, batches = stream
    store = _open(backend_db(db_path))
    _ingest(store, batches[:n_batches])
    worker = _worker(store, cfg, checkpoint_samples=10**6)
    _drain(worker)
    rec = store.load_device("ins", with_state=False)
    assert rec.processed_seq == n_batches - 1 and rec.checkpoint is None  # nothing written yet
    return store, worker, rec


def _versions(store):
    return [(v.status, v.calibration, v.provenance.get("seq_range")) for v in store.history("ins")]


def _same_calibration(a, b) -> None:
    assert [(s, r) for s, _, r in a] == [(s, r) for s, _, r in b]
    for (_, ca, _), (_, cb, _) in zip(a, b):
        assert ca.keys() == cb.keys()
        pa, pb = ca["params"], cb["params"]
        assert pa.keys() == pb.keys()
        # bit for bit: the replay feeds the batches since the checkpoint in one call, and the
        # pose store's sums do not depend on how windows are split into calls
        assert pa == pb and ca["std"] == cb["std"]


def test_a_worker_that_restores_from_a_checkpoint_publishes_what_one_that_never_stopped_does(tmp_path, stream):
    cfg, batches = stream
    ref_store = _open(backend_db(tmp_path / "ref.db"))
    store = _open(backend_db(tmp_path / "ckpt.db"))
    try:
        _ingest(ref_store, batches)
        ref = _worker(ref_store, cfg, checkpoint_samples=0)  # the state written every cycle
        _drain(ref)
        ref_versions = _versions(ref_store)
        assert len(ref_versions) >= 2, "the stream must publish versions for the comparison to mean something"

        _ingest(store, batches[:37])
        first = _worker(store, cfg, checkpoint_samples=CKPT)
        cycles = _drain(first)
        rec = store.load_device("ins", with_state=False)
        assert rec.processed_seq == 36
        # one checkpoint every 5 cycles, and the last is behind
        assert first.metrics.get("selfcal_worker_checkpoints_total") == cycles // 5
        assert rec.checkpoint is not None and rec.checkpoint.seq < 36
        behind = 36 - rec.checkpoint.seq

        # the first worker is gone without a word (kill -9): a second one takes over
        _ingest(store, batches[37:])
        second = _worker(store, cfg, checkpoint_samples=CKPT)
        _drain(second)
        assert second.replays == 1
        assert second.metrics.get("selfcal_worker_replayed_samples_total") == behind * N
        _same_calibration(_versions(store), ref_versions)
        final = store.load_device("ins", with_state=False)
        assert final.processed_seq == 59 and final.samples_processed == 60 * N

        # a stop writes the cached state: the next restore needs no replay, and its
        # calibrator is the never-stopped one
        assert second.flush_checkpoints() == (1 if final.checkpoint.seq != 59 else 0)
        rec = store.load_device("ins", with_state=False)
        assert rec.checkpoint.seq == 59
        third = _worker(store, cfg, checkpoint_samples=CKPT)
        cal = third._calibrator(rec)
        assert third.replays == 0
        want = ref._calibrator(ref_store.load_device("ins", with_state=False)).calibration()
        got = cal.calibration()
        assert got["params"] == want["params"] and got["std"] == want["std"]
    finally:
        store.close()
        ref_store.close()


def test_a_checkpoint_is_not_written_over_a_newer_cycle(tmp_path, stream):
    """``write_checkpoint`` at a seq the device has moved past writes nothing (a slow
    worker must not put an old state over a newer one)."""
    store, worker, _ = _fed(tmp_path / "stale.db", stream, 3)
    try:
        assert not store.write_checkpoint("ins", 1, "{}", {})
        assert store.load_device("ins").checkpoint is None
        assert worker.flush_checkpoints() == 1
        rec = store.load_device("ins")
        assert rec.checkpoint.seq == 2 and rec.calibrator_state and rec.checkpoint.feed_state["samples"] == 3 * N
    finally:
        store.close()


@pytest.mark.skipif(__import__("service_helpers").backend() != "postgresql",
                    reason="PostgreSQL scale-out (runs in the SELFCAL_TEST_BACKEND=postgresql pass)")
def test_a_worker_keeps_an_idle_devices_lease_and_writes_its_checkpoint_when_it_gives_it_up(tmp_path, stream):
    """With leases (PostgreSQL), a device fed everything it had stays leased for
    ``idle_s``: batches stored by another process are found and fed by the same worker
    from its cached calibrator, no state written; when the lease is given up, the state
    is written as the checkpoint at the last fed seq."""
    from selfcal_service.metrics import Metrics
    from selfcal_service.pg_store import PostgresStore
    from selfcal_service.settings import load_settings
    from selfcal_service.worker import CalibratorFactory, LeaseConfig, RefitWorker

    cfg, batches = stream
    url = backend_db(tmp_path / "lease.db")
    api, db = PostgresStore(url), PostgresStore(url)  # an API process's store, the worker's
    api.open()
    db.open()
    factory = CalibratorFactory(load_settings({}, environ={}).calibrator,
                                config={k: v for k, v in cfg.items() if k not in ("service", "gateway")})
    worker = RefitWorker(db, factory, Metrics(), checkpoint_samples=10**6,
                         lease=LeaseConfig(owner="w1", ttl_s=5.0, poll_s=0.05, idle_s=1.5))

    try:
        worker.start()
        _ingest(api, batches[:1])
        _wait_for(lambda: api.load_device("ins", with_state=False).processed_seq == 0, "batch 0 fed")
        t_fed = time.monotonic()
        _ingest(api, batches[1:2])  # stored by another process: the worker is not told
        _wait_for(lambda: api.load_device("ins", with_state=False).processed_seq == 1, "batch 1 fed")
        if time.monotonic() - t_fed < 1.0:  # (a machine slower than that proves nothing here)
            assert api.lease_counts() == {"w1": 1}
            assert api.load_device("ins", with_state=False).checkpoint is None  # no state written yet
        _wait_for(lambda: api.lease_counts() == {}, "the idle lease given up")
        rec = api.load_device("ins")
        assert rec.checkpoint is not None and rec.checkpoint.seq == 1 and rec.checkpoint.feed_state["samples"] == 2 * N
        assert worker.cycles == 2 and worker.replays == 0
    finally:
        worker.stop()
        api.close()
        db.close()


@pytest.mark.skipif(__import__("service_helpers").backend() != "postgresql",
                    reason="PostgreSQL scale-out (runs in the SELFCAL_TEST_BACKEND=postgresql pass)")
def test_a_worker_repairs_leases_it_does_not_know_of_or_has_lost(tmp_path, stream):
    """Orphan: a lease committed in the database whose reply the worker never got (a
    connection that broke after the commit) was renewed by every heartbeat and fed by no
    one. Lost: a lease that lapsed and went to another worker stayed in the worker's set,
    and each batch then cost a restore and a refused commit. The heartbeat now reconciles
    both with the database."""
    import threading

    from selfcal_service.metrics import Metrics
    from selfcal_service.pg_store import PostgresStore
    from selfcal_service.settings import load_settings
    from selfcal_service.worker import CalibratorFactory, LeaseConfig, RefitWorker

    cfg, batches = stream
    url = backend_db(tmp_path / "repair.db")
    api, db = PostgresStore(url), PostgresStore(url)
    api.open()
    db.open()
    factory = CalibratorFactory(load_settings({}, environ={}).calibrator,
                                config={k: v for k, v in cfg.items() if k not in ("service", "gateway")})
    worker = RefitWorker(db, factory, Metrics(), lease=LeaseConfig(owner="w1", ttl_s=1.5, poll_s=0.05, idle_s=30.0))

    try:
        _ingest(api, batches[:1])  # stored; the worker is not told (another API process)
        assert api.acquire_leases("w1", 1.5, 10) == ["ins"]  # committed, its reply "lost"
        worker.start()
        _wait_for(lambda: api.load_device("ins", with_state=False).processed_seq == 0, "the orphan fed")
        assert worker.metrics.get("selfcal_worker_lease_repairs_total", kind="orphan") == 1
        assert "ins" in worker._leased  # released by the repair, then leased again by affinity
        # lost: the lease moves to another worker behind this one's back
        api._read("UPDATE devices SET lease_owner = 'w2', lease_expires = 1e12 WHERE device_id = 'ins' "
                  "RETURNING 1")
        _wait_for(lambda: "ins" not in worker._leased, "the lost lease forgotten")
        assert worker.metrics.get("selfcal_worker_lease_repairs_total", kind="lost") == 1
        _ingest(api, batches[1:2])
        worker.notify("ins")  # w2's device: not leased, not fed, no restore
        time.sleep(1.0)
        assert api.load_device("ins", with_state=False).processed_seq == 0 and worker.replays == 0
        # a refit thread whose commit is refused for a lost lease (LeaseLost: the one-round-trip
        # commit tells it apart from a changed device) forgets the device at once (a worker
        # without a lease thread here: no heartbeat repairs it first)
        w3 = RefitWorker(db, factory, Metrics(), lease=LeaseConfig(owner="w3", ttl_s=1.5, poll_s=0.05))
        w3._leased.add("ins")
        w3._enqueue("ins")
        shard = w3._shards[0]
        refit = threading.Thread(target=w3._loop, args=(shard,), daemon=True)
        refit.start()
        _wait_for(lambda: w3.conflicts == 1 and w3.busy == 0, "w3's cycle refused")
        w3._stop.set()
        with shard.cond:
            shard.cond.notify_all()
        refit.join(10)
        assert "ins" not in w3._leased and "ins" not in w3._idle and shard.pending == {}
    finally:
        worker.stop()
        api.close()
        db.close()


def test_a_bounded_cache_writes_the_calibrators_it_drops_and_restores_them_the_same(tmp_path, stream):
    """With ``cache_max_devices`` = 1 and two devices fed in turn, each cycle drops the
    other device's calibrator (written first, as it is ahead of its checkpoint) and
    restores its own: the versions are those of an unbounded worker."""
    cfg, batches = stream
    ref_store, store = _open(backend_db(tmp_path / "ref2.db")), _open(backend_db(tmp_path / "lru.db"))
    try:
        for st in (ref_store, store):
            _ingest(st, batches)
            _ingest(st, batches, device="other")
        ref = _worker(ref_store, cfg, checkpoint_samples=CKPT)
        lru = _worker(store, cfg, checkpoint_samples=CKPT)
        lru.cache_max_devices = 1
        for w in (ref, lru):
            for _ in range(60):
                w.process("ins")
                w.process("other")
        assert len(lru._cache) == 1 and lru.metrics.get("selfcal_worker_evictions_total") >= 118
        assert lru.replays == 0  # every dropped calibrator was written at its last seq: nothing to replay
        for dev in ("ins", "other"):
            assert store.load_device(dev, with_state=False).processed_seq == 59
            _same_calibration([(v.status, v.calibration, v.provenance.get("seq_range")) for v in store.history(dev)],
                              [(v.status, v.calibration, v.provenance.get("seq_range")) for v in ref_store.history(dev)])
        assert len(ref_store.history("ins")) >= 2
    finally:
        store.close()
        ref_store.close()


def test_a_cycle_whose_commit_fails_leaves_no_calibrator_behind(tmp_path, stream):
    """The cached calibrator is fed before the commit: when the commit fails it is dropped
    while the device lock is still held (nothing can write or seed it), and the next cycle
    restores the device and feeds the batch once."""
    from selfcal_service.storage import StorageUnavailable

    cfg, batches = stream
    store = _open(backend_db(tmp_path / "fail.db"))
    try:
        _ingest(store, batches[:2])
        worker = _worker(store, cfg, checkpoint_samples=10**6)
        worker.process("ins")
        assert "ins" in worker._cache and "ins" in worker._dirty
        commit = store.commit_progress

        def failing(progress):
            raise StorageUnavailable("the database went away (test)")

        store.commit_progress = failing
        with pytest.raises(StorageUnavailable):
            worker.process("ins")
        assert "ins" not in worker._cache and "ins" not in worker._dirty
        store.commit_progress = commit
        worker.process("ins")
        rec = store.load_device("ins", with_state=False)
        assert rec.processed_seq == 1 and rec.samples_processed == 2 * N and rec.feed_state["samples"] == 2 * N
        assert worker.replays == 1  # batch 0, fed again after the restore; batch 1 once
    finally:
        store.close()


@pytest.mark.skipif(__import__("service_helpers").backend() != "postgresql",
                    reason="PostgreSQL scale-out (runs in the SELFCAL_TEST_BACKEND=postgresql pass)")
def test_a_worker_whose_device_was_seeded_elsewhere_does_not_write_its_older_state(tmp_path, stream):
    """On a shared database an admin seed in another process writes the device's state at
    the same seq with a new revision; a worker's cached (unseeded) calibrator must not be
    written over it when it gives the device up."""
    store, worker, rec = _fed(tmp_path / "seeded.db", stream, 2)
    try:
        assert "ins" in worker._dirty
        other = _worker(store, stream[0], checkpoint_samples=10**6)  # the admin's process
        from selfcal_service.storage import NewVersion

        other.publish_admin("ins", NewVersion("provisional", "factory", {}, {}),
                            seed={"matrix": np.eye(3).tolist(), "offset": [0.01, 0.0, 0.0]})
        seeded = store.load_device("ins")
        assert seeded.checkpoint.seq == 1 and seeded.state_rev == rec.state_rev + 1
        assert worker.flush_checkpoints() == 0  # refused: the revision moved on
        assert store.load_device("ins").calibrator_state == seeded.calibrator_state
    finally:
        store.close()


def test_a_rollback_by_the_worker_leaves_its_calibrator_due_for_its_checkpoint(tmp_path, stream):
    """An admin rollback through the worker that holds a device's calibrator ahead of its
    checkpoint changes the device's revision, not the calibrator: the calibrator is still
    written as the checkpoint when the worker stops (on PostgreSQL the write checks the
    revision, so the worker must follow it)."""
    from selfcal_service.storage import NewVersion

    store, worker, _ = _fed(tmp_path / "rollback.db", stream, 2)
    try:
        assert "ins" in worker._dirty
        worker.publish_admin("ins", NewVersion("provisional", "rollback", {"params": {}}, {}))
        assert worker.flush_checkpoints() == 1
        rec = store.load_device("ins")
        assert rec.checkpoint.seq == 1 and rec.calibrator_state and rec.checkpoint.feed_state["samples"] == 2 * N
    finally:
        store.close()


def test_a_checkpoint_written_as_a_patch_restores_the_calibrator_exactly(tmp_path, stream):
    """Every checkpoint after the first written as a patch against the first (the base): a
    worker that restores the device from base + patch has the calibrator of the one that
    wrote it, byte for byte, and the pose coverage read from them is the full state's. A
    checkpoint in full (``checkpoint_patch_fraction`` 0) replaces the base and clears the
    patch."""
    from selfcal_service.coverage import pose_coverage

    cfg, batches = stream
    store = _open(backend_db(tmp_path / "patch.db"))
    try:
        _ingest(store, batches[:20])
        first = _worker(store, cfg, checkpoint_samples=CKPT)
        first.checkpoint_patch_fraction = 1e9  # never a new base
        _drain(first)
        assert first.metrics.get("selfcal_worker_checkpoints_total") == 4  # at seqs 4, 9, 14, 19
        assert first.metrics.get("selfcal_worker_checkpoint_patches_total") == 3
        rec = store.load_device("ins")
        assert rec.checkpoint.seq == 19 and rec.calibrator_patch is not None
        base_at = json.loads(rec.calibrator_state)["n_samples"]
        assert base_at == 5 * N  # the base is still the first checkpoint

        second = _worker(store, cfg, checkpoint_samples=CKPT)
        cal = second._calibrator(store.load_device("ins", with_state=False))
        assert second.replays == 0
        want = first._cache["ins"][1].to_json()
        assert cal.to_json() == want
        assert pose_coverage(rec.calibrator_state, None, patch_json=rec.calibrator_patch) == \
            pose_coverage(want, None)

        # the restoring worker patches the same base further, then writes in full
        _ingest(store, batches[20:30])
        second.checkpoint_patch_fraction = 1e9
        assert second.process("ins")  # 1 batch a cycle
        for _ in range(4):
            second.process("ins")
        assert second.metrics.get("selfcal_worker_checkpoint_patches_total") == 1
        rec = store.load_device("ins")
        assert rec.checkpoint.seq == 24 and json.loads(rec.calibrator_state)["n_samples"] == base_at
        second.checkpoint_patch_fraction = 0.0
        _drain(second)
        rec = store.load_device("ins")
        assert rec.checkpoint.seq == 29 and rec.calibrator_patch is None
        assert rec.calibrator_state == second._cache["ins"][1].to_json()
    finally:
        store.close()


def test_a_patch_is_never_written_onto_a_base_another_worker_replaced(tmp_path, stream):
    """A worker that lost a device late writes its full state (a new base) after another
    worker restored the device from the old base. The second worker's next patch, made
    against the old base, is refused by the store (a conflict: nothing of the cycle is
    written); the worker restores from the new base and goes on, and a restore then gives
    its calibrator exactly. (Before the base tag, the patch went onto the new base and no
    restore of the device could succeed again.)"""
    cfg, batches = stream
    store = _open(backend_db(tmp_path / "rebased.db"))
    try:
        _ingest(store, batches[:7])
        old = _worker(store, cfg, checkpoint_samples=CKPT)
        _drain(old)  # a base at seq 4; seqs 5 and 6 fed since, not written
        new = _worker(store, cfg, checkpoint_samples=CKPT)
        new.checkpoint_patch_fraction = 1e9
        new._calibrator(store.load_device("ins", with_state=False))  # the old base + a replay of 5, 6
        assert "ins" in new._bases
        old.checkpoint_patch_fraction = 0.0
        assert old.flush_checkpoints() == 1  # the late full write: a new base at seq 6
        _ingest(store, batches[7:20])
        conflicts = 0
        for _ in range(40):
            try:
                if not new.process("ins"):
                    break
            except Exception as exc:  # noqa: BLE001 - the loop's handling, in short
                assert "checkpoint changed under the worker" in str(exc)
                conflicts += 1
        assert conflicts == 1 and new.replays == 2  # the refused cycle, then a restore from the new base
        rec = store.load_device("ins")
        assert rec.processed_seq == 19 and rec.checkpoint.seq > 6 and rec.calibrator_patch is not None
        fresh = _worker(store, cfg, checkpoint_samples=CKPT)
        cal = fresh._calibrator(store.load_device("ins", with_state=False))  # base + patch + replay
        assert cal.to_json() == new._cache["ins"][1].to_json()
    finally:
        store.close()


def test_a_checkpoint_patch_is_written_only_onto_its_base(tmp_path, stream):
    """The store's guard itself: a patch tagged with another base is not written (the
    cycle is a conflict, ``write_checkpoint`` returns False); tagged with the stored base,
    it is, and the base stays."""
    from selfcal_service.storage import ConflictError, Progress, base_tag_of

    cfg, batches = stream
    store = _open(backend_db(tmp_path / "guard.db"))
    try:
        _ingest(store, batches[:3])

        def cycle(seq, state=None, patch=None, patch_base=None):
            rec = store.load_device("ins", with_state=False)
            return Progress(device_id="ins", expected_processed_seq=rec.processed_seq, processed_seq=seq,
                            samples_added=N, calibrator_state=state, calibrator_patch=patch,
                            calibrator_patch_base=patch_base, calibrator_status="provisional", last_refit=None,
                            feed_state={"samples": (seq + 1) * N}, fed_seqs=[seq], expected_state_rev=rec.state_rev)

        store.commit_progress(cycle(0, state='{"base": 0}')).result(timeout=30)
        with pytest.raises(ConflictError, match="checkpoint changed"):
            store.commit_progress(cycle(1, patch='{"p": 1}', patch_base=base_tag_of('{"base": 1}'))).result(timeout=30)
        rec = store.load_device("ins")
        assert (rec.processed_seq, rec.checkpoint.seq, rec.calibrator_patch) == (0, 0, None)  # nothing written
        assert not store.write_checkpoint("ins", 0, None, {}, state_rev=rec.state_rev, patch='{"p": 0}',
                                          patch_base=base_tag_of('{"base": 1}'))
        store.commit_progress(cycle(1, patch='{"p": 1}', patch_base=base_tag_of('{"base": 0}'))).result(timeout=30)
        rec = store.load_device("ins")
        assert (rec.calibrator_state, rec.calibrator_patch, rec.checkpoint.seq) == ('{"base": 0}', '{"p": 1}', 1)
        assert rec.calibrator_base_tag == base_tag_of('{"base": 0}')
    finally:
        store.close()


def _fed_across_resets(db_path, cfg, batches, checkpoint_samples: int):
    """A store with ``batches`` fed by a worker with ``time_reset_gap_s`` 60: (store, the
    worker, the device's record)."""
    store = _open(backend_db(db_path))
    _ingest(store, batches)
    first = _worker(store, cfg, checkpoint_samples, time_reset_gap_s=60.0)
    while first.process("ins"):
        pass
    return store, first, store.load_device("ins", with_state=False)


def test_a_clock_reset_is_replayed_at_the_time_it_was_first_fed(tmp_path, stream):
    """A device clock that goes back (a reboot) is fed after a gap, never backwards; a
    worker that restores the device from a checkpoint before the reset feeds the batches
    at the times they were first fed, even with another ``time_reset_gap_s``: the same
    calibrator as the worker that fed them."""
    cfg, batches = stream
    reboot = 6  # the insole restarts before batch 6: its clock begins again at 5 s
    shift = batches[reboot][1][0] - 5.0
    rebooted = [(k, t - (shift if k >= reboot else 0.0), acc, temp, pres) for k, t, acc, temp, pres in batches[:9]]

    store, first, rec = _fed_across_resets(tmp_path / "reset.db", cfg, rebooted, CKPT)
    try:
        assert rec.processed_seq == 8 and rec.checkpoint is not None and rec.checkpoint.seq < reboot
        assert first.metrics.get("selfcal_clock_resets_total") == 1
        last_before = batches[reboot - 1][1][-1]
        offset = rec.feed_state["t_offset_s"]
        assert offset == pytest.approx(last_before - 5.0 + 60.0)  # 60 s after the last sample before it
        assert rec.feed_state["reset_offsets"] == [[reboot, offset]]
        want = first._calibrator(rec).to_json()

        second = _worker(store, cfg, CKPT, time_reset_gap_s=600.0)  # the setting changed since
        got = second._calibrator(rec)
        assert second.replays == 1
        assert got.to_json() == want
    finally:
        store.close()


def test_many_clock_resets_after_the_checkpoint_are_replayed_at_their_first_times(tmp_path, stream):
    """A device whose clock restarts at every batch (40 resets, no checkpoint yet): every
    reset's offset is kept, and a restore under another ``time_reset_gap_s`` still gives
    the calibrator that first fed them (a review found the first 8 of 40 refed at other
    times when only the last 32 were kept)."""
    cfg, batches = stream
    restarted = [(k, t - (t[0] - 5.0) if k else t, acc, temp, pres) for k, t, acc, temp, pres in batches[:41]]

    store, first, rec = _fed_across_resets(tmp_path / "resets.db", cfg, restarted, 10**9)
    try:
        assert rec.processed_seq == 40 and rec.checkpoint is None
        assert first.metrics.get("selfcal_clock_resets_total") == 40
        assert [r[0] for r in rec.feed_state["reset_offsets"]] == list(range(1, 41))
        want = first._calibrator(rec).calibration()
        for gap_s in (600.0, 6.0):
            got = _worker(store, cfg, 10**9, time_reset_gap_s=gap_s)._calibrator(rec).calibration()
            assert got["version"] == want["version"] and got["params"] == want["params"]
    finally:
        store.close()
