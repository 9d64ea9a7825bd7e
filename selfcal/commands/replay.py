"""``selfcal replay --days D --refit-every-days R --seed S [--devices N] [--json]``."""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from selfcal.config import load_config
from selfcal.errors import InputError
from selfcal.sim import EFFECT_NAMES


def add_arguments(parser) -> None:
    parser.add_argument("--days", type=float, default=30.0, help="simulated days of wear")
    parser.add_argument("--refit-every-days", type=float, default=3.0,
                        help="the insole paper's protocol period (0: the calibrator's own scheduler)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--devices", type=int, default=1, help="independent devices (seeds seed..seed+N-1), across processes")
    parser.add_argument("--workers", type=int, default=None, help="processes for --devices (default: CPU count)")
    parser.add_argument("--effects", default="", help=f"comma-separated sensor effects to simulate: {', '.join(EFFECT_NAMES)}")
    parser.add_argument("--model", default="affine9", help="the calibrator's model")
    parser.add_argument("--level", choices=("poses", "samples"), default="poses",
                        help="feed still windows (fast) or the full 20 Hz stream through the detector")
    parser.add_argument("--no-random-init", action="store_true", help="start from the nominal model, not random [0, 1]")
    parser.add_argument("--checkpoint", metavar="FILE", help="checkpoint after every refit; resume from it")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    from selfcal.replay import replay, replay_fleet

    effects = tuple(e for e in args.effects.split(",") if e)
    bad = [e for e in effects if e not in EFFECT_NAMES]
    if bad:
        raise InputError(f"--effects: unknown {bad}; choose from {list(EFFECT_NAMES)}")
    if args.days <= 0 or args.refit_every_days < 0 or args.devices < 1:
        raise InputError("--days must be > 0, --refit-every-days >= 0, --devices >= 1")
    cfg = load_config(args.config)
    kw = dict(days=args.days, refit_every_days=args.refit_every_days, config=cfg, effects=effects,
              model=args.model, level=args.level, random_init=not args.no_random_init)
    progress = not args.no_progress and (sys.stderr.isatty() or args.devices > 1)
    t0 = time.perf_counter()
    if args.devices == 1:
        out = replay(seed=args.seed, checkpoint=args.checkpoint, progress=progress, **kw)
    else:
        if args.checkpoint:
            raise InputError("--checkpoint works with one device")
        results = replay_fleet(args.devices, args.seed, workers=args.workers, progress=progress, **kw)
        wall = time.perf_counter() - t0
        last = [r["refits"][-1] for r in results if r["refits"]]
        out = {
            "devices": args.devices, "days": args.days, "wall_s": wall,
            "device_days_per_s": args.devices * args.days / wall,
            "final_sphere_norm_rms_mg": {
                "median": float(np.median([x["sphere_norm_rms_mg"] for x in last])),
                "max": float(np.max([x["sphere_norm_rms_mg"] for x in last])),
            },
            "time_to_calibrated_h": [r["time_to_calibrated_h"] for r in results],
            "results": results,
        }
    if args.json:
        print(json.dumps(out))
        return 0
    if args.devices > 1:
        print(f"{args.devices} devices x {args.days:g} days in {out['wall_s']:.1f} s: "
              f"{out['device_days_per_s']:.1f} simulated device-days/s; final sphere RMS median "
              f"{out['final_sphere_norm_rms_mg']['median']:.3f} mg, max {out['final_sphere_norm_rms_mg']['max']:.3f} mg")
        return 0
    print(f"replay seed {out['seed']}: {out['days']:g} days, refit every {out['refit_every_days']:g} days, "
          f"level {out['level']}, effects {out['effects'] or 'none'}; first 'calibrated' after "
          f"{out['time_to_calibrated_h']:.1f} h" if out["time_to_calibrated_h"] is not None else "never 'calibrated'")
    print(f"{'day':>5} {'param rel err':>14} {'sphere RMS mg':>14} {'tilt deg':>9} {'poses':>6} {'fit ms':>7}  outcome")
    for row in [out["initial"]] + out["refits"]:
        fit = f"{row['fit_ms']:7.2f}" if row.get("fit_ms") is not None else "      -"
        outcome = "initial" if row.get("published") is None else ("published" if row["published"] else row["reason"])
        print(f"{row['day']:5.1f} {row['param_rel_error']:14.4f} {row['sphere_norm_rms_mg']:14.3f} "
              f"{row['tilt_error_deg']:9.3f} {row['n_poses']:6d} {fit}  {outcome}")
    return 0
