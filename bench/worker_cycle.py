"""What one refit-worker cycle costs, in one process, on SQLite: a device fed one batch.

``D`` devices each get ``K`` batches of ``B`` samples of simulated 20 Hz insole wear
(stored as the API stores them), then the worker (``selfcal_service.main.make_worker``,
the real calibrator) feeds them one batch a cycle, device after device, as a worker that
keeps up does. Printed: ms a cycle and samples/s, the CPU a cycle costs (this process,
and the whole machine: PostgreSQL's server runs beside it), the share of the cycle spent in the
calibrator's feed, in serialising its state, and in the database commit, the state
written per cycle, and what a fresh worker's restore of a device costs (its checkpoint,
then the batches fed since, again). ``--worn-days`` starts every device from the state of
an insole worn that long (a fleet at steady state); ``--checkpoint-samples`` runs the
settings given, paired. A refit tier's
samples/s per core is at most this figure (loopback PostgreSQL and the API's load come on
top).

    python bench/worker_cycle.py [--devices 50] [--batches 20] [--batch-samples 400]
                                 [--worn-days 7] [--checkpoint-samples 0,12000]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # pg_cluster


def worn_state(cfg: dict, ch, i0: int, acc_only: bool = False) -> tuple[str, dict, int]:
    """A calibrator fed the first ``i0`` samples of the simulated stream ``ch`` (``acc_only``:
    without temperature and pressure, for a load that sends only g): (its state as JSON,
    the feed bookkeeping a worker would have stored with it, its pose cells)."""
    from selfcal.calibrator import OnlineCalibrator

    cal = OnlineCalibrator(config={k: v for k, v in cfg.items() if k not in ("service", "gateway")})
    for a in range(0, i0, 1_000_000):
        b = min(i0, a + 1_000_000)
        cal.feed_samples(ch.t_s[a:b], ch.acc_g[a:b], temp_c=None if acc_only else ch.temp_c[a:b],
                         pressure_kpa=None if acc_only else ch.pressure_kpa[a:b])
    feed = {"t_offset_s": 0.0, "last_t_s": float(ch.t_s[i0 - 1]), "first_t_s": float(ch.t_s[0]),
            "first_seq": 0, "samples": i0}
    return cal.to_json(), feed, len(cal.store)


def machine_busy_s() -> float:
    """CPU seconds the whole machine has spent busy since boot (all cores, every process:
    the database server included), from ``/proc/stat``; NaN where there is none."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except OSError:
        return float("nan")
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle, iowait
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")  # guest time is counted in user already


