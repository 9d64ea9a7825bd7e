"""The refusal log and the fleet query at the store level, on the backend of this pass.

``commit_progress`` appends a cycle's refusals in its transaction and keeps a device's
newest ``REFUSALS_KEPT_PER_DEVICE``; ``fleet`` returns each device's newest refusal, its
backlog and the served version's figures; a PostgreSQL database of schema 1 migrates (to 3).
"""

from __future__ import annotations

import hashlib
import time

import pytest

from service_helpers import backend, backend_db, only_postgres

from selfcal_service.storage import NewVersion, Progress, RefusalRecord


def _open(tmp_path):
    if backend() == "postgresql":
        from selfcal_service.pg_store import PostgresStore

        store = PostgresStore(backend_db(tmp_path / "refusals.db"))
    else:
        from selfcal_service.sqlite_store import SQLiteStore

        store = SQLiteStore(str(tmp_path / "refusals.db"))
    store.open()
    return store


def _cycle(device, refusals, versions=()):
    return Progress(device_id=device, expected_processed_seq=None, processed_seq=None, samples_added=0,
                    calibrator_state=None, calibrator_status=None, last_refit=None, feed_state={},
                    new_versions=list(versions), refusals=refusals)


def _ingest(store, device, seq):
    payload = f"{device}-{seq}".encode()
    store.submit_batch(device, seq, 4, payload, time.time(), hashlib.sha256(payload).digest(), 1000).result(timeout=30)


def test_refusals_are_appended_trimmed_per_device_and_listed_in_the_fleet(tmp_path, monkeypatch):
    import selfcal_service.pg_store as pg_store
    import selfcal_service.sqlite_store as sqlite_store

    monkeypatch.setattr(sqlite_store, "REFUSALS_KEPT_PER_DEVICE", 5)
    monkeypatch.setattr(pg_store, "REFUSALS_KEPT_PER_DEVICE", 5)
    store = _open(tmp_path)
    try:
        calib = {"model": "affine9", "params": {}, "predicted_sphere_rms_mg": 3.25, "n_poses": 17,
                 "residual_rms_mg": 0.5}
        store.commit_progress(_cycle("dev-a", [], [NewVersion("provisional", "refit", calib, {})])).result(timeout=30)
        for k in range(3):  # 9 refusals in 3 cycles: the newest 5 stay
            store.commit_progress(_cycle("dev-a", [
                RefusalRecord("refit", "no_significant_change", f"cycle {k} refit {i}", t_s=100.0 * k + i)
                for i in range(2)] + [RefusalRecord("batch", "late", f"late: seq {k}", seq=k)])).result(timeout=30)
        store.commit_progress(_cycle("dev-b", [RefusalRecord("refit", "insufficient_coverage", "2 cells")])).result(
            timeout=30)
        for seq in range(3):
            _ingest(store, "dev-b", seq)
        kept = store.refusals("dev-a", 100)
        assert [(r.kind, r.message) for r in kept] == [
            ("refit", "cycle 1 refit 0"), ("refit", "cycle 1 refit 1"), ("batch", "late: seq 1"),
            ("refit", "cycle 2 refit 0"), ("refit", "cycle 2 refit 1"), ("batch", "late: seq 2")][1:]
        assert kept[-1].seq == 2 and kept[-2].t_s == 201.0 and all(r.at is not None for r in kept)
        assert [r.message for r in store.refusals("dev-a", 2)] == ["cycle 2 refit 1", "late: seq 2"]
        assert [r.reason for r in store.refusals("dev-b", 100)] == ["insufficient_coverage"]
        a, b = store.fleet(None, 10)
        assert (a.device_id, a.status, a.version, a.source, a.model) == ("dev-a", "provisional", 1, "refit", "affine9")
        assert (a.predicted_sphere_rms_mg, a.n_poses, a.residual_rms_mg) == (3.25, 17, 0.5)
        assert a.last_refusal == kept[-1] and a.backlog_batches == 0 and a.last_seen is None
        assert b.version is None and b.status == "uncalibrated" and b.backlog_batches == 3
        assert b.last_seen is not None and b.last_refusal.reason == "insufficient_coverage"
        assert [f.device_id for f in store.fleet("dev-a", 10)] == ["dev-b"]
        assert [f.device_id for f in store.fleet(None, 10, "dev-b")] == ["dev-b"]
        assert store.fleet(None, 10, "dev-z") == []
    finally:
        store.close()


