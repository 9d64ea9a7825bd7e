"""What the refit worker writes to the database with a checkpoint: one device's calibrator state.

The service persists a device's whole calibrator state (``OnlineCalibrator.to_json``) as
its checkpoint, in the transaction of the cycle that brings the samples fed since the
last one to ``[service] checkpoint_samples`` (0: every cycle, as before checkpoints), so
that a restarted or replacing worker resumes exactly. This prints, for one simulated
insole fed its still windows day by day (the replay's poses level, seed ``--seed``), the
state's size and what it holds (pose store, detector, the rest), the time to serialise
and to restore it, and what that means for a fleet if it were written at one cycle per
device per batch (``checkpoint_samples = 0``).

Since checkpoints may be patches against a stored base (``selfcal.checkpoint``, ``[service]
checkpoint_patch_fraction``), it also prints the patch against the state of that day
after ``--checkpoint-s`` more of wear (the first checkpoint after the base) and after
``--patch-age-h`` (an older base), and the fleet's checkpoint write rate at one checkpoint
per device per ``--checkpoint-s``, in full and as first patches.

    python bench/state_size.py [--days 1,3,7,14,30] [--devices 10000] [--batch-s 20]
                               [--checkpoint-s 600] [--patch-age-h 6]
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
    ap.add_argument("--checkpoint-s", type=float, default=600.0,
                    help="seconds of wear between checkpoints (12 000 samples at 20 Hz = 600 s)")
    ap.add_argument("--patch-age-h", type=float, default=6.0, help="age of the base for the second patch column, h")
    args = ap.parse_args(argv)
    days = [float(x) for x in args.days.split(",")]
    cfg = load_config()
    cal_cfg = {k: v for k, v in cfg.items() if k not in ("service", "gateway")}
    sim = Simulation(SimConfig.from_section(section(cfg, "sim")), np.random.default_rng(args.seed),
                     days=max(days) + args.patch_age_h / 24 + 0.01, seed=args.seed)
    poses = sim.poses()
    t_mid = poses.t_s + poses.duration_s / 2
    cal = OnlineCalibrator(config=cal_cfg)
    rate = args.devices / args.batch_s
    print(f"one insole (seed {args.seed}); a fleet of {args.devices} at one cycle per {args.batch_s:g}-s batch = "
          f"{rate:.0f} state writes/s\n")
    ckpt_rate = args.devices / args.checkpoint_s
    print(f"| days | cells | state KiB | pose store KiB | detector KiB | to_json ms | restore ms | fleet writes MB/s "
          f"| patch KiB after {args.checkpoint_s:g} s | after {args.patch_age_h:g} h | patch ms | restore from a patch ms "
          f"| fleet checkpoints MB/s, full / patch |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")

    def feed(t0_s: float, t1_s: float) -> None:
        sel = (t_mid >= t0_s) & (t_mid < t1_s)
        cal.feed_poses(poses.mean_g[sel], poses.sd_g[sel], poses.n[sel], t_mid[sel], poses.temp_c[sel])

    done = 0.0
    for d in days:
        feed(done * 86400, d * 86400)
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
        # the base is this day's state; its first patch comes a checkpoint later, then older
        base = cal.checkpoint_base(text)
        feed(d * 86400, d * 86400 + args.checkpoint_s)
        t0 = time.perf_counter()
        for _ in range(reps):
            first = cal.checkpoint_patch(base)
        t_patch = (time.perf_counter() - t0) / reps
        t0 = time.perf_counter()
        for _ in range(reps):
            OnlineCalibrator.from_checkpoint(text, first)
        t_from_patch = (time.perf_counter() - t0) / reps
        feed(d * 86400 + args.checkpoint_s, d * 86400 + args.patch_age_h * 3600)
        older = cal.checkpoint_patch(base)
        done = d + args.patch_age_h / 24
        print(f"| {d:g} | {len(cal.store)} | {len(text) / 1024:.0f} | {kib(parts.get('store')):.0f} | "
              f"{kib(parts.get('detector')):.0f} | {t_json * 1e3:.2f} | {t_restore * 1e3:.2f} | "
              f"{len(text) * rate / 1e6:.0f} | {len(first) / 1024:.1f} | {len(older) / 1024:.1f} | "
              f"{t_patch * 1e3:.2f} | {t_from_patch * 1e3:.2f} | "
              f"{len(text) * ckpt_rate / 1e6:.1f} / {len(first) * ckpt_rate / 1e6:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
