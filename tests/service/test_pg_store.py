"""PostgresStore's shared-database contracts, with two store instances (two "processes").

Runs in the ``SELFCAL_TEST_BACKEND=postgresql`` pass. Checks what the HTTP tests cannot
force deterministically: a concurrent resend from another process, a cycle whose lease
was lost, a cycle that started before another writer changed the device, and two
workers leasing disjoint devices with expiry.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import time
from collections.abc import Callable

import pytest

from service_helpers import backend_db, only_postgres

from selfcal_service.pg_store import PostgresStore
from selfcal_service.storage import ConflictError, NewVersion, Progress, SeqConflict

pytestmark = only_postgres


@pytest.fixture()
def two_stores(tmp_path):
    url = backend_db(tmp_path / "pg-store.db")
    a, b = PostgresStore(url), PostgresStore(url)
    a.open()
    b.open()  # the second open finds the schema and runs no migration
    yield a, b
    a.close()
    b.close()


def _ingest(store, device, seq, payload=b"x" * 64):
    return store.submit_batch(device, seq, 4, payload, time.time(), hashlib.sha256(payload).digest(), 100_000)


def test_the_same_seq_from_two_processes_is_stored_once(two_stores):
    a, b = two_stores
    with cf.ThreadPoolExecutor(8) as pool:
        futs = [pool.submit(lambda s=s, q=q: _ingest(s, "dev-1", q).result(timeout=30))
                for q in range(20) for s in (a, b, a, b)]
        results = [f.result() for f in futs]
    assert sum(not r.duplicate for r in results) == 20  # each seq stored once, the rest duplicates
    dev, _ = a.current("dev-1")
    assert dev.batches_stored == 20 and a.backlog() == 20
    with pytest.raises(SeqConflict):
        _ingest(b, "dev-1", 3, payload=b"y" * 64).result(timeout=30)


def _progress(dev, **kw):
    base = dict(device_id="dev-2", expected_processed_seq=dev.processed_seq, processed_seq=0, samples_added=4,
                calibrator_state="{}", calibrator_status="provisional", last_refit=None, feed_state={},
                new_versions=[NewVersion("provisional", "refit", {"params": {}}, {})], fed_seqs=[0],
                expected_state_rev=dev.state_rev)
    base.update(kw)
    return Progress(**base)


def test_a_cycle_that_lost_its_lease_or_its_starting_state_writes_nothing(two_stores):
    a, b = two_stores
    _ingest(a, "dev-2", 0).result(timeout=30)
    assert a.acquire_leases("worker-a", 30.0, 10) == ["dev-2"]
    assert b.acquire_leases("worker-b", 30.0, 10) == []  # leased: not for b
    dev = a.load_device("dev-2")
    with pytest.raises(ConflictError, match="lease"):  # b never held it
        b.commit_progress(_progress(dev, lease_owner="worker-b")).result(timeout=30)
    stale = _progress(dev, lease_owner="worker-a", expected_state_rev=dev.state_rev + 7)
    with pytest.raises(ConflictError, match="changed"):
        a.commit_progress(stale).result(timeout=30)
    assert a.history("dev-2") == [] and a.backlog() == 1  # nothing written by either
    assert a.commit_progress(_progress(dev, lease_owner="worker-a")).result(timeout=30) == [1]
    after = a.load_device("dev-2")
    assert after.state_rev == dev.state_rev + 1 and after.processed_seq == 0 and a.backlog() == 0
    with pytest.raises(ConflictError):  # the same cycle again (a replay after a crash) is refused
        a.commit_progress(_progress(dev, lease_owner="worker-a")).result(timeout=30)
    assert len(a.history("dev-2")) == 1


def test_a_session_frozen_inside_a_transaction_loses_its_locks_to_the_server(tmp_path, monkeypatch):
    """A worker host that freezes (or is partitioned) mid-group keeps its transaction open
    with the device rows locked. The server ends such a session after
    IDLE_IN_TRANSACTION_S, so another process's write of those devices waits that long,
    not its whole statement_timeout (after which it failed: a 503 for every batch of them)."""
    import psycopg

    from selfcal_service import pg_store

    monkeypatch.setattr(pg_store, "IDLE_IN_TRANSACTION_S", 1.0)
    url = backend_db(tmp_path / "pg-frozen.db")
    a, b = PostgresStore(url), PostgresStore(url, statement_timeout_s=8.0)
    a.open()
    b.open()
    try:
        _ingest(a, "dev-f", 0).result(timeout=30)
        frozen = psycopg.connect(**a._connect_kwargs())
        assert frozen.execute("SHOW idle_in_transaction_session_timeout").fetchone()[0] == "1s"
        frozen.execute("BEGIN")
        frozen.execute("SELECT 1 FROM devices WHERE device_id = 'dev-f' FOR UPDATE")  # then nothing more
        assert not _ingest(b, "dev-f", 1).result(timeout=30).duplicate  # stored once the server ended it
        assert b.backlog() == 2
        with pytest.raises(psycopg.Error, match="idle-in-transaction"):  # the frozen client finds its session gone
            frozen.execute("SELECT 1")
        frozen.close()
    finally:
        a.close()
        b.close()


def test_two_workers_lease_disjoint_devices_and_an_expired_lease_moves_on(two_stores):
    a, b = two_stores
    for i in range(6):
        _ingest(a, f"dev-l{i}", 0).result(timeout=30)
    got_a = a.acquire_leases("worker-a", 0.6, 3)
    got_b = b.acquire_leases("worker-b", 30.0, 10)
    assert len(got_a) == 3 and len(got_b) == 3 and not set(got_a) & set(got_b)
    assert a.acquire_leases("worker-a", 0.6, 10) == []  # its own are not handed out again
    assert a.renew_leases("worker-a", 0.6) == 3
    time.sleep(0.8)  # worker a stops renewing (killed): its leases expire
    assert sorted(b.acquire_leases("worker-b", 30.0, 10)) == sorted(got_a)
    assert a.lease_counts() == {"worker-b": 6}


def test_a_heartbeat_renews_every_lease_of_its_worker_without_writing_a_device_row(two_stores):
    a, b = two_stores
    for i in range(3):
        _ingest(a, f"dev-h{i}", 0).result(timeout=30)
    assert len(a.acquire_leases("worker-a", 0.6, 3)) == 3
    rows_before = a._read("SELECT device_id, xmin::text FROM devices WHERE lease_owner = 'worker-a' ORDER BY 1")
    for _ in range(4):  # 1.2 s: twice the lease time, each lease kept by the heartbeats alone
        time.sleep(0.3)
        assert a.heartbeat("worker-a", 0.6)[1] == 3
        assert b.acquire_leases("worker-b", 30.0, 10) == []
    assert a.lease_counts() == {"worker-a": 3}
    assert a._read("SELECT device_id, xmin::text FROM devices WHERE lease_owner = 'worker-a' "
                   "ORDER BY 1") == rows_before  # no device row was rewritten
    time.sleep(0.8)  # the heartbeats stop (a killed worker): every lease lapses at once
    assert a.lease_counts() == {}
    assert len(b.acquire_leases("worker-b", 30.0, 10)) == 3


def test_a_worker_takes_back_the_devices_it_gave_up_first_among_the_oldest_waiting(two_stores):
    """Lease affinity: among the ``limit * workers + AFFINITY_SLACK`` devices that waited longest, a
    worker takes those it gave up last first (their calibrators are in its memory), and
    those no live worker fed last; when fewer than ``limit`` of these are among them, the
    oldest others are taken (a slower worker's devices move on)."""
    from selfcal_service.pg_store import AFFINITY_SLACK

    a, b = two_stores
    a.heartbeat("worker-a", 60.0)  # both live
    b.heartbeat("worker-b", 60.0)
    window = 2 + AFFINITY_SLACK  # for limit 2, one live worker (the default)
    mine = [f"dev-a{i:02d}" for i in range(4)]
    theirs = [f"dev-b{i:02d}" for i in range(window + 2)]
    for d in mine + theirs:
        _ingest(a, d, 0).result(timeout=30)
    assert sorted(a.acquire_leases("worker-a", 30.0, len(mine), prefer=mine)) == mine
    assert sorted(b.acquire_leases("worker-b", 30.0, len(theirs), prefer=theirs)) == theirs
    for d in mine:
        a.release_lease("worker-a", d)
    for d in theirs:
        b.release_lease("worker-b", d)
    assert a._read("SELECT last_owner FROM devices WHERE device_id = %s", (mine[0],)) == [("worker-a",)]

    def wait_order(order):
        for age, d in enumerate(order):
            a._read("UPDATE devices SET updated_at = %s WHERE device_id = %s RETURNING 1", (1000.0 + age, d))

    # worker a's own devices are among the window (behind window - 2 of worker b's): taken first
    wait_order(theirs[: window - 2] + mine + theirs[window - 2:])
    assert sorted(a.acquire_leases("worker-a", 30.0, 2)) == mine[:2]
    # worker b's own: the oldest two
    assert sorted(b.acquire_leases("worker-b", 30.0, 2)) == theirs[:2]
    # the window is all worker b's devices (they waited longest): worker a takes the oldest two
    a.release_lease("worker-a", mine[0])
    a.release_lease("worker-a", mine[1])
    wait_order(theirs[2:] + mine)
    # with two live workers the window is twice as deep: worker a's own are in it again
    assert sorted(a.acquire_leases("worker-a", 30.0, 2, workers=2)) == mine[:2]
    a.release_lease("worker-a", mine[0])
    a.release_lease("worker-a", mine[1])
    wait_order(theirs[2:] + mine)
    assert sorted(a.acquire_leases("worker-a", 30.0, 2)) == theirs[2:4]
    # a device no live worker fed last (new, or a stopped worker's) is everyone's own
    _ingest(a, "dev-new", 0).result(timeout=30)
    wait_order(theirs[4:] + ["dev-new"])  # the youngest of the window
    assert a.acquire_leases("worker-a", 30.0, 1) == ["dev-new"]
    b.forget_worker("worker-b")
    assert a.acquire_leases("worker-a", 30.0, 1) == [theirs[4]]  # the oldest: worker b is gone


def test_a_batch_the_database_refuses_does_not_sink_its_group(two_stores):
    """The ingest runs without a client savepoint (one round trip): a batch whose insert
    fails on the server is undone by the function's own savepoint, refused alone, and
    the batches committed with it in the same group are stored."""
    import psycopg

    a, _ = two_stores
    with psycopg.connect(a.url, autocommit=True) as conn:  # a fault only seq 13 meets
        conn.execute("CREATE FUNCTION refuse_13() RETURNS trigger LANGUAGE plpgsql AS $$ BEGIN "
                     "IF NEW.seq = 13 THEN RAISE EXCEPTION 'seq 13 refused by a test trigger'; END IF; "
                     "RETURN NEW; END $$")
        conn.execute("CREATE TRIGGER refuse_13 BEFORE INSERT ON batches FOR EACH ROW EXECUTE FUNCTION refuse_13()")
    try:
        futs = [_ingest(a, "dev-g", q) for q in range(10, 17)]  # queued together: one or a few groups
        outcomes = []
        for f in futs:
            try:
                outcomes.append(f.result(timeout=30).duplicate)
            except Exception as exc:  # noqa: BLE001 - the refusal under test
                outcomes.append(str(exc))
        assert outcomes[:3] == [False] * 3 and outcomes[4:] == [False] * 3, outcomes
        assert "seq 13 refused by a test trigger" in outcomes[3]
        dev, _ = a.current("dev-g")
        assert dev.batches_stored == 6 and a.backlog() == 6
    finally:
        with psycopg.connect(a.url, autocommit=True) as conn:
            conn.execute("DROP TRIGGER refuse_13 ON batches")
            conn.execute("DROP FUNCTION refuse_13()")


def test_a_batch_the_driver_refuses_before_sending_fails_alone(two_stores):
    """A value psycopg refuses before it reaches the server (a NUL byte in a text field,
    which the API's device-id pattern never lets through) fails that ingest alone: the
    transaction is still open, so the rest of its group commits."""
    a, _ = two_stores
    futs = [_ingest(a, "dev-n", 0), _ingest(a, "dev-\x00", 0), _ingest(a, "dev-n", 1)]
    assert not futs[0].result(timeout=30).duplicate and not futs[2].result(timeout=30).duplicate
    with pytest.raises(Exception, match="NUL"):
        futs[1].result(timeout=30)
    dev, _ = a.current("dev-n")
    assert dev.batches_stored == 2


def _rows(store, device):
    """Everything a cycle writes for ``device``, without the device id and write times."""
    dev = store.load_device(device)
    batches = store._read("SELECT seq, state, reason FROM batches WHERE device_id = %s ORDER BY seq", (device,))
    versions = [(v.version, v.status, v.source, v.calibration, v.provenance) for v in store.history(device)]
    return ((dev.processed_seq, dev.samples_processed, dev.calibrator_state, dev.calibrator_status, dev.last_refit,
             dev.feed_state, dev.current_version, dev.state_rev, dev.checkpoint),
            batches, versions)


def test_the_one_round_trip_commit_writes_and_refuses_as_the_statements_do(two_stores):
    """``selfcal_progress()`` (the cycles without rejections or refusals) and the
    statement-by-statement commit, given the same cycles on two devices: the same
    refusals with the same messages, and the same rows written, checkpoints included."""
    a, _ = two_stores
    paths = {"dev-f": a._commit_progress_function, "dev-s": a._commit_progress_statements}
    for device in paths:
        for q in range(4):
            _ingest(a, device, q).result(timeout=30)
        assert device in a.acquire_leases("w", 30.0, 10)

    def cycle(device, **kw):
        dev = a.load_device(device, with_state=False)
        base = dict(device_id=device, expected_processed_seq=dev.processed_seq, expected_state_rev=dev.state_rev,
                    lease_owner="w", samples_added=4, calibrator_state=None, calibrator_status="provisional",
                    last_refit={"t": 1.5}, feed_state={"samples": 4}, new_versions=[])
        base.update(kw)
        return Progress(**base)

    v = [NewVersion("provisional", "refit", {"params": {"b": [0.1]}}, {"n": 1}),
         NewVersion("calibrated", "refit", {"params": {"b": [0.2]}}, {"n": 2})]
    script = [  # (cycle arguments, the refusal expected or None)
        (dict(processed_seq=0, fed_seqs=[0], calibrator_state='{"s": 0}', new_versions=v[:1]), None),
        (dict(processed_seq=2, fed_seqs=[1, 2], new_versions=v), None),  # two versions, no checkpoint
        (dict(processed_seq=3, fed_seqs=[3], expected_state_rev=99), "changed under the worker"),
        (dict(processed_seq=3, fed_seqs=[3], expected_processed_seq=0), "changed under the worker"),
        (dict(processed_seq=3, fed_seqs=[3], lease_owner="other"), "lease of other lost"),
        (dict(processed_seq=3, fed_seqs=[3], calibrator_state='{"s": 3}', calibrator_status="calibrated",
              last_refit=None), None),
    ]
    for kw, refused in script:
        outcomes = {}
        for device, commit in paths.items():
            try:
                outcomes[device] = ("ok", commit(cycle(device, **kw)).result(timeout=30))
            except ConflictError as exc:
                outcomes[device] = ("refused", str(exc).replace(device, "DEV"))
        assert outcomes["dev-f"] == outcomes["dev-s"], kw
        if refused:
            assert outcomes["dev-f"][0] == "refused" and refused in outcomes["dev-f"][1]
        assert _rows(a, "dev-f") == _rows(a, "dev-s"), kw
    # an older checkpoint never replaces a newer one, on either path: the cycle is refused
    # as a conflict (since checkpoint patches: a checkpoint not written is never silent)
    for device, commit in paths.items():
        a.write_checkpoint(device, 3, '{"s": "newer"}', {"samples": 9})
        a._read("UPDATE checkpoints SET seq = 10 WHERE device_id = %s RETURNING 1", (device,))
        with pytest.raises(ConflictError, match="checkpoint changed under the worker"):
            commit(cycle(device, processed_seq=3, fed_seqs=[], calibrator_state='{"s": "older"}')).result(timeout=30)
        assert a.load_device(device).calibrator_state == '{"s": "newer"}'
    assert _rows(a, "dev-f") == _rows(a, "dev-s")
    assert [x.version for x in a.history("dev-f")] == [1, 2, 3]
    # a device the cycle does not find is created only when the checks pass
    with pytest.raises(ConflictError, match="changed under the worker"):
        a._commit_progress_function(Progress(device_id="dev-new", expected_processed_seq=5, processed_seq=6,
                                             samples_added=1, calibrator_state=None, calibrator_status=None,
                                             last_refit=None, feed_state={})).result(timeout=30)
    assert a.load_device("dev-new") is None



def _has_lz4(conn) -> bool:
    from selfcal_service.pg_store import _HAS_LZ4

    return conn.execute(_HAS_LZ4).fetchone()[0]


def _compression(conn) -> dict[str, str]:
    rows = conn.execute("SELECT attrelid::regclass::text || '.' || attname, attcompression FROM pg_attribute "
                        "WHERE attrelid IN ('batches'::regclass, 'checkpoints'::regclass) AND attnum > 0 "
                        "AND NOT attisdropped AND attcompression <> ''").fetchall()
    return dict(rows)


LZ4 = {"batches.payload": "l", "checkpoints.base": "l", "checkpoints.patch": "l"}


def _back_to_pglz(conn) -> None:
    for col in LZ4:
        table, name = col.split(".")
        conn.execute(f"ALTER TABLE {table} ALTER COLUMN {name} SET COMPRESSION pglz")


def test_large_values_are_compressed_with_lz4_from_the_next_start(tmp_path):
    """New payloads and checkpoints are written with lz4 (where the server has it); a
    database whose columns lack it gets it at the next start, and a batch stored with pglz
    before reads back unchanged after it. The schema version does not change."""
    import numpy as np
    import psycopg

    from selfcal_service.pg_store import SCHEMA_VERSION

    url = backend_db(tmp_path / "pg-lz4.db")
    store = PostgresStore(url)
    store.open()
    store.close()
    rng = np.random.default_rng(7)
    # a batch's worth of quantised samples: compressible, and above the 2-kB TOAST threshold
    old_payload = (np.round(rng.normal(0, 50, 3200)) / 1024).astype("<f8").tobytes()
    new_payload = (np.round(rng.normal(0, 50, 3200)) / 1024).astype("<f8").tobytes()
    with psycopg.connect(url, autocommit=True) as conn:
        if not _has_lz4(conn):
            pytest.skip("this PostgreSQL server has no lz4 (before 14, or built without it)")
        assert _compression(conn) == LZ4  # a new database
        _back_to_pglz(conn)  # as a database created before lz4 was set
        conn.execute("INSERT INTO devices(device_id, created_at) VALUES ('dev-z', 0)")
        conn.execute("INSERT INTO batches(device_id, seq, n_samples, received_at, payload) "
                     "VALUES ('dev-z', 0, 800, 0, %s)", (old_payload,))
    store = PostgresStore(url)
    try:
        store.open()
        _ingest(store, "dev-z", 1, payload=new_payload).result(timeout=30)
        got = [(b.seq, bytes(b.payload)) for b in store.pending_batches("dev-z", 10)]
        assert got == [(0, old_payload), (1, new_payload)]
    finally:
        store.close()
    with psycopg.connect(url, autocommit=True) as conn:
        assert conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0] == str(SCHEMA_VERSION)
        assert _compression(conn) == LZ4
        methods = conn.execute("SELECT seq, pg_column_compression(payload) FROM batches "
                               "WHERE device_id = 'dev-z' ORDER BY seq").fetchall()
        assert methods == [(0, "pglz"), (1, "lz4")]


