"""In-process unit tests: settings precedence, API-key parsing, binary codec, batch checks."""

from __future__ import annotations

import numpy as np
import pytest
from service_helpers import only_sqlite

from selfcal.errors import InputError
from selfcal_service.auth import AuthError, KeyRing, parse_api_keys
from selfcal_service.schemas import Batch, FieldError, check_batch, decode_binary
from selfcal_service.settings import load_settings
from selfcal_service.worker import jsonable


def test_settings_precedence_defaults_config_env_flags():
    s = load_settings({}, environ={})
    assert s.port == 8000 and s.sqlite_synchronous == "FULL"
    s = load_settings({"port": 9000, "max_batch_samples": 50}, environ={})
    assert s.port == 9000 and s.max_batch_samples == 50
    s = load_settings({"port": 9000}, environ={"SELFCAL_PORT": "9100"})
    assert s.port == 9100
    s = load_settings({"port": 9000}, overrides={"port": 9200, "host": None}, environ={"SELFCAL_PORT": "9100"})
    assert s.port == 9200 and s.host == "127.0.0.1"


def test_settings_errors_name_the_key():
    with pytest.raises(InputError, match=r"\[service\]\.colour"):
        load_settings({"colour": "red"}, environ={})
    with pytest.raises(InputError, match="sqlite_synchronous"):
        load_settings({}, environ={"SELFCAL_SQLITE_SYNCHRONOUS": "OFF"})
    with pytest.raises(InputError, match="api_keys"):
        load_settings({}, environ={"SELFCAL_API_KEYS": "short=read"})


def test_settings_repr_hides_keys():
    s = load_settings({}, environ={"SELFCAL_API_KEYS": "verysecretkey=read"})
    assert "verysecretkey" not in repr(s)


@pytest.mark.parametrize(
    "spec,match",
    [
        ("k", "entry #1"),
        ("longenoughkey=", "scopes"),
        ("longenoughkey=read+write", "scopes"),
        ("goodkey123=read,=admin", "entry #2"),
    ],
)
def test_bad_key_specs(spec, match):
    with pytest.raises(ValueError, match=match):
        parse_api_keys(spec)


def test_keyring_scopes():
    ring = KeyRing(" aaaaaaaa1=ingest , bbbbbbbb2=read+admin ,")
    assert len(ring) == 2
    ring.check("Bearer aaaaaaaa1", "ingest")
    ring.check("bearer bbbbbbbb2", "admin")
    for header, scope, status in [
        (None, "read", 401),
        ("Bearer", "read", 401),
        ("Token aaaaaaaa1", "ingest", 401),
        ("Bearer aaaaaaaa", "ingest", 401),
        ("Bearer aaaaaaaa1", "read", 403),
    ]:
        with pytest.raises(AuthError) as err:
            ring.check(header, scope)
        assert err.value.status == status
        assert "aaaaaaaa1" not in err.value.message


def _batch(n=30, temp=True, k=4, seed=0) -> Batch:
    rng = np.random.default_rng(seed)
    return Batch(
        seq=12345678901,
        t_s=np.cumsum(rng.uniform(0.0, 0.1, n)),
        acc_g=rng.uniform(-2, 2, (n, 3)),
        temp_c=rng.uniform(0, 40, n) if temp else None,
        pressure_kpa=rng.uniform(0, 300, (n, k)) if k else None,
    )


@pytest.mark.parametrize("temp,k", [(True, 4), (False, 0), (True, 0), (False, 16)])
def test_binary_round_trip_exact(temp, k):
    b = _batch(temp=temp, k=k)
    raw = b.to_bytes()
    assert len(raw) == 20 + 8 * b.n * (4 + int(temp) + k)
    d = decode_binary(raw)
    assert d.seq == b.seq
    np.testing.assert_array_equal(d.t_s, b.t_s)
    np.testing.assert_array_equal(d.acc_g, b.acc_g)
    for x, y in ((d.temp_c, b.temp_c), (d.pressure_kpa, b.pressure_kpa)):
        assert (x is None) == (y is None)
        if x is not None:
            np.testing.assert_array_equal(x, y)
    assert d.to_bytes() == raw


@pytest.mark.parametrize(
    "change,field",
    [
        (lambda b: b.t_s.__setitem__(3, b.t_s[2] - 1e-3), "t_s[3]"),
        (lambda b: b.t_s.__setitem__(0, np.inf), "t_s[0]"),
        (lambda b: b.acc_g.__setitem__((5, 1), 16.01), "ay_g[5]"),
        (lambda b: b.acc_g.__setitem__((6, 2), np.nan), "az_g[6]"),
        (lambda b: b.temp_c.__setitem__(7, -40.5), "temp_c[7]"),
        (lambda b: b.pressure_kpa.__setitem__((8, 3), 2000.5), "pressure_kpa[8][3]"),
        (lambda b: b.pressure_kpa.__setitem__((9, 0), -0.1), "pressure_kpa[9][0]"),
    ],
)
def test_check_batch_names_first_bad_value(change, field):
    b = _batch()
    check_batch(b, max_samples=100, max_pressure_channels=16)  # valid before the change
    change(b)
    with pytest.raises(FieldError) as err:
        check_batch(b, max_samples=100, max_pressure_channels=16)
    assert err.value.field == field


