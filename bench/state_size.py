"""What the refit worker writes to the database with a checkpoint: one device's calibrator state.

The service persists a device's whole calibrator state (``OnlineCalibrator.to_json``) as
its checkpoint, in the transaction of the cycle that brings the samples fed since the
last one to ``[service] checkpoint_samples`` (0: every cycle, as before checkpoints), so
that a restarted or replacing worker resumes exactly. This prints, for one simulated
insole fed its still windows day by day (the replay's poses level, seed ``--seed``), the
state's size and what it holds (pose store, detector, the rest), the time to serialise
and to restore it, and what that means for a fleet if it were written at one cycle per
device per batch (``checkpoint_samples = 0``).

    python bench/state_size.py [--days 1,3,7,14,30] [--devices 10000] [--batch-s 20]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from selfcal.calibrator import OnlineCalibrator
from selfcal.config import load_config, section
from selfcal.sim.config import SimConfig
from selfcal.sim.simulator import Simulation


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", default="1,3,7,14,30", help="days of wear at which to measure")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--devices", type=int, default=10_000, help="fleet size for the write-rate column")
    ap.add_argument("--batch-s", type=float, default=20.0, help="seconds of samples per batch (one cycle each)")
    args = ap.parse_args(argv)
    days = [float(x) for x in args.days.split(",")]
    cfg = load_config()
    cal_cfg = {k: v for k, v in cfg.items() if k not in ("service", "gateway")}
    sim = Simulation(SimConfig.from_section(section(cfg, "sim")), np.random.default_rng(args.seed), days=max(days),
                     seed=args.seed)
    poses = sim.poses()
    t_mid = poses.t_s + poses.duration_s / 2
    cal = OnlineCalibrator(config=cal_cfg)
    rate = args.devices / args.batch_s
    print(f"one insole (seed {args.seed}); a fleet of {args.devices} at one cycle per {args.batch_s:g}-s batch = "
          f"{rate:.0f} state writes/s\n")
    print("| days | cells | state KiB | pose store KiB | detector KiB | to_json ms | restore ms | fleet writes MB/s |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    done = 0.0
    for d in days:
        sel = (t_mid >= done * 86400) & (t_mid < d * 86400)
        cal.feed_poses(poses.mean_g[sel], poses.sd_g[sel], poses.n[sel], t_mid[sel], poses.temp_c[sel])
        done = d
        reps = 5
        t0 = time.perf_counter()
        for _ in range(reps):
            text = cal.to_json()
        t_json = (time.perf_counter() - t0) / reps
        t0 = time.perf_counter()
        for _ in range(reps):
            OnlineCalibrator.from_json(text)
        t_restore = (time.perf_counter() - t0) / reps
        parts = json.loads(text)
        kib = lambda x: len(json.dumps(x)) / 1024  # noqa: E731
        print(f"| {d:g} | {len(cal.store)} | {len(text) / 1024:.0f} | {kib(parts.get('store')):.0f} | "
              f"{kib(parts.get('detector')):.0f} | {t_json * 1e3:.2f} | {t_restore * 1e3:.2f} | "
              f"{len(text) * rate / 1e6:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