def test_a_start_does_not_wait_on_a_long_reader_to_set_lz4(tmp_path, caplog):
    """ALTER TABLE's exclusive lock would queue every ingest behind a session reading
    ``batches`` (a dump, a long query): the start gives up on lz4 after a short lock
    timeout, opens, ingests, and sets it at a later start."""
    import psycopg

    url = backend_db(tmp_path / "pg-lz4-lock.db")
    store = PostgresStore(url)
    store.open()
    store.close()
    with psycopg.connect(url, autocommit=True) as conn:
        if not _has_lz4(conn):
            pytest.skip("this PostgreSQL server has no lz4 (before 14, or built without it)")
        _back_to_pglz(conn)
    reader = psycopg.connect(url)  # a transaction left open on batches (ACCESS SHARE)
    try:
        reader.execute("SELECT count(*) FROM batches").fetchone()
        store = PostgresStore(url)
        t0 = time.monotonic()
        with caplog.at_level("WARNING", logger="selfcal.service.postgres"):
            store.open()
        try:
            assert time.monotonic() - t0 < 15
            assert "lz4 compression not set" in caplog.text
            assert not _ingest(store, "dev-l", 0).result(timeout=30).duplicate
        finally:
            store.close()
        with psycopg.connect(url, autocommit=True) as conn:
            assert _compression(conn) == {col: "p" for col in LZ4}  # unchanged
    finally:
        reader.close()
    store = PostgresStore(url)
    store.open()
    store.close()
    with psycopg.connect(url, autocommit=True) as conn:
        assert _compression(conn) == LZ4


