"""Virtual insoles: bumble BLE peripherals that stream a pluggable sample source.

A :class:`VirtualInsole` is a bumble ``Device`` on its own
:class:`~selfcal.gateway.virtual.controller.VirtualController`, sharing a
:class:`bumble.link.LocalLink` with the gateway's adapter. It advertises the
insole service, serves the GATT layout of :mod:`selfcal.gateway.codec`, and
streams samples from a *source* as notifications.

Sample sources
--------------
A source is an iterator, or a callable returning the next chunk (``None`` when
exhausted), of chunks ``(t_s, acc_g, pressure_kpa, temp_c)`` with shapes
``(n,)``, ``(n, 3)`` g, ``(n, 4)`` kPa, ``(n,)`` °C, uniformly sampled at the
insole's ``sample_rate_hz``. Chunks may have any length. The packets carry the
sample index (device time), not ``t_s``: the gateway reconstructs
``t_s = index / sample_rate_hz``, which equals the source's ``t_s`` when the
source starts at 0. When the source is exhausted the insole stops sending.

Device time and time acceleration
---------------------------------
Device time runs from power-on at ``speed`` times wall time: the insole
produces ``sample_rate_hz * speed`` samples per wall second. Samples produced
while nobody is subscribed (not connected yet, link lost) are consumed and
dropped, as by firmware without a buffer, so the gateway sees them as a
sequence gap.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Iterator
from typing import Any, Union

import numpy as np
from bumble import att, hci
from bumble.core import AdvertisingData, UUID
from bumble.device import Device
from bumble.gatt import Characteristic, CharacteristicValue, Service
from bumble.transport.common import AsyncPipeSink

from selfcal.gateway import codec
from selfcal.gateway.virtual.controller import QuietHost, VirtualController, drop_link

log = logging.getLogger(__name__)

Chunk = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
SampleSource = Union[Iterator[Chunk], Callable[[], Union[Chunk, None]]]


class StillPoseSource:
    """Default sample source: a sequence of still poses plus white noise.

    Each pose holds for ``pose_duration_s``: gravity in a random direction
    (mostly flat, as an insole on the floor or a foot at rest), fixed pressure
    cells, temperature drifting slowly around ``temp_c``.

    Parameters
    ----------
    seed : int
        Seed of the ``np.random.Generator`` (reproducible streams).
    sample_rate_hz : float
        Output sample rate, Hz.
    pose_duration_s : float
        How long each still pose lasts, s.
    noise_g : float
        Accelerometer white-noise standard deviation, g.
    chunk_size : int
        Samples per chunk.
    temp_c : float
        Mean temperature, °C.
    max_tilt_deg : float
        Largest tilt of a pose from flat, degrees.

    Examples
    --------
    >>> t_s, acc_g, pressure_kpa, temp_c = next(iter(StillPoseSource(seed=1)))
    >>> acc_g.shape
    (20, 3)
    """

    def __init__(
        self,
        seed: int = 0,
        sample_rate_hz: float = 20.0,
        pose_duration_s: float = 5.0,
        noise_g: float = 0.002,
        chunk_size: int = 20,
        temp_c: float = 30.0,
        max_tilt_deg: float = 60.0,
    ):
        self.seed = seed
        self.sample_rate_hz = sample_rate_hz
        self.pose_duration_s = pose_duration_s
        self.noise_g = noise_g
        self.chunk_size = chunk_size
        self.temp_c = temp_c
        self.max_tilt_deg = max_tilt_deg
        self._rng = np.random.default_rng(seed)
        self._index = 0
        self._pose_end = 0
        self._g = np.array([0.0, 0.0, 1.0])
        self._p = np.zeros(4)

    def __iter__(self) -> StillPoseSource:
        return self

    def _new_pose(self, start: int) -> None:
        tilt = np.deg2rad(self.max_tilt_deg) * np.sqrt(self._rng.uniform())
        azimuth = self._rng.uniform(0, 2 * np.pi)
        self._g = np.array(
            [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]
        )
        self._p = self._rng.uniform(5.0, 150.0, size=4)
        self._pose_end = start + max(1, int(round(self.pose_duration_s * self.sample_rate_hz)))

    def __next__(self) -> Chunk:
        n = self.chunk_size
        acc = np.empty((n, 3))
        prs = np.empty((n, 4))
        k = 0
        while k < n:
            if self._index + k >= self._pose_end:
                self._new_pose(self._index + k)
            m = min(n - k, self._pose_end - (self._index + k))
            acc[k : k + m] = self._g
            prs[k : k + m] = self._p
            k += m
        acc += self._rng.normal(0.0, self.noise_g, size=(n, 3))
        prs += self._rng.normal(0.0, 0.5, size=(n, 4))
        idx = np.arange(self._index, self._index + n)
        t_s = idx / self.sample_rate_hz
        temp = self.temp_c + 0.5 * np.sin(2 * np.pi * t_s / 3600.0)
        self._index += n
        return t_s, acc, np.clip(prs, 0.0, None), temp


def _as_chunk_iterator(source: SampleSource) -> Iterator[Chunk]:
    if callable(source) and not hasattr(source, "__next__"):
        fn = source

        def gen() -> Iterator[Chunk]:
            while True:
                chunk = fn()
                if chunk is None:
                    return
                yield chunk

        return gen()
    return iter(source)  # type: ignore[arg-type]


class _Buffer:
    """FIFO of samples pulled from a source in chunks."""

    def __init__(self, source: SampleSource):
        self._it = _as_chunk_iterator(source)
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.size = 0
        self.exhausted = False

    def _fill(self, n: int) -> None:
        while self.size < n and not self.exhausted:
            try:
                _t, acc, prs, temp = next(self._it)
            except StopIteration:
                self.exhausted = True
                return
            acc = np.asarray(acc, dtype=float).reshape(-1, 3)
            prs = np.asarray(prs, dtype=float).reshape(acc.shape[0], 4)
            temp = np.broadcast_to(np.asarray(temp, dtype=float), (acc.shape[0],))
            self._parts.append((acc, prs, temp))
            self.size += acc.shape[0]

    def take(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Remove and return up to ``n`` samples (fewer if the source ran out)."""
        self._fill(n)
        if not self._parts:
            return np.empty((0, 3)), np.empty((0, 4)), np.empty(0)
        acc = np.concatenate([p[0] for p in self._parts])
        prs = np.concatenate([p[1] for p in self._parts])
        temp = np.concatenate([p[2] for p in self._parts])
        k = min(n, acc.shape[0])
        rest = (acc[k:], prs[k:], temp[k:])
        self._parts = [rest] if rest[0].shape[0] else []
        self.size = rest[0].shape[0]
        return acc[:k], prs[:k], temp[:k]