def test_a_decreasing_time_is_named_with_plain_numbers():
    b = _batch()
    b.t_s[4] = b.t_s[3] - 0.05
    with pytest.raises(FieldError, match=r"t_s must be non-decreasing: -?[0-9.e-]+ < previous [0-9.e-]+$") as err:
        check_batch(b, max_samples=100, max_pressure_channels=16)
    assert err.value.field == "t_s[4]" and "np." not in str(err.value)  # (numpy reprs: np.float64(0.15))


def test_check_batch_limits():
    with pytest.raises(FieldError, match="limit of 10"):
        check_batch(_batch(n=11), max_samples=10, max_pressure_channels=16)
    with pytest.raises(FieldError, match="channels"):
        check_batch(_batch(k=5), max_samples=100, max_pressure_channels=4)


def test_jsonable_makes_plain_json():
    out = jsonable({"a": np.float64(np.nan), "b": np.arange(3), "c": (np.int32(2), np.bool_(True)), 4: np.inf})
    assert out == {"a": None, "b": [0, 1, 2], "c": [2, True], "4": None}


# ----------------------------------------------------------------- schema migration
V1_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE devices (device_id TEXT PRIMARY KEY, created_at REAL NOT NULL,
    batches_stored INTEGER NOT NULL DEFAULT 0, processed_seq INTEGER,
    samples_processed INTEGER NOT NULL DEFAULT 0, calibrator_state TEXT, calibrator_status TEXT,
    last_refit TEXT, feed_state TEXT, current_version INTEGER, updated_at REAL);
CREATE TABLE batches (device_id TEXT NOT NULL, seq INTEGER NOT NULL, n_samples INTEGER NOT NULL,
    received_at REAL NOT NULL, payload BLOB NOT NULL, PRIMARY KEY (device_id, seq));
CREATE TABLE versions (device_id TEXT NOT NULL, version INTEGER NOT NULL, status TEXT NOT NULL,
    source TEXT NOT NULL, created_at REAL NOT NULL, calibration TEXT NOT NULL, provenance TEXT NOT NULL,
    PRIMARY KEY (device_id, version));
INSERT INTO meta VALUES ('schema_version', '1');
"""


@only_sqlite
def test_v1_database_migrates_and_keeps_the_resend_rules(tmp_path):
    """A schema-1 database (batches 0 and 1 stored, 0 fed) opens as schema 4 (2: batch
    states; 3: the refusal log; 4: checkpoints): batch 0 is fed, 1 pending; a resend of 1
    with its own bytes is a duplicate, with other bytes a conflict (the migration hashed
    the stored payloads); the device's calibrator state is its checkpoint at seq 0."""
    import hashlib
    import sqlite3

    from selfcal_service.sqlite_store import SQLiteStore
    from selfcal_service.storage import SeqConflict

    db = tmp_path / "v1.db"
    b0, b1 = _batch(seed=1), _batch(seed=2)
    b0.seq, b1.seq = 0, 1
    conn = sqlite3.connect(db)
    conn.executescript(V1_SCHEMA)
    conn.execute("INSERT INTO devices(device_id, created_at, batches_stored, processed_seq, calibrator_state, "
                 "feed_state) VALUES ('d', 0, 2, 0, '{\"state\": 1}', '{\"samples\": 7}')")
    for b in (b0, b1):
        conn.execute("INSERT INTO batches VALUES ('d', ?, ?, 0, ?)", (b.seq, b.n, b.to_bytes()))
    conn.commit()
    conn.close()
    store = SQLiteStore(str(db))
    store.open()
    try:
        assert [p.seq for p in store.pending_batches("d", 10)] == [1]
        rec = store.load_device("d")
        assert rec.calibrator_state == '{"state": 1}'
        assert rec.checkpoint is not None and rec.checkpoint.seq == 0 and rec.checkpoint.feed_state == {"samples": 7}
        assert store.load_device("d", with_state=False).calibrator_state is None
        assert [b.seq for b in store.fed_batches("d", None, 0, 10)] == [0]
        same = b1.to_bytes()
        assert store.submit_batch("d", 1, b1.n, same, 1.0, hashlib.sha256(same).digest(), 100).result().duplicate
        other = _batch(seed=3)
        other.seq = 1
        with pytest.raises(SeqConflict):
            store.submit_batch("d", 1, other.n, other.to_bytes(), 1.0,
                               hashlib.sha256(other.to_bytes()).digest(), 100).result()
    finally:
        store.close()
    conn = sqlite3.connect(db)
    version = conn.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()[0]
    assert version == "5"  # v2 added the batch states, v3 the refusal log (empty), v4 checkpoints, v5 patches
    assert conn.execute("SELECT COUNT(*) FROM checkpoint_patches").fetchone()[0] == 0
    assert conn.execute("SELECT COUNT(*) FROM checkpoints WHERE base_tag IS NULL").fetchone()[0] == 1  # migrated
    assert conn.execute("SELECT COUNT(*) FROM refusals").fetchone()[0] == 0
    assert conn.execute("SELECT calibrator_state FROM devices").fetchall() == [(None,)]  # moved, not copied


