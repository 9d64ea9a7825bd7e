"""How many virtual insoles one gateway process handles at 20 Hz, and at what CPU share.

Runs N virtual insoles (bumble peripherals, real time, 20 Hz), the unchanged
gateway over the bumble bleak backend, and an in-process fake service
(``httpx.MockTransport``, dedupe by (device, seq)) in ONE process, for several
N. The CPU share is the process's user+system CPU time over wall time, so it
*includes* the simulated insoles, both bumble protocol stacks (peripheral and
central side) and the fake service: an upper bound for the gateway alone (on a
real host the insoles are elsewhere and the host stack is BlueZ in C).

"Handled" means: every insole connected and, over the measurement window, the
gateway received >= 99 % of the samples the insoles produced, with no
malformed packet.

Usage::

    python bench/gateway_load.py                       # N = 25 50 100 200
    python bench/gateway_load.py --n 100 300 --seconds 20
    python bench/gateway_load.py --samples-per-packet 1  # one sample per notification
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import resource
import sys
import tempfile
import time
from pathlib import Path

import httpx

from selfcal.gateway import Gateway
from selfcal.gateway.virtual import VirtualBleStack


def _fake_service() -> tuple[httpx.MockTransport, dict]:
    seen: dict[tuple[str, int], int] = {}

    def handler(request: httpx.Request) -> httpx.Response:
        device_id = request.url.path.split("/")[2]
        batch = json.loads(request.content)
        key = (device_id, batch["seq"])
        duplicate = key in seen
        seen.setdefault(key, len(batch["t_s"]))
        return httpx.Response(
            200, json={"device_id": device_id, "seq": batch["seq"], "accepted": len(batch["t_s"]), "duplicate": duplicate}
        )

    return httpx.MockTransport(handler), seen


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


async def measure(n: int, seconds: float, samples_per_packet: int, rate_hz: float) -> dict:
    transport, seen = _fake_service()
    with tempfile.TemporaryDirectory() as tmp:
        async with VirtualBleStack() as stack:
            insoles = await stack.start_insoles(
                n, sample_rate_hz=rate_hz, max_samples_per_packet=samples_per_packet
            )
            config = {"batch_max_samples": 200, "batch_max_age_s": 5.0, "flush_timeout_s": 5.0}
            async with Gateway(
                "http://fake-service", "bench", spool_path=Path(tmp) / "spool.db",
                ble=stack.backend(), config=config, http_transport=transport,
            ) as gw:
                t_connect = time.perf_counter()
                try:
                    await gw.wait_for(lambda s: s["totals"]["devices_connected"] == n, timeout_s=60 + n * 0.2)
                except Exception as exc:  # noqa: BLE001 - reported as "not handled"
                    print(f"  N={n}: not all connected: {exc}", file=sys.stderr)
                connect_s = time.perf_counter() - t_connect
                await asyncio.sleep(2.0)  # warm-up: first packets, first batches
                s0 = gw.stats()
                produced0 = sum(i.samples_produced for i in insoles)
                cpu0, wall0 = _cpu_s(), time.perf_counter()
                await asyncio.sleep(seconds)
                cpu1, wall1 = _cpu_s(), time.perf_counter()
                s1 = gw.stats()
                produced1 = sum(i.samples_produced for i in insoles)
            final = gw.stats()
    wall = wall1 - wall0
    received = s1["totals"]["samples_received"] - s0["totals"]["samples_received"]
    produced = produced1 - produced0
    return {
        "n_insoles": n,
        "connected": s1["totals"]["devices_connected"],
        "connect_all_s": round(connect_s, 2),
        "samples_per_s_expected": round(n * rate_hz, 1),
        "samples_per_s_produced": round(produced / wall, 1),
        "samples_per_s_received": round(received / wall, 1),
        "received_fraction": round(received / produced, 4) if produced else 0.0,
        "samples_lost": s1["totals"]["samples_lost"] - s0["totals"]["samples_lost"],
        "malformed": s1["totals"]["malformed_packets"],
        "cpu_share_core": round((cpu1 - cpu0) / wall, 3),
        "forwarded_all_at_stop": final["totals"]["samples_forwarded"] == final["totals"]["samples_received"],
        "batches_at_service": len(seen),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[25, 50, 100, 200], help="insole counts to try")
    parser.add_argument("--seconds", type=float, default=10.0, help="measurement window per N (s)")
    parser.add_argument("--samples-per-packet", type=int, default=10, help="insole packing cap (1..19 at MTU 247)")
    parser.add_argument("--rate-hz", type=float, default=20.0)
    parser.add_argument("--json", action="store_true", help="one JSON object per N")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    logging.getLogger("bumble").setLevel(logging.CRITICAL)
    print(
        f"gateway load: {args.rate_hz:g} Hz, {args.samples_per_packet} samples/notification, "
        f"{args.seconds:g} s window; CPU share includes insoles + both bumble stacks + fake service"
    )
    if not args.json:
        print(f"{'N':>5} {'conn':>5} {'conn_s':>7} {'exp/s':>8} {'rx/s':>8} {'rx %':>7} {'lost':>6} {'CPU core':>9} {'ms/insole/s':>12}")
    best = 0
    for n in args.n:
        r = asyncio.run(measure(n, args.seconds, args.samples_per_packet, args.rate_hz))
        handled = r["connected"] == n and r["received_fraction"] >= 0.99 and r["malformed"] == 0
        r["handled"] = handled
        if handled:
            best = max(best, n)
        if args.json:
            print(json.dumps(r))
        else:
            print(
                f"{n:>5} {r['connected']:>5} {r['connect_all_s']:>7.1f} {r['samples_per_s_expected']:>8.0f}"
                f" {r['samples_per_s_received']:>8.0f} {100 * r['received_fraction']:>6.1f}% {r['samples_lost']:>6}"
                f" {r['cpu_share_core']:>9.3f} {1000 * r['cpu_share_core'] / n:>12.2f}"
                + ("" if handled else "  NOT HANDLED")
            )
    print(f"largest N handled: {best} insoles at {args.rate_hz:g} Hz")
    return 0


if __name__ == "__main__":
    sys.exit(main())