class VirtualInsole:
    """A virtual smart insole: BLE peripheral + sample source + fault injection.

    Create through :meth:`VirtualBleStack.add_insole
    <selfcal.gateway.virtual.VirtualBleStack.add_insole>`.

    Parameters
    ----------
    stack : VirtualBleStack
        The virtual radio it lives on.
    device_id : str
        Id reported in the info record (used in the service URL).
    address : str
        Random static BLE address.
    source : SampleSource, optional
        Sample source; default :class:`StillPoseSource` seeded from the index.
    sample_rate_hz : float
        Sample rate reported in the info record, Hz.
    speed : float
        Device time per wall time (1 = real time).
    firmware : str
        Firmware string of the info record.
    max_samples_per_packet : int
        Latency cap on samples per packet (the MTU may impose fewer).
    advertising_interval_ms : float
        Advertising interval, ms.

    Attributes
    ----------
    samples_produced : int
        Samples taken from the source (device time in samples).
    samples_sent : int
        Samples sent in well-formed notifications.
    packets_sent : int
        Notifications sent (malformed ones included).
    connected : bool
        A central is connected.
    subscribed : bool
        Notifications are enabled on the data characteristic.
    fail_info_reads : int
        Fault injection: the next this-many info reads get ATT error 0x0E
        (Unlikely Error).
    """

    def __init__(
        self,
        stack: Any,
        device_id: str,
        address: str,
        source: SampleSource | None = None,
        sample_rate_hz: float = 20.0,
        speed: float = 1.0,
        firmware: str = "virtual-1.0",
        max_samples_per_packet: int = 10,
        advertising_interval_ms: float = 1000.0,
    ):
        codec.validate_device_id(device_id)
        if speed <= 0:
            raise codec.CodecError(f"speed must be > 0, got {speed}")
        self.stack = stack
        self.device_id = device_id
        self.address = address
        self.sample_rate_hz = float(sample_rate_hz)
        self.speed = float(speed)
        self.firmware = firmware
        self.max_samples_per_packet = int(max_samples_per_packet)
        self.advertising_interval_ms = advertising_interval_ms
        self._buffer = _Buffer(source if source is not None else StillPoseSource(sample_rate_hz=sample_rate_hz))
        self.samples_produced = 0
        self.samples_sent = 0
        self.packets_sent = 0
        self.fail_info_reads = 0
        self._corrupt_next = 0
        self._skip_next = 0
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._pending_n = 0
        self._pending_seq = 0
        self.powered = False
        self._t0: float | None = None
        self._connection: Any = None
        self.subscribed = False

        self.controller = VirtualController(f"insole-{device_id}", link=stack.link)
        self.device = Device(
            name=device_id,
            address=hci.Address(address),
            host=QuietHost(self.controller, AsyncPipeSink(self.controller)),
        )
        self.data_char = Characteristic(
            codec.DATA_CHAR_UUID,
            Characteristic.Properties.NOTIFY,
            Characteristic.READABLE,
            # bumble does not check READABLE: without an explicit ATT error, a
            # read of a notify-only value raises inside the server and the
            # client waits for its 30 s GATT timeout.
            CharacteristicValue(read=self._read_data),
        )
        self.control_char = Characteristic(
            codec.CONTROL_CHAR_UUID,
            Characteristic.Properties.READ | Characteristic.Properties.WRITE,
            Characteristic.READABLE | Characteristic.WRITEABLE,
            CharacteristicValue(read=self._read_info, write=self._write_control),
        )
        self.device.add_service(Service(codec.SERVICE_UUID, [self.data_char, self.control_char]))
        self.data_char.on(Characteristic.EVENT_SUBSCRIPTION, self._on_subscription)
        self.device.on("connection", self._on_connection)
        name = device_id.encode("ascii")
        name_type = AdvertisingData.COMPLETE_LOCAL_NAME
        if len(name) > 8:
            name, name_type = name[:8], AdvertisingData.SHORTENED_LOCAL_NAME
        self.device.advertising_data = bytes(
            AdvertisingData(
                [
                    (
                        AdvertisingData.FLAGS,
                        bytes(
                            [
                                AdvertisingData.LE_GENERAL_DISCOVERABLE_MODE_FLAG
                                | AdvertisingData.BR_EDR_NOT_SUPPORTED_FLAG
                            ]
                        ),
                    ),
                    (
                        AdvertisingData.COMPLETE_LIST_OF_128_BIT_SERVICE_CLASS_UUIDS,
                        bytes(UUID(codec.SERVICE_UUID)),
                    ),
                    (name_type, name),
                ]
            )
        )

    # -- GATT callbacks ----------------------------------------------------
    def _read_data(self, _connection: Any) -> bytes:
        raise att.ATT_Error(att.ATT_READ_NOT_PERMITTED_ERROR)

    def info(self) -> codec.DeviceInfo:
        """The info record this insole serves."""
        return codec.DeviceInfo(
            device_id=self.device_id,
            firmware=self.firmware,
            sample_rate_hz=self.sample_rate_hz,
            max_samples_per_packet=self.max_samples_per_packet,
        )

    def _read_info(self, _connection: Any) -> bytes:
        if self.fail_info_reads > 0:
            self.fail_info_reads -= 1
            raise att.ATT_Error(att.ATT_UNLIKELY_ERROR_ERROR)
        return codec.encode_info(self.info())

    def _write_control(self, _connection: Any, value: bytes) -> None:
        try:
            self.max_samples_per_packet = codec.decode_control(value)
        except codec.MalformedPacketError as exc:
            raise att.ATT_Error(att.ErrorCode.VALUE_NOT_ALLOWED) from exc

    def _on_connection(self, connection: Any) -> None:
        self._connection = connection
        connection.on(connection.EVENT_DISCONNECTION, self._on_disconnection)

    def _on_disconnection(self, _reason: int) -> None:
        self._connection = None
        self.subscribed = False
        self._drop_pending()
        if self.powered:
            asyncio.get_running_loop().create_task(self._advertise())

    def _on_subscription(self, _bearer: Any, notify_enabled: bool, _indicate: bool) -> None:
        self.subscribed = bool(notify_enabled)

    @property
    def connected(self) -> bool:
        """A central is connected to this insole."""
        return self._connection is not None

    # -- life cycle --------------------------------------------------------
    async def _advertise(self) -> None:
        if not self.powered or self._connection is not None:
            return
        try:
            await self.device.start_advertising(
                advertising_interval_min=self.advertising_interval_ms,
                advertising_interval_max=self.advertising_interval_ms,
            )
        except Exception as exc:  # noqa: BLE001 - a powered-off race; logged
            log.debug("%s: start_advertising: %r", self.device_id, exc)

    async def power_on(self) -> None:
        """Boot: join the radio, start device time and advertising."""
        if self.powered:
            return
        if self.controller not in self.stack.link.controllers:
            self.stack.link.add_controller(self.controller)
        if self._t0 is None:
            await self.device.power_on()
            self._t0 = asyncio.get_running_loop().time()
        self.powered = True
        await self._advertise()

    async def power_off(self) -> None:
        """The insole disappears: links cut without a word, off the radio.

        Device time keeps running (the sensor keeps sampling); when powered
        on again the gateway sees a sequence gap.
        """
        self.powered = False
        try:
            await self.device.stop_advertising()
        except Exception as exc:  # noqa: BLE001
            log.debug("%s: stop_advertising: %r", self.device_id, exc)
        drop_link(self.controller)
        if self.controller in self.stack.link.controllers:
            self.stack.link.remove_controller(self.controller)

    def drop_link(self) -> int:
        """Inject a link loss (supervision timeout on both sides); returns links cut."""
        return drop_link(self.controller)

    async def disconnect(self) -> None:
        """Peripheral-initiated disconnection (then advertises again)."""
        connection = self._connection
        if connection is not None:
            await connection.disconnect()

    def inject_malformed(self, count: int = 1) -> None:
        """Send the next ``count`` packets with a corrupted header (their samples are lost)."""
        self._corrupt_next += count

    @property
    def unsent_samples(self) -> int:
        """Samples produced and held for a packet not yet full."""
        return self._pending_n

    def inject_gap(self, samples: int) -> None:
        """Lose the next ``samples`` samples over the air (sequence gap).

        The next samples are the unsent ones first (a partial packet held),
        so exactly ``samples`` are lost whenever this is called.
        """
        self._skip_next += samples

    # -- streaming ---------------------------------------------------------
    def _drop_pending(self) -> None:
        self._pending = []
        self._pending_n = 0

    def _packet_size(self) -> int:
        mtu = self._connection.att_mtu if self._connection is not None else 23
        return codec.samples_per_packet(mtu, self.max_samples_per_packet)

    @property
    def exhausted(self) -> bool:
        """The source has no more samples."""
        return self._buffer.exhausted and self._buffer.size == 0

    async def pump(self, now: float) -> None:
        """Produce the samples due at loop time ``now`` and send full packets."""
        if self._t0 is None or self.exhausted:
            return
        due = int((now - self._t0) * self.sample_rate_hz * self.speed) - self.samples_produced
        if due <= 0:
            return
        acc, prs, temp = self._buffer.take(due)
        n = acc.shape[0]
        first = self.samples_produced
        self.samples_produced += n
        if not (self.subscribed and self.powered and self._connection is not None):
            self._drop_pending()
            return
        if self._skip_next:
            # The next samples over the air are the unsent ones first: the
            # pending partial packet, then the new ones; exactly the skipped
            # count is lost, whatever the pump's timing.
            if self._pending:
                first = self._pending_seq
                acc = np.concatenate([p[0] for p in self._pending] + [acc])
                prs = np.concatenate([p[1] for p in self._pending] + [prs])
                temp = np.concatenate([p[2] for p in self._pending] + [temp])
                n = acc.shape[0]
                self._drop_pending()
            k = min(self._skip_next, n)
            self._skip_next -= k
            acc, prs, temp, first, n = acc[k:], prs[k:], temp[k:], first + k, n - k
        if n == 0:
            return
        if not self._pending:
            self._pending_seq = first
        self._pending.append((acc, prs, temp))
        self._pending_n += n
        size = self._packet_size()
        if self._pending_n < size:
            return
        acc = np.concatenate([p[0] for p in self._pending])
        prs = np.concatenate([p[1] for p in self._pending])
        temp = np.concatenate([p[2] for p in self._pending])
        seq = self._pending_seq
        full = (acc.shape[0] // size) * size
        for start in range(0, full, size):
            sl = slice(start, start + size)
            payload = codec.encode_packet(seq + start, acc[sl], prs[sl], float(np.mean(temp[sl])))
            if self._corrupt_next:
                self._corrupt_next -= 1
                payload = bytes([0xF0 | payload[0] & 0x0F]) + payload[1:]
            else:
                self.samples_sent += size
            connection = self._connection
            if connection is None:
                return
            await self.device.notify_subscriber(connection, self.data_char, payload)
            self.packets_sent += 1
        rest = acc.shape[0] - full
        if rest:
            self._pending = [(acc[full:], prs[full:], temp[full:])]
            self._pending_seq = seq + full
        else:
            self._pending = []
        self._pending_n = rest