def _backends(url: str) -> int:
    """Sessions open on ``url``'s database, this one's aside."""
    import psycopg

    with psycopg.connect(url, autocommit=True) as conn:
        return conn.execute("SELECT count(*) FROM pg_stat_activity WHERE datname = current_database() "
                            "AND pid <> pg_backend_pid()").fetchone()[0]


def test_a_read_on_the_event_loop_answers_as_a_read_in_a_thread(two_stores):
    """``current_async`` (the GET route's read, in the event loop) returns what ``current``
    does: an unknown device, a device with batches only, one with a served version."""
    import asyncio

    a, _ = two_stores
    _ingest(a, "dev-2", 0).result(timeout=30)
    _ingest(a, "dev-3", 0).result(timeout=30)
    assert a.acquire_leases("worker-a", 30.0, 10) == ["dev-2", "dev-3"]
    a.commit_progress(_progress(a.load_device("dev-2"), lease_owner="worker-a")).result(timeout=30)

    async def reads():
        return [await a.current_async(d) for d in ("dev-2", "dev-3", "nobody")]

    got = asyncio.run(reads())
    assert got == [a.current("dev-2"), a.current("dev-3"), None]
    assert got[0][1].version == 1 and got[1][1] is None and got[1][0].batches_stored == 1


def _until(cond, timeout_s: float = 10.0) -> bool:
    """Poll ``cond()`` until it holds (True) or ``timeout_s`` passed (False)."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def _terminate_all(url) -> None:
    """End every other session of ``url``'s database (as a server restart does), and wait
    until they are gone."""
    import psycopg

    with psycopg.connect(url, autocommit=True) as conn:
        pids = [r[0] for r in conn.execute(
            "SELECT pg_terminate_backend(pid), pid FROM pg_stat_activity WHERE datname = current_database() "
            "AND pid <> pg_backend_pid()").fetchall() for r in [r[1:]]]
        assert _until(lambda: not conn.execute("SELECT count(*) FROM pg_stat_activity WHERE pid = ANY(%s)",
                                               (pids,)).fetchone()[0])


def _runs_counter(url) -> tuple[str, Callable[[], int]]:
    """A statement that counts its runs on the server (a sequence: a cancelled statement's
    nextval stays) and sleeps 5 s, and the count so far: no clock in the assertion."""
    import psycopg

    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("DROP SEQUENCE IF EXISTS t_runs")
        conn.execute("CREATE SEQUENCE t_runs")

    def runs() -> int:
        with psycopg.connect(url, autocommit=True) as conn:
            value, called = conn.execute("SELECT last_value, is_called FROM t_runs").fetchone()
        return int(value) if called else 0

    return "SELECT nextval('t_runs'), pg_sleep(5)", runs


def _create(url):
    """Create the schema on ``url`` (a store opened and closed)."""
    store = PostgresStore(url)
    store.open()
    store.close()


def _readers(url, limit=3, **kw):
    """An AsyncReaders pool on ``url`` with the store's connection arguments (and ``kw``)."""
    from selfcal_service.pg_async import AsyncReaders

    base = PostgresStore(url)._connect_kwargs
    return AsyncReaders(lambda: {**base(), **kw}, limit=limit)