# ----------------------------------------------------------------- ordering contract
def _planner(window_s: float = 10.0):
    from selfcal_service.metrics import Metrics
    from selfcal_service.worker import RefitWorker

    return RefitWorker(store=None, factory=None, metrics=Metrics(), reorder_window_s=window_s)


def _device(processed_seq, **feed):
    from selfcal_service.storage import DeviceRecord

    return DeviceRecord("d", 0, processed_seq, 0, None, None, None, dict(feed), None, None)


def _pending(seq: int, received_at: float):
    from selfcal_service.storage import PendingBatch

    return PendingBatch(seq, 20, received_at, b"")


def test_plan_feeds_in_order_holds_gaps_rejects_late():
    w = _planner(10.0)
    take, late, held = w._plan(_device(3), [_pending(1, 0.0), _pending(4, 0.0), _pending(5, 0.0), _pending(7, 99.0)], 100.0)
    assert [r.seq for r in take] == [4, 5] and [r.seq for r in late] == [1] and [r.seq for r in held] == [7]
    take, late, held = w._plan(_device(5), [_pending(7, 80.0), _pending(8, 95.0)], 100.0)  # the gap is 20 s old
    assert [r.seq for r in take] == [7, 8] and not late and not held
    take, late, held = w._plan(_device(None), [_pending(0, 99.0), _pending(1, 99.0)], 100.0)
    assert [r.seq for r in take] == [0, 1]


def test_plan_a_batch_the_calibrator_refused_leaves_no_gap():
    """seq 7 was refused by the calibrator (6 is the highest fed): 8 is fed at once."""
    take, late, held = _planner(10.0)._plan(_device(6, handled_seq=7), [_pending(8, 99.9)], 100.0)
    assert [r.seq for r in take] == [8] and not held and not late


def test_held_devices_come_back_in_time_order_from_one_thread():
    """Devices held (reorder window, min_cycle_interval_s) are enqueued when their time
    comes, soonest first, by one thread for them all (not a timer thread per device: with
    a cycle interval every insole of a fleet is held between its cycles); a device is held
    once at a time, and nothing comes back after stop()."""
    import threading
    import time

    w = _planner(10.0)
    came_back: list[str] = []
    w._enqueue = came_back.append  # what the waker does with a device whose time came
    before = threading.active_count()
    delays = {f"d{i}": d for i, d in enumerate([2.0, 0.2, 1.1] * 200)}
    for device_id, delay in delays.items():
        w._hold(device_id, delay)
    w._hold("d1", 0.0)  # held already: not shortened, not doubled
    assert threading.active_count() == before + 1 and len(w._held) == 600
    time.sleep(0.6)
    assert sorted(came_back) == sorted(f"d{i}" for i in range(1, 600, 3))  # the 0.2-s ones only
    deadline = time.monotonic() + 10.0
    while len(came_back) < 600 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert len(came_back) == 600 and [delays[d] for d in came_back] == sorted(delays[d] for d in came_back)
    assert not w._held and w.idle()

    def refuse(device_id):
        raise RuntimeError("enqueue failed")

    w._enqueue = refuse  # a device whose enqueue fails: the others still come back
    w._hold("bad", 0.05)
    time.sleep(0.3)
    w._enqueue = came_back.append
    w._hold("next", 0.05)
    deadline = time.monotonic() + 5.0
    while "next" not in came_back and time.monotonic() < deadline:
        time.sleep(0.05)
    assert "next" in came_back and not w._held
    w._hold("late", 0.2)
    w.stop()
    time.sleep(0.4)
    assert "late" not in came_back and not w._waker.is_alive() and not w._held and w.idle()


