"""The unchanged gateway over the bumble virtual BLE stack, against a fake service."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from gw_fake_service import FakeService, LiveServer
from gw_helpers import FAST_CONFIG, run

from selfcal.gateway import Gateway
from selfcal.gateway.virtual import VirtualBleStack

pytestmark = pytest.mark.ble


def _gateway(stack, service, spool_path, **config):
    return Gateway(
        "http://service.test", service.key, spool_path=spool_path, ble=stack.backend(),
        config={**FAST_CONFIG, **config}, http_transport=service.transport(),
    )


def _connected(n):
    return lambda s: s["totals"]["devices_connected"] == n


def _contiguous(service, device_id):
    t = np.array(service.samples(device_id)["t_s"])
    return t, np.allclose(np.diff(t), 0.05)


def test_streams_many_insoles_at_20_hz_in_order_without_loss(tmp_path):
    service = FakeService()

    async def body():
        async with VirtualBleStack() as stack:
            insoles = await stack.start_insoles(4)
            async with _gateway(stack, service, tmp_path / "spool.db") as gw:
                await gw.wait_for(_connected(4), 10)
                await gw.wait_for(lambda s: all(d["samples_forwarded"] >= 40 for d in s["devices"].values()), 10)
            stats = gw.stats()
            return insoles, stats

    insoles, stats = run(body())
    for insole in insoles:
        dev = stats["devices"][insole.device_id]
        assert dev["samples_received"] == insole.samples_sent > 0
        assert dev["samples_forwarded"] == dev["samples_received"]  # graceful stop flushed
        assert (dev["gaps"], dev["malformed_packets"], dev["spool_batches"]) == (0, 0, 0)
        assert service.order[insole.device_id] == list(range(len(service.order[insole.device_id])))
        t, uniform = _contiguous(service, insole.device_id)
        assert uniform and len(t) == insole.samples_sent
        assert t[0] == pytest.approx(round(t[0] * 20) / 20)  # device time: index / 20 Hz
    assert stats["totals"]["duplicates"] == 0 and service.duplicates == 0


def test_custom_sample_source_values_reach_the_service_quantised(tmp_path):
    service = FakeService()
    rate = 20.0

    def ramp():
        k = 0
        while True:
            idx = np.arange(k, k + 7)
            t = idx / rate
            acc = np.stack([np.sin(t), np.cos(t), 0.001 * idx], axis=1)
            prs = np.stack([idx * 0.25 % 1000, np.full(7, 10.0), np.full(7, 20.5), np.zeros(7)], axis=1)
            yield t, acc, prs, np.full(7, 31.2)
            k += 7

    async def body(tmp):
        async with VirtualBleStack() as stack:
            (insole,) = await stack.start_insoles(1, source_factory=lambda i: ramp(), speed=10.0)
            async with _gateway(stack, service, tmp) as gw:
                await gw.wait_for(lambda s: s["totals"]["samples_forwarded"] >= 200, 10)
        return insole

    insole = run(body(tmp_path / "s.db"))
    got = service.samples(insole.device_id)
    t = np.array(got["t_s"])
    idx = np.rint(t * rate).astype(int)
    np.testing.assert_allclose(np.array(got["ax_g"]), np.sin(idx / rate), atol=0.5 / 4096 + 1e-6)
    np.testing.assert_allclose(np.array(got["az_g"]), 0.001 * idx, atol=0.5 / 4096 + 1e-6)
    np.testing.assert_allclose(np.array(got["pressure_kpa"])[:, 2], 20.5)
    np.testing.assert_allclose(np.array(got["temp_c"]), 31.2)


def test_time_acceleration_sends_device_time_faster_than_wall_time(tmp_path):
    service = FakeService()

    async def body():
        async with VirtualBleStack() as stack:
            (insole,) = await stack.start_insoles(1, speed=100.0)
            async with _gateway(stack, service, tmp_path / "s.db", batch_max_samples=400) as gw:
                await gw.wait_for(lambda s: s["totals"]["samples_forwarded"] >= 2000, 15)
        return insole

    insole = run(body())
    t, uniform = _contiguous(service, insole.device_id)
    assert uniform and t[-1] - t[0] >= 99.9  # >= 100 s of device time in about a wall second


def test_reconnects_after_peripheral_disconnect_and_link_loss(tmp_path):
    service = FakeService()

    async def body():
        async with VirtualBleStack() as stack:
            a, b = await stack.start_insoles(2, advertising_interval_ms=100, speed=4.0)
            async with _gateway(stack, service, tmp_path / "s.db") as gw:
                await gw.wait_for(_connected(2), 10)
                await gw.wait_for(lambda s: s["totals"]["samples_received"] >= 40, 10)
                await a.disconnect()  # peripheral-initiated
                assert b.drop_link() == 1  # supervision timeout, nothing over the air
                await gw.wait_for(lambda s: all(l["connects"] == 2 for l in s["links"].values()), 10)
                before = gw.stats()["devices"]
                await gw.wait_for(
                    lambda s: all(s["devices"][k]["samples_received"] > before[k]["samples_received"] + 20 for k in before), 10
                )
            return a, b, gw.stats()

    a, b, stats = run(body())
    for insole in (a, b):
        dev = stats["devices"][insole.device_id]
        link = stats["links"][insole.address]
        assert link["disconnects"] == 1
        assert dev["samples_received"] == insole.samples_sent
        assert service.n_samples(insole.device_id) == dev["samples_received"]
        # whatever the insole produced while nobody listened is accounted as lost:
        # received + lost spans the device time from first to last sample
        t = np.array(service.samples(insole.device_id)["t_s"])
        assert dev["samples_received"] + dev["samples_lost"] == round((t[-1] - t[0]) * 20) + 1
        assert np.all(np.diff(t) > 0)


def test_gatt_error_on_info_read_is_counted_and_retried(tmp_path):
    service = FakeService()

    async def body():
        async with VirtualBleStack() as stack:
            (insole,) = await stack.start_insoles(1, advertising_interval_ms=100, speed=4.0)
            insole.fail_info_reads = 2
            async with _gateway(stack, service, tmp_path / "s.db") as gw:
                await gw.wait_for(lambda s: s["totals"]["samples_received"] >= 20, 10)
            return insole, gw.stats()

    insole, stats = run(body())
    link = stats["links"][insole.address]
    assert link["gatt_errors"] == 2 and "GATT" in link["last_error"]
    assert link["connects"] == 3
    assert stats["devices"][insole.device_id]["samples_forwarded"] >= 20


def test_malformed_packets_are_counted_and_streaming_continues(tmp_path):
    service = FakeService()

    async def body():
        async with VirtualBleStack() as stack:
            (insole,) = await stack.start_insoles(1, speed=4.0)
            async with _gateway(stack, service, tmp_path / "s.db") as gw:
                await gw.wait_for(lambda s: s["totals"]["samples_received"] >= 20, 10)
                insole.inject_malformed(3)
                await gw.wait_for(lambda s: s["totals"]["malformed_packets"] == 3, 10)
                await gw.wait_for(lambda s: s["totals"]["samples_lost"] == 30, 10)  # next good packet
                # Inject while a partial packet is held: the gap must still be
                # exactly 7 samples (it once lost the held ones too, now and then).
                for _ in range(200):
                    if insole.unsent_samples:
                        break
                    await asyncio.sleep(0.005)
                assert insole.unsent_samples, "no partial packet was ever held"
                insole.inject_gap(7)  # lost over the air: a sequence gap
                n = gw.stats()["totals"]["samples_received"]
                await gw.wait_for(lambda s: s["totals"]["samples_received"] >= n + 20, 10)
            return insole, gw.stats()

    insole, stats = run(body())
    dev = stats["devices"][insole.device_id]
    assert dev["malformed_packets"] == 3
    assert dev["samples_lost"] == 3 * 10 + 7  # the malformed packets' samples + the gap
    assert dev["gaps"] == 2
    assert dev["connected"] is False and stats["links"][insole.address]["disconnects"] == 0


def test_device_gone_is_forgotten_and_found_again(tmp_path):
    service = FakeService()

    async def body():
        async with VirtualBleStack() as stack:
            (insole,) = await stack.start_insoles(1, advertising_interval_ms=100, speed=4.0)
            async with _gateway(stack, service, tmp_path / "s.db", device_gone_s=0.3) as gw:
                await gw.wait_for(lambda s: s["totals"]["samples_received"] >= 20, 10)
                await insole.power_off()
                await gw.wait_for(lambda s: s["links"][insole.address]["state"] == "gone", 10)
                assert gw.stats()["devices"][insole.device_id]["connected"] is False
                received = gw.stats()["totals"]["samples_received"]
                await insole.power_on()
                await gw.wait_for(lambda s: s["totals"]["samples_received"] > received + 20, 10)
            return insole, gw.stats()

    insole, stats = run(body())
    assert stats["links"][insole.address]["connects"] == 2
    assert stats["devices"][insole.device_id]["samples_lost"] > 0


@pytest.mark.service
def test_service_down_then_back_over_real_http_and_restart_is_idempotent(tmp_path):
    """Batches spool while the (real, local) server is down, survive a gateway
    restart with their seq, and are delivered exactly once when it returns."""
    service = FakeService()
    spool = tmp_path / "spool.db"

    async def body():
        server = LiveServer(service)
        async with VirtualBleStack() as stack:
            await stack.start_insoles(2, speed=5.0)
            config = {**FAST_CONFIG, "flush_timeout_s": 0.2}
            # 1) service down: everything goes to the spool
            async with Gateway(server.url, service.key, spool_path=spool, ble=stack.backend(), config=config) as gw:
                await gw.wait_for(lambda s: s["spool_batches"] >= 6, 15)
                assert gw.stats()["service"]["up"] is False
                assert "ConnectError" in gw.stats()["service"]["last_error"]
            spooled = gw.stats()["spool_batches"]
            assert spooled >= 6 and service.requests == 0
            # 2) a new gateway process on the same spool, service back up
            await server.start()
            try:
                async with Gateway(server.url, service.key, spool_path=spool, ble=stack.backend(), config=config) as gw2:
                    await gw2.wait_for(lambda s: s["spool_batches"] == 0 and s["totals"]["batches_forwarded"] > spooled, 15)
                    await server.stop()  # 3) down again mid-stream ...
                    await gw2.wait_for(lambda s: s["service"]["up"] is False, 10)
                    await server.start()  # ... and back
                    await gw2.wait_for(lambda s: s["service"]["up"] is True and s["spool_batches"] == 0, 15)
                    n = gw2.stats()["totals"]["batches_forwarded"]
                    await gw2.wait_for(lambda s: s["totals"]["batches_forwarded"] > n, 10)
            finally:
                await server.stop()
            return gw2.stats()

    stats = run(body(), timeout_s=45)
    assert stats["spool_batches"] == 0
    for device_id, seqs in service.order.items():
        assert seqs == list(range(len(seqs))), f"{device_id}: seqs not contiguous/in order: {seqs}"
        t = np.array(service.samples(device_id)["t_s"])
        assert np.all(np.diff(t) > 0)  # device time never goes back, across the gateway restart
    assert service.duplicates == 0
