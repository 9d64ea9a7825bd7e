"""Fleet replay throughput: simulated device-days per second, per core, on this machine.

In one run, for each level (``poses``: the simulator's still windows; ``samples``: the
20 Hz stream through the detector) and each engine (the local process pool with 1 and
2 processes, and Dask ``distributed`` on a local cluster of 2 single-threaded workers):
``N`` devices x ``D`` days of the paper's protocol (a refit every 3 days), with the
throughput, the throughput per core, and the final accuracy (identical across engines
for the same seeds). Progress goes to stderr.

Every row is the steady state: numba's kernels are loaded in this process (and so in
every forked pool process) before the first timed run, and a Dask cluster is started and
its workers load them before its runs are timed. What a process pays once, at its start
(imports, the kernels loaded from numba's cache and checked against the Python code, or
compiled into an empty cache as after an install), and a Dask cluster's start, are rows of
their own (``--no-startup`` skips them). With the kernels loaded, a plan shorter than 10
days uses them too, where a fresh ``selfcal replay`` plans it in Python (the same plan,
bit for bit; ``selfcal.sim.plan_numba.LOAD_FOR_DAYS``). A long-horizon row (``--long-days``, one device
in this process, 365 days by default) gives the rate a fleet-year replay runs at, with its
user and system CPU, its minor page faults and the process's peak RSS: memory touched for
the first time costs system time here. It is run twice (``--long-runs``): the second run
reuses memory the first one touched, so the two tell compute from first-touch memory (on
this VM, a fresh process's first touches cost ~2 s of a year's simulator, see
docs/performance.md).

Then, unless ``--no-stages``, where a samples-level device-day goes (one device, one
process, the same seed): the simulator alone (the 20 Hz stream of every channel), the
detector alone on that stream, and the random draws the stream cannot do without (three
accelerometer axes, four pressure channels and the temperature: 8 standard normals a
sample, by numpy's Generator and by the simulator's numba draws, the same numbers), each
as device-days/s; and, for the poses level, the simulator's schedule and still windows
alone. A stage slower than the goal bounds the whole replay below it.

    python bench/replay_throughput.py                        # 4 devices x 10 days, both levels
    python bench/replay_throughput.py --days 365 --devices 8 --levels poses --engines processes:2
    python bench/replay_throughput.py --days 45 --levels poses --engines processes:1 --effects bias_step

``--effects`` switches sensor effects on in the simulator (``selfcal replay --effects``):
with ``bias_step`` every device's offset jumps once, and the calibrator that finds it
keeps its cells from either side apart from then on (a barrier in the pose store).
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
    ap.add_argument("--effects", default="", help="sensor effects on, comma-separated (e.g. bias_step)")
    ap.add_argument("--no-stages", action="store_true", help="skip the per-stage figures")
    ap.add_argument("--stage-days", type=float, default=2.0, help="days of the one device timed stage by stage")
    ap.add_argument("--no-startup", action="store_true", help="skip the start-up rows (a fresh process, a cold cache)")
    ap.add_argument("--long-days", type=float, default=365.0,
                    help="days of the long-horizon row (one device, this process, poses level; 0: skip)")
    ap.add_argument("--long-runs", type=int, default=2,
                    help="times the long-horizon row is run in this process (the later ones on memory already touched)")
    args = ap.parse_args(argv)
    cfg = load_config()
    effects = tuple(e for e in args.effects.split(",") if e)
    print(f"replay throughput: {args.devices} devices x {args.days:g} days, refit every "
          f"{args.refit_every_days:g} days, {os.cpu_count()} CPUs"
          + (f", effects: {', '.join(effects)}" if effects else "") + "\n")
    print("| level | engine | workers | wall s | device-days/s | per core | final sphere RMS mg (median, max) |")
    print("|---|---|---:|---:|---:|---:|---|")
    reference: dict[str, list] = {}
    warm_up()  # the rows below are the steady state; what a process pays once is timed apart
    clusters: dict[int, tuple] = {}
    startup_rows: list[tuple[str, float]] = []
    breakdown: dict[str, tuple] = {}
    try:
        run_rows(args, cfg, effects, reference, clusters, startup_rows, breakdown)
    finally:
        for cluster, client, _ in clusters.values():
            client.close()
            cluster.close()
    print_breakdown(breakdown, args.devices * args.days)
    if args.long_days > 0:
        for run in range(max(args.long_runs, 1)):
            print_long(cfg, args.long_days, args.refit_every_days, args.seed, effects, run)
    if not args.no_startup:
        print_startup(startup_rows)
    if not args.no_stages:
        print_stages(cfg, args.stage_days, args.seed)
    return 0


def run_rows(args, cfg: dict, effects: tuple, reference: dict, clusters: dict, startup_rows: list,
             breakdown: dict) -> None:
    """The table's rows, one per level and engine (a Dask cluster of each size is started
    once, into ``clusters``, and closed by the caller)."""
    for level in args.levels.split(","):
        for spec in args.engines.split(","):
            engine, _, n = spec.partition(":")
            workers = int(n or 1)
            scheduler = None
            if engine == "dask":
                if workers not in clusters:
                    clusters[workers] = start_dask(workers)
                    startup_rows.append((f"a local Dask cluster of {workers} workers started, its workers' kernels "
                                         "loaded", clusters[workers][2]))
                scheduler = clusters[workers][0].scheduler_address
            t0 = time.perf_counter()
            res = replay_fleet(args.devices, seed=args.seed, workers=workers, progress=True, engine=engine,
                               scheduler=scheduler, days=args.days, refit_every_days=args.refit_every_days,
                               config=cfg, level=level, effects=effects)
            wall = time.perf_counter() - t0
            final = np.array([r["refits"][-1]["sphere_norm_rms_mg"] for r in res])
            if level not in breakdown and engine == "processes" and workers <= 1:
                # where its device-days went: a row run in this process, one device after the
                # other (with several processes, each stage's wall time would count the waits
                # for a core, and an idle process none)
                breakdown[level] = (res, wall)
            rate = args.devices * args.days / wall
            same = ""
            if level in reference:
                same = " (same results)" if np.array_equal(final, reference[level]) else " (RESULTS DIFFER)"
            else:
                reference[level] = final
            print(f"| {level} | {engine} | {workers} | {wall:.1f} | {rate:.2f} | {rate / min(workers, os.cpu_count() or 1):.2f} "
                  f"| {np.median(final):.3f}, {final.max():.3f}{same} |", flush=True)


def print_breakdown(breakdown: dict[str, tuple], device_days: float) -> None:
    """Per level, the replays' own stage clocks (``stage_s`` of :func:`selfcal.replay.replay`)
    summed over the devices of the level's ``processes:1`` row (run in this process, one
    device after the other), in ms per device-day."""
    from selfcal.replay import StageClock

    if not breakdown:
        print("\n(no processes:1 row: where a device-day goes is measured on one)")
        return
    print("\nwhere a device-day goes (each level's processes:1 row, its devices summed; ms per device-day):\n")
    print("| level | " + " | ".join(StageClock.STAGES) + " | other | all (wall) |")
    print("|---|" + "---:|" * (len(StageClock.STAGES) + 2))
    for level, (res, wall) in breakdown.items():
        stages = {k: sum(r["stage_s"][k] for r in res) for k in StageClock.STAGES}
        cells = [f"{1e3 * stages[k] / device_days:.1f}" for k in StageClock.STAGES]
        other = wall - sum(stages.values())
        print(f"| {level} | " + " | ".join(cells) + f" | {1e3 * other / device_days:.1f} | "
              f"{1e3 * wall / device_days:.1f} |", flush=True)


def warm_up() -> None:
    """Load (or compile into numba's cache) the simulator planner's and draws', the
    detector's, the error models' and the sums' kernels in this process, as a long run has
    them after its first seconds."""
    from selfcal import model_numba, sums_numba
    from selfcal.detect_numba import kernels_now
    from selfcal.sim import draw_numba, plan_numba

    plan_numba.kernels()
    draw_numba.load()
    kernels_now()
    model_numba.load()
    sums_numba.load()


def start_dask(workers: int) -> tuple:
    """``(cluster, client, seconds)``: the local cluster ``replay_fleet`` makes, started and
    its workers' kernels loaded."""
    from distributed import Client

    from selfcal.replay import local_dask_cluster

    t0 = time.perf_counter()
    cluster = local_dask_cluster(workers)
    client = Client(cluster)
    client.run(warm_up)
    return cluster, client, time.perf_counter() - t0


def print_long(cfg: dict, days: float, refit_every_days: float, seed: int, effects: tuple = (), run: int = 0) -> None:
    """One device over a long horizon in this process (poses level): device-days/s, its
    user and system CPU (system: mostly memory touched for the first time), its minor page
    faults and the process's peak RSS so far; ``run`` > 0: a repeat in the same process."""
    import resource

    from selfcal.replay import _replay_one

    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    # as every engine runs a device (one BLAS thread)
    res = _replay_one(dict(days=days, refit_every_days=refit_every_days, seed=seed, config=cfg, level="poses",
                           effects=effects))
    wall, r1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF)
    again = f", run {run + 1} in this process (memory its earlier runs touched reused)" if run else ""
    print(f"\nlong horizon, one device (seed {seed}) x {days:g} days at the poses level, this process{again}: "
          f"{wall:.1f} s, {days / wall:.1f} device-days/s (CPU: user {r1.ru_utime - r0.ru_utime:.1f} s, "
          f"system {r1.ru_stime - r0.ru_stime:.1f} s; simulator {res['stage_s']['simulation']:.1f} s; "
          f"{r1.ru_minflt - r0.ru_minflt} minor page faults, peak RSS {r1.ru_maxrss / 1024:.0f} MB); final sphere RMS "
          f"{res['refits'][-1]['sphere_norm_rms_mg']:.3f} mg", flush=True)