@pytest.mark.parametrize("parser", ["h11", "httptools"])
def test_protocol_sets_tcp_nodelay_even_on_a_socket_without_proto(parser):
    """uvicorn's worker processes get the listening socket back with proto 0, and asyncio
    then skips TCP_NODELAY: each response body waited ~40 ms for a delayed ACK."""
    import asyncio
    import socket

    from selfcal_service.http_protocol import protocol_class

    TimedH11Protocol = protocol_class(parser)  # noqa: N806 - the class under test

    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)  # as uvicorn's bind_socket makes it: proto 0
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    cli = socket.create_connection(srv.getsockname())
    shared, _ = srv.accept()  # an accepted socket inherits proto 0
    assert shared.proto == 0 and shared.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) == 0

    class Transport:
        def get_extra_info(self, name, default=None):
            return {"socket": shared, "sockname": ("127.0.0.1", 1), "peername": ("127.0.0.1", 2)}.get(name, default)

        def is_closing(self):
            return False

        def close(self):
            pass

    class Config:
        pass

    loop = asyncio.new_event_loop()
    try:
        proto = TimedH11Protocol.__new__(TimedH11Protocol)
        # only what connection_made touches in H11Protocol
        proto.connections, proto.loop, proto.logger = set(), loop, __import__("logging").getLogger("t")
        TimedH11Protocol.connection_made(proto, Transport())
        assert shared.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) == 1
        proto._disarm()
    finally:
        loop.close()
        for s in (shared, cli, srv):
            s.close()


def test_the_served_calibration_says_why_it_is_provisional():
    from selfcal_service.main import calibration_out
    from selfcal_service.storage import DeviceRecord, VersionRecord

    dev = DeviceRecord("insole-1", 3, 2, 1200, None, "provisional", None, {}, 4, 0.0)
    reason = "the 40 cells since the last version disagree with the model (offset jump chi2 88.0 on 3 > 21.1): a bias step?"
    ver = VersionRecord(4, "provisional", "refit", 0.0, {"model": "affine9", "status_reason": reason}, {})
    out = calibration_out("insole-1", dev, ver)
    assert out.status == "provisional" and out.status_reason == reason
    assert calibration_out("insole-1", dev, VersionRecord(4, "calibrated", "refit", 0.0, {}, {})).status_reason is None


def test_per_process_gauges_carry_the_pid_and_a_dead_process_drops_out(tmp_path):
    import json
    import os
    import time

    from selfcal_service.metrics import GAUGE_FRESH_S, Metrics

    m = Metrics(tmp_path)
    m.gauge("selfcal_worker_queue_depth", lambda: 3)
    m.gauge("selfcal_backlog_batches", lambda: 7, per_process=False)
    m.inc("selfcal_ingest_samples_total", 5)
    other = {"counters": [["selfcal_ingest_samples_total", [], 2.0]], "hist": [], "pid": 4242,
             "gauges": {"selfcal_worker_queue_depth": 9.0}}
    live, dead = tmp_path / "4242-aaaa.json", tmp_path / "4343-bbbb.json"
    live.write_text(json.dumps(other))
    dead.write_text(json.dumps({**other, "pid": 4343, "gauges": {"selfcal_worker_queue_depth": 99.0}}))
    old = time.time() - GAUGE_FRESH_S - 5
    os.utime(dead, (old, old))
    text = m.render()
    assert f'selfcal_worker_queue_depth{{pid="{os.getpid()}"}} 3' in text
    assert 'selfcal_worker_queue_depth{pid="4242"} 9' in text
    assert 'pid="4343"' not in text  # a dead process's gauges go away ...
    assert "selfcal_ingest_samples_total 9" in text  # ... its counters stay (5 + 2 + 2)
    assert "selfcal_backlog_batches 7" in text and 'selfcal_backlog_batches{' not in text


def test_gc_pauses_are_timed_by_generation_and_the_callback_goes_away():
    import gc

    from selfcal_service.metrics import Metrics

    m = Metrics()
    before = len(gc.callbacks)
    m.track_gc()
    try:
        gc.collect()  # a full collection: generation 2
        text = m.render()
    finally:
        m.untrack_gc()
    assert len(gc.callbacks) == before
    counts = {line.split("{")[1].split("}")[0]: float(line.rpartition(" ")[2])
              for line in text.splitlines() if line.startswith("selfcal_gc_pause_seconds_count")}
    assert counts['generation="2",role="api"'] >= 1
    gc.collect()  # untracked: no more counts
    key = ("selfcal_gc_pause_seconds", (("generation", "2"), ("role", "api")))
    assert m._hist[key][-2] == counts['generation="2",role="api"']
    w = Metrics()
    w.track_gc(role="worker")  # a refit worker's pauses stall no request: apart from the API's
    try:
        gc.collect()
    finally:
        w.untrack_gc()
    assert 'selfcal_gc_pause_seconds_count{generation="2",role="worker"}' in w.render()
    assert 'role="api"' not in w.render()