def test_event_loop_reads_bound_their_connections_and_replace_a_broken_one(tmp_path):
    """At most ``limit`` connections however many reads wait; the idle connections a
    restarted server broke are replaced by one new connection, once; a statement timeout
    is not retried and leaves the other idle connections alone."""
    import asyncio

    from selfcal_service.storage import StorageUnavailable

    url = backend_db(tmp_path / "pg-async.db")
    _create(url)

    async def scenario():
        readers = _readers(url, limit=3, options="-c statement_timeout=1000")
        peak = 0

        async def one(i):
            nonlocal peak
            rows = await readers.read("SELECT %s::int, pg_sleep(0.05)", (i,))
            peak = max(peak, readers.connections)
            return rows[0][0]

        assert sorted(await asyncio.gather(*(one(i) for i in range(30)))) == list(range(30))
        assert peak == 3 and readers.connections == 3
        assert await asyncio.to_thread(_backends, url) == 3
        idle = list(readers._idle)
        slow, runs = await asyncio.to_thread(_runs_counter, url)
        with pytest.raises(StorageUnavailable, match="QueryCanceled"):
            await readers.read(slow)
        assert await asyncio.to_thread(runs) == 1  # one statement timeout, not retried
        assert readers.connections == 2 and all(not c.closed for c in readers._idle)
        # the server ends every session (a restart): the next read reconnects, once
        await asyncio.to_thread(_terminate_all, url)
        assert (await readers.read("SELECT 41 + 1"))[0][0] == 42
        assert readers.connections == 1 and all(c.closed for c in idle)
        # a statement that ends its own session: run again once on a new connection, then a 503
        with pytest.raises(StorageUnavailable, match="read failed"):
            await readers.read("SELECT pg_terminate_backend(pg_backend_pid())")
        assert readers.connections == 0
        readers.close()
        with pytest.raises(StorageUnavailable, match="closed"):
            await readers.read("SELECT 1")

    asyncio.run(scenario())
    assert _until(lambda: _backends(url) == 0)


