"""Helpers of the gateway tests (imported by the test modules)."""

from __future__ import annotations

import asyncio


def run(coro, timeout_s: float = 30.0):
    """Run one async test body on a fresh event loop, bounded in time."""

    async def bounded():
        return await asyncio.wait_for(coro, timeout_s)

    return asyncio.run(bounded())


#: Gateway settings that keep the tests fast: short batches and backoffs.
FAST_CONFIG = {
    "batch_max_samples": 40,
    "batch_max_age_s": 0.5,
    "reconnect_initial_s": 0.05,
    "reconnect_max_s": 0.2,
    "backoff_initial_s": 0.05,
    "backoff_max_s": 0.2,
    "http_timeout_s": 2.0,
    "flush_timeout_s": 5.0,
    "device_gone_s": 5.0,
}