def test_tune_gc_freezes_what_exists_and_sets_the_young_threshold():
    import gc

    from selfcal_service.main import tune_gc

    old = gc.get_threshold()
    try:
        tune_gc(load_settings({"gc_gen0_threshold": 5000}, environ={}))
        assert gc.get_freeze_count() > 0 and gc.get_threshold()[0] == 5000
    finally:
        gc.unfreeze()
        gc.set_threshold(*old)
    tune_gc(load_settings({"gc_freeze": False}, environ={}))
    try:
        assert gc.get_freeze_count() == 0
    finally:
        gc.set_threshold(*old)


def test_sqlite_checkpoint_patches_have_their_own_table_and_the_same_guards():
    """SQLite keeps the latest patch in ``checkpoint_patches`` (a column beside the base
    made it rewrite the whole record). The effective checkpoint is the patch's seq and
    bookkeeping; never an older checkpoint over a newer one, never a patch onto another
    base or onto no base; a full write replaces the base and deletes the patch."""
    import sqlite3

    from selfcal_service import sqlite_store
    from selfcal_service.storage import base_tag_of

    conn = sqlite3.connect(":memory:", isolation_level=None)
    conn.executescript(sqlite_store._SCHEMA)
    write = sqlite_store.write_checkpoint_sqlite

    def stored():
        return conn.execute(f"SELECT {sqlite_store._CKPT_COLS}, c.base, p.patch, c.base_tag "
                            f"FROM (SELECT 'd' AS device_id) d {sqlite_store._CKPT_JOIN}").fetchone()

    b5 = '{"b": 5}'
    assert not write(conn, "d", 1, None, {}, 0.0, patch="P1", patch_base=base_tag_of(b5))  # no base to patch
    assert stored()[0] == 0
    assert write(conn, "d", 5, b5, {"s": 5}, 0.0)
    assert write(conn, "d", 7, None, {"s": 7}, 0.0, patch="P7", patch_base=base_tag_of(b5))
    assert stored() == (1, 7, '{"s":7}', b5, "P7", base_tag_of(b5))
    assert not write(conn, "d", 6, '{"b": 6}', {"s": 6}, 0.0)  # older than the patch
    assert not write(conn, "d", 6, None, {"s": 6}, 0.0, patch="P6", patch_base=base_tag_of(b5))
    assert not write(conn, "d", None, b5, {}, 0.0)
    assert not write(conn, "d", 8, None, {"s": 8}, 0.0, patch="P8", patch_base=base_tag_of('{"b": 0}'))
    assert stored() == (1, 7, '{"s":7}', b5, "P7", base_tag_of(b5))
    assert write(conn, "d", 8, '{"b": 8}', {"s": 8}, 0.0)  # a new base: the patch goes
    assert stored() == (1, 8, '{"s":8}', '{"b": 8}', None, base_tag_of('{"b": 8}'))
    assert conn.execute("SELECT COUNT(*) FROM checkpoint_patches").fetchone()[0] == 0
    with pytest.raises(ValueError):
        write(conn, "d", 9, '{"b": 9}', {}, 0.0, patch="P9", patch_base="x")  # both


def test_a_worker_waiting_to_lease_a_device_is_not_idle():
    """idle() counts the devices an ingest handed to the lease thread (not yet leased nor
    queued), and the pass that is leasing them: a test or a drain that waits for idle()
    does not stop before the cycle of a device just ingested."""
    w = _planner(10.0)
    assert w.idle()
    w._wanted["d1"] = None  # notify() with leases: for the lease thread
    assert not w.idle()
    w._wanted.clear()
    w._leasing = True  # the lease thread took it and is leasing it
    assert not w.idle()
    w._leasing = False
    assert w.idle()


def test_a_restored_calibrator_states_what_a_new_one_does_when_the_service_has_no_selection_section():
    """The factory applies the service's ``[selection]`` to a restored calibrator; with no
    such section it used to add an empty one to the state, so a restored device's state
    text (and checkpoint digest) differed from the live one's. Now the same, both ways."""
    from selfcal.config import load_config
    from selfcal_service.worker import CalibratorFactory

    full = {k: v for k, v in load_config().items() if k not in ("service", "gateway")}
    for config in ({k: v for k, v in full.items() if k != "selection"}, full):
        factory = CalibratorFactory("selfcal.calibrator:OnlineCalibrator", config=config)
        live = factory.create()
        assert factory.restore(live.to_json()).to_json() == live.to_json()