@only_postgres
def test_a_schema_1_postgres_database_gets_the_refusal_log(tmp_path):
    import psycopg

    from selfcal_service.pg_store import SCHEMA_VERSION, PostgresStore

    url = backend_db(tmp_path / "pg-v1.db")
    store = PostgresStore(url)
    store.open()
    store.close()
    with psycopg.connect(url, autocommit=True) as conn:  # back to what schema 1 had
        conn.execute("DROP TABLE refusals")
        conn.execute("DROP FUNCTION selfcal_ingest")  # v3's one-round-trip ingest
        conn.execute("DROP FUNCTION selfcal_progress")  # v5's one-round-trip worker commit
        conn.execute("ALTER TABLE devices DROP COLUMN last_owner")  # v5's lease affinity
        conn.execute("ALTER TABLE devices DROP CONSTRAINT devices_leases_by_heartbeat")  # v5's leases
        conn.execute("ALTER TABLE devices DROP COLUMN lease_expires")
        conn.execute("DROP TABLE checkpoints")  # v4: the state in devices.calibrator_state until then
        conn.execute("DROP TABLE workers")
        conn.execute("ALTER TABLE devices DROP CONSTRAINT devices_state_in_checkpoints")
        conn.execute("INSERT INTO devices(device_id, created_at, processed_seq, calibrator_state, feed_state) "
                     "VALUES ('dev-s', 0, 4, '{\"s\": 1}', '{\"samples\": 100}')")
        conn.execute("UPDATE meta SET value = '1' WHERE key = 'schema_version'")
    store = PostgresStore(url)
    store.open()
    try:
        store.commit_progress(_cycle("dev-m", [RefusalRecord("refit", "implausible", "scale")])).result(timeout=30)
        assert [r.reason for r in store.refusals("dev-m", 10)] == ["implausible"]
        # v3: ingest through the function the migration created
        first = store.submit_batch("dev-m", 0, 1, b"x", 1.0, b"d", 1000).result(timeout=30)
        again = store.submit_batch("dev-m", 0, 1, b"x", 1.0, b"d", 1000).result(timeout=30)
        assert (first.duplicate, again.duplicate) == (False, True)
        # v4: the calibrator state is the device's checkpoint at its processed seq
        rec = store.load_device("dev-s")
        assert rec.calibrator_state == '{"s": 1}' and rec.checkpoint.seq == 4
        assert rec.checkpoint.feed_state == {"samples": 100}
        # v5: a cycle without refusals commits through the function the migration created
        cycle = _cycle("dev-s", [])
        cycle.expected_processed_seq, cycle.processed_seq, cycle.fed_seqs = 4, 5, [5]
        assert store.commit_progress(cycle).result(timeout=30) == []
        assert store.load_device("dev-s", with_state=False).processed_seq == 5
    finally:
        store.close()
    with psycopg.connect(url, autocommit=True) as conn:
        assert conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0] == str(SCHEMA_VERSION)
        assert conn.execute("SELECT calibrator_state FROM devices WHERE device_id = 'dev-s'").fetchone() == (None,)
        with pytest.raises(psycopg.errors.CheckViolation):  # a schema-3 process cannot write a state there
            conn.execute("UPDATE devices SET calibrator_state = '{}' WHERE device_id = 'dev-s'")
        with pytest.raises(psycopg.errors.CheckViolation):  # nor a schema-4 worker take or renew a lease
            conn.execute("UPDATE devices SET lease_owner = 'old', lease_until = 1e12 WHERE device_id = 'dev-s'")
        # v6: one cycle function, the one that takes a checkpoint patch
        assert conn.execute("SELECT array_agg(pronargs) FROM pg_proc WHERE proname = 'selfcal_progress'"
                            ).fetchone()[0] == [18]
    assert SCHEMA_VERSION == 6


