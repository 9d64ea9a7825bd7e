"""``selfcal demo [--devices N] [--hours H] [--speed S] [--kill-service-at F] [--json]``.

The whole system on one machine: the service (a subprocess, SQLite in a temporary
folder), N virtual insoles streaming simulated wearers over a virtual BLE stack, and
the gateway. Ends with each device's calibration measured against its simulation truth.
See ``docs/demo.md``.
"""

from __future__ import annotations

import argparse
import json
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # selfcal.demo is imported when the command runs: it pulls in the simulator (~0.4 s),
    # which every other command (and --version) would otherwise pay for
    parser.add_argument("--devices", type=int, default=4, help="virtual insoles (default 4)")
    parser.add_argument("--hours", type=float, default=None,
                        help="hours of wear streamed per insole (default 6: selfcal.demo.DEFAULT_HOURS)")
    parser.add_argument("--speed", type=float, default=None,
                        help="device time per wall time (default: 28 800 samples/s in all, at most 720x)")
    parser.add_argument("--kill-service-at", type=float, default=None, metavar="F",
                        help="SIGKILL the service at this fraction of the run (0..1) and restart it")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first simulated wearer (others: +1, +2, ...)")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument("--no-progress", action="store_true", help="no live status on stderr")
    parser.add_argument("-v", "--verbose", action="store_true", help="show the gateway's and bumble's warnings")
    parser.add_argument("--timeout", type=float, default=900.0, metavar="S", help="give up after S seconds")


def run(args: argparse.Namespace) -> int:
    from importlib.util import find_spec

    from selfcal.demo import DEFAULT_HOURS, DemoOptions, format_table, run_demo
    from selfcal.errors import InputError

    missing = [m for m in ("fastapi", "uvicorn", "httpx", "bleak", "bleak_retry_connector", "bumble") if find_spec(m) is None]
    if missing:  # pragma: no cover - depends on the install
        raise InputError(f"the demo needs the 'service' and 'ble' extras (pip install 'selfcal[service,ble]'); "
                         f"missing: {', '.join(missing)}")

    opts = DemoOptions(
        devices=args.devices, hours=DEFAULT_HOURS if args.hours is None else args.hours, speed=args.speed, kill_service_at=args.kill_service_at,
        seed=args.seed, config=args.config, progress=not args.no_progress, verbose=args.verbose,
        timeout_s=args.timeout,
    )
    result = run_demo(opts)
    if args.json:
        print(json.dumps(result))
    else:
        print(format_table(result))
    ok = result["lost_samples"] == 0 and all(d["samples_sent"] == d["samples_stored"] for d in result["devices"])
    if not ok:
        print("selfcal demo: samples were lost between the insoles and the service (see above)", file=sys.stderr)
        return 1
    return 0