# ----------------------------------------------------------------- group commit
def test_a_write_whose_caller_gave_up_is_dropped_and_the_writer_lives_on(tmp_path):
    """A request's timeout cancels its queued write's future (asyncio.wait_for over
    wrap_future). The writer must drop that write unwritten and keep serving: resolving a
    cancelled future raises, and that had killed the writer thread (every later write hung)."""
    import asyncio
    import hashlib
    import threading

    from selfcal_service.sqlite_store import SQLiteStore

    store = SQLiteStore(str(tmp_path / "g.db"))
    store.open()
    try:
        gate, entered = threading.Event(), threading.Event()

        def blocker(conn):
            entered.set()
            assert gate.wait(10)
            return "first"

        first = store._submit(blocker)
        assert entered.wait(10)  # the writer is inside the first group
        b = _batch(seed=5)
        b.seq = 0
        payload = b.to_bytes()

        async def give_up():  # as the ingest route does, with a timeout that expires
            with pytest.raises(asyncio.TimeoutError):
                await asyncio.wait_for(asyncio.wrap_future(store.submit_batch(
                    "d", 0, b.n, payload, 1.0, hashlib.sha256(payload).digest(), 100)), timeout=0.05)

        asyncio.run(give_up())
        ran = []
        gone = store._submit(lambda conn: ran.append(1))
        assert gone.cancel()  # queued, not taken yet: cancellable
        gate.set()
        assert first.result(10) == "first"
        later = store._submit(lambda conn: "alive")
        assert later.result(10) == "alive"  # the writer outlived the cancelled futures
        assert store.writer_alive()
        assert ran == []  # the cancelled write never ran
        assert store.pending_batches("d", 10) == []  # nor did the timed-out batch: a resend stores it once
        again = store.submit_batch("d", 0, b.n, payload, 1.0, hashlib.sha256(payload).digest(), 100).result(10)
        assert not again.duplicate and [p.seq for p in store.pending_batches("d", 10)] == [0]
    finally:
        store.close()


def test_the_refreezer_freezes_each_full_collections_survivors_and_frees_frozen_cycles_each_period():
    """The embedded service's calibrators arrive after start: each full collection scanned
    them all (~90 ms at 10 000 insoles). Survivors of a full collection are frozen; once a
    period everything is unfrozen, so cyclic garbage that died frozen is freed."""
    import gc
    import weakref

    from selfcal_service.gc_policy import Refreezer

    class Node:
        pass

    now = [0.0]
    gc.collect()
    r = Refreezer(600.0, clock=lambda: now[0]).install()
    try:
        a, b = Node(), Node()
        a.other, b.other = b, a  # a reference cycle: only the collector can free it
        alive = weakref.ref(a)
        gc.collect()
        assert r.freezes == 1 and gc.get_freeze_count() > 0 and gc.is_tracked(a)
        assert a not in gc.get_objects()  # frozen: no collection scans it
        del a, b
        now[0] = 599.0
        gc.collect()
        assert alive() is not None and r.unfreezes == 0  # died frozen: not freed yet
        now[0] = 600.0
        gc.collect()  # at its end everything is unfrozen ...
        assert r.unfreezes == 1 and gc.get_freeze_count() == 0
        gc.collect()  # ... and the next full collection frees the cycle, then freezes the rest
        assert alive() is None and r.freezes == 3 and gc.get_freeze_count() > 0
        gc.collect(1)  # a young collection changes nothing
        assert r.freezes == 3
    finally:
        r.remove()
        gc.unfreeze()
    assert r._on_gc not in gc.callbacks
    with pytest.raises(ValueError, match="unfreeze_every_s"):
        Refreezer(0.0)


def test_tune_gc_installs_the_refreezer_only_with_a_period_and_the_start_freeze():
    import gc

    from selfcal_service.main import tune_gc

    old = gc.get_threshold()
    try:
        r = tune_gc(load_settings({"gc_unfreeze_every_s": 5.0}, environ={}))
        assert r is not None and r._on_gc in gc.callbacks and r.unfreeze_every_s == 5.0
        r.remove()
        gc.unfreeze()
        assert tune_gc(load_settings({"gc_unfreeze_every_s": 0}, environ={})) is None
        gc.unfreeze()
        assert tune_gc(load_settings({"gc_freeze": False}, environ={})) is None
    finally:
        gc.unfreeze()
        gc.set_threshold(*old)