def test_a_cancelled_read_returns_at_once_and_its_statement_ends_on_its_own(tmp_path):
    """A caller cancelled mid-read (a client gone) is not held by the statement; the
    statement finishes on its own connection, within the limit, which then serves again."""
    import asyncio

    url = backend_db(tmp_path / "pg-async-cancel.db")
    _create(url)

    async def scenario():
        readers = _readers(url, limit=2)
        assert (await readers.read("SELECT 6"))[0][0] == 6  # one connection, idle
        t0 = time.monotonic()
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(readers.read("SELECT pg_sleep(6)"), 0.2)
        assert time.monotonic() - t0 < 4.0  # not held by the statement (6 s) nor psycopg's cancel (5 s)
        assert readers.connections == 1 and not readers._idle  # still running its statement
        assert (await readers.read("SELECT 7"))[0][0] == 7  # the other slot, a new connection
        deadline = time.monotonic() + 20
        while len(readers._idle) < 2 and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        assert readers.connections == 2 and len(readers._idle) == 2  # back in the pool, not closed under it
        assert (await readers.read("SELECT 8"))[0][0] == 8
        readers.close()

    asyncio.run(scenario())


def test_closing_while_reads_run_ends_each_with_rows_or_a_503_and_closes_every_connection(tmp_path):
    """In the loop (an app's shutdown) and from another thread (``store.close()``): no read
    hangs, none fails with anything but StorageUnavailable, no connection is closed under
    a running statement, and every connection is closed in the end."""
    import asyncio
    import threading

    from selfcal_service.storage import StorageUnavailable

    url = backend_db(tmp_path / "pg-async-close.db")
    store = PostgresStore(url, max_idle_readers=3)
    store.open()
    _ingest(store, "dev-c", 0).result(timeout=30)

    async def in_the_loop():
        readers = _readers(url, limit=3)
        tasks = [asyncio.ensure_future(readers.read("SELECT %s::int, pg_sleep(0.5)", (i,))) for i in range(8)]
        deadline = time.monotonic() + 10
        while readers.connections < 3 and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        running = list(readers._open)
        assert len(running) == 3
        readers.close()
        done = await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 15)
        rows = [d for d in done if isinstance(d, list)]
        refused = [d for d in done if isinstance(d, StorageUnavailable)]
        assert len(rows) == 3 and len(refused) == 5, done  # the running three finished, the waiting refused
        assert readers.connections == 0 and all(c.closed for c in running)

    asyncio.run(in_the_loop())
    outcomes: list = []

    def reader_thread():
        async def reads():
            async def one():
                while True:
                    try:
                        outcomes.append(await store.current_async("dev-c"))
                    except StorageUnavailable as exc:
                        outcomes.append(exc)
                        return
            await asyncio.gather(*(one() for _ in range(6)))
        asyncio.run(reads())

    t = threading.Thread(target=reader_thread)
    t.start()
    assert _until(lambda: len(outcomes) >= 20)  # the other loop reads
    store.close()  # from this thread, while the other's loop reads
    t.join(15)
    assert not t.is_alive()
    assert len(outcomes) > 20 and sum(isinstance(o, StorageUnavailable) for o in outcomes) == 6
    assert all(isinstance(o, StorageUnavailable) or o[0].batches_stored == 1 for o in outcomes)
    assert _until(lambda: _backends(url) == 0)

    async def after():
        return await store.current_async("dev-c")

    with pytest.raises(StorageUnavailable, match="closed"):
        asyncio.run(after())
    with pytest.raises(StorageUnavailable, match="closed"):  # the thread reads too
        store.current("dev-c")
    assert _until(lambda: _backends(url) == 0)


