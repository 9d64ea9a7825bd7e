"""SQLite spool (persisted batch seq, order) and the HTTP forwarder (retry, backoff, reject)."""

from __future__ import annotations

import asyncio
import json

from gw_fake_service import FakeService
from gw_helpers import run

from selfcal.gateway.forwarder import Forwarder
from selfcal.gateway.spool import Spool


def _body(seq: int, n: int = 3) -> bytes:
    return json.dumps({"seq": seq, "t_s": [0.0] * n, "ax_g": [0.0] * n, "ay_g": [0.0] * n, "az_g": [1.0] * n}).encode()


def test_batch_seq_and_unwrap_state_survive_reopening(tmp_path):
    path = tmp_path / "spool.db"
    spool = Spool(path)
    assert [spool.put_batch("a", 3, _body, 9, 0) for _ in range(3)] == [0, 1, 2]
    assert spool.put_batch("b", 3, _body, 99, 7) == 0
    spool.close()
    spool = Spool(path)
    state = spool.device_state("a")
    assert (state.next_batch_seq, state.last_count, state.count_offset) == (3, 9, 0)
    assert spool.device_state("b").count_offset == 7
    assert spool.put_batch("a", 3, _body, 12, 0) == 3
    # the head of each device is its oldest batch; bodies carry their own seq
    heads = {b.device_id: b for b in spool.heads()}
    assert heads["a"].seq == 0 and json.loads(heads["a"].body)["seq"] == 0
    spool.ack(heads["a"])
    assert {b.device_id: b.seq for b in spool.heads()} == {"a": 1, "b": 0}
    assert spool.depth() == {"a": (3, 9), "b": (1, 3)}


def test_forwarder_retries_with_backoff_then_delivers_in_order(tmp_path):
    service = FakeService(up=False)
    spool = Spool(tmp_path / "s.db")
    for _ in range(5):
        spool.put_batch("dev-1", 3, _body, None, 0)
    acks = []

    async def body():
        fwd = Forwarder(
            "http://svc", service.key, spool, transport=service.transport(),
            backoff_initial_s=0.01, backoff_max_s=0.05,
            on_ack=lambda d, n, dup: acks.append((d, n, dup)),
        )
        assert not await fwd.flush(0.2)
        assert fwd.service_up is False and "503" in fwd.last_error
        assert fwd.retries >= 2
        service.up = True
        assert await fwd.flush(2.0)
        await fwd.stop()

    run(body())
    assert service.order["dev-1"] == [0, 1, 2, 3, 4]
    assert acks == [("dev-1", 3, False)] * 5
    assert spool.heads() == []


def test_lost_acknowledgement_is_resent_and_deduplicated(tmp_path):
    service = FakeService(fail_after_commit=1)  # commits seq 0 but answers 500
    spool = Spool(tmp_path / "s.db")
    spool.put_batch("dev-1", 3, _body, None, 0)
    spool.put_batch("dev-1", 3, _body, None, 0)

    async def body():
        fwd = Forwarder("http://svc", service.key, spool, transport=service.transport(), backoff_initial_s=0.01)
        assert await fwd.flush(2.0)
        await fwd.stop()
        return fwd

    fwd = run(body())
    assert service.order["dev-1"] == [0, 1]
    assert service.duplicates == 1 and fwd.duplicates == 1
    assert service.n_samples("dev-1") == 6  # the resend was not counted twice


def test_refused_batches_go_to_the_rejected_table_and_do_not_block(tmp_path):
    service = FakeService()
    spool = Spool(tmp_path / "s.db")
    spool.put_batch("dev-1", 3, lambda seq: b'{"seq": %d}' % seq, None, 0)  # no t_s: 422
    spool.put_batch("dev-1", 3, _body, None, 0)

    async def body():
        fwd = Forwarder("http://svc", service.key, spool, transport=service.transport())
        assert await fwd.flush(2.0)
        await fwd.stop()
        return fwd

    fwd = run(body())
    assert fwd.rejected == 1 and spool.rejected_count() == 1
    assert service.order["dev-1"] == [1]


def test_wrong_key_keeps_batches_and_reports_401(tmp_path):
    service = FakeService()
    spool = Spool(tmp_path / "s.db")
    spool.put_batch("dev-1", 3, _body, None, 0)

    async def body():
        fwd = Forwarder("http://svc", "wrong-key", spool, transport=service.transport(), backoff_initial_s=0.01)
        assert not await fwd.flush(0.1)
        await fwd.stop()
        return fwd

    fwd = run(body())
    assert "HTTP 401" in fwd.last_error
    assert len(spool.heads()) == 1 and spool.rejected_count() == 0