_STARTUP = (
    "import time; t0 = time.perf_counter(); import selfcal.replay; "
    "from selfcal.sim import draw_numba, plan_numba; from selfcal.detect_numba import kernels_now; "
    "from selfcal import model_numba, sums_numba; plan_numba.kernels(); draw_numba.load(); kernels_now(); "
    "model_numba.load(); sums_numba.load(); "
    "print(time.perf_counter() - t0)"
)


def print_startup(rows: list[tuple[str, float]]) -> None:
    """What a process pays once: a fresh interpreter's imports and kernels (from numba's
    cache, and into an empty one), measured in subprocesses; and the rows measured above."""
    import subprocess
    import tempfile

    def fresh(env_extra: dict) -> float:
        env = dict(os.environ, **env_extra)
        out = subprocess.run([sys.executable, "-c", _STARTUP], env=env, capture_output=True, text=True)
        if out.returncode != 0:
            raise SystemExit(f"the start-up measurement failed:\n{out.stderr}")
        return float(out.stdout.strip().splitlines()[-1])

    if os.environ.get("SELFCAL_NUMBA", "").strip() == "0":
        print("\n(SELFCAL_NUMBA=0: the start-up rows below are the imports alone, no kernel is loaded)")

    with tempfile.TemporaryDirectory() as cold:
        measured = [("a fresh process: imports, the kernels loaded from numba's cache and checked", fresh({})),
                    ("a fresh process with an empty numba cache (the first run after an install): the kernels "
                     "compiled", fresh({"NUMBA_CACHE_DIR": cold}))]
    print("\nstart-up, paid once per process (not in the rows above):\n")
    print("| what | s |")
    print("|---|---:|")
    for name, sec in measured + rows:
        print(f"| {name} | {sec:.1f} |", flush=True)


