"""What one refit-worker cycle costs, in one process, on SQLite: a device fed one batch.

``D`` devices each get ``K`` batches of ``B`` samples of simulated 20 Hz insole wear
(stored as the API stores them), then the worker (``selfcal_service.main.make_worker``,
the real calibrator) feeds them one batch a cycle, device after device, as a worker that
keeps up does. Printed: ms a cycle and samples/s, and the share of the cycle spent in the
calibrator's feed, in serialising its state, and in the database commit. A refit tier's
samples/s per core is at most this figure (loopback PostgreSQL and the API's load come on
top).

    python bench/worker_cycle.py [--devices 50] [--batches 20] [--batch-samples 400]
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "service"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=50)
    ap.add_argument("--batches", type=int, default=20, help="batches per device (one cycle each)")
    ap.add_argument("--batch-samples", type=int, default=400, help="samples per batch (400 = 20 s at 20 Hz)")
    ap.add_argument("--seed", type=int, default=2)
    args = ap.parse_args(argv)

    from selfcal.calibrator import OnlineCalibrator
    from selfcal.config import load_config, section
    from selfcal.sim.config import SimConfig
    from selfcal.sim.simulator import Simulation
    from selfcal_service.main import make_worker, open_store
    from selfcal_service.metrics import Metrics
    from selfcal_service.schemas import Batch
    from selfcal_service.settings import load_settings
    from selfcal_service.worker import CalibratorFactory

    cfg = load_config()
    n = args.batches * args.batch_samples
    sim = Simulation(SimConfig.from_section(section(cfg, "sim")), np.random.default_rng(args.seed),
                     days=n / 20.0 / 86400 * 1.1)
    ch = sim.samples()
    if len(ch.t_s) < n:
        raise SystemExit(f"the simulation gave {len(ch.t_s)} samples, {n} needed")
    timers = {"feed": 0.0, "to_json": 0.0}
    feed0, json0 = OnlineCalibrator.feed_samples, OnlineCalibrator.to_json

    def timed(name, fn):
        def run(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                timers[name] += time.perf_counter() - t0
        return run

    with tempfile.TemporaryDirectory() as tmp:
        settings = load_settings(section(cfg, "service"), overrides={"db_path": f"{tmp}/cycle.db"}, environ={})
        store = open_store(settings)
        store.open()
        try:
            factory = CalibratorFactory(settings.calibrator,
                                        config={k: v for k, v in cfg.items() if k not in ("service", "gateway")})
            worker = make_worker(store, factory, Metrics(), settings)
            worker.max_batches = 1  # one batch a cycle: a worker that keeps up
            for d in range(args.devices):
                for k in range(args.batches):
                    sl = slice(k * args.batch_samples, (k + 1) * args.batch_samples)
                    payload = Batch(seq=k, t_s=ch.t_s[sl], acc_g=ch.acc_g[sl], temp_c=ch.temp_c[sl],
                                    pressure_kpa=ch.pressure_kpa[sl]).to_bytes()
                    store.submit_batch(f"dev{d:04d}", k, args.batch_samples, payload, time.time(),
                                       hashlib.sha256(payload).digest(), 10**6).result()
            OnlineCalibrator.feed_samples = timed("feed", feed0)
            OnlineCalibrator.to_json = timed("to_json", json0)
            t0 = time.perf_counter()
            for _ in range(args.batches):
                for d in range(args.devices):
                    worker.process(f"dev{d:04d}")
            wall = time.perf_counter() - t0
        finally:
            OnlineCalibrator.feed_samples, OnlineCalibrator.to_json = feed0, json0
            store.close()
    cycles = args.devices * args.batches
    rest = wall - timers["feed"] - timers["to_json"]
    print(f"{cycles} cycles of {args.batch_samples} samples in {wall:.2f} s: {wall / cycles * 1e3:.2f} ms a cycle, "
          f"{cycles * args.batch_samples / wall:,.0f} samples/s; calibrator feed {timers['feed'] / cycles * 1e3:.2f} ms, "
          f"state to JSON {timers['to_json'] / cycles * 1e3:.2f} ms, the rest (database, decoding, bookkeeping) "
          f"{rest / cycles * 1e3:.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