def preload(store, device_id: str, worn: tuple[str, dict, int], checkpoint_age: int = 0) -> None:
    """Give a device (no batch fed yet) the worn state, as a cycle that fed the wear would
    have written it. ``checkpoint_age`` > 0: its checkpoint is written as if that many of
    the worn samples had come after it (the state itself is the worn one), so that a
    fleet's devices come due for their next checkpoint at different times, as worn
    devices do, instead of all at once ``checkpoint_samples`` after the preload."""
    from selfcal_service.storage import Progress

    store.commit_progress(Progress(
        device_id=device_id, expected_processed_seq=None, processed_seq=None, samples_added=0,
        calibrator_state=worn[0], calibrator_status="calibrated", last_refit=None, feed_state=worn[1])).result()
    if checkpoint_age > 0:
        feed = dict(worn[1], samples=int(worn[1]["samples"]) - int(checkpoint_age))
        if not store.write_checkpoint(device_id, None, worn[0], feed):
            raise RuntimeError(f"{device_id}: the preloaded checkpoint was not rewritten")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=50)
    ap.add_argument("--batches", type=int, default=20, help="batches per device (one cycle each)")
    ap.add_argument("--batch-samples", type=int, default=400, help="samples per batch (400 = 20 s at 20 Hz)")
    ap.add_argument("--worn-days", type=float, default=0.0,
                    help="start every device from the state of an insole worn this long (0: empty)")
    ap.add_argument("--checkpoint-samples", default="0,12000",
                    help="comma-separated [service] checkpoint_samples to run, paired (0: the state every cycle)")
    ap.add_argument("--backends", default="sqlite",
                    help="comma-separated: sqlite, postgresql (a throw-away loopback cluster, tests/pg_cluster.py)")
    ap.add_argument("--patch-fractions", default="0.25",
                    help="comma-separated [service] checkpoint_patch_fraction to run, paired (0: every checkpoint "
                         "in full)")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--profile", default="",
                    help="write a cProfile of the timed cycles alone to FILE.<backend>.<checkpoint_samples>")
    args = ap.parse_args(argv)

    from selfcal.calibrator import OnlineCalibrator
    from selfcal.config import load_config, section
    from selfcal.sim.config import SimConfig
    from selfcal.sim.simulator import Simulation

    cfg = load_config()
    n = args.batches * args.batch_samples
    sim = Simulation(SimConfig.from_section(section(cfg, "sim")), np.random.default_rng(args.seed),
                     days=args.worn_days + n / 20.0 / 86400 * 1.1)
    ch = sim.samples()
    i0 = int(np.searchsorted(ch.t_s, args.worn_days * 86400.0))
    if len(ch.t_s) < i0 + n:
        raise SystemExit(f"the simulation gave {len(ch.t_s) - i0} samples after the wear, {n} needed")
    worn = None
    if i0 > 0:  # one insole's state after the wear, given to every device as its checkpoint
        worn = worn_state(cfg, ch, i0)
        print(f"worn {args.worn_days:g} days: {worn[2]} pose cells, state {len(worn[0]) / 1024:,.0f} KiB")
    modes = [int(x) for x in args.checkpoint_samples.split(",")]
    pg = None
    try:
        for backend in args.backends.split(","):
            if backend == "postgresql" and pg is None:
                from pg_cluster import PgCluster, unavailable

                why = unavailable()
                if why:
                    raise SystemExit(f"PostgreSQL unavailable: {why}")
                pg = PgCluster().start()
            fractions = [float(x) for x in args.patch_fractions.split(",")]
            for i, (every, fraction) in enumerate((e, f) for e in modes for f in fractions):
                db = pg.create_database(f"cycle_{i}") if backend == "postgresql" else None
                run(cfg, ch, i0, args, every, worn, backend, db, fraction)
    finally:
        if pg is not None:
            pg.stop()
    return 0


def wal_bytes(db: str | None) -> float:
    """PostgreSQL's write-ahead log position in bytes (NaN on SQLite)."""
    if db is None:
        return float("nan")
    import psycopg

    with psycopg.connect(db, autocommit=True) as conn:
        return float(conn.execute("SELECT pg_wal_lsn_diff(pg_current_wal_lsn(), '0/0')").fetchone()[0])


