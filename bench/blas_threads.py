"""What OpenBLAS's threads cost selfcal: one BLAS thread against a thread per core.

Runs the same replay (one device, the poses level) in fresh processes, alternating
``OPENBLAS_NUM_THREADS=1`` (what ``selfcal`` sets, :mod:`selfcal.blas_threads`) with
OpenBLAS's default of a thread per core. It does so alone, and beside a process that keeps
one core busy, as a server's request threads or another worker would. Printed, per
condition: the median wall time, the CPU time of the replay's process, and the wall
time of its two calibrators (the ``protocol`` and ``as_shipped`` stages). Also printed: whether the
results were the same in every run (a hash of the refits' rows).

    python bench/blas_threads.py [--days 120] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

from selfcal.blas_threads import THREAD_VARIABLES

_CHILD = """
import hashlib, json, resource, sys, time
from selfcal.config import load_config
from selfcal.replay import replay
from selfcal import model_numba, sums_numba
model_numba.load(); sums_numba.load()
cfg = load_config()
replay(days=2, seed=100, config=cfg)  # warm: the first call's imports and caches
r0 = resource.getrusage(resource.RUSAGE_SELF); t0 = time.perf_counter()
r = replay(days=float(sys.argv[1]), seed=100, config=cfg)
wall = time.perf_counter() - t0; r1 = resource.getrusage(resource.RUSAGE_SELF)
rows = [{k: v for k, v in row.items() if k != "fit_ms"} for row in r["refits"]]
print(json.dumps({"wall_s": wall, "cpu_s": (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime),
                  "refits_s": r["stage_s"]["protocol"] + r["stage_s"]["as_shipped"],
                  "hash": hashlib.sha256(json.dumps(rows, sort_keys=True, default=str).encode()).hexdigest()[:16]}))
"""

def run_child(days: float, threads: int) -> dict:
    """One replay of ``days`` in a fresh process with ``threads`` BLAS threads."""
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    env["OPENBLAS_NUM_THREADS"] = str(threads)
    q = subprocess.run([sys.executable, "-c", _CHILD, str(days)], capture_output=True, text=True, env=env,
                       timeout=1800)
    if q.returncode != 0:
        raise SystemExit(f"the replay's process failed:\n{q.stderr}")
    return json.loads(q.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=float, default=120.0, help="days of the replay (one device, poses level)")
    ap.add_argument("--rounds", type=int, default=3, help="runs of each condition, alternated")
    args = ap.parse_args(argv)
    cores = os.cpu_count() or 1
    print(f"one device x {args.days:g} days at the poses level, {cores} CPUs, {args.rounds} rounds alternated\n")
    if cores < 2:
        print("one core: OpenBLAS runs one thread whatever is asked; nothing to compare")
        return 0
    conditions = [(busy, threads) for busy in (False, True) for threads in (1, cores)]
    got: dict[tuple, list[dict]] = {c: [] for c in conditions}
    for rnd in range(args.rounds):
        for busy, threads in conditions:
            spinner = None
            if busy:
                spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
                time.sleep(0.2)
            try:
                got[(busy, threads)].append(run_child(args.days, threads))
            finally:
                if spinner is not None:
                    spinner.kill()
                    spinner.wait()
            print(f"round {rnd + 1}/{args.rounds}: {'busy' if busy else 'alone'}, {threads} thread(s) done",
                  file=sys.stderr, flush=True)
    print("| other core | BLAS threads | wall s (median) | CPU s (median) | refits s (median) |")
    print("|---|---:|---:|---:|---:|")
    med = {c: {k: statistics.median(r[k] for r in got[c]) for k in ("wall_s", "cpu_s", "refits_s")}
           for c in conditions}
    for busy, threads in conditions:
        m = med[(busy, threads)]
        print(f"| {'busy' if busy else 'idle'} | {threads} | {m['wall_s']:.2f} | {m['cpu_s']:.2f} | {m['refits_s']:.2f} |")
    for busy in (False, True):
        one, many = med[(busy, 1)], med[(busy, cores)]
        print(f"\n{'busy' if busy else 'idle'} core: a thread per core against one: wall x{many['wall_s'] / one['wall_s']:.2f}, "
              f"CPU x{many['cpu_s'] / one['cpu_s']:.2f}, refits x{many['refits_s'] / one['refits_s']:.2f}")
    hashes = {r["hash"] for runs in got.values() for r in runs}
    print(f"\nresults: {'the same in every run' if len(hashes) == 1 else 'DIFFERENT: ' + ', '.join(sorted(hashes))}")
    return 0 if len(hashes) == 1 else 1


if __name__ == "__main__":
    sys.exit(main())
