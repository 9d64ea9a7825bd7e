"""The bumble virtual stack under plain bleak: scan, connect, GATT errors, timeouts, link loss."""

from __future__ import annotations

import asyncio

import pytest
from bleak import BleakClient, BleakScanner
from bleak.exc import BleakGATTProtocolError
from bumble import hci
from bumble.controller import Controller
from gw_helpers import run

from selfcal.gateway import codec
from selfcal.gateway.virtual import VirtualBleStack

pytestmark = pytest.mark.ble


async def _discover(stack, scanner_cls, n):
    found = {}
    async with BleakScanner(
        lambda d, a: found.setdefault(d.address, (d, a)), service_uuids=[codec.SERVICE_UUID], backend=scanner_cls
    ):
        for _ in range(100):
            if len(found) >= n:
                break
            await asyncio.sleep(0.01)
    return found


def test_scan_connect_read_info_and_notify_over_bleak():
    async def body():
        async with VirtualBleStack() as stack:
            insoles = await stack.start_insoles(2, firmware="fw-9")
            scanner_cls, client_cls = stack.adapter.backend()
            found = await _discover(stack, scanner_cls, 2)
            assert set(found) == {i.address for i in insoles}
            device, adv = found[insoles[0].address]
            assert codec.SERVICE_UUID in adv.service_uuids
            async with BleakClient(device, backend=client_cls) as client:
                assert client.mtu_size == 247
                info = codec.decode_info(await client.read_gatt_char(codec.CONTROL_CHAR_UUID))
                assert (info.device_id, info.firmware, info.sample_rate_hz) == ("insole-0000", "fw-9", 20.0)
                # a notify-only characteristic answers an explicit ATT error, at once
                with pytest.raises(BleakGATTProtocolError) as err:
                    await asyncio.wait_for(client.read_gatt_char(codec.DATA_CHAR_UUID), 2.0)
                assert err.value.code == 0x02  # Read Not Permitted
                # control: cap the packet size
                await client.write_gatt_char(codec.CONTROL_CHAR_UUID, codec.encode_control(4), response=True)
                with pytest.raises(BleakGATTProtocolError):
                    await client.write_gatt_char(codec.CONTROL_CHAR_UUID, b"\x09", response=True)
                packets = []
                await client.start_notify(codec.DATA_CHAR_UUID, lambda _c, d: packets.append(codec.decode_packet(d)))
                while len(packets) < 3:
                    await asyncio.sleep(0.02)
                assert [p.n for p in packets[:3]] == [4, 4, 4]
                assert packets[1].seq == packets[0].seq + 4

    run(body())


def test_connect_timeout_does_not_wedge_the_adapter():
    """bumble's controller ignores LE Create Connection Cancel; ours completes it."""

    async def body():
        async with VirtualBleStack() as stack:
            absent, present = await stack.start_insoles(2)
            scanner_cls, client_cls = stack.adapter.backend()
            found = await _discover(stack, scanner_cls, 2)
            await absent.power_off()
            with pytest.raises(asyncio.TimeoutError):
                await BleakClient(found[absent.address][0], timeout=0.2, backend=client_cls).connect()
            assert stack.adapter.controller.pending_le_connection is None
            client = BleakClient(found[present.address][0], timeout=2.0, backend=client_cls)
            await client.connect()
            assert client.is_connected
            await client.disconnect()

    run(body())


def test_stock_bumble_controller_still_leaves_a_cancelled_connection_pending():
    """Pins the upstream bug our VirtualController works around: if this fails,
    bumble fixed it and the override can go."""

    async def body():
        controller = Controller("stock")
        command = hci.HCI_LE_Create_Connection_Command(
            le_scan_interval=16, le_scan_window=16, initiator_filter_policy=0,
            peer_address_type=1, peer_address=hci.Address("E0:00:00:00:00:01"), own_address_type=1,
            connection_interval_min=24, connection_interval_max=40, max_latency=0,
            supervision_timeout=42, min_ce_length=0, max_ce_length=0,
        )
        controller.on_hci_le_create_connection_command(command)
        controller.on_hci_le_create_connection_cancel_command(hci.HCI_LE_Create_Connection_Cancel_Command())
        return controller.pending_le_connection

    assert run(body()) is not None


def test_injected_link_loss_reaches_both_hosts():
    async def body():
        async with VirtualBleStack() as stack:
            (insole,) = await stack.start_insoles(1)
            scanner_cls, client_cls = stack.adapter.backend()
            found = await _discover(stack, scanner_cls, 1)
            lost = asyncio.Event()
            client = BleakClient(found[insole.address][0], lambda _c: lost.set(), backend=client_cls)
            await client.connect()
            assert insole.connected
            assert insole.drop_link() == 1
            await asyncio.wait_for(lost.wait(), 2.0)
            assert not client.is_connected and not insole.connected
            await asyncio.sleep(0.05)  # the insole advertises again: reconnectable
            await client.connect()
            assert client.is_connected
            await client.disconnect()

    run(body())
