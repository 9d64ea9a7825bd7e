"""Fleet replay throughput: simulated device-days per second, per core, on this machine.

In one run, for each level (``poses``: the simulator's still windows; ``samples``: the
20 Hz stream through the detector) and each engine (the local process pool with 1 and
2 processes, and Dask ``distributed`` on a local cluster of 2 single-threaded workers):
``N`` devices x ``D`` days of the paper's protocol (a refit every 3 days), with the
throughput, the throughput per core, and the final accuracy (identical across engines
for the same seeds). Progress goes to stderr.

    python bench/replay_throughput.py                        # 4 devices x 10 days, both levels
    python bench/replay_throughput.py --days 365 --devices 8 --levels poses --engines processes:2
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from selfcal.config import load_config
from selfcal.replay import replay_fleet


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=float, default=10.0)
    ap.add_argument("--devices", type=int, default=4)
    ap.add_argument("--refit-every-days", type=float, default=3.0)
    ap.add_argument("--levels", default="poses,samples")
    ap.add_argument("--engines", default="processes:1,processes:2,dask:2",
                    help="engine:workers, comma-separated (engines: processes, dask, ray)")
    ap.add_argument("--seed", type=int, default=100)
    args = ap.parse_args(argv)
    cfg = load_config()
    print(f"replay throughput: {args.devices} devices x {args.days:g} days, refit every "
          f"{args.refit_every_days:g} days, {os.cpu_count()} CPUs\n")
    print("| level | engine | workers | wall s | device-days/s | per core | final sphere RMS mg (median, max) |")
    print("|---|---|---:|---:|---:|---:|---|")
    reference: dict[str, list] = {}
    for level in args.levels.split(","):
        for spec in args.engines.split(","):
            engine, _, n = spec.partition(":")
            workers = int(n or 1)
            t0 = time.perf_counter()
            res = replay_fleet(args.devices, seed=args.seed, workers=workers, progress=True, engine=engine,
                               days=args.days, refit_every_days=args.refit_every_days, config=cfg, level=level)
            wall = time.perf_counter() - t0
            final = np.array([r["refits"][-1]["sphere_norm_rms_mg"] for r in res])
            rate = args.devices * args.days / wall
            same = ""
            if level in reference:
                same = " (same results)" if np.array_equal(final, reference[level]) else " (RESULTS DIFFER)"
            else:
                reference[level] = final
            print(f"| {level} | {engine} | {workers} | {wall:.1f} | {rate:.2f} | {rate / min(workers, os.cpu_count() or 1):.2f} "
                  f"| {np.median(final):.3f}, {final.max():.3f}{same} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
