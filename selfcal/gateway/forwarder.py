"""Forward spooled batches to the service over HTTP, with retry and backoff.

The forwarder drains the :class:`~selfcal.gateway.spool.Spool` in rounds: each
round posts the oldest pending batch of every device (concurrently across
devices, so one device's order is never broken) as
``POST {service_url}/devices/{device_id}/samples`` with
``Authorization: Bearer KEY`` (see ``docs/internals.md``).

Outcomes of a POST:

* 200 -> acknowledged (``duplicate: true`` too): the batch leaves the spool;
* network error, timeout, 408, 429, 5xx, 401/403 (wrong key) and 404 (wrong
  URL) -> kept; that device backs off exponentially with jitter
  (``backoff_initial_s`` doubling up to ``backoff_max_s``) and retries, while the
  other devices go on (one device whose batches always fail held every device back);
* 409 -> the service holds this seq with other content (the spool was lost or
  replaced, two gateways serve one insole, or a power cut rolled an older spool back):
  the device's pending batches get new seqs after the spool's, then further ahead
  (doubling) at each 409 in a row, and are sent again: nothing is dropped (they were
  moved to ``rejected``, and their samples lost);
* 400, 413, 422 -> the batch itself is refused: moved to the spool's ``rejected``
  table so it cannot block the device's later batches.
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
REJECT_STATUSES = frozenset({400, 413, 422})

#: The farthest a 409 moves a device's seqs past the spool's (the service refuses a seq more
#: than its ``max_seq_jump``, 100 000 by default, above the device's highest stored one).
MAX_SEQ_SKIP = 50_000

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
    batches_sent, duplicates, retries, rejected, renumbered : int
        Counters since start (``renumbered``: batches given new seqs after a 409).
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
        self.renumbered = 0
        self._device_failures: dict[str, int] = {}  # failed posts in a row, per device
        self._device_retry_at: dict[str, float] = {}  # loop time before which a device is not posted
        self._conflicts: dict[str, int] = {}  # 409s in a row, per device

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
                    self._device_retry_at.clear()  # now, whatever each device's backoff
                    if await self._drain():
                        return True
                    pause = min(self._delay(), deadline - loop.time())
                    await asyncio.sleep(max(pause, 0.0))
        except TimeoutError:
            return not self.spool.heads(1)

    def _delay(self, failures: int | None = None) -> float:
        """A jittered backoff (s) after ``failures`` in a row (default: failed rounds)."""
        k = self.consecutive_failures if failures is None else failures
        base = min(self.backoff_max_s, self.backoff_initial_s * 2 ** max(k - 1, 0))
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
            if ok:
                self._retry_at = 0.0
            else:  # the first device whose backoff ends (a new batch of another device wakes it sooner)
                waits = [t for t in self._device_retry_at.values() if t > loop.time()]
                self._retry_at = min(waits) if waits else loop.time() + self._delay()

    async def _drain(self) -> bool:
        """Post rounds of head batches until the spool is empty (True), or until every
        device left is waiting out its own backoff (False). A device whose post fails waits;
        the others go on."""
        async with self._drain_lock:
            loop = asyncio.get_running_loop()
            while True:
                heads = self.spool.heads()
                if not heads:
                    return True
                now = loop.time()
                ready = [b for b in heads if self._device_retry_at.get(b.device_id, 0.0) <= now]
                if not ready:
                    return False
                outcomes = await asyncio.gather(*(self._post(batch) for batch in ready), return_exceptions=True)
                results = []
                for batch, outcome in zip(ready, outcomes):
                    if isinstance(outcome, BaseException):  # (the spool's own error: kept, retried)
                        if isinstance(outcome, asyncio.CancelledError):
                            raise outcome
                        log.error("%s seq %d: %r (kept in the spool)", batch.device_id, batch.seq, outcome)
                        self._device_backoff(batch.device_id)
                        outcome = False
                    results.append(outcome)
                if not any(results):
                    self.consecutive_failures += 1
                else:
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
            self._device_ok(batch.device_id)
            self.service_up = True
            self.batches_sent += 1
            self.duplicates += duplicate
            if self.on_ack is not None:
                self.on_ack(batch.device_id, batch.n_samples, duplicate)
            return True
        detail = response.text[:200]
        if status == 409:
            self.service_up = True
            self._device_ok(batch.device_id, conflicts=False)
            k = self._conflicts.get(batch.device_id, 0) + 1
            self._conflicts[batch.device_id] = k
            start = max(self.spool.next_seq(batch.device_id), batch.seq + 1) + min(2 ** (k - 1) - 1, MAX_SEQ_SKIP)
            n = self.spool.renumber(batch.device_id, start)
            self.renumbered += n
            log.warning("service holds %s seq %d with other content (HTTP 409: %s): its %d pending batch(es) "
                        "renumbered from seq %d and sent again", batch.device_id, batch.seq, detail, n, start)
            return True
        if status in REJECT_STATUSES:
            self.service_up = True
            self.rejected += 1
            reason = f"HTTP {status}: {detail}"
            log.error("service rejected %s batch seq %d for good: %s", batch.device_id, batch.seq, reason)
            self.spool.reject(batch, status, reason)
            self._device_ok(batch.device_id)
            return True
        return self._failed(batch, f"POST {self.url(batch.device_id)}: HTTP {status}: {detail}")

    def _device_ok(self, device_id: str, conflicts: bool = True) -> None:
        """The device's post was answered: its backoff ends (and, with ``conflicts``, its
        count of 409s in a row)."""
        self._device_failures.pop(device_id, None)
        self._device_retry_at.pop(device_id, None)
        if conflicts:
            self._conflicts.pop(device_id, None)

    def _device_backoff(self, device_id: str) -> None:
        k = self._device_failures.get(device_id, 0) + 1
        self._device_failures[device_id] = k
        self._device_retry_at[device_id] = asyncio.get_running_loop().time() + self._delay(k)

    def _failed(self, batch: SpooledBatch, message: str) -> bool:
        self._device_backoff(batch.device_id)
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
