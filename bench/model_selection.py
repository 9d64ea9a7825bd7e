"""Online model selection in replays: does the calibrator switch in the effect the sensor has,
and only then? (issue "self-extending calibration")

For each effect (default ``temperature_bias``), ``--devices`` insoles are replayed for
``--days`` days (``selfcal replay``'s default protocol: a refit every 3 days) twice:

* starting from ``affine9``, with online model selection (as shipped);
* with the right model ``affine9+effect`` from the start (the reference).

It prints how many devices switched, the median day of the switch, what they switched
to, and the final true whole-sphere error of each against the reference (ratio). Then
``--clean-devices`` effect-free insoles are replayed from ``affine9`` and every switch
is a false one, and so is every bias step found (steps are not model switches: the
calibrator down-weights the cells from before one).

    python bench/model_selection.py                       # 20 + 20 with the effect, 50 clean
    python bench/model_selection.py --effects temperature_bias,temperature_scale --devices 5 --clean-devices 10
    python bench/model_selection.py --schedule shipped --effects "" --clean-devices 50   # daily checks
    python bench/model_selection.py --screen-ratio 0      # every candidate fitted (no one-step screen)
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from selfcal.config import load_config
from selfcal.replay import replay_fleet


def final_sphere(r: dict) -> float:
    """True whole-sphere RMS (mg) of the last refit of one replay."""
    return float(r["refits"][-1]["sphere_norm_rms_mg"]) if r["refits"] else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--effects", default="temperature_bias")
    ap.add_argument("--devices", type=int, default=20)
    ap.add_argument("--clean-devices", type=int, default=50)
    ap.add_argument("--days", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--schedule", choices=("protocol", "shipped"), default="protocol",
                    help="protocol: selfcal replay's default (a refit, and so at most one check, every 3 days); "
                         "shipped: the calibrator's own scheduler (a check every day of data, as the service runs)")
    ap.add_argument("--screen-ratio", type=float, default=None,
                    help="[selection] screen_ratio (default: the shipped one; 0 fits every candidate at every check)")
    args = ap.parse_args(argv)
    cfg = load_config(None)
    if args.screen_ratio is not None:
        cfg.setdefault("selection", {})["screen_ratio"] = args.screen_ratio
    kw = dict(days=args.days, refit_every_days=3.0 if args.schedule == "protocol" else 0.0, config=cfg,
              workers=args.workers, progress=True)
    print(f"schedule: {args.schedule}; screen_ratio {cfg.get('selection', {}).get('screen_ratio')}")
    for effect in [e for e in args.effects.split(",") if e]:
        t0 = time.perf_counter()
        sel = replay_fleet(args.devices, args.seed, effects=(effect,), model="affine9", **kw)
        ref = replay_fleet(args.devices, args.seed, effects=(effect,), model=f"affine9+{effect}", **kw)
        print(f"\n## effect {effect}: {args.devices} insoles x {args.days:g} days ({time.perf_counter() - t0:.0f} s)")
        print("| seed | switches | first switch day | final model | final sphere mg | right model from start mg | ratio |")
        print("|---:|---|---:|---|---:|---:|---:|")
        firsts, ratios, right = [], [], 0
        for a, b in zip(sel, ref):
            sw = a["model_switches"]
            first = sw[0]["day"] if sw else None
            if first is not None:
                firsts.append(first)
            right += a["model_final"] == f"affine9+{effect}"
            fa, fb = final_sphere(a), final_sphere(b)
            ratios.append(fa / fb if fb > 0 else float("nan"))
            print(f"| {a['seed']} | {' '.join(s['change'][0] + ':' + s['effect'] for s in sw) or '-'} | "
                  f"{'-' if first is None else f'{first:.1f}'} | {a['model_final']} | {fa:.3f} | {fb:.3f} | "
                  f"{ratios[-1]:.2f} |")
        med = f"{np.median(firsts):.1f}" if firsts else "-"
        print(f"\n{effect}: {len(firsts)}/{args.devices} switched, median day of the first switch {med}; "
              f"{right}/{args.devices} end on affine9+{effect}; final sphere error / right-model reference: "
              f"median {np.nanmedian(ratios):.2f}, max {np.nanmax(ratios):.2f}")
    if args.clean_devices:
        t0 = time.perf_counter()
        clean = replay_fleet(args.clean_devices, args.seed + 1000, effects=(), model="affine9", **kw)
        switched = [r for r in clean if r["model_switches"]]
        checks = [r["selection_checks"] for r in clean]
        print(f"\n## no effect: {args.clean_devices} insoles x {args.days:g} days ({time.perf_counter() - t0:.0f} s), "
              f"{sum(checks)} checks ({min(checks)}-{max(checks)} per device)")
        print(f"false switches: {len(switched)}/{args.clean_devices} devices"
              + "".join(f"\n  seed {r['seed']}: " + ", ".join(f"day {s['day']:.1f} {s['change']} {s['effect']} "
                                                            f"(z {s['heldout_z_larger_model']}, chi2 {s['wald_chi2']})"
                                                            for s in r["model_switches"]) for r in switched))
        stepped = [r for r in clean if r.get("bias_steps")]
        print(f"false bias steps: {len(stepped)}/{args.clean_devices} devices"
              + "".join(f"\n  seed {r['seed']}: " + ", ".join(f"day {s['day']:.1f}: {s['size_mg']} mg at "
                                                            f"{s['t_step_s'] / 86400:.1f} d (z {s['heldout_z']}, "
                                                            f"chi2 {s['wald_chi2']})" for s in r["bias_steps"])
                        for r in stepped))
    return 0


if __name__ == "__main__":
    sys.exit(main())