def run(cfg, ch, i0: int, args, checkpoint_samples: int, worn, backend: str, db: str | None,
        patch_fraction: float = 0.25) -> None:
    from selfcal.calibrator import OnlineCalibrator
    from selfcal.config import section
    from selfcal_service.main import make_worker, open_store
    from selfcal_service.metrics import Metrics
    from selfcal_service.schemas import Batch
    from selfcal_service.settings import load_settings
    from selfcal_service.worker import CalibratorFactory

    timers = {"feed": 0.0, "to_json": 0.0}
    feed0, json0, patch0 = OnlineCalibrator.feed_samples, OnlineCalibrator.to_json, OnlineCalibrator.checkpoint_patch

    def timed(name, fn):
        def run_(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                timers[name] += time.perf_counter() - t0
        return run_

    def to_json(self):
        return timed("to_json", json0)(self)

    def checkpoint_patch(self, base):
        return timed("to_json", patch0)(self, base)

    with tempfile.TemporaryDirectory() as tmp:
        settings = load_settings(section(cfg, "service"), environ={},
                                 overrides={"db_path": db or f"{tmp}/cycle.db", "checkpoint_samples": checkpoint_samples,
                                            "checkpoint_patch_fraction": patch_fraction})
        store = open_store(settings)
        store.open()
        try:
            factory = CalibratorFactory(settings.calibrator,
                                        config={k: v for k, v in cfg.items() if k not in ("service", "gateway")})
            worker = make_worker(store, factory, Metrics(), settings)
            worker.max_batches = 1  # one batch a cycle: a worker that keeps up
            worker.lease = None  # the only worker: no leases to take (PostgreSQL)
            for d in range(args.devices):
                for k in range(args.batches):
                    sl = slice(i0 + k * args.batch_samples, i0 + (k + 1) * args.batch_samples)
                    payload = Batch(seq=k, t_s=ch.t_s[sl], acc_g=ch.acc_g[sl], temp_c=ch.temp_c[sl],
                                    pressure_kpa=ch.pressure_kpa[sl]).to_bytes()
                    store.submit_batch(f"dev{d:04d}", k, args.batch_samples, payload, time.time(),
                                       hashlib.sha256(payload).digest(), 10**6).result()
                if worn is not None:
                    preload(store, f"dev{d:04d}", worn)
            OnlineCalibrator.feed_samples = timed("feed", feed0)
            OnlineCalibrator.to_json = to_json
            OnlineCalibrator.checkpoint_patch = checkpoint_patch
            for d in range(args.devices):  # every device's calibrator restored (not timed)
                worker._calibrator(store.load_device(f"dev{d:04d}", with_state=False))
            timers.update(feed=0.0, to_json=0.0)
            written0 = worker.metrics.get("selfcal_worker_checkpoint_bytes_total")
            patches0 = worker.metrics.get("selfcal_worker_checkpoint_patches_total")
            ckpts0 = worker.metrics.get("selfcal_worker_checkpoints_total")
            wal0 = wal_bytes(db)
            prof = None
            if args.profile:
                import cProfile
                prof = cProfile.Profile()
            t0, c0, m0 = time.perf_counter(), time.process_time(), machine_busy_s()
            if prof is not None:
                prof.enable()
            for _ in range(args.batches):
                for d in range(args.devices):
                    worker.process(f"dev{d:04d}")
            if prof is not None:
                prof.disable()
            wall = time.perf_counter() - t0
            cpu, busy = time.process_time() - c0, machine_busy_s() - m0
            wal = wal_bytes(db) - wal0
            written = worker.metrics.get("selfcal_worker_checkpoint_bytes_total") - written0
            patches = worker.metrics.get("selfcal_worker_checkpoint_patches_total") - patches0
            ckpts = worker.metrics.get("selfcal_worker_checkpoints_total") - ckpts0
            assert worker.replays == 0, "a worker that keeps its calibrators never replays"
            # what a takeover costs: a fresh worker restores every device (checkpoint + replay)
            fresh = make_worker(store, factory, Metrics(), settings)
            fresh.lease = None
            t1 = time.perf_counter()
            for d in range(args.devices):
                fresh._calibrator(store.load_device(f"dev{d:04d}", with_state=False))
            restore = (time.perf_counter() - t1) / args.devices
            replayed = fresh.metrics.get("selfcal_worker_replayed_samples_total") / args.devices
        finally:
            OnlineCalibrator.feed_samples, OnlineCalibrator.to_json = feed0, json0
            OnlineCalibrator.checkpoint_patch = patch0
            store.close()
    cycles = args.devices * args.batches
    rest = wall - timers["feed"] - timers["to_json"]
    if prof is not None:
        out = f"{args.profile}.{backend}.{checkpoint_samples}"
        prof.dump_stats(out)
        print(f"profile of the cycles (cProfile, so the figures below are slowed by it): {out}")
    print(f"{backend}, checkpoint_samples {checkpoint_samples}, patch fraction {patch_fraction:g}: {cycles} cycles of {args.batch_samples} samples in {wall:.2f} s: "
          f"{wall / cycles * 1e3:.2f} ms a cycle, {cycles * args.batch_samples / wall:,.0f} samples/s; CPU a cycle "
          f"{cpu / cycles * 1e3:.2f} ms in this process, {busy / cycles * 1e3:.2f} ms on the machine (the database "
          f"included); calibrator feed "
          f"{timers['feed'] / cycles * 1e3:.2f} ms, state serialised (full or patch) {timers['to_json'] / cycles * 1e3:.2f} ms, the rest "
          f"(database, decoding, bookkeeping) {rest / cycles * 1e3:.2f} ms; {ckpts:,.0f} checkpoints ({patches:,.0f} "
          f"patches), state written {written / cycles / 1024:,.1f} KiB a cycle"
          + ("" if wal != wal else f", write-ahead log {wal / cycles / 1024:,.1f} KiB a cycle")
          + f"; a restore {restore * 1e3:.1f} ms (replaying {replayed:,.0f} samples)")


if __name__ == "__main__":
    sys.exit(main())
