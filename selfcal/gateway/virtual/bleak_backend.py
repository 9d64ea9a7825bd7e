"""bleak backends running on a bumble host: real HCI/L2CAP/ATT/GATT, no kernel.

bleak lets callers pass ``backend=`` classes to :class:`bleak.BleakScanner` and
:class:`bleak.BleakClient`. :class:`BumbleAdapter` is a bumble central (host +
:class:`~selfcal.gateway.virtual.controller.VirtualController`) on a
:class:`bumble.link.LocalLink`; :meth:`BumbleAdapter.backend` returns scanner
and client backend classes bound to it. Code written against bleak's public API
(the gateway) runs unchanged over it.

What the backend does that BlueZ does for a bleak client on Linux:

* connections are serialised per adapter (one LE Create Connection at a time);
* the ATT MTU is exchanged on connect (``preferred_mtu``, 247 by default);
* the whole GATT database is discovered on connect;
* ATT error responses become :class:`bleak.exc.BleakGATTProtocolError`;
* a connect that times out raises :class:`asyncio.TimeoutError`.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from bleak.backends.characteristic import BleakGATTCharacteristic
from bleak.backends.client import BaseBleakClient, NotifyCallback
from bleak.backends.descriptor import BleakGATTDescriptor
from bleak.backends.device import BLEDevice
from bleak.backends.scanner import AdvertisementData, BaseBleakScanner
from bleak.backends.service import BleakGATTService, BleakGATTServiceCollection
from bleak.exc import BleakError, BleakGATTProtocolError
from bleak.uuids import normalize_uuid_str
from bumble import att, core, hci
from bumble.core import AdvertisingData
from bumble.device import Device, Peer
from bumble.gatt import Characteristic
from bumble.link import LocalLink
from bumble.transport.common import AsyncPipeSink

from selfcal.gateway import codec
from selfcal.gateway.virtual.controller import QuietHost, VirtualController

log = logging.getLogger(__name__)

# bumble resolves every UUID parsed from an advertisement against a global
# registry with a linear scan (UUID.register); a new UUID goes to the end, so
# each advertisement of ours cost ~150 slow comparisons. Put the insole service
# first (a name registry only: behaviour is unchanged).
_SERVICE = core.UUID(codec.SERVICE_UUID, "selfcal insole")
if _SERVICE not in core.UUID.UUIDS[:1]:
    core.UUID.UUIDS.insert(0, _SERVICE)

_PROPERTY_NAMES = [
    (Characteristic.Properties.BROADCAST, "broadcast"),
    (Characteristic.Properties.READ, "read"),
    (Characteristic.Properties.WRITE_WITHOUT_RESPONSE, "write-without-response"),
    (Characteristic.Properties.WRITE, "write"),
    (Characteristic.Properties.NOTIFY, "notify"),
    (Characteristic.Properties.INDICATE, "indicate"),
    (Characteristic.Properties.AUTHENTICATED_SIGNED_WRITES, "authenticated-signed-writes"),
    (Characteristic.Properties.EXTENDED_PROPERTIES, "extended-properties"),
]


def _uuid_str(uuid: core.UUID) -> str:
    return normalize_uuid_str(uuid.to_hex_str("-"))


def address_str(address: hci.Address) -> str:
    """bleak-style address text of a bumble address (no type qualifier)."""
    return address.to_string(with_type_qualifier=False)


class BumbleAdapter:
    """A virtual BLE adapter: a bumble central host on a virtual controller.

    Parameters
    ----------
    link : bumble.link.LocalLink
        The virtual radio shared with the peripherals.
    address : str
        Random static address of the adapter.
    preferred_mtu : int
        ATT MTU requested on every connection (BlueZ uses 517; 247 matches
        common phone/embedded stacks).
    gatt_timeout_s : float
        Limit on each GATT procedure issued by the client backend.

    Examples
    --------
    >>> adapter = BumbleAdapter(link)              # doctest: +SKIP
    >>> await adapter.power_on()                   # doctest: +SKIP
    >>> scanner_cls, client_cls = adapter.backend()  # doctest: +SKIP
    >>> BleakScanner(backend=scanner_cls)          # doctest: +SKIP
    """

    def __init__(
        self,
        link: LocalLink,
        address: str = "C0:5E:1F:CA:00:01",
        preferred_mtu: int = 247,
        gatt_timeout_s: float = 10.0,
    ):
        self.link = link
        self.preferred_mtu = preferred_mtu
        self.gatt_timeout_s = gatt_timeout_s
        self.controller = VirtualController("gateway-adapter", link=link)
        self.device = Device(
            name="selfcal-gateway",
            address=hci.Address(address),
            host=QuietHost(self.controller, AsyncPipeSink(self.controller)),
        )
        self.connect_lock = asyncio.Lock()
        self._scanners: set[BumbleScanner] = set()
        self._scanning = False
        self._scan_lock = asyncio.Lock()
        self._powered = False
        self.device.on("advertisement", self._on_advertisement)

    async def power_on(self) -> None:
        """Reset the virtual controller and bring the host up (idempotent)."""
        if not self._powered:
            await self.device.power_on()
            self._powered = True

    async def close(self) -> None:
        """Stop scanning and disconnect everything."""
        if self._scanning:
            await self.device.stop_scanning()
            self._scanning = False
        for connection in list(self.device.connections.values()):
            try:
                await asyncio.wait_for(connection.disconnect(), 2.0)
            except Exception:  # noqa: BLE001 - best effort on teardown
                pass

    def backend(self) -> tuple[type[BaseBleakScanner], type[BaseBleakClient]]:
        """bleak backend classes bound to this adapter.

        Returns
        -------
        (scanner_backend, client_backend)
            Pass them as ``backend=`` to :class:`bleak.BleakScanner` and
            :class:`bleak.BleakClient` (or to the gateway's ``BleBackend``).
        """
        scanner = type("BumbleScannerBackend", (BumbleScanner,), {"adapter": self})
        client = type("BumbleClientBackend", (BumbleClient,), {"adapter": self})
        return scanner, client

    async def _add_scanner(self, scanner: BumbleScanner) -> None:
        await self.power_on()
        async with self._scan_lock:
            self._scanners.add(scanner)
            if not self._scanning:
                await self.device.start_scanning(filter_duplicates=False)
                self._scanning = True

    async def _remove_scanner(self, scanner: BumbleScanner) -> None:
        async with self._scan_lock:
            self._scanners.discard(scanner)
            if not self._scanners and self._scanning:
                self._scanning = False
                await self.device.stop_scanning()

    def _on_advertisement(self, advertisement: Any) -> None:
        for scanner in list(self._scanners):
            scanner._on_advertisement(advertisement)


class BumbleScanner(BaseBleakScanner):
    """bleak scanner backend on a :class:`BumbleAdapter` (bound by ``adapter.backend()``)."""

    adapter: BumbleAdapter

    def __init__(
        self,
        detection_callback: Any,
        service_uuids: list[str] | None,
        scanning_mode: str = "active",
        **kwargs: Any,
    ):
        super().__init__(detection_callback, service_uuids)
        self._scanning_mode = scanning_mode

    async def start(self) -> None:
        """Start receiving advertisements (clears ``seen_devices``)."""
        self.seen_devices = {}
        await self.adapter._add_scanner(self)

    async def stop(self) -> None:
        """Stop receiving advertisements."""
        await self.adapter._remove_scanner(self)

    def _on_advertisement(self, advertisement: Any) -> None:
        data: AdvertisingData = advertisement.data
        uuids: list[str] = []
        for ad_type in (
            AdvertisingData.COMPLETE_LIST_OF_16_BIT_SERVICE_CLASS_UUIDS,
            AdvertisingData.INCOMPLETE_LIST_OF_16_BIT_SERVICE_CLASS_UUIDS,
            AdvertisingData.COMPLETE_LIST_OF_128_BIT_SERVICE_CLASS_UUIDS,
            AdvertisingData.INCOMPLETE_LIST_OF_128_BIT_SERVICE_CLASS_UUIDS,
        ):
            for value in data.get_all(ad_type):
                items = value if isinstance(value, list) else [value]
                uuids.extend(_uuid_str(u) for u in items)
        if not self.is_allowed_uuid(uuids):
            return
        name = data.get(AdvertisingData.COMPLETE_LOCAL_NAME) or data.get(
            AdvertisingData.SHORTENED_LOCAL_NAME
        )
        manufacturer: dict[int, bytes] = {}
        for item in data.get_all(AdvertisingData.MANUFACTURER_SPECIFIC_DATA):
            company, payload = item
            manufacturer[int(company)] = bytes(payload)
        address = address_str(advertisement.address)
        adv = AdvertisementData(
            local_name=name if isinstance(name, str) else None,
            manufacturer_data=manufacturer,
            service_data={},
            service_uuids=uuids,
            tx_power=None,
            rssi=int(advertisement.rssi),
            platform_data=(advertisement,),
        )
        device = self.create_or_update_device(
            address, address, adv.local_name, advertisement.address, adv
        )
        self.call_detection_callbacks(device, adv)


class BumbleClient(BaseBleakClient):
    """bleak client backend on a :class:`BumbleAdapter` (bound by ``adapter.backend()``)."""

    adapter: BumbleAdapter

    def __init__(
        self,
        address_or_ble_device: BLEDevice | str,
        *,
        disconnected_callback: Callable[[], None] | None = None,
        timeout: float = 10.0,
        **kwargs: Any,
    ):
        super().__init__(
            address_or_ble_device, disconnected_callback=disconnected_callback, timeout=timeout
        )
        if isinstance(address_or_ble_device, BLEDevice) and isinstance(
            address_or_ble_device.details, hci.Address
        ):
            self._peer_address = address_or_ble_device.details
            self._name = address_or_ble_device.name
        else:
            self._peer_address = hci.Address(str(self.address))
            self._name = None
        self._connection: Any = None
        self._peer: Peer | None = None
        self._subscriptions: dict[int, Callable[[bytes], None]] = {}
        self._disconnecting = False

    # -- connectivity ---------------------------------------------------
    @property
    def name(self) -> str:
        """The advertised name, else the address with dashes."""
        return self._name or str(self.address).replace(":", "-")

    @property
    def mtu_size(self) -> int:
        """Negotiated ATT MTU (23 before the exchange)."""
        return int(self._connection.att_mtu) if self._connection is not None else 23

    @property
    def is_connected(self) -> bool:
        """True between a successful connect and the disconnection."""
        return self._connection is not None

    async def connect(self, pair: bool = False, timeout: float | None = None, **kwargs: Any) -> None:
        """Connect, exchange the MTU and discover the GATT database.

        Raises
        ------
        asyncio.TimeoutError
            If no connection is established within ``timeout`` seconds (the
            controller's pending connection is cancelled).
        bleak.exc.BleakError
            On a connection failure or a failed discovery.
        """
        timeout = self._timeout if timeout is None else timeout
        adapter = self.adapter
        await adapter.power_on()
        if self._connection is not None:
            return
        async with adapter.connect_lock:
            try:
                connection = await adapter.device.connect(self._peer_address, timeout=timeout)
            except core.TimeoutError as exc:
                raise asyncio.TimeoutError(
                    f"{self.address}: no connection within {timeout} s"
                ) from exc
            except core.ConnectionError as exc:
                raise BleakError(f"{self.address}: connection failed: {exc}") from exc
        self._connection = connection
        self._disconnecting = False
        connection.on(connection.EVENT_DISCONNECTION, self._on_disconnection)
        try:
            async with asyncio.timeout(adapter.gatt_timeout_s):
                peer = Peer(connection)
                self._peer = peer
                await peer.request_mtu(adapter.preferred_mtu)
                self.services = await self._discover(peer)
        except BaseException as exc:
            await self._teardown()
            if isinstance(exc, (TimeoutError, core.TimeoutError, att.ATT_Error)):
                raise BleakError(f"{self.address}: GATT discovery failed: {exc!r}") from exc
            raise

    async def _discover(self, peer: Peer) -> BleakGATTServiceCollection:
        collection = BleakGATTServiceCollection()
        services = await peer.discover_services()
        for service in services:
            bleak_service = BleakGATTService(service, service.handle, _uuid_str(service.uuid))
            collection.add_service(bleak_service)
            for char in await service.discover_characteristics():
                props = [name for flag, name in _PROPERTY_NAMES if char.properties & flag]
                bleak_char = BleakGATTCharacteristic(
                    char,
                    char.handle,
                    _uuid_str(char.uuid),
                    props,  # type: ignore[arg-type]
                    lambda: self.mtu_size - 3,
                    bleak_service,
                )
                collection.add_characteristic(bleak_char)
                for desc in await char.discover_descriptors():
                    collection.add_descriptor(
                        BleakGATTDescriptor(desc, desc.handle, _uuid_str(desc.type), bleak_char)
                    )
        return collection

    def _on_disconnection(self, reason: int) -> None:
        solicited = self._disconnecting
        self._connection = None
        self._peer = None
        self._subscriptions.clear()
        if not solicited and self._disconnected_callback is not None:
            self._disconnected_callback()

    async def _teardown(self) -> None:
        connection = self._connection
        if connection is None:
            return
        self._disconnecting = True
        try:
            await asyncio.wait_for(connection.disconnect(), 5.0)
        except Exception as exc:  # noqa: BLE001 - link may already be gone
            log.debug("%s: disconnect: %r", self.address, exc)
        finally:
            self._connection = None
            self._peer = None

    async def disconnect(self) -> None:
        """Disconnect (no-op if not connected); the disconnected callback is not called."""
        await self._teardown()

    async def pair(self, *args: Any, **kwargs: Any) -> None:
        """Pairing is not used by the insole protocol."""
        raise BleakError("pairing is not supported by the bumble virtual backend")

    async def unpair(self) -> None:
        """Pairing is not used by the insole protocol."""
        raise BleakError("pairing is not supported by the bumble virtual backend")

    # -- I/O --------------------------------------------------------------
    def _require_peer(self) -> Peer:
        if self._peer is None:
            raise BleakError(f"{self.address}: not connected")
        return self._peer

    async def _gatt(self, coro: Any) -> Any:
        try:
            return await asyncio.wait_for(coro, self.adapter.gatt_timeout_s)
        except att.ATT_Error as exc:
            raise BleakGATTProtocolError(int(exc.error_code)) from exc
        except asyncio.CancelledError:
            if self._connection is None:
                raise BleakError(f"{self.address}: disconnected during a GATT request") from None
            raise
        except core.TimeoutError as exc:
            raise asyncio.TimeoutError(f"{self.address}: GATT request timed out") from exc

    async def read_gatt_char(
        self, characteristic: BleakGATTCharacteristic, *, use_cached: bool = False, **kwargs: Any
    ) -> bytearray:
        """Read a characteristic value (long reads included)."""
        peer = self._require_peer()
        return bytearray(await self._gatt(peer.read_value(characteristic.obj)))

    async def read_gatt_descriptor(
        self, descriptor: BleakGATTDescriptor, *, use_cached: bool = False, **kwargs: Any
    ) -> bytearray:
        """Read a descriptor value."""
        peer = self._require_peer()
        return bytearray(await self._gatt(peer.read_value(descriptor.obj)))

    async def write_gatt_char(
        self, characteristic: BleakGATTCharacteristic, data: Any, response: bool
    ) -> None:
        """Write a characteristic (with or without response)."""
        peer = self._require_peer()
        await self._gatt(peer.write_value(characteristic.obj, bytes(data), with_response=response))

    async def write_gatt_descriptor(self, descriptor: BleakGATTDescriptor, data: Any) -> None:
        """Write a descriptor (with response)."""
        peer = self._require_peer()
        await self._gatt(peer.write_value(descriptor.obj, bytes(data), with_response=True))

    async def start_notify(
        self, characteristic: BleakGATTCharacteristic, callback: NotifyCallback, **kwargs: Any
    ) -> None:
        """Enable notifications (writes the CCCD) and route them to ``callback``."""
        peer = self._require_peer()

        def on_value(value: bytes) -> None:
            callback(bytearray(value))

        self._subscriptions[characteristic.handle] = on_value
        await self._gatt(peer.subscribe(characteristic.obj, on_value))

    async def stop_notify(self, characteristic: BleakGATTCharacteristic) -> None:
        """Disable notifications on ``characteristic``."""
        peer = self._require_peer()
        subscriber = self._subscriptions.pop(characteristic.handle, None)
        await self._gatt(peer.unsubscribe(characteristic.obj, subscriber))


__all__ = [
    "BumbleAdapter",
    "BumbleClient",
    "BumbleScanner",
    "address_str",
]
