"""A bumble virtual controller with the fixes our tests need.

bumble's in-process :class:`bumble.controller.Controller` (0.0.236) is a good
enough link layer for GATT over a :class:`bumble.link.LocalLink`, with three
gaps that matter for a gateway test-bench:

1. ``LE Create Connection Cancel`` answers *success* but neither clears the
   pending connection nor sends the *LE Connection Complete* (status
   *Unknown Connection Identifier*) that the spec requires. The host's
   ``Device.connect(timeout=...)`` then waits forever after its timeout, and
   every later connect is refused with *Command Disallowed*: one timed-out
   connect wedges the virtual adapter. :class:`VirtualController` implements
   the cancel properly.
2. The virtual link has no supervision timeout: a peripheral that vanishes
   leaves both sides "connected". :func:`drop_link` injects what a real
   controller reports after the supervision timeout (*Disconnection Complete*,
   reason *Connection Timeout*, 0x08) on both sides.
3. :class:`bumble.link.LocalLink` delivers every advertising PDU to every
   controller and looks the destination of every ACL packet up by scanning all
   connections of all controllers: O(N^2) work with N insoles, which saturates
   the event loop long before 100 insoles. :class:`VirtualLink` delivers
   advertisements only to controllers that scan or initiate (the others drop
   them anyway) and indexes controllers by address.
4. bumble formats every HCI packet into a coloured debug string with an
   f-string, *whether or not* debug logging is enabled; with a hundred insoles
   that formatting costs more than the protocol itself. :class:`VirtualController`
   and :class:`QuietHost` skip it unless the ``bumble`` loggers are at DEBUG.
5. A connection is only established when the target's *next* advertising PDU
   goes by, so connecting N insoles one after the other costs N advertising
   intervals (and short intervals flood the loop with advertisements). A real
   initiator catches the next advertising event within a few ms of the
   advertiser's interval; :class:`VirtualController` connects at once when the
   target is advertising, so long, realistic intervals (1 s) stay cheap.
6. The default LE ACL buffer is 27 bytes, so every notification bigger than
   that is split into HCI fragments by the host; we advertise 251-byte
   buffers (LE Data Length Extension), as current controllers do.
"""

from __future__ import annotations

import asyncio
import logging

from bumble import hci, ll
from bumble.controller import Controller
from bumble.host import Host
from bumble.link import LocalLink

_controller_log = logging.getLogger("bumble.controller")
_host_log = logging.getLogger("bumble.host")


class QuietHost(Host):
    """:class:`bumble.host.Host` without the eager per-packet debug formatting."""

    def on_hci_packet(self, packet: hci.HCI_Packet) -> None:
        if _host_log.isEnabledFor(logging.DEBUG) or self.snooper:
            super().on_hci_packet(packet)
            return
        match packet:
            case hci.HCI_Event():
                self.on_hci_event_packet(packet)
            case hci.HCI_AclDataPacket():
                self.on_hci_acl_data_packet(packet)
            case _:
                super().on_hci_packet(packet)

    def send_hci_packet(self, packet: hci.HCI_Packet) -> None:
        if _host_log.isEnabledFor(logging.DEBUG) or self.snooper:
            super().send_hci_packet(packet)
        elif self.hci_sink:
            self.hci_sink.on_packet(bytes(packet))


class VirtualLink(LocalLink):
    """:class:`bumble.link.LocalLink` that scales to hundreds of controllers.

    Same semantics for the LE features we use (legacy/extended advertising,
    connections, ACL data); periodic advertising is not supported.
    """

    def __init__(self) -> None:
        super().__init__()
        self._by_address: dict[bytes, Controller] = {}

    def _index(self) -> None:
        self._by_address = {}
        for c in self.controllers:
            for address in (c.public_address, c.random_address):
                if address != hci.Address.ANY:
                    self._by_address.setdefault(bytes(address.address_bytes), c)

    def add_controller(self, controller: Controller) -> None:
        super().add_controller(controller)
        self._index()

    def remove_controller(self, controller: Controller) -> None:
        super().remove_controller(controller)
        self._index()

    def on_address_changed(self, controller: Controller) -> None:
        self._index()

    def find_le_controller(self, address: hci.Address) -> Controller | None:
        found = self._by_address.get(bytes(address.address_bytes))
        return found if found is not None else super().find_le_controller(address)

    def send_advertising_pdu(self, sender_controller: Controller, packet: ll.AdvertisingPdu) -> None:
        loop = asyncio.get_running_loop()
        for c in self.controllers:
            if c is sender_controller:
                continue
            if isinstance(packet, ll.ConnectInd) or c.le_scan_enable or c.pending_le_connection:
                loop.call_soon(c.on_ll_advertising_pdu, packet)