@only_postgres
def test_a_schema_5_postgres_database_gets_checkpoint_patches(tmp_path):
    """v5 -> v6: the checkpoints get a patch column (the stored states are bases, with no
    tag: no patch is written onto one, the next checkpoint is in full) and the cycle
    function of schema 5 is dropped, so a schema-5 worker left running cannot commit a
    full state under another worker's patch; a cycle then commits a patch."""
    from selfcal_service.storage import ConflictError, base_tag_of

    import psycopg

    from selfcal_service.pg_store import PostgresStore

    url = backend_db(tmp_path / "pg-v5.db")
    store = PostgresStore(url)
    store.open()
    store.close()
    args = "TEXT, BIGINT, BIGINT, TEXT, BIGINT, BIGINT, TEXT, TEXT, TEXT, DOUBLE PRECISION, TEXT, BIGINT[], " \
           "TEXT[], TEXT[], TEXT[], TEXT[]"
    with psycopg.connect(url, autocommit=True) as conn:  # back to schema 5
        conn.execute("DROP FUNCTION selfcal_progress")
        conn.execute(f"CREATE FUNCTION selfcal_progress({args}, OUT conflict TEXT, OUT numbers INTEGER[], "
                     "OUT error TEXT) LANGUAGE sql AS $$ SELECT 'schema 5'::text, NULL::integer[], NULL::text $$")
        conn.execute("ALTER TABLE checkpoints DROP COLUMN patch")
        conn.execute("ALTER TABLE checkpoints DROP COLUMN base_tag")
        conn.execute("ALTER TABLE checkpoints RENAME COLUMN base TO state")
        conn.execute("INSERT INTO devices(device_id, created_at, processed_seq, feed_state) "
                     "VALUES ('dev-5', 0, 4, '{\"samples\": 100}')")
        conn.execute("INSERT INTO checkpoints(device_id, seq, state, feed_state, written_at) "
                     "VALUES ('dev-5', 4, '{\"s\": 1}', '{\"samples\": 100}', 0)")
        conn.execute("UPDATE meta SET value = '5' WHERE key = 'schema_version'")
    store = PostgresStore(url)
    store.open()
    try:
        rec = store.load_device("dev-5")
        assert (rec.calibrator_state, rec.calibrator_patch, rec.checkpoint.seq) == ('{"s": 1}', None, 4)
        assert rec.calibrator_base_tag is None
        cycle = _cycle("dev-5", [])
        cycle.expected_processed_seq, cycle.processed_seq, cycle.fed_seqs = 4, 5, [5]
        cycle.calibrator_patch, cycle.calibrator_patch_base = '{"p": 5}', base_tag_of('{"s": 1}')
        with pytest.raises(ConflictError, match="checkpoint changed"):
            store.commit_progress(cycle).result(timeout=30)
        cycle.calibrator_state, cycle.calibrator_patch, cycle.calibrator_patch_base = '{"s": 5}', None, None
        assert store.commit_progress(cycle).result(timeout=30) == []
        cycle = _cycle("dev-5", [])
        cycle.expected_processed_seq, cycle.processed_seq, cycle.fed_seqs = 5, 6, [6]
        cycle.calibrator_patch, cycle.calibrator_patch_base = '{"p": 6}', base_tag_of('{"s": 5}')
        assert store.commit_progress(cycle).result(timeout=30) == []
        rec = store.load_device("dev-5")
        assert (rec.calibrator_state, rec.calibrator_patch, rec.checkpoint.seq) == ('{"s": 5}', '{"p": 6}', 6)
    finally:
        store.close()
    with psycopg.connect(url, autocommit=True) as conn:
        assert conn.execute("SELECT array_agg(pronargs) FROM pg_proc WHERE proname = 'selfcal_progress'"
                            ).fetchone()[0] == [18]
        with pytest.raises(psycopg.errors.UndefinedColumn):  # a schema-5 worker's checkpoint write
            conn.execute("INSERT INTO checkpoints(device_id, seq, state, feed_state, written_at) "
                         "VALUES ('dev-5', 6, '{}', '{}', 0) ON CONFLICT (device_id) DO UPDATE SET state = excluded.state")


def test_the_refit_worker_logs_refits_without_a_model_and_rejected_batches():
    from selfcal_service.worker import refusals_of

    events = [{"published": True, "t_s": 1.0},
              {"published": False, "reason": "worse_than_current", "message": "x" * 500, "t_s": 2.5},
              {"published": False, "reason": None, "message": None, "t_s": "not a time"}]
    out = refusals_of(events, [(7, 20, "late: seq 7 arrived after seq 9 was fed")])
    assert [(r.kind, r.reason, r.t_s, r.seq) for r in out] == [
        ("refit", "worse_than_current", 2.5, None), ("refit", None, None, None), ("batch", "late", None, 7)]
    assert len(out[0].message) == 300 and out[2].message.startswith("late: seq 7")
