"""How much do soaks help the z tempco? Simulated insole wear with a temperature offset
effect, fed to the online calibrator (``affine9+temperature_bias``) with and without the
off-foot still windows (the insole lying in its shoe while it cools to ambient: soaks).

For each wearer it prints the first day on which ``tbz`` is determined, and its final
error (mg/°C and in reported sd), with soaks and without; then the medians.

    python bench/soak_replay.py --wearers 10 --days 14
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from selfcal.calibrator import OnlineCalibrator
from selfcal.config import load_config, section
from selfcal.sim import SimConfig, Simulation
from selfcal.sim.wearer import OFF

MODEL = "affine9+temperature_bias"


def run(seed: int, days: float, with_soaks: bool, cfg: dict) -> dict:
    sim_cfg = SimConfig.from_section(section(cfg, "sim")).with_effects(["temperature_bias"])
    sim = Simulation(sim_cfg, np.random.default_rng(seed), days=days, seed=seed)
    p = sim.poses()
    keep = np.all(p.sd_g <= float(section(cfg, "detector").get("sd_max_g", 0.010)), axis=1)
    if not with_soaks:
        keep &= p.activity != OFF
    true_tbz = sim.truth.sensor.model_params()["tbz"]
    cal = OnlineCalibrator(cfg, MODEL)
    first_day, est = None, None
    t_mid = p.t_s + 0.5 * p.duration_s
    for hour in range(int(np.ceil(days * 24))):
        sel = keep & (t_mid >= hour * 3600.0) & (t_mid < (hour + 1) * 3600.0)
        cal.feed_poses(p.mean_g[sel], p.sd_g[sel], p.n[sel], t_mid[sel], p.temp_c[sel])
        c = cal.calibration()
        if c is None:
            continue
        est = (c["params"]["tbz"], c["std"]["tbz"])
        if first_day is None and "tbz" in c.get("determined", []):
            first_day = (hour + 1) / 24.0
    out = {"seed": seed, "soaks": with_soaks, "windows": int(keep.sum()), "tbz_true_mg": true_tbz * 1e3,
           "first_day_determined": first_day}
    if est is not None:
        out.update(tbz_mg=est[0] * 1e3, tbz_sd_mg=est[1] * 1e3, err_mg=abs(est[0] - true_tbz) * 1e3,
                   err_sd=abs(est[0] - true_tbz) / est[1] if est[1] else float("nan"))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--wearers", type=int, default=10)
    ap.add_argument("--days", type=float, default=14.0)
    ap.add_argument("--seed", type=int, default=500)
    args = ap.parse_args(argv)
    cfg = load_config()
    print(f"{args.wearers} wearers x {args.days:g} days, effect temperature_bias, model {MODEL}\n")
    print("| wearer | soaks | windows | tbz true mg/°C | first day tbz determined | final tbz ± sd | error mg/°C (sd) |")
    print("|---|---|---:|---:|---:|---|---|")
    rows = []
    for i in range(args.wearers):
        for with_soaks in (True, False):
            r = run(args.seed + i, args.days, with_soaks, cfg)
            rows.append(r)
            est = f"{r['tbz_mg']:+.3f} ± {r['tbz_sd_mg']:.3f}" if "tbz_mg" in r else "—"
            err = f"{r['err_mg']:.3f} ({r['err_sd']:.1f})" if "err_mg" in r else "—"
            day = f"{r['first_day_determined']:.2f}" if r["first_day_determined"] else "never"
            print(f"| {r['seed']} | {'with' if with_soaks else 'without'} | {r['windows']} | {r['tbz_true_mg']:+.3f} "
                  f"| {day} | {est} | {err} |", flush=True)
    for with_soaks in (True, False):
        sub = [r for r in rows if r["soaks"] == with_soaks]
        days = [r["first_day_determined"] for r in sub if r["first_day_determined"]]
        errs = [r["err_mg"] for r in sub if "err_mg" in r]
        print(f"\n{'with' if with_soaks else 'without'} soaks: tbz determined for {len(days)}/{len(sub)} wearers, "
              f"median first day {np.median(days) if days else float('nan'):.2f}; median final error "
              f"{np.median(errs) if errs else float('nan'):.4f} mg/°C, median final sd "
              f"{np.median([r['tbz_sd_mg'] for r in sub if 'tbz_sd_mg' in r]):.4f} mg/°C")
    return 0


if __name__ == "__main__":
    sys.exit(main())