class VirtualController(Controller):
    """:class:`bumble.controller.Controller` with a working connection cancel.

    Parameters
    ----------
    name : str
        Name used in bumble's logs.
    link : bumble.link.LocalLink
        The shared virtual radio.
    **kwargs
        Passed to :class:`bumble.controller.Controller`.
    """

    le_acl_data_packet_length = 251
    supported_max_tx_octets = 251
    supported_max_rx_octets = 251
    suggested_max_tx_octets = 251

    def on_hci_packet(self, packet: hci.HCI_Packet) -> None:
        if _controller_log.isEnabledFor(logging.DEBUG):
            super().on_hci_packet(packet)
            return
        match packet:
            case hci.HCI_Command():
                self.on_hci_command_packet(packet)
            case hci.HCI_AclDataPacket():
                self.on_hci_acl_data_packet(packet)
            case _:
                super().on_hci_packet(packet)

    def send_hci_packet(self, packet: hci.HCI_Packet) -> None:
        if _controller_log.isEnabledFor(logging.DEBUG):
            super().send_hci_packet(packet)
        elif self.host:
            asyncio.get_running_loop().call_soon(self.host.on_packet, bytes(packet))

    def on_hci_le_create_connection_command(self, command):  # noqa: D401
        """Create the connection now if the target is advertising (see module notes)."""
        result = super().on_hci_le_create_connection_command(command)
        asyncio.get_running_loop().call_soon(self._connect_if_advertising)
        return result

    def on_hci_le_extended_create_connection_command(self, command):  # noqa: D401
        """Create the connection now if the target is advertising (see module notes)."""
        result = super().on_hci_le_extended_create_connection_command(command)
        asyncio.get_running_loop().call_soon(self._connect_if_advertising)
        return result

    def _connect_if_advertising(self) -> None:
        pending = self.pending_le_connection
        if pending is None or self.link is None:
            return
        address = pending.peer_address
        target = self.link.find_le_controller(address)
        if target is None or target is self:
            return
        legacy = target.le_legacy_advertiser
        advertising = (legacy.enabled and legacy.address == address) or any(
            s.enabled and s.address == address for s in target.advertising_sets.values()
        )
        if advertising and not self.le_connections.get(address):
            self.create_le_connection(address)

    def on_hci_le_create_connection_cancel_command(self, _command):  # noqa: D401
        """Spec behaviour (Vol 4, Part E, 7.8.13): cancel and report the failure."""
        pending = self.pending_le_connection
        if pending is None:
            return hci.HCI_StatusReturnParameters(hci.HCI_ErrorCode.COMMAND_DISALLOWED_ERROR)
        self.pending_le_connection = None
        peer_address = pending.peer_address
        event = hci.HCI_LE_Connection_Complete_Event(
            status=hci.HCI_ErrorCode.UNKNOWN_CONNECTION_IDENTIFIER_ERROR,
            connection_handle=0,
            role=hci.Role.CENTRAL,
            peer_address_type=peer_address.address_type,
            peer_address=peer_address,
            connection_interval=0,
            peripheral_latency=0,
            supervision_timeout=0,
            central_clock_accuracy=0,
        )
        # After the Command Complete that the caller sends for this command.
        asyncio.get_running_loop().call_soon(self.send_hci_packet, event)
        return hci.HCI_StatusReturnParameters(hci.HCI_ErrorCode.SUCCESS)


def drop_link(controller: Controller, reason: int = hci.HCI_ErrorCode.CONNECTION_TIMEOUT_ERROR) -> int:
    """Cut every LE connection of ``controller`` as a supervision timeout would.

    Both ends get an HCI *Disconnection Complete* with ``reason`` and nothing
    is sent over the air (no LL_TERMINATE_IND), as when a device walks out of
    range or its battery dies.

    Parameters
    ----------
    controller : Controller
        One end of the connections (typically a virtual insole's controller).
    reason : int
        HCI error code reported to both hosts; default 0x08 (Connection Timeout).

    Returns
    -------
    int
        Number of connections cut.
    """
    cut = 0
    for connection in list(controller.le_connections.values()):
        link = controller.link
        peer = link.find_le_controller(connection.peer_address) if link else None
        if peer is not None and peer is not controller:
            peer_connection = peer.le_connections.get(connection.self_address)
            if peer_connection is not None:
                peer.on_le_disconnected(peer_connection, reason)
        controller.on_le_disconnected(connection, reason)
        cut += 1
    return cut
