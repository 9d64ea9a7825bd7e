"""``selfcal gateway``: run the BLE gateway (insoles -> service).

Examples::

    selfcal gateway --service-url http://127.0.0.1:8000 --key $KEY
    selfcal gateway --service-url http://127.0.0.1:8000 --key $KEY --adapter hci1
    selfcal gateway --service-url http://127.0.0.1:8000 --key $KEY --virtual 20 --speed 60 --duration 60
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import signal
import sys
from typing import Any

from selfcal.config import load_config, section
from selfcal.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the gateway's options to ``parser``."""
    parser.add_argument("--service-url", required=True, metavar="URL", help="base URL of the calibration service")
    parser.add_argument(
        "--key",
        metavar="KEY",
        default=os.environ.get("SELFCAL_GATEWAY_KEY"),
        help="API key with the ingest scope (default: $SELFCAL_GATEWAY_KEY)",
    )
    parser.add_argument("--spool", metavar="FILE", default="selfcal-gateway-spool.db", help="SQLite spool file")
    parser.add_argument("--adapter", metavar="HCI", help="BlueZ adapter, e.g. hci1 (default: the system's default)")
    parser.add_argument("--address", action="append", default=[], metavar="MAC", help="only these insoles (repeatable)")
    parser.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: run until Ctrl-C)")
    parser.add_argument("--stats-every", type=float, default=10.0, metavar="S", help="print a status line every S seconds (0: never)")
    parser.add_argument("--virtual", type=int, default=0, metavar="N", help="no hardware: run N virtual insoles (bumble) in-process")
    parser.add_argument("--speed", type=float, default=1.0, help="with --virtual: device time per wall time")
    parser.add_argument("--json", action="store_true", help="print the final stats as one JSON object")
    parser.add_argument("-v", "--verbose", action="store_true", help="log connections and retries")


def _status_line(stats: dict[str, Any]) -> str:
    t = stats["totals"]
    svc = stats["service"]
    state = {True: "up", False: "DOWN", None: "?"}[svc["up"]]
    return (
        f"insoles {t['devices_connected']}/{len(stats['devices'])} connected | samples rx {t['samples_received']}"
        f" fwd {t['samples_forwarded']} lost {t['samples_lost']} malformed {t['malformed_packets']}"
        f" | spool {stats['spool_batches']} batches | service {state}"
    )


async def _main(args: argparse.Namespace, cfg: dict[str, Any]) -> dict[str, Any]:
    from selfcal.gateway import BleBackend, Gateway

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
        except (NotImplementedError, RuntimeError):  # pragma: no cover - non-Unix
            pass
    stack = None
    if args.virtual:
        from selfcal.gateway.virtual import VirtualBleStack

        stack = VirtualBleStack()
        await stack.__aenter__()
        await stack.start_insoles(args.virtual, speed=args.speed)
        ble = stack.backend()
    else:
        ble = BleBackend(bluez_adapter=args.adapter)
    try:
        async with Gateway(args.service_url, args.key, spool_path=args.spool, config=cfg, ble=ble) as gw:
            t_end = loop.time() + args.duration if args.duration else None
            while not stop.is_set():
                timeout = args.stats_every or None
                if t_end is not None:
                    remaining = t_end - loop.time()
                    if remaining <= 0:
                        break
                    timeout = min(timeout or remaining, remaining)
                try:
                    await asyncio.wait_for(stop.wait(), timeout)
                except TimeoutError:
                    if args.stats_every and not args.json:
                        print(_status_line(gw.stats()), flush=True)
        return gw.stats()
    finally:
        if stack is not None:
            await stack.aclose()


def run(args: argparse.Namespace) -> int:
    """Run the gateway until Ctrl-C / SIGTERM / ``--duration``; 0 on a clean stop."""
    if not args.key:
        raise InputError("--key: an API key is required (or set SELFCAL_GATEWAY_KEY)")
    if args.virtual < 0:
        raise InputError(f"--virtual: must be >= 0, got {args.virtual}")
    if args.speed <= 0:
        raise InputError(f"--speed: must be > 0, got {args.speed}")
    cfg = dict(section(load_config(args.config), "gateway"))
    if args.address:
        cfg["addresses"] = args.address
    from selfcal.gateway.gateway import load_gateway_config

    cfg_model = load_gateway_config(cfg)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    if not args.verbose:
        logging.getLogger("bumble").setLevel(logging.ERROR)
        logging.getLogger("httpx").setLevel(logging.WARNING)
    stats = asyncio.run(_main(args, cfg_model))
    if args.json:
        print(json.dumps(stats, sort_keys=True))
    else:
        print(_status_line(stats))
        if stats["spool_batches"]:
            print(f"{stats['spool_batches']} batches left in {args.spool}; they are sent on the next start")
    return 0