def print_stages(cfg: dict, days: float, seed: int) -> None:
    """Device-days/s of each stage of one device's replay, alone, on this process."""
    from selfcal.config import section
    from selfcal.detect import StaticDetector
    from selfcal.sim import draw_numba
    from selfcal.sim.config import SimConfig
    from selfcal.sim.simulator import Simulation

    sim_cfg = SimConfig.from_section(section(cfg, "sim"))
    rows = []
    t0 = time.perf_counter()
    sim = Simulation(sim_cfg, np.random.default_rng(seed), days=days, seed=seed)
    sim.poses()
    rows.append(("poses level: the simulator's schedule and still windows", time.perf_counter() - t0, None))
    t0 = time.perf_counter()
    chunks = list(sim.iter_samples(chunk_s=3600, truth=False))  # as the replay streams it
    n = sum(len(c.t_s) for c in chunks)
    rows.append(("samples level: the simulator's 20 Hz stream as a replay takes it (schedule excluded, no truth "
                 "columns)", time.perf_counter() - t0, n))
    det = StaticDetector(section(cfg, "detector"))
    t0 = time.perf_counter()
    found = sum(len(det.feed(c.t_s, c.acc_g, temp_c=c.temp_c, pressure_kpa=c.pressure_kpa).t_start_s)
                for c in chunks)
    rows.append((f"samples level: the detector on that stream, 1 h chunks ({found} windows)", time.perf_counter() - t0, n))
    for label, accelerate in (("numpy's Generator", False), ("the simulator's draws (numba's, once loaded)", None)):
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        for c in chunks:
            draw_numba.standard_normal(rng, (len(c.t_s), 8), accelerate)
        rows.append((f"samples level: 8 standard normals a sample, nothing else: {label}", time.perf_counter() - t0, n))
    print(f"\nwhere the time goes, one device x {days:g} days (seed {seed}), one process:\n")
    print("| stage | s | device-days/s | M samples/s |")
    print("|---|---:|---:|---:|")
    for name, wall, samples in rows:
        rate = f"{samples / wall / 1e6:.2f}" if samples else "—"
        print(f"| {name} | {wall:.2f} | {days / wall:.1f} | {rate} |", flush=True)


if __name__ == "__main__":
    sys.exit(main())
