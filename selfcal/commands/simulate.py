"""``selfcal simulate``: write a simulated insole recording and its truth.

Output: ``PATH`` (recording CSV, contract of design.md) and the truth file beside it:
``PATH`` without a trailing ``.csv`` plus ``.truth.json`` (``day.csv`` ->
``day.truth.json``; ``day.rec`` -> ``day.rec.truth.json``).

``--kind samples`` streams the sample table chunk by chunk (a month never sits in
memory; columns ``t_s,ax_g,ay_g,az_g,temp_c,p1_kpa..p4_kpa``); ``--kind poses`` writes
the still-window table with ``selfcal.io.write_recording``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import TYPE_CHECKING
from pathlib import Path

import numpy as np

from selfcal.config import load_config, section
from selfcal.errors import InputError
from selfcal.scoring import truth_path
from selfcal.sim.config import EFFECT_NAMES, SimConfig

if TYPE_CHECKING:  # the simulator itself loads when the command runs (scipy.signal: ~0.4 s)
    from selfcal.sim.simulator import PoseTable, Simulation

#: The simulated wear simulate and replay accept (days): a minute, and a century.
MIN_DAYS, MAX_DAYS = 1.0 / 1440.0, 36_500.0

SAMPLE_COLUMNS = ("t_s", "ax_g", "ay_g", "az_g", "temp_c", "p1_kpa", "p2_kpa", "p3_kpa", "p4_kpa")
#: 8 decimals of g hold the simulated sensor's 1/256-g steps exactly (6 rounded every level by up
#: to 0.5 ug, the same way at every window of a posture: a small coherent error, docs/simulation.md)
_FMT = "%.4f,%.8f,%.8f,%.8f,%.2f,%.2f,%.2f,%.2f,%.2f"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``selfcal simulate``."""
    parser.add_argument("--days", type=float, default=None, help="simulated days (default [sim].days = 1)")
    parser.add_argument("--seed", type=int, required=True, help="random seed (same seed, same output)")
    parser.add_argument("--out", required=True, metavar="PATH", help="recording to write (CSV)")
    parser.add_argument("--rate-hz", type=float, default=None, help="sample rate (default [sim.ble].rate_hz = 20)")
    parser.add_argument("--effects", default=None,
                        help=f"comma-separated effects to switch on (others off): {','.join(EFFECT_NAMES)}; "
                             "'none' for none; default: as in the config")
    parser.add_argument("--kind", choices=("samples", "poses"), default="samples")
    parser.add_argument("--json", action="store_true", help="print one JSON summary on stdout")


def _meta_lines(kind: str, sim: Simulation, seed: int) -> list[str]:
    return [
        "# selfcal-recording v1",
        f"# kind={kind}",
        "# sensor=selfcal simulated insole (selfcal.sim), foot frame x toes y left z up",
        f"# seed={seed}",
        f"# days={sim.days:g}",
        f"# rate_hz={sim.rate_hz:g}",
        f"# effects={','.join(sim.truth.sensor.enabled) or 'none'}",
        "# p1..p4: heel, midfoot, 1st metatarsal, toe pressure in kPa",
    ]


def write_samples_csv(path: str | os.PathLike, sim: Simulation, seed: int, progress: bool = False) -> int:
    """Stream the sample table of ``sim`` to ``path`` (atomic replace); return rows written."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    rows = 0
    try:
        with tmp.open("w", encoding="utf-8", newline="\n") as fh:
            fh.write("\n".join(_meta_lines("samples", sim, seed)) + "\n")
            fh.write(",".join(SAMPLE_COLUMNS) + "\n")
            for c in sim.iter_samples(progress=progress):
                if len(c) == 0:
                    continue
                table = np.column_stack([c.t_s, c.acc_g, c.temp_c, c.pressure_kpa])
                np.savetxt(fh, table, fmt=_FMT)
                rows += len(c)
        os.replace(tmp, path)
    except BaseException:  # Ctrl-C, a full disk: no half-written file is left behind
        tmp.unlink(missing_ok=True)
        raise
    return rows


def write_poses_csv(path: str | os.PathLike, poses: PoseTable, sim: Simulation, seed: int) -> int:
    """Write the poses table with ``selfcal.io.write_recording``; return rows written."""
    from selfcal.io import Recording, write_recording

    meta = {}
    for line in _meta_lines("poses", sim, seed)[2:]:
        key, _, value = line[2:].partition("=")
        if value:
            meta[key] = value
    rec = Recording(
        kind="poses", unit="g", t_s=poses.t_s, acc=poses.mean_g, temp_c=poses.temp_c,
        pressure=poses.pressure_kpa, pressure_unit="kpa", sd=poses.sd_g, duration_s=poses.duration_s,
        n=poses.n, meta=meta,
    )
    write_recording(path, rec)
    return len(poses)


def run(args: argparse.Namespace) -> int:
    """Simulate and write the recording + truth; print a summary."""
    cfg = SimConfig.from_section(section(load_config(args.config), "sim"))
    if args.effects is not None:
        names = [] if args.effects.strip().lower() in ("", "none") else [
            e.strip() for e in args.effects.split(",") if e.strip()]
        cfg = cfg.with_effects(names)
    if args.days is not None and not (np.isfinite(args.days) and MIN_DAYS <= args.days <= MAX_DAYS):
        raise InputError(f"--days: must be a number from {MIN_DAYS:g} to {MAX_DAYS:g}, got {args.days}")
    if args.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {args.seed}")
    if args.rate_hz is not None and not 0 < args.rate_hz <= 1000:
        raise InputError(f"--rate-hz: must be in (0, 1000], got {args.rate_hz}")
    out = Path(args.out)
    from selfcal.commands.calibrate import check_writable

    check_writable(str(out))  # a folder, a missing folder: before the work, not after it
    check_writable(str(truth_path(out)))
    t0 = time.perf_counter()
    from selfcal.sim.simulator import Simulation

    sim = Simulation(cfg, np.random.default_rng(args.seed), days=args.days, rate_hz=args.rate_hz, seed=args.seed)
    if args.kind == "samples":
        rows = write_samples_csv(out, sim, args.seed, progress=sys.stderr.isatty())
    else:
        rows = write_poses_csv(out, sim.poses(), sim, args.seed)
    tp = truth_path(out)
    truth = sim.truth.to_dict()
    truth.update({"kind": args.kind, "recording": out.name, "rows": rows})
    tmp = tp.with_name(tp.name + ".tmp")
    tmp.write_text(json.dumps(truth, indent=2) + "\n")
    os.replace(tmp, tp)
    summary = {
        "recording": str(out), "truth": str(tp), "kind": args.kind, "rows": rows, "days": sim.days,
        "rate_hz": sim.rate_hz, "seed": args.seed, "effects": list(sim.truth.sensor.enabled),
        "params": truth["params"], "elapsed_s": round(time.perf_counter() - t0, 3),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {rows} {args.kind} rows ({sim.days:g} days at {sim.rate_hz:g} Hz) to {out}")
        print(f"truth: {tp}  effects: {', '.join(summary['effects']) or 'none'}  ({summary['elapsed_s']} s)")
    return 0