def test_closing_refuses_the_reads_waiting_for_a_turn_at_once(tmp_path):
    """Reads queued behind a long statement are refused when the pool closes, not when
    the statement ends; a failed connect while the pool has a connection open fails that
    read alone (the server is up), not every read for a while."""
    import asyncio

    from selfcal_service.storage import StorageUnavailable

    url = backend_db(tmp_path / "pg-async-waiters.db")
    _create(url)

    async def scenario():
        readers = _readers(url, limit=1)
        long = asyncio.ensure_future(readers.read("SELECT pg_sleep(6)"))
        waiting = [asyncio.ensure_future(readers.read("SELECT 1")) for _ in range(3)]
        await asyncio.sleep(0.3)
        t0 = time.monotonic()
        readers.close()
        done = await asyncio.wait_for(asyncio.gather(*waiting, return_exceptions=True), 10)
        assert time.monotonic() - t0 < 4.0, "the waiting reads waited for the statement (6 s)"
        assert all(isinstance(d, StorageUnavailable) for d in done), done
        assert len(await long) == 1  # the running statement ends normally
        assert readers.connections == 0

        good = PostgresStore(url)._connect_kwargs
        calls = []

        def kwargs():  # the first connect works; the next ones find nobody listening
            calls.append(1)
            return good() if len(calls) == 1 else {**good(), "conninfo": f"postgresql://x@127.0.0.1:{_free_port()}/x"}

        from selfcal_service.pg_async import AsyncReaders

        readers = AsyncReaders(kwargs, limit=2)
        long = asyncio.ensure_future(readers.read("SELECT pg_sleep(0.5)"))
        while readers.connections < 1:
            await asyncio.sleep(0.01)
        for _ in range(2):  # each tries its own connect: no "not reached" window with one open
            with pytest.raises(StorageUnavailable, match="read failed"):
                await readers.read("SELECT 1")
        await long
        assert (await readers.read("SELECT 2"))[0][0] == 2  # on the pooled connection
        readers.close()

    asyncio.run(scenario())


