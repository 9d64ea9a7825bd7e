"""The BLE gateway: insoles -> batches -> spool -> service.

Written against bleak's public API only (:class:`bleak.BleakScanner`,
:class:`bleak.BleakClient`, ``bleak_retry_connector.establish_connection``).
Which Bluetooth stack runs underneath is chosen by :class:`BleBackend`: the
platform default (BlueZ over D-Bus on Linux) or any bleak backend classes, e.g.
the bumble virtual stack of :mod:`selfcal.gateway.virtual`.

Per insole (one task per BLE address): wait for an advertisement, connect
(``establish_connection``), read the info record, subscribe to the data
characteristic, then decode each notification, detect sequence gaps and device
restarts, and append the samples to the device's open batch. A batch is closed
when it holds ``batch_max_samples`` samples, is ``batch_max_age_s`` old, or the
link goes down; a closed batch gets its persisted ``seq`` and goes to the
SQLite spool, which the :class:`~selfcal.gateway.forwarder.Forwarder` drains.
The open batches are journalled in the spool every ``journal_every_s``: after a
crash the next start spools what was journalled, so a ``kill -9`` or a power cut
loses at most that long of each insole's samples (counted as a gap when the
insole's next packet arrives).
After a link loss the task waits for the insole to advertise again and
reconnects; an insole not heard for ``device_gone_s`` is forgotten until it
advertises again.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from selfcal.errors import InputError
from selfcal.gateway import codec
from selfcal.gateway.errors import GatewayError
from selfcal.gateway.forwarder import Forwarder
from selfcal.gateway.spool import OpenSamples, Spool

#: The service's plausible sensor temperatures (degC, selfcal_service.schemas): a batch with a
#: reading outside them is sent without its temperatures (the service refuses the whole batch).
TEMP_MIN_C, TEMP_MAX_C = -40.0, 85.0

#: While the spool cannot store (a full disk), a device's samples stay open, at most this many
#: batches of them; beyond it the oldest are dropped and counted (``samples_dropped``).
SPOOL_RETRY_MAX_BATCHES = 50

log = logging.getLogger(__name__)


class GatewayConfig(BaseModel):
    """The ``[gateway]`` section of the configuration (units in the names)."""

    model_config = ConfigDict(extra="forbid")

    batch_max_samples: int = Field(200, ge=1, le=2_000)  # the service's max_batch_samples default
    batch_max_age_s: float = Field(5.0, gt=0)
    journal_every_s: float = Field(1.0, ge=0)  # 0: open batches are not journalled
    connect_concurrency: int = Field(1, ge=1, le=64)
    connect_attempts: int = Field(2, ge=1, le=10)
    reconnect_initial_s: float = Field(0.5, ge=0)
    reconnect_max_s: float = Field(30.0, ge=0)
    device_gone_s: float = Field(60.0, gt=0)
    max_samples_per_packet: int | None = Field(None, ge=1, le=255)
    addresses: list[str] = Field(default_factory=list)
    http_timeout_s: float = Field(10.0, gt=0)
    http_concurrency: int = Field(8, ge=1, le=256)
    backoff_initial_s: float = Field(0.5, gt=0)
    backoff_max_s: float = Field(60.0, gt=0)
    flush_timeout_s: float = Field(10.0, ge=0)
    seed: int = 0


def load_gateway_config(cfg: dict[str, Any] | GatewayConfig | None) -> GatewayConfig:
    """Validate a ``[gateway]`` section; errors name the key.

    Raises
    ------
    selfcal.errors.InputError
        For an unknown key or a value out of range.
    """
    if isinstance(cfg, GatewayConfig):
        return cfg
    try:
        return GatewayConfig(**(cfg or {}))
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise InputError(f"config [gateway] {where}: {first['msg']}") from exc


@dataclass(frozen=True)
class BleBackend:
    """Which bleak backend the gateway uses.

    Attributes
    ----------
    scanner, client : type or None
        bleak backend classes (``backend=`` of :class:`bleak.BleakScanner` /
        :class:`bleak.BleakClient`); None = the platform default (BlueZ on Linux).
    bluez_adapter : str or None
        BlueZ adapter name (``"hci1"``); None = the default adapter.
    """

    scanner: type | None = None
    client: type | None = None
    bluez_adapter: str | None = None

    def kwargs(self, kind: str) -> dict[str, Any]:
        """Keyword arguments for ``BleakScanner`` (``kind="scanner"``) or ``BleakClient``."""
        out: dict[str, Any] = {}
        backend = self.scanner if kind == "scanner" else self.client
        if backend is not None:
            out["backend"] = backend
        if self.bluez_adapter:
            out["bluez"] = {"adapter": self.bluez_adapter}
        return out


@dataclass
class _DeviceState:
    """Per-device (per ``device_id``) decoding and batching state."""

    device_id: str
    tracker: codec.SeqTracker
    address: str = ""
    firmware: str = ""
    sample_rate_hz: float = 0.0
    connected: bool = False
    samples_received: int = 0
    samples_forwarded: int = 0
    samples_lost: int = 0
    gaps: int = 0
    restarts: int = 0
    malformed_packets: int = 0
    batches_forwarded: int = 0
    duplicates: int = 0
    spool_errors: int = 0  # batches the spool could not store (kept open, tried again)
    samples_dropped: int = 0  # received, then dropped: the spool failed past SPOOL_RETRY_MAX_BATCHES
    temp_dropped: int = 0  # batches sent without temperature: a reading outside the service's range
    samples_recovered: int = 0  # journalled open samples of a run that crashed, spooled at this start
    counts: list[np.ndarray] = field(default_factory=list)
    acc: list[np.ndarray] = field(default_factory=list)
    pressure: list[np.ndarray] = field(default_factory=list)
    temp: list[np.ndarray] = field(default_factory=list)
    open_n: int = 0
    open_since: float = 0.0
    journalled_n: int = 0  # the first open samples, already in the spool's journal

    def append_open(self, counts: np.ndarray, acc_g: np.ndarray, pressure_kpa: np.ndarray, temp_c: np.ndarray) -> None:
        """Add samples to the open batch: counts (n,), acc_g (n, 3) g, pressure_kpa (n, 4) kPa, temp_c (n,) degC."""
        self.counts.append(counts)
        self.acc.append(acc_g)
        self.pressure.append(pressure_kpa)
        self.temp.append(temp_c)
        self.open_n += len(counts)


@dataclass
class _Link:
    """Per-address connection state."""

    address: str
    ble_device: Any
    last_seen: float
    advertised: asyncio.Event = field(default_factory=asyncio.Event)
    task: asyncio.Task[None] | None = None
    state: str = "idle"
    device_id: str | None = None
    connects: int = 0
    disconnects: int = 0
    connect_failures: int = 0
    gatt_errors: int = 0
    info_errors: int = 0
    last_error: str | None = None


class Gateway:
    """The BLE gateway as an async context manager.

    Parameters
    ----------
    service_url : str
        Base URL of the calibration service.
    key : str
        API key (``ingest`` scope), sent as ``Authorization: Bearer KEY``.
    spool_path : str or Path
        SQLite spool file (batches in flight, batch seq numbers).
    config : dict or GatewayConfig, optional
        The ``[gateway]`` section; defaults as in ``selfcal/configs/default.toml``.
    ble : BleBackend, optional
        bleak backend; default the platform's (BlueZ on Linux).
    http_transport : httpx.AsyncBaseTransport, optional
        Custom HTTP transport (tests).

    Examples
    --------
    >>> async with Gateway("http://127.0.0.1:8000", "KEY", spool_path="spool.db") as gw:  # doctest: +SKIP
    ...     await asyncio.sleep(3600)
    ...     print(gw.stats()["totals"])
    """

    def __init__(
        self,
        service_url: str,
        key: str,
        *,
        spool_path: str | Path,
        config: dict[str, Any] | GatewayConfig | None = None,
        ble: BleBackend | None = None,
        http_transport: Any = None,
    ):
        if not service_url.startswith(("http://", "https://")):
            raise InputError(f"service_url must start with http:// or https://, got {service_url!r}")
        if not key:
            raise InputError("key must not be empty")
        self.service_url = service_url
        self.config = load_gateway_config(config)
        self.ble = ble or BleBackend()
        self.spool_path = spool_path
        self._key = key
        self._http_transport = http_transport
        self._spool: Spool | None = None
        self._forwarder: Forwarder | None = None
        self._devices: dict[str, _DeviceState] = {}
        self._links: dict[str, _Link] = {}
        self._scanner: Any = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._stopping = asyncio.Event()
        self._connect_sem = asyncio.Semaphore(self.config.connect_concurrency)
        self._addresses = {a.upper() for a in self.config.addresses}
        self._started = False
        self._final_spool: tuple[dict[str, tuple[int, int]], int] = ({}, 0)

    # -- life cycle --------------------------------------------------------
    async def __aenter__(self) -> Gateway:
        await self.start()
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.stop()

    async def start(self) -> None:
        """Open the spool, start forwarding and scanning."""
        if self._started:
            return
        from bleak import BleakScanner

        cfg = self.config
        self._spool = Spool(self.spool_path)
        self._forwarder = Forwarder(
            self.service_url,
            self._key,
            self._spool,
            transport=self._http_transport,
            timeout_s=cfg.http_timeout_s,
            concurrency=cfg.http_concurrency,
            backoff_initial_s=cfg.backoff_initial_s,
            backoff_max_s=cfg.backoff_max_s,
            seed=cfg.seed,
            on_ack=self._on_ack,
        )
        self._forwarder.start()
        self._recover_open()
        if self._spool.heads(1):
            self._forwarder.wake()  # batches left by a previous run
        self._scanner = BleakScanner(
            self._on_advertisement,
            service_uuids=[codec.SERVICE_UUID],
            **self.ble.kwargs("scanner"),
        )
        await self._scanner.start()
        self._spawn(self._batch_timer())
        self._started = True
        log.info("gateway started: forwarding to %s, spool %s", self.service_url, self.spool_path)

    async def stop(self) -> None:
        """Disconnect, close open batches, flush the spool (``flush_timeout_s``), close."""
        if not self._started:
            return
        self._started = False
        self._stopping.set()
        try:
            await self._scanner.stop()
        except Exception as exc:  # noqa: BLE001 - the adapter may be gone already
            log.warning("stopping the scanner: %r", exc)
        links = [link.task for link in self._links.values() if link.task is not None]
        if links:
            done, pending = await asyncio.wait(links, timeout=10.0)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for dev in self._devices.values():
            self._close_batch(dev)
        assert self._forwarder is not None and self._spool is not None
        flushed = await self._forwarder.flush(self.config.flush_timeout_s)
        if not flushed:
            log.warning("service unreachable at shutdown: batches stay in the spool %s", self.spool_path)
        await self._forwarder.stop()
        self._final_spool = (self._spool.depth(), self._spool.rejected_count())
        self._spool.close()
        self._spool = None

    def _spawn(self, coro: Any) -> asyncio.Task[Any]:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # -- scanning ------------------------------------------------------------
    def _on_advertisement(self, device: Any, _adv: Any) -> None:
        if self._stopping.is_set():
            return
        address = device.address
        if self._addresses and address.upper() not in self._addresses:
            return
        now = time.monotonic()
        link = self._links.get(address)
        if link is None:
            link = self._links[address] = _Link(address=address, ble_device=device, last_seen=now)
        link.ble_device = device
        link.last_seen = now
        link.advertised.set()
        if link.task is None or link.task.done():
            link.task = asyncio.get_running_loop().create_task(self._run_link(link))

    # -- one insole ------------------------------------------------------------
    async def _run_link(self, link: _Link) -> None:
        cfg = self.config
        failures = 0
        while not self._stopping.is_set():
            # Connect only to an insole heard advertising since the last session:
            # a connect to an absent insole would block for the stack's timeout.
            link.state = "waiting"
            if not link.advertised.is_set():
                remaining = cfg.device_gone_s - (time.monotonic() - link.last_seen)
                if not await self._wait_event(link.advertised, max(remaining, 0.0)):
                    if not self._stopping.is_set():
                        link.state = "gone"
                        log.info("%s: not heard for %.0f s, forgotten", link.address, cfg.device_gone_s)
                    return
            if self._stopping.is_set():
                break
            link.advertised.clear()
            ok = await self._session(link)
            link.advertised.clear()
            failures = 0 if ok else failures + 1
            if failures and not self._stopping.is_set():
                delay = min(cfg.reconnect_max_s, cfg.reconnect_initial_s * 2 ** (failures - 1))
                link.state = "backoff"
                await self._wait_event(self._stopping, delay)
        link.state = "stopped"

    async def _wait_event(self, event: asyncio.Event, timeout_s: float) -> bool:
        """Wait for ``event`` (True), the gateway stopping or ``timeout_s`` (False)."""
        waits = {asyncio.ensure_future(event.wait()), asyncio.ensure_future(self._stopping.wait())}
        try:
            await asyncio.wait(
                waits, timeout=None if timeout_s == float("inf") else timeout_s,
                return_when=asyncio.FIRST_COMPLETED,
            )
        finally:
            for w in waits:
                w.cancel()
        return event.is_set() and (event is self._stopping or not self._stopping.is_set())

    async def _session(self, link: _Link) -> bool:
        """One connection; returns True if it streamed (so reconnect without backoff)."""
        from bleak import BleakClient
        from bleak.exc import BleakError, BleakGATTProtocolError
        from bleak_retry_connector import establish_connection

        cfg = self.config
        disconnected = asyncio.Event()
        client = None
        dev: _DeviceState | None = None
        streamed = False
        link.state = "connecting"
        try:
            async with self._connect_sem:
                if self._stopping.is_set():
                    return True
                client = await establish_connection(
                    BleakClient,
                    link.ble_device,
                    link.ble_device.name or link.address,
                    disconnected_callback=lambda _c: disconnected.set(),
                    max_attempts=cfg.connect_attempts,
                    **self.ble.kwargs("client"),
                )
            link.connects += 1
            info = codec.decode_info(await client.read_gatt_char(codec.CONTROL_CHAR_UUID))
            dev = self._device(info, link)
            if cfg.max_samples_per_packet is not None:
                await client.write_gatt_char(
                    codec.CONTROL_CHAR_UUID, codec.encode_control(cfg.max_samples_per_packet), response=True
                )
            await client.start_notify(codec.DATA_CHAR_UUID, lambda _ch, data: self._on_packet(dev, data))
            dev.connected = True
            link.state = "connected"
            streamed = True
            log.info("%s (%s): streaming at %.2f Hz, MTU %d", dev.device_id, link.address, dev.sample_rate_hz, client.mtu_size)
            await self._wait_event(disconnected, float("inf"))
            if disconnected.is_set():
                link.disconnects += 1
                log.info("%s (%s): link lost", dev.device_id, link.address)
        except codec.MalformedPacketError as exc:
            link.info_errors += 1
            link.last_error = f"info record: {exc}"
            log.warning("%s: bad info record: %s", link.address, exc)
        except BleakGATTProtocolError as exc:
            link.gatt_errors += 1
            link.last_error = f"GATT error: {exc}"
            log.warning("%s: GATT error: %s", link.address, exc)
        except (BleakError, TimeoutError, OSError) as exc:
            if client is None:
                link.connect_failures += 1
            link.last_error = f"{type(exc).__name__}: {exc}"
            log.warning("%s: %s: %s", link.address, type(exc).__name__, exc)
        except Exception as exc:  # noqa: BLE001 - a backend bug must not end the insole's task
            link.last_error = f"unexpected {type(exc).__name__}: {exc}"
            log.exception("%s: unexpected error in the BLE session", link.address)
        finally:
            if dev is not None:
                dev.connected = False
                self._close_batch(dev)
            if client is not None:
                try:
                    await asyncio.wait_for(client.disconnect(), timeout=5.0)
                except Exception as exc:  # noqa: BLE001 - the link may be gone already
                    log.debug("%s: disconnect: %r", link.address, exc)
            link.state = "disconnected"
        return streamed

    def _known_device(self, device_id: str) -> _DeviceState:
        """The device's state, made at first sight from the spool's persisted sample-index
        state (so a device whose spooled batches are acknowledged before it reconnects
        still continues its timeline where the last run left it)."""
        dev = self._devices.get(device_id)
        if dev is None:
            assert self._spool is not None
            state = self._spool.device_state(device_id)
            dev = _DeviceState(device_id=device_id, tracker=codec.SeqTracker(state.last_count, state.count_offset))
            self._devices[device_id] = dev
        return dev

    def _device(self, info: codec.DeviceInfo, link: _Link) -> _DeviceState:
        dev = self._known_device(info.device_id)
        if dev.open_n and dev.sample_rate_hz != info.sample_rate_hz:
            self._close_batch(dev)
        dev.address = link.address
        dev.firmware = info.firmware
        dev.sample_rate_hz = info.sample_rate_hz
        link.device_id = info.device_id
        return dev

    # -- data path -------------------------------------------------------------
    def _on_packet(self, dev: _DeviceState, data: bytearray) -> None:
        try:
            packet = codec.decode_packet(data)
        except codec.MalformedPacketError as exc:
            dev.malformed_packets += 1
            log.debug("%s: malformed packet dropped: %s", dev.device_id, exc)
            return
        first, lost, restarted = dev.tracker.feed(packet.seq, packet.n)
        if lost:
            dev.gaps += 1
            dev.samples_lost += lost
        if restarted:
            dev.restarts += 1
            log.info("%s: sample index went backwards: insole restarted", dev.device_id)
        n = packet.n
        dev.samples_received += n
        if not dev.open_n:
            dev.open_since = time.monotonic()
        dev.append_open(np.arange(first, first + n, dtype=np.int64), packet.acc_g, packet.pressure_kpa,
                        np.full(n, packet.temp_c))
        if dev.open_n >= self.config.batch_max_samples:
            self._close_batch(dev)

    def _close_batch(self, dev: _DeviceState) -> None:
        """Spool the device's open samples as batches of at most ``batch_max_samples`` (more
        than one only after the spool failed: those samples were kept open)."""
        if not dev.open_n or self._spool is None:
            return
        counts = np.concatenate(dev.counts)
        acc = np.concatenate(dev.acc)
        pressure = np.concatenate(dev.pressure)
        temp = np.concatenate(dev.temp)
        size = self.config.batch_max_samples
        done = 0
        while done < len(counts):
            part = slice(done, done + size)
            try:
                self._spool_batch(dev, counts[part], acc[part], pressure[part], temp[part])
            except Exception as exc:  # noqa: BLE001 - a full disk must not kill the BLE side
                # the samples stay open and are tried again at the next close; past a bound
                # the oldest go (counted in samples_dropped), so memory cannot grow without end
                dev.spool_errors += 1
                keep = SPOOL_RETRY_MAX_BATCHES * size
                drop = max(0, len(counts) - done - keep)
                rest = slice(done + drop, None)
                dev.counts, dev.acc, dev.pressure, dev.temp = [counts[rest]], [acc[rest]], [pressure[rest]], [temp[rest]]
                dev.open_n = len(counts) - done - drop
                dev.journalled_n = max(0, dev.journalled_n - done - drop)
                dev.samples_dropped += drop
                log.error("%s: cannot spool a batch of %d samples (%r): kept open and tried again%s", dev.device_id,
                          len(counts[part]), exc, f"; the oldest {drop} samples dropped" if drop else "")
                break
            done += size
        else:
            dev.counts, dev.acc, dev.pressure, dev.temp = [], [], [], []
            dev.open_n = 0
            dev.journalled_n = 0
        if done and self._forwarder is not None:
            self._forwarder.wake()

    def _spool_batch(self, dev: _DeviceState, counts: np.ndarray, acc: np.ndarray, pressure: np.ndarray,
                     temp: np.ndarray) -> None:
        """Store one batch in the spool (raises what the spool raises)."""
        assert self._spool is not None
        rate = dev.sample_rate_hz
        payload: dict[str, Any] = {
            "t_s": np.round(counts / rate, 6).tolist(),
            "ax_g": np.round(acc[:, 0], 6).tolist(),
            "ay_g": np.round(acc[:, 1], 6).tolist(),
            "az_g": np.round(acc[:, 2], 6).tolist(),
        }
        # the service refuses a whole batch for one temperature outside its plausible range (a
        # sensor's sentinel, a fault): such a batch goes without its temperatures, not refused
        if np.all(np.isfinite(temp)) and np.all((temp >= TEMP_MIN_C) & (temp <= TEMP_MAX_C)):
            payload["temp_c"] = np.round(temp, 2).tolist()
        elif np.any(np.isfinite(temp)):
            dev.temp_dropped += 1
        payload["pressure_kpa"] = pressure.tolist()

        def make_body(seq: int) -> bytes:
            return json.dumps({"seq": seq, **payload}, separators=(",", ":")).encode()

        self._spool.put_batch(dev.device_id, len(counts), make_body, dev.tracker.last_count, dev.tracker.offset,
                              stored_count=int(counts[-1]))

    def _journal_open(self) -> None:
        """Journal every device's open samples not journalled yet, in one transaction (a
        failure is logged and tried again at the next tick: the samples stay open)."""
        if self._spool is None:
            return
        parts, devs = [], []
        for dev in self._devices.values():
            if dev.open_n > dev.journalled_n:
                k = dev.journalled_n
                parts.append(OpenSamples(dev.device_id, dev.sample_rate_hz, np.concatenate(dev.counts)[k:],
                                         np.concatenate(dev.acc)[k:], np.concatenate(dev.pressure)[k:],
                                         np.concatenate(dev.temp)[k:], dev.tracker.last_count, dev.tracker.offset))
                devs.append(dev)
        if not parts:
            return
        try:
            self._spool.journal(parts)
        except Exception as exc:  # noqa: BLE001 - a full disk must not kill the BLE side
            log.error("cannot journal the open batches of %d devices (%r): tried again at the next tick",
                      len(parts), exc)
            return
        for dev in devs:
            dev.journalled_n = dev.open_n

    def _recover_open(self) -> None:
        """Spool the open samples a crashed run journalled (each device's in batches, its
        sample-index state as the journal left it), so they are sent like any others."""
        assert self._spool is not None
        for device_id, parts in self._spool.journalled().items():
            dev = self._known_device(device_id)
            last = parts[-1]
            if dev.tracker.last_count is None or last.tracker_last > dev.tracker.last_count:
                dev.tracker = codec.SeqTracker(last.tracker_last, last.tracker_offset)
            for part in parts:
                if not len(part.counts):
                    continue
                if dev.open_n and part.sample_rate_hz != dev.sample_rate_hz:
                    self._close_batch(dev)
                dev.sample_rate_hz = part.sample_rate_hz
                dev.append_open(part.counts, part.acc_g, part.pressure_kpa, part.temp_c)
                dev.journalled_n = dev.open_n
                dev.samples_recovered += len(part.counts)
            if dev.open_n:
                log.info("%s: %d journalled samples of the last run recovered", device_id, dev.open_n)
                self._close_batch(dev)
            else:
                self._spool.drop_journal(device_id)  # every sample in it is stored

    async def _batch_timer(self) -> None:
        cfg = self.config
        period = min(1.0, cfg.batch_max_age_s / 2, cfg.journal_every_s or 1.0)
        journalled = time.monotonic()
        while True:
            await asyncio.sleep(period)
            now = time.monotonic()
            for dev in self._devices.values():
                if dev.open_n and now - dev.open_since >= cfg.batch_max_age_s:
                    self._close_batch(dev)
            if cfg.journal_every_s and now - journalled >= cfg.journal_every_s - 1e-3:
                self._journal_open()
                journalled = now

    def _on_ack(self, device_id: str, n_samples: int, duplicate: bool) -> None:
        dev = self._known_device(device_id)
        dev.samples_forwarded += n_samples
        dev.batches_forwarded += 1
        dev.duplicates += duplicate

    # -- observability -----------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Counters per device and per BLE address, spool depth and service state.

        Returns
        -------
        dict
            ``devices``: per device id ``address, connected, firmware,
            sample_rate_hz, samples_received, samples_forwarded, samples_lost,
            gaps, restarts, malformed_packets, batches_forwarded, duplicates,
            spool_errors, samples_dropped, temp_dropped, samples_recovered,
            open_batch_samples, spool_batches, spool_samples``;
            ``links``: per address ``state, device_id, connects, disconnects,
            connect_failures, gatt_errors, info_errors, last_error``;
            ``totals``: the device counters summed, plus ``devices_connected``;
            ``spool_batches``, ``spool_samples``, ``rejected_batches``;
            ``service``: ``up`` (None before the first request), ``last_error``,
            ``consecutive_failures``, ``retries``.
        """
        if self._spool is not None:
            depth, spool_rejected = self._spool.depth(), self._spool.rejected_count()
        else:  # stopped: what was left in the spool at shutdown
            depth, spool_rejected = self._final_spool
        devices: dict[str, dict[str, Any]] = {}
        for dev_id, dev in self._devices.items():
            batches, samples = depth.get(dev_id, (0, 0))
            devices[dev_id] = {
                "address": dev.address,
                "connected": dev.connected,
                "firmware": dev.firmware,
                "sample_rate_hz": dev.sample_rate_hz,
                "samples_received": dev.samples_received,
                "samples_forwarded": dev.samples_forwarded,
                "samples_lost": dev.samples_lost,
                "gaps": dev.gaps,
                "restarts": dev.restarts,
                "malformed_packets": dev.malformed_packets,
                "batches_forwarded": dev.batches_forwarded,
                "duplicates": dev.duplicates,
                "spool_errors": dev.spool_errors,
                "samples_dropped": dev.samples_dropped,
                "temp_dropped": dev.temp_dropped,
                "samples_recovered": dev.samples_recovered,
                "open_batch_samples": dev.open_n,
                "spool_batches": batches,
                "spool_samples": samples,
            }
        links = {
            address: {
                "state": link.state,
                "device_id": link.device_id,
                "connects": link.connects,
                "disconnects": link.disconnects,
                "connect_failures": link.connect_failures,
                "gatt_errors": link.gatt_errors,
                "info_errors": link.info_errors,
                "last_error": link.last_error,
            }
            for address, link in self._links.items()
        }
        keys = (
            "samples_received", "samples_forwarded", "samples_lost", "gaps", "restarts",
            "malformed_packets", "batches_forwarded", "duplicates", "spool_errors", "samples_dropped", "temp_dropped",
            "samples_recovered",
        )
        totals: dict[str, Any] = {k: sum(d[k] for d in devices.values()) for k in keys}
        totals["devices_connected"] = sum(d["connected"] for d in devices.values())
        fwd = self._forwarder
        return {
            "devices": devices,
            "links": links,
            "totals": totals,
            "spool_batches": sum(b for b, _ in depth.values()),
            "spool_samples": sum(s for _, s in depth.values()),
            "rejected_batches": spool_rejected,
            "service": {
                "up": fwd.service_up if fwd else None,
                "last_error": fwd.last_error if fwd else None,
                "consecutive_failures": fwd.consecutive_failures if fwd else 0,
                "retries": fwd.retries if fwd else 0,
                "renumbered": fwd.renumbered if fwd else 0,
            },
        }

    async def wait_for(self, predicate: Callable[[dict[str, Any]], bool], timeout_s: float, poll_s: float = 0.05) -> dict[str, Any]:
        """Poll :meth:`stats` until ``predicate(stats)`` holds.

        Raises
        ------
        GatewayError
            If it does not hold within ``timeout_s``; the message holds the
            last totals.
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while True:
            stats = self.stats()
            if predicate(stats):
                return stats
            if loop.time() >= deadline:
                raise GatewayError(
                    f"condition not met within {timeout_s} s; totals={stats['totals']}, "
                    f"spool_batches={stats['spool_batches']}, service={stats['service']}"
                )
            await asyncio.sleep(poll_s)