def test_a_device_whose_cycles_keep_failing_is_held_with_a_doubling_hold_and_starves_no_other(tmp_path):
    """A device whose cycle raises (a corrupt checkpoint, a calibrator bug) made its refit
    thread sleep 0.5 s before retrying it, at every failure: a few such devices starved
    every other device of their shard. The thread now goes on at once, and the device is
    held 0.5, 1, 2 ... s (at most FAILURE_HOLD_MAX_S); a success resets the count."""
    import threading
    import time

    from selfcal_service.metrics import Metrics
    from selfcal_service.sqlite_store import SQLiteStore
    from selfcal_service.worker import FAILURE_HOLD_MAX_S, CalibratorFactory, RefitWorker

    store = SQLiteStore(str(tmp_path / "poison.db"))
    store.open()
    worker = RefitWorker(store, CalibratorFactory("service_fakes:FakeCalibrator"), Metrics())
    holds, fed, fail = [], [], {"bad": 3}
    worker._hold = lambda device_id, delay_s: holds.append((device_id, delay_s))

    def process(device_id):
        fed.append(device_id)
        if fail.get(device_id, 0) > 0:
            fail[device_id] -= 1
            raise RuntimeError("corrupt checkpoint")
        return False

    worker.process = process
    shard = worker._shards[0]
    thread = threading.Thread(target=worker._loop, args=(shard,), daemon=True)
    thread.start()
    try:
        def feed(device_id):
            n = len(fed)
            worker._enqueue(device_id)
            t_end = time.monotonic() + 30
            while len(fed) == n or worker.busy:
                assert time.monotonic() < t_end
                time.sleep(0.005)

        for device_id in ("bad", "good", "bad", "good", "bad", "bad", "bad"):
            feed(device_id)
        fail["bad"] = 1
        feed("bad")
        assert fed == ["bad", "good", "bad", "good", "bad", "bad", "bad", "bad"]
        assert holds == [("bad", 0.5), ("bad", 1.0), ("bad", 2.0), ("bad", 0.5)]  # reset by the success
        assert worker.metrics.get("selfcal_worker_errors_total") == 4 and worker._failures == {"bad": 1}
        assert worker.queue_depth() == 0  # nothing re-enqueued behind the hold's back
        worker._failures["bad"] = 30
        assert worker._failed("bad") == FAILURE_HOLD_MAX_S
    finally:
        worker._stop.set()
        with shard.cond:
            shard.cond.notify_all()
        thread.join(10)
        store.close()


@only_sqlite
def test_a_batch_stored_after_its_request_timed_out_is_fed_once_it_is_resent(tmp_path):
    """A write already running when ``write_timeout_s`` expires cannot be cancelled: the
    client got a 503 and the batch was stored. Its resend was answered as a duplicate, which
    told the worker nothing, so the embedded worker never fed it (nothing looks for pending
    batches after start): the device's calibration stayed behind until its next batch."""
    import threading
    import time

    from fastapi.testclient import TestClient
    from service_helpers import KEY_SPEC, auth

    from selfcal_service.main import create_app
    from selfcal_service.sqlite_store import SQLiteStore

    class SlowCommits(SQLiteStore):
        slow_next = False

        def submit_batch(self, *a, **k):
            if not self.slow_next:
                return super().submit_batch(*a, **k)
            self.slow_next = False
            gate = threading.Event()
            self._submit(lambda conn: gate.wait(5))  # the writer busy: the batch and a slow op in one group
            fut = super().submit_batch(*a, **k)
            # a slow commit (an fsync on a busy disk) that ends only once the client has its
            # 503: the timeout is met for sure, however slow or loaded the machine
            self._submit(lambda conn: self.release.wait(30))
            gate.set()
            return fut

    db = str(tmp_path / "t.db")
    store = SlowCommits(db)
    store.release = threading.Event()
    settings = load_settings(None, environ={}, overrides={
        "db_path": db, "api_keys": KEY_SPEC, "calibrator": "service_fakes:FakeCalibrator",
        "write_timeout_s": 2.0, "gc_freeze": False})  # ample for the ordinary writes under load
    app = create_app(settings, config={"fake": {"publish_after_samples": 30}}, store=store)

    def post(client, seq):
        rng = np.random.default_rng(seq)
        body = Batch(seq=seq, t_s=seq + np.arange(20) / 20.0, acc_g=rng.normal([0, 0, 1], 0.002, (20, 3))).to_bytes()
        return client.post("/devices/d1/samples", content=body,
                           headers={**auth("ingest"), "Content-Type": "application/x-selfcal-batch"})

    with TestClient(app) as client:
        for seq in range(3):
            assert post(client, seq).status_code == 200
        store.slow_next = True
        try:
            assert post(client, 3).status_code == 503  # ... and stored just after
        finally:
            store.release.set()
        deadline = time.monotonic() + 10
        while store.pending_batches("d1", 10) == [] and time.monotonic() < deadline:
            time.sleep(0.05)
        resent = post(client, 3)
        assert resent.status_code == 200 and resent.json()["duplicate"]
        while time.monotonic() < deadline:
            cal = client.get("/devices/d1/calibration", headers=auth("read")).json()
            if cal["processed_seq"] == 3:
                break
            time.sleep(0.05)
        assert cal["processed_seq"] == 3 and cal["samples_processed"] == 80