def test_reads_fail_fast_on_a_server_that_does_not_answer_and_never_block_the_loop(tmp_path):
    """A host that accepts TCP and never answers: the first reads wait out the connect
    timeout (2 s, libpq's least) in the loop without blocking it; the reads waiting behind
    them fail at once instead of each waiting its own."""
    import asyncio
    import socket

    from selfcal_service.storage import StorageUnavailable

    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(64)  # the kernel completes handshakes; nobody ever answers
    url = f"postgresql://selfcal@127.0.0.1:{silent.getsockname()[1]}/nothing"

    async def scenario():
        readers = _readers(url, limit=8, connect_timeout=2)
        gaps = []

        async def ticker():
            last = time.monotonic()
            while True:
                await asyncio.sleep(0.01)
                now = time.monotonic()
                gaps.append(now - last)
                last = now

        tick = asyncio.ensure_future(ticker())
        t0 = time.monotonic()
        done = await asyncio.gather(*(readers.read("SELECT 1") for _ in range(20)), return_exceptions=True)
        took = time.monotonic() - t0
        tick.cancel()
        assert all(isinstance(d, StorageUnavailable) for d in done), done
        assert 1.0 < took < 5.0  # one connect timeout, 2 s (without the fail-fast: 3 rounds, 6 s)
        assert max(gaps) < 1.5 and readers.connections == 0  # a connect holding the loop: >= 2 s

    try:
        asyncio.run(scenario())
    finally:
        silent.close()


