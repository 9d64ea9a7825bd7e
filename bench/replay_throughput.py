"""Fleet replay throughput: simulated device-days per second on this machine.

Runs ``selfcal replay --days D --devices N`` (the paper's protocol per device, across
processes, with a progress bar) and prints the throughput and the final accuracy.
Usage: ``python bench/replay_throughput.py [--days 365] [--devices 8] [--workers W]``.
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
    ap.add_argument("--days", type=float, default=365.0)
    ap.add_argument("--devices", type=int, default=8)
    ap.add_argument("--workers", type=int, default=os.cpu_count())
    ap.add_argument("--refit-every-days", type=float, default=3.0)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    res = replay_fleet(args.devices, seed=100, workers=args.workers, progress=True, days=args.days,
                       refit_every_days=args.refit_every_days, config=load_config())
    wall = time.perf_counter() - t0
    final = np.array([r["refits"][-1]["sphere_norm_rms_mg"] for r in res])
    per_dev = np.array([r["wall_s"] for r in res])
    print(f"{args.devices} devices x {args.days:g} days on {args.workers} worker processes: {wall:.1f} s wall")
    print(f"throughput: {args.devices * args.days / wall:.2f} simulated device-days/s "
          f"({args.days / np.median(per_dev):.2f} device-days/s per process, median)")
    print(f"final sphere RMS: median {np.median(final):.3f} mg, max {final.max():.3f} mg; "
          f"refits per device: {len(res[0]['refits'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
