"""Forward spooled batches to the service over HTTP, with retry and backoff.

The forwarder drains the :class:`~selfcal.gateway.spool.Spool` in rounds: each
round posts the oldest pending batch of every device (concurrently across
devices, so one device's order is never broken) as
``POST {service_url}/devices/{device_id}/samples`` with
``Authorization: Bearer KEY`` (see ``docs/internals.md``).

Outcomes of a POST:

* 200 -> acknowledged (``duplicate: true`` too): the batch leaves the spool;
* network error, timeout, 408, 429, 5xx, 401/403 (wrong key) and 404 (wrong
  URL) -> kept; the forwarder backs off exponentially with jitter
  (``backoff_initial_s`` doubling up to ``backoff_max_s``) and retries;
* 400, 409, 413, 422 -> the batch itself is refused: moved to the spool's
  ``rejected`` table so it cannot block the device's later batches.
"""

from __future__ import annotations

import asyncio
import json
import logging
import random
from collections.abc import Callable

import httpx

from selfcal.gateway.spool import Spool, SpooledBatch

log = logging.getLogger(__name__)

#: Statuses that mean "this batch will never be accepted".
REJECT_STATUSES = frozenset({400, 409, 413, 422})

AckCallback = Callable[[str, int, bool], None]


class Forwarder:
    """Drains the spool to the service.

    Parameters
    ----------
    service_url : str
        Base URL of the service, e.g. ``http://127.0.0.1:8000``.
    key : str
        API key with the ``ingest`` scope.
    spool : Spool
    transport : httpx.AsyncBaseTransport, optional
        Custom transport (tests: ``httpx.MockTransport``).
    timeout_s : float
        Per-request timeout, s.
    concurrency : int
        Maximum requests in flight.
    backoff_initial_s, backoff_max_s : float
        First and largest retry delay, s.
    seed : int
        Seed of the jitter's random generator.
    on_ack : callable, optional
        ``on_ack(device_id, n_samples, duplicate)`` after each acknowledged batch.

    Attributes
    ----------
    service_up : bool or None
        Outcome of the last request (None before the first).
    last_error : str or None
        Description of the last failure.
    consecutive_failures : int
        Failed rounds since the last success.
    batches_sent, duplicates, retries, rejected : int
        Counters since start.
    """

    def __init__(
        self,
        service_url: str,
        key: str,
        spool: Spool,
        *,
        transport: httpx.AsyncBaseTransport | None = None,
        timeout_s: float = 10.0,
        concurrency: int = 8,
        backoff_initial_s: float = 0.5,
        backoff_max_s: float = 60.0,
        seed: int = 0,
        on_ack: AckCallback | None = None,
    ):
        self.service_url = service_url.rstrip("/")
        self.spool = spool
        self.timeout_s = timeout_s
        self.concurrency = concurrency
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.on_ack = on_ack
        self._rng = random.Random(seed)
        self._client = httpx.AsyncClient(
            transport=transport,
            timeout=timeout_s,
            headers={"Authorization": f"Bearer {key}", "Content-Type": "application/json"},
            limits=httpx.Limits(max_connections=concurrency, max_keepalive_connections=concurrency),
        )
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._sem = asyncio.Semaphore(concurrency)
        self._drain_lock = asyncio.Lock()
        self._retry_at = 0.0
        self.service_up: bool | None = None
        self.last_error: str | None = None
        self.consecutive_failures = 0
        self.batches_sent = 0
        self.duplicates = 0
        self.retries = 0
        self.rejected = 0

    def url(self, device_id: str) -> str:
        """The samples endpoint of ``device_id``."""
        return f"{self.service_url}/devices/{device_id}/samples"

    def start(self) -> None:
        """Start the background drain loop."""
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run())

    def wake(self) -> None:
        """A new batch is in the spool (ignored while backing off)."""
        self._wake.set()

    async def stop(self) -> None:
        """Stop the drain loop and close the HTTP client (the spool is left as is)."""
        if self._task is not None:
            # cancel until the task is really done: a cancel can be absorbed by a
            # coroutine that was about to finish a wait
            while not self._task.done():
                self._task.cancel()
                await asyncio.wait({self._task}, timeout=0.5)
            if not self._task.cancelled() and self._task.exception() is not None:
                log.warning("forwarder loop ended with %r", self._task.exception())
            self._task = None
        await self._client.aclose()

    async def flush(self, timeout_s: float) -> bool:
        """Try to empty the spool now, ignoring the backoff, for at most ``timeout_s``.

        Returns
        -------
        bool
            True if the spool is empty.
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    if await self._drain():
                        return True
                    pause = min(self._delay(), deadline - loop.time())
                    await asyncio.sleep(max(pause, 0.0))
        except TimeoutError:
            return not self.spool.heads(1)

    def _delay(self) -> float:
        base = min(self.backoff_max_s, self.backoff_initial_s * 2 ** max(self.consecutive_failures - 1, 0))
        return self._rng.uniform(base / 2, base)

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            wait = self._retry_at - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)
            else:
                # asyncio.timeout, not wait_for: on Python 3.11 wait_for can swallow a
                # cancel that races with the event being set (CPython gh-86296), and
                # stop() would then wait forever
                try:
                    async with asyncio.timeout(1.0):
                        await self._wake.wait()
                except TimeoutError:
                    pass
            self._wake.clear()
            try:
                ok = await self._drain()
            except Exception:  # noqa: BLE001 - never let the loop die; retried later
                log.exception("forwarder round failed")
                ok = False
            self._retry_at = 0.0 if ok else loop.time() + self._delay()

    async def _drain(self) -> bool:
        """Post rounds of head batches until the spool is empty (True) or a round fails."""
        async with self._drain_lock:
            while True:
                heads = self.spool.heads()
                if not heads:
                    return True
                results = await asyncio.gather(*(self._post(batch) for batch in heads))
                if not all(results):
                    self.consecutive_failures += 1
                    return False
                self.consecutive_failures = 0

    async def _post(self, batch: SpooledBatch) -> bool:
        """POST one batch; returns False if it must be retried later."""
        async with self._sem:
            try:
                response = await self._client.post(self.url(batch.device_id), content=batch.body)
            except httpx.HTTPError as exc:
                return self._failed(batch, f"POST {self.url(batch.device_id)}: {type(exc).__name__}: {exc}")
        status = response.status_code
        if status == 200:
            if self.service_up is False:
                log.warning("service reachable again: draining the spool")
            duplicate = False
            try:
                duplicate = bool(response.json().get("duplicate", False))
            except (ValueError, AttributeError):
                log.warning("service answered 200 without a JSON body for %s seq %d", batch.device_id, batch.seq)
            self.spool.ack(batch)
            self.service_up = True
            self.batches_sent += 1
            self.duplicates += duplicate
            if self.on_ack is not None:
                self.on_ack(batch.device_id, batch.n_samples, duplicate)
            return True
        detail = response.text[:200]
        if status in REJECT_STATUSES:
            self.service_up = True
            self.rejected += 1
            reason = f"HTTP {status}: {detail}"
            log.error("service rejected %s batch seq %d for good: %s", batch.device_id, batch.seq, reason)
            self.spool.reject(batch, status, reason)
            return True
        return self._failed(batch, f"POST {self.url(batch.device_id)}: HTTP {status}: {detail}")

    def _failed(self, batch: SpooledBatch, message: str) -> bool:
        was_up = self.service_up is not False
        self.service_up = False
        self.last_error = message
        self.retries += 1
        self.spool.failed_attempt(batch)
        # one warning per outage, not one per batch and retry
        (log.warning if was_up else log.debug)(
            "%s (batch %s seq %d kept in spool; retrying with backoff)", message, batch.device_id, batch.seq
        )
        return False


def batch_body(
    seq: int,
    t_s: list[float],
    acc_g: list[list[float]],
    pressure_kpa: list[list[float]] | None,
    temp_c: list[float] | None,
) -> bytes:
    """The JSON body of one batch (``docs/internals.md``, HTTP batch)."""
    body: dict[str, object] = {
        "seq": seq,
        "t_s": t_s,
        "ax_g": [a[0] for a in acc_g],
        "ay_g": [a[1] for a in acc_g],
        "az_g": [a[2] for a in acc_g],
    }
    if temp_c is not None:
        body["temp_c"] = temp_c
    if pressure_kpa is not None:
        body["pressure_kpa"] = pressure_kpa
    return json.dumps(body, separators=(",", ":")).encode()
