"""A virtual BLE world for tests, the bench and the demo (bumble, in-process).

:class:`VirtualBleStack` owns one :class:`bumble.link.LocalLink` (the "radio"),
one gateway adapter (:class:`~selfcal.gateway.virtual.bleak_backend.BumbleAdapter`)
and any number of :class:`~selfcal.gateway.virtual.insole.VirtualInsole`.
:meth:`VirtualBleStack.backend` hands the gateway bleak backend classes, so the
unchanged gateway runs over real HCI/L2CAP/ATT/GATT in one process.

Examples
--------
>>> async with VirtualBleStack() as stack:                       # doctest: +SKIP
...     insoles = await stack.start_insoles(10, source_factory=my_source, speed=60)
...     async with Gateway(url, key, spool_path="spool.db", ble=stack.backend()) as gw:
...         await asyncio.sleep(60)
...         print(gw.stats())
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from selfcal.gateway.virtual.bleak_backend import BumbleAdapter, BumbleClient, BumbleScanner
from selfcal.gateway.virtual.controller import VirtualController, VirtualLink, drop_link
from selfcal.gateway.virtual.insole import SampleSource, StillPoseSource, VirtualInsole

log = logging.getLogger(__name__)


def insole_address(index: int) -> str:
    """Random static address of the ``index``-th virtual insole (0 <= index < 2**24)."""
    if not 0 <= index < 2**24:
        raise ValueError(f"insole index must be in 0..2**24-1, got {index}")
    return f"E0:5E:1F:{index >> 16 & 0xFF:02X}:{index >> 8 & 0xFF:02X}:{index & 0xFF:02X}"


class VirtualBleStack:
    """The virtual radio, the gateway's adapter and the insoles on it.

    Parameters
    ----------
    tick_s : float
        Wall-clock period at which insoles produce their due samples, s.
    preferred_mtu : int
        ATT MTU the gateway adapter requests on connect.

    Attributes
    ----------
    link : VirtualLink
    adapter : BumbleAdapter
        The gateway side (bleak backends bound to it via :meth:`backend`).
    insoles : list of VirtualInsole
    """

    def __init__(self, tick_s: float = 0.05, preferred_mtu: int = 247):
        self.tick_s = tick_s
        self.link = VirtualLink()
        self.adapter = BumbleAdapter(self.link, preferred_mtu=preferred_mtu)
        self.insoles: list[VirtualInsole] = []
        self._ticker: asyncio.Task[None] | None = None

    async def __aenter__(self) -> VirtualBleStack:
        await self.adapter.power_on()
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.aclose()

    def backend(self) -> Any:
        """The gateway's :class:`~selfcal.gateway.gateway.BleBackend` for this stack."""
        from selfcal.gateway.gateway import BleBackend

        scanner, client = self.adapter.backend()
        return BleBackend(scanner=scanner, client=client)

    async def add_insole(
        self,
        device_id: str | None = None,
        source: SampleSource | None = None,
        *,
        power_on: bool = True,
        **kwargs: Any,
    ) -> VirtualInsole:
        """Create (and by default power on) one virtual insole.

        Parameters
        ----------
        device_id : str, optional
            Default ``"insole-NNNN"`` from its index.
        source : SampleSource, optional
            Sample source; default a :class:`StillPoseSource` seeded with the index.
        power_on : bool
            Boot it now (advertising starts).
        **kwargs
            Passed to :class:`VirtualInsole` (``sample_rate_hz``, ``speed``,
            ``max_samples_per_packet``, ``firmware``, ...).
        """
        index = len(self.insoles)
        device_id = device_id or f"insole-{index:04d}"
        if source is None:
            source = StillPoseSource(seed=index, sample_rate_hz=kwargs.get("sample_rate_hz", 20.0))
        insole = VirtualInsole(self, device_id, insole_address(index), source, **kwargs)
        self.insoles.append(insole)
        if power_on:
            await insole.power_on()
        self._ensure_ticker()
        return insole

    async def start_insoles(
        self,
        n: int,
        source_factory: Callable[[int], SampleSource] | None = None,
        **kwargs: Any,
    ) -> list[VirtualInsole]:
        """Create and power on ``n`` insoles.

        Parameters
        ----------
        n : int
            How many.
        source_factory : callable, optional
            ``source_factory(i)`` returns the sample source of the i-th new
            insole; default :class:`StillPoseSource` seeded with its index.
        **kwargs
            Passed to :meth:`add_insole`.
        """
        out = []
        for i in range(n):
            source = source_factory(i) if source_factory is not None else None
            out.append(await self.add_insole(source=source, **kwargs))
        return out

    def _ensure_ticker(self) -> None:
        if self._ticker is None or self._ticker.done():
            self._ticker = asyncio.get_running_loop().create_task(self._tick())

    async def _tick(self) -> None:
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            now = loop.time()
            for insole in self.insoles:
                try:
                    await insole.pump(now)
                except Exception:  # noqa: BLE001 - one bad insole must not stop the radio
                    log.exception("virtual insole %s failed to send", insole.device_id)
            next_t += self.tick_s
            await asyncio.sleep(max(0.0, next_t - loop.time()))

    async def aclose(self) -> None:
        """Stop the insoles' clock, power everything off."""
        if self._ticker is not None:
            self._ticker.cancel()
            try:
                await self._ticker
            except asyncio.CancelledError:
                pass
            self._ticker = None
        for insole in self.insoles:
            if insole.powered:
                await insole.power_off()
        await self.adapter.close()


__all__ = [
    "BumbleAdapter",
    "BumbleClient",
    "BumbleScanner",
    "SampleSource",
    "StillPoseSource",
    "VirtualBleStack",
    "VirtualController",
    "VirtualInsole",
    "VirtualLink",
    "drop_link",
    "insole_address",
]