def test_stop_returns_even_when_woken_in_the_same_iteration(tmp_path):
    """Regression: on Python 3.11 `asyncio.wait_for` could swallow the cancel of stop()
    when the wake event was set in the same loop iteration; stop() then never returned."""
    import asyncio

    service = FakeService()
    spool = Spool(tmp_path / "s.db")

    async def body():
        for _ in range(200):
            fwd = Forwarder("http://svc", service.key, spool, transport=service.transport())
            fwd.start()
            await asyncio.sleep(0)
            fwd.wake()
            await asyncio.wait_for(fwd.stop(), timeout=5.0)

    run(body(), timeout_s=60)


def _samples_body(t0: float, n: int = 3):
    return lambda seq: json.dumps({"seq": seq, "t_s": [t0 + i for i in range(n)], "ax_g": [0.0] * n,
                                   "ay_g": [0.0] * n, "az_g": [1.0] * n}).encode()


def test_a_seq_the_service_holds_with_other_content_is_renumbered_not_dropped(tmp_path):
    """A lost or replaced spool starts its seqs at 0 again; the service holds those seqs
    with the old spool's batches and answers 409. The batches were moved to ``rejected``
    (their samples lost); now the device's pending batches get new seqs, further ahead at
    each 409 in a row, and every sample arrives, in order."""
    service = FakeService()
    service.conflicting("dev-1", range(10))
    spool = Spool(tmp_path / "s.db")
    for k in range(3):
        spool.put_batch("dev-1", 3, _samples_body(100.0 + 3 * k), None, 0)
    spool.put_batch("dev-2", 3, _samples_body(0.0), None, 0)
    fwd = run(_flush(service, spool))
    assert fwd.rejected == 0 and spool.rejected_count() == 0 and fwd.renumbered >= 3
    new = service.order["dev-1"][10:]
    assert len(new) == 3 and min(new) >= 10 and new == sorted(new) and new[-1] - new[0] == 2  # kept together
    assert service.samples("dev-1")["t_s"][-9:] == [100.0 + i for i in range(9)]  # every sample, in order
    assert all(service.batches[("dev-1", s)]["seq"] == s for s in new)  # each body names its new seq
    assert spool.next_seq("dev-1") == new[-1] + 1 and service.order["dev-2"] == [0]
    # the next batch follows them
    spool.put_batch("dev-1", 3, _samples_body(200.0), None, 0)
    run(_flush(service, spool))
    assert service.order["dev-1"][-1] == new[-1] + 1


async def _flush(service, spool) -> Forwarder:
    """A forwarder that empties the spool (within 5 s), then stops."""
    fwd = Forwarder("http://svc", service.key, spool, transport=service.transport(), backoff_initial_s=0.01)
    assert await fwd.flush(5.0)
    await fwd.stop()
    return fwd


def test_renumbering_refuses_a_start_below_the_pending_seqs(tmp_path):
    import pytest

    from selfcal.gateway.errors import GatewayError

    spool = Spool(tmp_path / "s.db")
    for _ in range(3):
        spool.put_batch("dev-1", 3, _body, None, 0)
    with pytest.raises(GatewayError, match="not above"):
        spool.renumber("dev-1", 2)
    assert [b.seq for b in spool.heads()] == [0]  # nothing changed
    assert spool.renumber("dev-1", 7) == 3 and spool.next_seq("dev-1") == 10
    assert [json.loads(b.body)["seq"] for b in spool.heads()] == [7]


def test_one_device_whose_posts_always_fail_holds_back_no_other(tmp_path):
    """Each round posted every device's head and backed off as a whole when any post
    failed: one device answered 500 for good moved the others at one batch per backoff.
    Now that device waits out its own backoff while the others drain."""
    service = FakeService(fail_devices={"dead"})
    spool = Spool(tmp_path / "s.db")
    spool.put_batch("dead", 3, _body, None, 0)
    for _ in range(10):
        spool.put_batch("live", 3, _body, None, 0)

    async def body():
        fwd = Forwarder("http://svc", service.key, spool, transport=service.transport(),
                        backoff_initial_s=30.0, backoff_max_s=60.0)
        fwd.start()
        fwd.wake()
        while len(service.order.get("live", [])) < 10:
            await asyncio.sleep(0.01)
        await fwd.stop()
        return fwd

    fwd = run(body())
    assert service.order["live"] == list(range(10))
    assert service.posts["dead"] == 1  # posted once, then waiting its own 15-30 s backoff
    assert [b.device_id for b in spool.heads()] == ["dead"] and fwd.retries == 1