@only_sqlite
def test_an_embedded_cycle_dropped_on_a_conflict_is_tried_again(tmp_path):
    """A cycle that met a concurrent change of its device was dropped, and the embedded
    worker (the only one feeding the device) never came back to the batches it had left."""
    import time

    from fastapi.testclient import TestClient
    from service_helpers import KEY_SPEC, auth

    from selfcal_service.main import create_app
    from selfcal_service.storage import ConflictError

    db = str(tmp_path / "c.db")
    settings = load_settings(None, environ={}, overrides={
        "db_path": db, "api_keys": KEY_SPEC, "calibrator": "service_fakes:FakeCalibrator", "gc_freeze": False})
    app = create_app(settings, config={"fake": {"publish_after_samples": 30}})
    with TestClient(app) as client:
        worker = app.state.worker
        real, calls = worker.process, []

        def conflicting_once(device_id):
            calls.append(device_id)
            if len(calls) == 1:
                raise ConflictError(f"device {device_id}: changed while its calibrator was restored")
            return real(device_id)

        worker.process = conflicting_once
        body = Batch(seq=0, t_s=np.arange(40) / 20.0, acc_g=np.tile([0.0, 0.0, 1.0], (40, 1))).to_bytes()
        r = client.post("/devices/d1/samples", content=body,
                        headers={**auth("ingest"), "Content-Type": "application/x-selfcal-batch"})
        assert r.status_code == 200
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            cal = client.get("/devices/d1/calibration", headers=auth("read")).json()
            if cal["processed_seq"] == 0:
                break
            time.sleep(0.05)
        assert cal["processed_seq"] == 0 and len(calls) >= 2


@only_sqlite
def test_a_first_start_that_fails_half_way_leaves_a_file_the_next_start_opens(tmp_path, monkeypatch):
    """The schema ran in autocommit and its version was written after it: a first start that
    died between the two left tables without a version, which every later start migrated
    again and failed on (the service never started on that file)."""
    import sqlite3

    import selfcal_service.sqlite_store as sq

    db = str(tmp_path / "half.db")
    monkeypatch.setattr(sq, "_SCHEMA", sq._SCHEMA + "\nINSERT INTO no_such_table VALUES (1);\n")  # dies at its end
    with pytest.raises(sqlite3.OperationalError):
        sq.SQLiteStore(db).open()
    monkeypatch.undo()
    store = sq.SQLiteStore(db)
    store.open()
    try:
        assert store.pending_devices() == []
    finally:
        store.close()


@only_sqlite
def test_a_rollback_to_a_version_of_a_model_the_calibrator_has_left_is_served(tmp_path):
    """Model selection can add an effect and drop it again: a rollback to a version published
    under the effect passed its parameters (tbx, ...) to a calibrator back on affine9, a 422.
    The version is served as it was, and the calibrator's prior is its linear part."""
    from fastapi.testclient import TestClient
    from service_helpers import KEY_SPEC, auth

    from selfcal.config import load_config
    from selfcal_service.main import create_app
    from selfcal_service.storage import NewVersion, Progress

    db = str(tmp_path / "r.db")
    settings = load_settings(None, environ={}, overrides={
        "db_path": db, "api_keys": KEY_SPEC, "calibrator": "selfcal.calibrator:OnlineCalibrator", "gc_freeze": False})
    app = create_app(settings, config=load_config())
    p9 = {"bx": 0.01, "by": 0.0, "bz": -0.02, "sx": 0.01, "sy": -0.01, "sz": 0.0, "nxy": 0.0, "nxz": 0.0, "nyz": 0.0}
    matrix, offset = [[1.01, 0, 0], [0, 0.99, 0], [0, 0, 1.0]], [0.01, 0.0, -0.02]
    with TestClient(app) as client:
        with_effect = {"model": "affine9+temperature_bias", "params": {**p9, "tbx": 1e-4, "tby": 0.0, "tbz": -1e-4},
                       "std": {k: 1e-3 for k in [*p9, "tbx", "tby", "tbz"]}, "matrix": matrix, "offset": offset,
                       "status": "calibrated"}
        app.state.store.commit_progress(Progress("d", None, None, 0, None, None, None, {}, [
            NewVersion("calibrated", "refit", with_effect, {})])).result(10)  # v1, as a refit writes it
        assert client.put("/devices/d/calibration", headers=auth("admin"),
                          json={"matrix": matrix, "offset": offset}).status_code == 200  # v2, affine9
        r = client.post("/devices/d/calibration/rollback", headers=auth("admin"), json={"to_version": 1})
        assert r.status_code == 200, r.json()
        assert r.json()["version"] == 3 and r.json()["model"] == "affine9+temperature_bias"
        assert r.json()["params"]["tbz"] == -1e-4