def test_a_thread_read_after_the_server_ended_every_session_reconnects(tmp_path):
    """The reader pool's idle connections all die together when the server restarts: the
    read retries on a new connection, not on another dead one from the pool. A statement
    timeout is not retried, and leaves the other idle connections alone."""
    from selfcal_service.storage import StorageUnavailable

    url = backend_db(tmp_path / "pg-restart.db")
    store = PostgresStore(url, max_idle_readers=4, statement_timeout_s=1.0)
    store.open()
    try:
        store._idle.extend(store._connect() for _ in range(4))
        slow, runs = _runs_counter(url)
        with pytest.raises(StorageUnavailable, match="QueryCanceled"):
            store._read(slow)
        assert runs() == 1  # one statement timeout, not retried
        assert len(store._idle) == 3
        _terminate_all(url)
        assert store.current("nobody") is None
        assert len(store._idle) == 1
    finally:
        store.close()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_thread_read_whose_reconnect_fails_is_a_503(tmp_path):
    """After a restart broke the pooled connection, the retry's new connection can fail too
    (the server not back yet): StorageUnavailable (the route's 503), not psycopg's error."""
    from selfcal_service.storage import StorageUnavailable

    url = backend_db(tmp_path / "pg-reconnect.db")
    store = PostgresStore(url)
    store.open()
    try:
        store._idle.append(store._connect())
        _terminate_all(url)
        good = store._connect_kwargs
        store._connect_kwargs = lambda: {**good(), "conninfo": f"postgresql://x@127.0.0.1:{_free_port()}/x"}
        with pytest.raises(StorageUnavailable, match="read failed"):
            store.current("nobody")
    finally:
        store.close()
