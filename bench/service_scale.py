"""Scale-out benchmark: the service on PostgreSQL with 1, 2 and 4 API processes, SQLite beside it.

In one run, on loopback: for each configuration a fresh database and a real
``selfcal serve`` (PostgreSQL: ``--workers N --no-refit`` plus ``--refit-workers``
``selfcal worker`` processes; SQLite: the single embedded process), then the load
process of ``bench/service_load.py`` (N insoles at 20 Hz, open loop, 20-s batches,
32 keep-alive connections, a GET prober at 100 Hz in its own process, as an app is).
It prints samples/s acknowledged, GET p50/p99 (and those of GETs sent from inside the
load loop, which wait behind its senders), the refit backlog (age of the oldest batch not
yet fed) sampled from ``/metrics`` every 2 s, and the CPU each tier used (the API
processes, the workers, PostgreSQL's server and backends, from ``/proc``); then a
projection of the machines needed for 100 000 insoles from the per-process figures and
from the CPU a sample costs each tier. The insoles send a simulated wearer's day
(``--data wear``) or synthetic poses in random directions (``--data sphere``, a worst case
for the refits).

    python bench/service_scale.py                                  # 10 000 devices, 20-s batches
    python bench/service_scale.py --devices 2000 --step-s 10 --procs 1,2

The PostgreSQL server is a throw-away cluster (tests/pg_cluster.py; scripts/postgres.sh
installs the binaries). Everything shares this machine's cores: the figures are what
this machine does, not what a cluster of machines would do; the projection says so.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "bench"))

from service_load import KEY, free_port, wait_up  # noqa: E402


def metrics(port: int) -> dict[str, float]:
    import httpx

    text = httpx.get(f"http://127.0.0.1:{port}/metrics", headers={"Authorization": f"Bearer {KEY}"}, timeout=30).text
    out: dict[str, float] = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, _, value = line.rpartition(" ")
            out[name] = float(value)
    return out


def gc_pauses(m: dict[str, float]) -> dict:
    """The API processes' garbage-collector pauses so far, from a ``/metrics`` scrape ``m``:
    per generation, ``(count, total s, count longer than 10 ms)`` (``role="api"``: the refit
    workers' own pauses, labelled ``worker``, stall no request)."""
    out = {}
    for g in (0, 1, 2):
        lab = f'generation="{g}",role="api"'
        n = m.get(f"selfcal_gc_pause_seconds_count{{{lab}}}", float("nan"))
        under = m.get(f'selfcal_gc_pause_seconds_bucket{{{lab},le="0.01"}}', float("nan"))
        out[g] = (n, m.get(f"selfcal_gc_pause_seconds_sum{{{lab}}}", float("nan")), n - under)
    return out


def preload_worn(db: str, args) -> None:
    """Every bench device gets the worn state before the service starts (bench/worker_cycle.py).
    Unless ``--in-step``, each device's checkpoint is given a random age below the
    checkpoint interval, so that the devices' next checkpoints are spread over it."""
    import numpy as np
    from worker_cycle import preload

    from selfcal_service.main import open_store
    from selfcal_service.settings import load_settings

    settings = load_settings({}, overrides={"db_path": db}, environ={})
    every = args.checkpoint_samples if args.checkpoint_samples is not None else settings.checkpoint_samples
    ages = np.zeros(args.devices, int) if args.in_step or every <= 1 else \
        np.random.default_rng(7).integers(0, every, args.devices)
    store = open_store(settings)
    store.open()
    try:
        t0 = time.monotonic()
        for d in range(args.devices):
            preload(store, f"bench-{d:05d}", args.worn, checkpoint_age=int(ages[d]))
        print(f"    preloaded {args.devices} worn devices in {time.monotonic() - t0:.0f} s", flush=True)
    finally:
        store.close()


def tree_cpu_s(roots: list[int]) -> float:
    """CPU seconds (user + system, with those of waited-for children) used so far by the
    processes ``roots`` and all their live descendants, from Linux's ``/proc``; NaN where
    there is none. The difference over a run is what that tier cost, busy or not."""
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    procs: dict[int, tuple[int, int]] = {}
    try:
        names = os.listdir("/proc")
    except OSError:
        return float("nan")
    for name in names:
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                rest = f.read().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        procs[int(name)] = (int(rest[1]), sum(int(x) for x in rest[11:15]))
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in procs.items():
        children.setdefault(ppid, []).append(pid)
    total, todo, seen = 0, [p for p in roots if p in procs], set()
    while todo:
        pid = todo.pop()
        if pid in seen:
            continue
        seen.add(pid)
        total += procs[pid][1]
        todo += children.get(pid, [])
    return total / tick if seen else float("nan")


def cpu_per_sample(r: dict) -> dict[str, float]:
    """CPU microseconds a sample, per tier, from a run's CPU seconds: the API and PostgreSQL
    per sample stored over the same span (the service's own counter), the workers per
    sample they fed."""
    out = {}
    acked = r["stored"]
    for tier, cpu in r["cpu_s"].items():
        n = r["samples_fed"] if tier == "workers" else acked
        if cpu == cpu and n == n and n > 0 and (tier != "workers" or r["refit_workers"]):
            out[tier] = cpu / n * 1e6
    return out


def postmaster_pid(pg) -> int | None:
    """The bench cluster's server process (its children are the backends)."""
    try:
        return int((pg.dir / "data" / "postmaster.pid").read_text().split()[0])
    except (OSError, ValueError, IndexError, TypeError):
        return None


def wal_bytes(db: str) -> float:
    """PostgreSQL's write-ahead-log position, in bytes since its start (NaN for SQLite): the
    difference over a run is every write the database had to persist (batches, versions,
    devices, checkpoints)."""
    if not db.startswith("postgresql"):
        return float("nan")
    import psycopg

    with psycopg.connect(db, autocommit=True) as conn:
        return float(conn.execute("SELECT pg_wal_lsn_diff(pg_current_wal_lsn(), '0/0')").fetchone()[0])


def run_config(label: str, db: str, procs: int, refit_workers: int, args, pg_pid: int | None = None) -> dict:
    if getattr(args, "worn", None) is not None:
        preload_worn(db, args)
    port = free_port()
    # one metrics folder for the API and the workers: /metrics adds the workers' refit counters
    metrics_dir = tempfile.mkdtemp(prefix="selfcal-bench-metrics-")
    env = dict(os.environ, SELFCAL_API_KEYS=f"{KEY}=ingest+read", SELFCAL_MIN_CYCLE_INTERVAL_S=str(args.min_cycle_s),
               SELFCAL_METRICS_DIR=metrics_dir)
    if args.checkpoint_samples is not None:
        env["SELFCAL_CHECKPOINT_SAMPLES"] = str(args.checkpoint_samples)
    if args.patch_fraction is not None:
        env["SELFCAL_CHECKPOINT_PATCH_FRACTION"] = str(args.patch_fraction)
    cmd = [sys.executable, "-m", "selfcal.cli", "serve", "--db", db, "--port", str(port), "--log-level", "warning"]
    if db.startswith("postgresql"):
        cmd += ["--workers", str(procs), "--no-refit"]
    else:
        cmd += ["--refit-threads", str(args.worker_threads)] if args.worker_threads else []
    server = subprocess.Popen(cmd, env=env, cwd=str(REPO), stderr=subprocess.DEVNULL)
    workers = [subprocess.Popen([sys.executable, "-m", "selfcal.cli", "worker", "--db", db, "--status-every-s", "0",
                                 *(["--threads", str(args.worker_threads)] if args.worker_threads else []),
                                 "--nice", str(args.worker_nice),
                                 *(["--idle"] if args.worker_idle else []),
                                 "--log-level", "warning"], env=env, cwd=str(REPO), stderr=subprocess.DEVNULL)
               for _ in range(refit_workers if db.startswith("postgresql") else 0)]
    backlog: list[tuple[float, float, float]] = []  # (t, oldest age s, batches)
    stop = threading.Event()
    try:
        wait_up(port)
        t0 = time.monotonic()

        def sample() -> None:
            while not stop.wait(2.0):
                try:
                    m = metrics(port)
                    backlog.append((time.monotonic() - t0, m.get("selfcal_backlog_oldest_age_seconds", float("nan")),
                                    m.get("selfcal_backlog_batches", float("nan"))))
                except Exception:  # noqa: BLE001 - a sample missed under load
                    pass

        wal0 = wal_bytes(db)
        tiers = {"api": [server.pid], "workers": [w.pid for w in workers],
                 "postgresql": [pg_pid] if pg_pid and db.startswith("postgresql") else []}
        cpu0 = {k: tree_cpu_s(v) for k, v in tiers.items()}
        stored0 = metrics(port).get("selfcal_ingest_samples_total", float("nan"))  # same span as the CPU
        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        load = subprocess.run(
            [sys.executable, str(REPO / "bench" / "service_load.py"), "--load-only", "--port", str(port),
             "--devices", str(args.devices), "--batch-s", str(args.batch_s), "--step-s", str(args.step_s),
             "--warmup-s", str(args.warmup_s), "--connections", str(args.connections), "--get-hz", "100",
             "--format", args.format, "--inflight-devices", "0", "--seed", "7",
             "--t0-s", repr(args.t0_s), "--t0-spread-s", repr(args.t0_spread_s),
             "--data", args.data, "--wear-seed", "2", "--wear-days", "1", "--wear-skip-days", repr(args.worn_days)],
            capture_output=True, text=True, timeout=900)
        stop.set()
        wal_s = time.monotonic() - t0
        wal = wal_bytes(db) - wal0
        cpu = {k: tree_cpu_s(v) - cpu0[k] for k, v in tiers.items()}
        try:
            stored = metrics(port).get("selfcal_ingest_samples_total", float("nan")) - stored0
        except Exception:  # noqa: BLE001 - then no CPU a sample for the API and the database
            stored = float("nan")
        rows = [json.loads(line) for line in load.stdout.splitlines() if line.startswith("{")]
        if not rows:
            raise RuntimeError(f"{label}: the load process printed nothing: {load.stderr[-1000:]}")
        r = rows[-1]
        try:
            m = metrics(port)  # one scrape at the end: collector pauses and worker cycles
        except Exception:  # noqa: BLE001 - the figures are missing, the run is not
            m = {}
        r.update(label=label, procs=procs, refit_workers=len(workers), backlog=backlog, gc=gc_pauses(m),
                 cycles=m.get("selfcal_worker_cycles_total", float("nan")),
                 samples_fed=m.get("selfcal_worker_samples_total", float("nan")),
                 checkpoints=m.get("selfcal_worker_checkpoints_total", float("nan")),
                 patches=m.get("selfcal_worker_checkpoint_patches_total", float("nan")),
                 checkpoint_mb=m.get("selfcal_worker_checkpoint_bytes_total", float("nan")) / 1e6,
                 replays=m.get("selfcal_worker_replays_total", float("nan")),
                 replayed=m.get("selfcal_worker_replayed_samples_total", float("nan")),
                 rejected=sum(v for k, v in m.items() if k.startswith("selfcal_rejected_batches_total")),
                 wal_mb_s=wal / wal_s / 1e6, cpu_s=cpu, run_s=wal_s, stored=stored)
        return r
    finally:
        stop.set()
        for p in [server, *workers]:
            p.send_signal(signal.SIGTERM)
        for p in [server, *workers]:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(metrics_dir, ignore_errors=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=10_000)
    ap.add_argument("--batch-s", type=float, default=20.0, help="seconds of samples per batch (400 at 20 Hz)")
    ap.add_argument("--step-s", type=float, default=20.0, help="measured seconds per configuration")
    ap.add_argument("--warmup-s", type=float, default=5.0)
    ap.add_argument("--connections", type=int, default=32)
    ap.add_argument("--procs", default="1,2,4", help="API process counts on PostgreSQL")
    ap.add_argument("--refit-workers", type=int, default=1, help="selfcal worker processes on PostgreSQL")
    ap.add_argument("--worker-nice", type=int, default=0, help="selfcal worker --nice N (PostgreSQL)")
    ap.add_argument("--worker-idle", action="store_true", help="selfcal worker --idle (SCHED_IDLE, Linux)")
    ap.add_argument("--worker-threads", type=int, default=None,
                    help="refit threads of each worker (and of SQLite's process); default: theirs "
                         "(selfcal worker 4, selfcal serve 1)")
    ap.add_argument("--format", choices=["json", "binary"], default="binary")
    ap.add_argument("--min-cycle-s", type=float, default=0.0,
                    help="[service] min_cycle_interval_s of the refit workers and SQLite's process (0: as batches come)")
    ap.add_argument("--no-sqlite", action="store_true")
    ap.add_argument("--worn-days", type=float, default=0.0,
                    help="start every device from the state of an insole worn this long (0: empty; a fleet at steady "
                         "state is worn: its states are ~1.2 MB after a week)")
    ap.add_argument("--data", choices=["wear", "sphere"], default="wear",
                    help="what the insoles send (bench/service_load.py --data): wear, a day of the simulated wearer "
                         "and sensor of the worn state (seed 2; with --worn-days, a day after as many days), each device "
                         "at its own point of it; sphere, the synthetic poses in random "
                         "directions of the earlier runs, which open a pose cell every few batches and so make every "
                         "calibrator refit every few minutes (~5x the refit work of wear)")
    ap.add_argument("--in-step", action="store_true",
                    help="with --worn-days: every device's clock continues the worn state's at once, so every "
                         "calibrator's time-based refit comes due in the same seconds, and every preloaded "
                         "checkpoint is as old as the others, so they all come due together (without it, each "
                         "device's clock resumes at a random point of its refit period and its checkpoint at a "
                         "random point of the checkpoint interval, as in a fleet worn for days)")
    ap.add_argument("--checkpoint-samples", type=int, default=None,
                    help="[service] checkpoint_samples of every process (default: the service's; 0: the state at every cycle)")
    ap.add_argument("--patch-fraction", type=float, default=None,
                    help="[service] checkpoint_patch_fraction of every process (default: the service's; 0: every "
                         "checkpoint in full)")
    args = ap.parse_args()

    from pg_cluster import PgCluster, unavailable

    why = unavailable()
    if why:
        print(f"PostgreSQL unavailable: {why}", file=sys.stderr)
        return 1
    print(f"selfcal service scale-out: {args.devices} insoles x 20 Hz, {args.batch_s:g}-s batches "
          f"({args.devices * 20:,} samples/s offered, {args.devices / args.batch_s:.0f} req/s), "
          f"{args.format} batches of {args.data} data, {os.cpu_count()} CPUs shared by everything", flush=True)
    results = []
    if args.worn_days > 0:
        import numpy as np
        from worker_cycle import worn_state

        from selfcal.config import load_config, section
        from selfcal.sim.config import SimConfig
        from selfcal.sim.simulator import Simulation

        cfg = load_config()
        ch = Simulation(SimConfig.from_section(section(cfg, "sim")), np.random.default_rng(2), days=args.worn_days).samples()
        args.worn = worn_state(cfg, ch, len(ch.t_s), acc_only=True)  # the load sends g only
        print(f"every device starts worn {args.worn_days:g} days: {args.worn[2]} pose cells, "
              f"state {len(args.worn[0]) / 1024:,.0f} KiB", flush=True)
        # the load's clocks continue the worn stream (no clock reset), each device at its own
        # point of the calibrator's refit period unless --in-step
        args.t0_s = float(ch.t_s[-1]) + 1.0
        args.t0_spread_s = 0.0 if args.in_step else 3600.0 * float(section(cfg, "scheduler")["refit_every_hours"])
        print(f"device clocks resume {'together' if args.in_step else f'spread over {args.t0_spread_s / 3600:g} h'} "
              f"after the worn stream", flush=True)
    else:
        args.t0_s = args.t0_spread_s = 0.0
    with PgCluster(max_connections=200) as pg, tempfile.TemporaryDirectory(prefix="selfcal-scale-") as tmp:
        configs = [] if args.no_sqlite else [("sqlite, 1 process (embedded refits)", f"{tmp}/scale.db", 1)]
        for n in [int(x) for x in args.procs.split(",") if x.strip()]:  # "" : SQLite alone
            nice = f" (nice {args.worker_nice})" if args.worker_nice and args.refit_workers else ""
            nice += " (idle)" if args.worker_idle and args.refit_workers else ""
            nice += f" (cycles >= {args.min_cycle_s:g} s apart)" if args.min_cycle_s and args.refit_workers else ""
            configs.append((f"postgresql, {n} API + {args.refit_workers} worker{nice}",
                            pg.create_database(f"scale_{n}"), n))
        for label, db, n in configs:
            r = run_config(label, db, n, args.refit_workers, args, pg_pid=postmaster_pid(pg))
            results.append(r)
            ages = [a for _, a, _ in r["backlog"] if a == a]
            print(f"{label:<40} acked {r['sustained_sps']:>8,.0f} samples/s ({r['req_per_s']:.0f} req/s)  "
                  f"GET p50 {r['app_get_p50_ms']:6.2f} ms  p99 {r['app_get_p99_ms']:7.2f} ms  errors {r['errors']}  "
                  f"oldest unfed batch: max {max(ages, default=float('nan')):.1f} s, "
                  f"last {ages[-1] if ages else float('nan'):.1f} s", flush=True)
            print(f"    the same GETs from inside the load generator's loop: p50 {r['get_p50_ms']:.2f} ms, "
                  f"p99 {r['get_p99_ms']:.2f} ms", flush=True)
            if r["wal_mb_s"] == r["wal_mb_s"]:
                print(f"    PostgreSQL write-ahead log: {r['wal_mb_s']:.1f} MB/s "
                      f"({r['wal_mb_s'] * 1e6 / max(1.0, r['sustained_sps']):.0f} bytes a sample acked)", flush=True)
            if r["cycles"] > 0:
                print(f"    refit cycles committed: {r['cycles']:,.0f} for {r['samples_fed']:,.0f} samples fed "
                      f"({r['samples_fed'] / r['cycles'] / (args.batch_s * 20):.1f} batches a cycle)", flush=True)
                if r.get("rejected"):
                    print(f"    batches rejected (not fed): {r['rejected']:,.0f}", flush=True)
                print(f"    calibrator states written (checkpoints): {r['checkpoints']:,.0f} ({r['patches']:,.0f} as "
                      f"patches against a stored base; {r['checkpoint_mb']:,.1f} MB in all); restores that "
                      f"replayed batches: {r['replays']:,.0f} ({r['replayed']:,.0f} samples fed again)", flush=True)
            r["cpu_us"] = cpu_per_sample(r)
            if r["cpu_us"]:
                print("    CPU over the run, cores busy: " + ", ".join(
                    f"{k} {v / r['run_s']:.2f}" for k, v in r["cpu_s"].items() if v == v) + "; CPU a sample: " + ", ".join(
                    f"{k} {v:.1f} us" for k, v in r["cpu_us"].items()) + " (workers: a sample fed; the others: acked)",
                    flush=True)
            if r.get("gc"):
                print("    garbage-collector pauses of the API process(es) (generation: count, total, over 10 ms): " + "; ".join(
                    f"{g}: {n:.0f}, {tot * 1e3:.0f} ms, {long_:.0f}" for g, (n, tot, long_) in r["gc"].items()), flush=True)
            print("    backlog over time (s: oldest age s / batches): " + ", ".join(
                f"{t:.0f}: {a:.1f}/{b:.0f}" for t, a, b in r["backlog"]), flush=True)
    # refit throughput: what was acknowledged minus what piled up (slope of the backlog). The
    # backlog fills first (batches wait for their cycle; with --min-cycle-s for the interval),
    # so over a run of 8 samples or more the slope of its second half is the steady one
    per_batch = args.batch_s * 20.0
    print("\nrefit throughput (acked minus backlog growth; the growth over the second half of the run "
          "when it has 8 backlog samples or more, the first minute's fill left out):")
    for r in results:
        pts = [(t, b) for t, _, b in r["backlog"] if b == b]
        slope = steady = 0.0
        if len(pts) >= 2:
            import numpy as np

            slope = steady = float(np.polyfit([t for t, _ in pts], [b for _, b in pts], 1)[0])
            if len(pts) >= 8:
                half = pts[len(pts) // 2:]
                steady = float(np.polyfit([t for t, _ in half], [b for _, b in half], 1)[0])
        r["fed_sps"] = max(0.0, r["sustained_sps"] - steady * per_batch)
        print(f"  {r['label']:<38} fed {r['fed_sps']:>9,.0f} samples/s; backlog grows {steady:6.1f} batches/s "
              f"({slope:.1f} over the whole run)")
    ingest = max(r["sustained_sps"] / max(1, r["procs"]) for r in results)
    refit = max((r["fed_sps"] / r["refit_workers"] for r in results if r["refit_workers"]), default=0.0)
    if refit <= 0:
        print("\nno refit worker ran (--refit-workers 0): no projection of the refit tier")
        return 0
    print(f"\nprojection for 100 000 insoles (2 000 000 samples/s, {args.batch_s:g}-s batches), from the best "
          f"per-process figures measured here: ingest {ingest:,.0f} samples/s per API process, refits "
          f"{refit:,.0f} samples/s per worker process -> about {2e6 / ingest:.0f} API processes and "
          f"{2e6 / max(refit, 1):.0f} refit workers, i.e. about {(2e6 / ingest + 2e6 / max(refit, 1)) / 2:.0f} "
          f"2-core machines besides PostgreSQL. The bottleneck is the refits (detector, pose store and "
          f"least squares in Python, one device at a time per worker). Every process here shared 2 cores "
          f"with the load generator and PostgreSQL, so these per-process figures are floors.")
    costs = [r["cpu_us"] for r in results if r.get("cpu_us") and "workers" in r["cpu_us"] and "postgresql" in r["cpu_us"]]
    if costs:
        best = {k: min(c[k] for c in costs) for k in ("api", "workers", "postgresql")}
        cores = {k: 2e6 * v / 1e6 for k, v in best.items()}
        print(f"\nfrom the CPU a sample costs each tier (busy or idle, so not a floor; least over the PostgreSQL runs): "
              + ", ".join(f"{k} {best[k]:.1f} us -> {cores[k]:.0f} cores" for k in best)
              + f" for 2 000 000 samples/s: about {sum(cores.values()):.0f} cores in all, "
              f"{cores['postgresql']:.0f} of them PostgreSQL's (one server or several, sharded by device).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
