"""The correlated-noise model of `selfcal diagnose` (selfcal/boutnoise.py), measured.

1. The GGIR 84-h wrist record under both noise models (``[diagnose] noise_model``
   ``independent``, the former behaviour, and ``bouts``), and under the bout noise with
   the opt-in GLS test (``correlated_test = "gls"``): lag-1 autocorrelation and bout
   share of the base-fit residuals, measured and simulated; the fitted noise terms; each
   candidate's F, design effect and the cause.
2. The same record under other bout rules (gap, turn): how much the numbers depend on it.
3. Synthetic bout-structured sets (tests/boutgen.py): recovery of injected bout / AR(1) /
   white terms over seeds (mean and sd of the estimates, share within 3 bootstrap sds).
4. Calls on bout-structured sets, effect-free and with a 0.3 mg/degC temperature bias, with
   a 2 mg per-bout error and a 1 mg AR(1) term: false alarms and named rate under both
   noise models and with the GLS test (95 % Wilson intervals).
5. Effect-free insole sets (tests/effectgen.py, windows far apart): false alarms under both.
6. The test of independence within bouts on independent residuals: its rejection rate.
7. The 84-h record within its bouts, after the ``temperature_bias`` fit: the residual
   (de-meaned per bout) against the time since the bout began, and the GLS test's F of
   each candidate with settling columns (each axis times ``exp(-t_since / tau)``) added
   to the base model's as nuisance.

Usage: ``python bench/bout_noise.py [--seeds N] [--skip-record]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from boutgen import bout_case  # noqa: E402
from effectgen import hidden_effect_case  # noqa: E402

from selfcal.boutnoise import estimate_bout_noise, find_bouts  # noqa: E402
from selfcal.diagnosis import diagnose_poses, diagnose_recording  # noqa: E402
from selfcal.fit import FitConfig, pose_sigma  # noqa: E402

RECORD = ROOT / "data" / "ggir-wrist-84h" / "poses.csv"


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson interval of a proportion k/n."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(c - h, 0.0), min(c + h, 1.0)


def _diag(poses, **diag):
    return diagnose_poses(poses["mean"], poses["sd"], poses["count"], poses["t_s"], poses["temp_c"],
                          config={"diagnose": diag})


def _fmt(x, nd=3):
    return "-" if x is None else f"{x:.{nd}g}"


#: the noise models and the test under correlated noise compared: (label, [diagnose] settings)
MODES = (("independent", {"noise_model": "independent"}),
         ("bouts", {"noise_model": "bouts", "correlated_test": "design_effect"}),
         ("bouts, GLS", {"noise_model": "bouts", "correlated_test": "gls"}))


def record_section(n_sim: int) -> None:
    print("## 1. GGIR 84-h wrist record, both noise models (and the GLS test under the bout noise)\n")
    for mode, settings in MODES:
        t0 = time.perf_counter()
        rep, _ = diagnose_recording(RECORD, {"diagnose": {**settings, "n_sim": n_sim}})
        el = time.perf_counter() - t0
        d = rep["discrepancy"]
        print(f"noise_model={mode} ({el:.1f} s, {n_sim} replicates): cause {rep['cause']}")
        for key in ("rms_mg", "lag1_autocorr", "bout_share", "temp_r2", "time_r2"):
            if key in d:
                v = d[key]
                print(f"  {key:<14} measured {_fmt(v['measured'])}, simulated {_fmt(v['simulated_mean'])} "
                      f"± {_fmt(v['simulated_sd'], 2)} (z {_fmt(v['z'])})")
        nm = rep["noise_model"]
        if nm.get("correlated_var_mg2"):
            sd = nm["std"]
            print(f"  noise model: bout {nm['sigma_bout_mg']:.2f} ± {sd['sigma_bout_mg']:.2f} mg, AR(1) "
                  f"{nm['sigma_ar_mg']:.2f} ± {sd['sigma_ar_mg']:.2f} mg, tau {nm['tau_s']:.0f} s "
                  f"(16-84 %: {sd['tau_s_16_84'][0]:.0f}-{sd['tau_s_16_84'][1]:.0f}), white {nm['sigma_white_mg']:.2f} "
                  f"± {sd['sigma_white_mg']:.2f} mg, measured noise {nm['measured_noise_mg']:.2f} mg; correlated share "
                  f"{nm['correlated_share']:.3f}; {nm['n_bouts']} bouts ({nm['n_multi_window_bouts']} of >= 2 windows); "
                  f"independence chi2 {nm['independence_test']['chi2']:.0f} for {nm['independence_test']['dof']} bouts")
        for e in rep["effects"]:
            est = e.get("estimate")
            tb = ""
            if est and e["name"] == "temperature_bias":
                tb = f", z estimate {est['value']['z']:.3f} ± {est['std']['z']:.3f} {est['unit']}"
            print(f"  {e['name']:<19} F {_fmt(e.get('f_stat'), 4):>8}  p {_fmt(e.get('p_value'), 2):>8}  design effect {_fmt(e.get('design_effect'), 3):>5}  "
                  f"gain (time, pose) {_fmt(e.get('gain_time'), 2)}, {_fmt(e.get('gain_pose'), 2)}  "
                  f"{'SELECTED' if e['selected'] else ('supported' if e.get('supported') else '-')}{tb}")
        print()


def residual_section() -> None:
    print("## 1b. 84-h record: correlation of consecutive base-fit residuals, by gap and by turn\n")
    rep, poses = diagnose_recording(RECORD, {"diagnose": {"n_sim": 2}}, keep_arrays=True)
    a = rep["_arrays"]
    o = np.argsort(a["t_s"])
    t, r, g = a["t_s"][o], a["res_base_mg"][o], a["gdir"][o]
    dt = np.diff(t)
    turn = np.degrees(np.arccos(np.clip(np.sum(g[1:] * g[:-1], axis=1), -1, 1)))
    for what, x, bins in (("gap (s)", dt, [(10, 10), (11, 30), (31, 60), (61, 300), (301, 3600), (3601, 1e9)]),
                          ("turn (deg), gap <= 60 s", turn, [(0, 1), (1, 3), (3, 5), (5, 10), (10, 30), (30, 180)])):
        cells = []
        for lo, hi in bins:
            m = (x >= lo) & (x <= hi) if what.startswith("gap") else (x >= lo) & (x < hi) & (dt <= 60)
            if m.sum() > 5:
                cells.append(f"{lo:g}-{hi:g}: {np.corrcoef(r[:-1][m], r[1:][m])[0, 1]:.3f} ({m.sum()})")
        print(f"  {what}: " + "; ".join(cells))
    bouts = find_bouts(a["t_s"], a["gdir"], 60.0, 5.0)
    same = np.diff(bouts.label_sorted) == 0
    print(f"  consecutive pairs inside one bout (gap <= 60 s, turn <= 5 deg): {same.mean():.3f}")
    noise = pose_sigma(poses["mean"], poses["sd"], poses["count"], FitConfig(sigma_floor_g=0.0))
    t0 = time.perf_counter()
    estimate_bout_noise(a["res_base_mg"] * 1e-3, noise, bouts)
    print(f"  estimate_bout_noise with 200 bootstrap resamples: {1e3 * (time.perf_counter() - t0):.0f} ms\n")


def rule_section(n_sim: int) -> None:
    print("## 2. 84-h record: sensitivity to the bout rule\n")
    print("| gap (s) | turn (deg) | bouts | bout (mg) | AR (mg) | tau (s) | white (mg) | correlated share "
          "| simulated lag-1 (measured) | tb F (design effect) | cause |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for gap, ang in ((30, 5), (60, 2), (60, 5), (60, 10), (120, 5), (300, 10)):
        rep, _ = diagnose_recording(RECORD, {"diagnose": {"n_sim": n_sim, "bout_gap_s": gap, "bout_angle_deg": ang}})
        nm = rep["noise_model"]
        lag = rep["discrepancy"]["lag1_autocorr"]
        tb = next(e for e in rep["effects"] if e["name"] == "temperature_bias")
        print(f"| {gap} | {ang} | {nm['n_bouts']} | {nm['sigma_bout_mg']:.2f} | {nm['sigma_ar_mg']:.2f} | "
              f"{_fmt(nm['tau_s'])} | {nm['sigma_white_mg']:.2f} | {nm['correlated_share']:.3f} | "
              f"{lag['simulated_mean']:.3f} ± {lag['simulated_sd']:.3f} ({lag['measured']:.3f}) | "
              f"{tb['f_stat']:.1f} ({tb['design_effect']:.1f}) | {rep['cause']} |")
    print()


def recovery_section(seeds: int) -> None:
    print("## 3. Recovery of injected noise terms (tests/boutgen.py)\n")
    cases = {
        "bout 2 mg + white 0.5 mg (200 bouts of 2-40 windows)":
            (dict(sigma_bout_mg=2.0, sigma_white_mg=0.5), {"sigma_bout_mg": 2.0, "sigma_ar_mg": 0.0, "sigma_white_mg": 0.5}),
        "bout 1.5 + AR 1.5 mg, tau 200 s + white 0.3 (300 bouts of 10-60)":
            (dict(n_bouts=300, windows=(10, 60), sigma_bout_mg=1.5, sigma_ar_mg=1.5, tau_s=200.0, sigma_white_mg=0.3),
             {"sigma_bout_mg": 1.5, "sigma_ar_mg": 1.5, "sigma_white_mg": 0.3, "tau_s": 200.0}),
    }
    for name, (kw, truth) in cases.items():
        est = {k: [] for k in truth}
        within = {k: 0 for k in truth if k != "tau_s"}
        cvar, cvar_in = [], 0
        for s in range(seeds):
            poses, _ = bout_case(np.random.default_rng(1000 + s), **kw)
            nm = _diag(poses, n_sim=2)["noise_model"]
            for k in truth:
                est[k].append(np.nan if nm[k] is None else nm[k])
            for k in within:
                within[k] += abs(nm[k] - truth[k]) <= 3 * nm["std"][k]
            cv_true = truth["sigma_bout_mg"] ** 2 + truth["sigma_ar_mg"] ** 2
            cvar.append(nm["correlated_var_mg2"])
            cvar_in += abs(nm["correlated_var_mg2"] - cv_true) <= 3 * nm["std"]["correlated_var_mg2"]
        print(f"{name}, {seeds} seeds:")
        for k, v in est.items():
            v = np.array(v, float)
            share = f", within 3 sd {within[k]}/{seeds}" if k in within else ""
            print(f"  {k:<15} truth {truth[k]:<6g} estimate {np.nanmean(v):.3f} ± {np.nanstd(v, ddof=1):.3f} (sd over seeds){share}")
        print(f"  correlated var  truth {cv_true:<6g} estimate {np.mean(cvar):.3f} ± {np.std(cvar, ddof=1):.3f} mg², "
              f"within 3 sd {cvar_in}/{seeds}")
    print()


def calls_section(seeds: int) -> None:
    print("## 4. Calls on bout-correlated sets (2 mg per bout + 1 mg AR(1), tau 300 s)\n")
    print("| effect | noise model | named | wrong | none | rate (95 % interval) |")
    print("|---|---|---|---|---|---|")
    for tb in (0.0, 0.3):
        calls = {mode: [] for mode, _ in MODES}
        for s in range(seeds):
            poses, _ = bout_case(np.random.default_rng(2000 + s), sigma_bout_mg=2.0, sigma_ar_mg=1.0, tau_s=300.0,
                                 tb_mg_per_c=tb)
            for mode, settings in MODES:
                calls[mode].append(_diag(poses, n_sim=2, noise_boot=0, **settings)["cause"])
        for mode, c in calls.items():
            named = sum(x == "temperature_bias" for x in c) if tb else 0
            wrong = sum(x is not None and (not tb or x != "temperature_bias") for x in c)
            none = sum(x is None for x in c)
            k = named if tb else wrong
            lo, hi = wilson(k, seeds)
            what = "named" if tb else "false alarms"
            print(f"| {'temperature_bias 0.3 mg/degC' if tb else 'none'} | {mode} | {named} | {wrong} | {none} | "
                  f"{what} {k}/{seeds} ({lo:.0%}-{hi:.0%}) |")
    print()


def effectgen_section(seeds: int) -> None:
    print("## 5. Effect-free insole sets (tests/effectgen.py: windows hours apart)\n")
    alarms = {"independent": 0, "bouts": 0}
    for s in range(seeds):
        poses, _ = hidden_effect_case(np.random.default_rng(888_000 + s), None)
        for mode in alarms:
            alarms[mode] += _diag(poses, n_sim=2, noise_model=mode)["cause"] is not None
    for mode, k in alarms.items():
        lo, hi = wilson(k, seeds)
        print(f"noise_model={mode}: false alarms {k}/{seeds} ({lo:.0%}-{hi:.0%})")
    print()


def independence_section(reps: int = 1000) -> None:
    print("## 6. Test of independence within bouts, on independent residuals\n")
    poses, _ = bout_case(np.random.default_rng(1))
    g = poses["mean"] / np.linalg.norm(poses["mean"], axis=1, keepdims=True)
    bouts = find_bouts(poses["t_s"], g)
    rng = np.random.default_rng(0)
    n = len(poses["t_s"])
    p = []
    for _ in range(reps):
        s = rng.uniform(0.2, 0.6, n) * 1e-3  # measured noise per window, g
        r = rng.normal(size=n) * np.sqrt(s**2 + 0.3e-3**2)  # plus 0.3 mg white
        p.append(estimate_bout_noise(r, s, bouts, n_boot=0).independence_p)
    p = np.array(p)
    print(f"{reps} draws on {bouts.n_bouts} bouts ({n} windows): p < 1e-3 in {np.sum(p < 1e-3)}, "
          f"p < 0.05 in {np.mean(p < 0.05):.1%}, p < 0.5 in {np.mean(p < 0.5):.1%}\n")


def settling_section(n_sim: int) -> None:
    print("## 7. The 84-h record within its bouts (after the temperature_bias fit)\n")
    from selfcal import diagnosis

    rep, _ = diagnose_recording(RECORD, {"diagnose": {"n_sim": n_sim}}, keep_arrays=True)
    arr = rep["_arrays"]
    t, g, r, temp = arr["t_s"], arr["gdir"], arr["res_ext_mg"], arr["temp_c"]
    bouts = find_bouts(t, g)
    o = bouts.order
    lab = bouts.label[o]
    ts = t[o]
    start = np.r_[True, lab[1:] != lab[:-1]]
    first = np.maximum.accumulate(np.where(start, np.arange(len(ts)), 0))
    since = np.empty(len(t))
    since[o] = ts - ts[first]
    lab_in = bouts.label
    count = np.bincount(lab_in)
    dev = r - (np.bincount(lab_in, r) / count)[lab_in]
    dtemp = temp - (np.bincount(lab_in, temp) / count)[lab_in]
    big = count[lab_in] >= 10
    print(f"{len(np.unique(lab_in[big]))} bouts of >= 10 windows\n")
    print("| time since the bout began (s) | windows | residual, de-meaned per bout, mean of the bouts' means (mg) | temperature, de-meaned (degC) |")
    print("|---|---:|---|---:|")
    edges = [0, 15, 30, 60, 120, 240, 480, 960, np.inf]
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = big & (since >= lo) & (since < hi)
        if m.sum() >= 20:
            # the sd of the mean from the bouts' own means in the bin (windows of one bout are correlated)
            per_bout = np.bincount(lab_in[m], dev[m])[np.unique(lab_in[m])] / np.bincount(lab_in[m])[np.unique(lab_in[m])]
            k = len(per_bout)
            se = per_bout.std(ddof=1) / np.sqrt(k) if k > 1 else float("nan")
            print(f"| {lo:g}-{hi:g} | {m.sum()} in {k} bouts | {per_bout.mean():+.3f} ± {se:.3f} | "
                  f"{dtemp[m].mean():+.3f} |")
    nuisance = np.column_stack([g[:, i] * np.exp(-since / tau) for tau in (60.0, 180.0, 600.0) for i in range(3)])
    plain = diagnosis._GlsBase

    class WithNuisance(plain):  # the base model's columns plus the settling columns
        def __init__(self, whiten, r, x):
            super().__init__(whiten, r, np.column_stack([x, nuisance]))

    print("\n| candidate | GLS F | GLS F with settling columns as nuisance |")
    print("|---|---:|---:|")
    rows = {}
    try:
        for label, cls in (("plain", plain), ("settling", WithNuisance)):
            diagnosis._GlsBase = cls
            rep, _ = diagnose_recording(RECORD, {"diagnose": {"n_sim": 2, "correlated_test": "gls"}})
            rows[label] = {e["name"]: e.get("f_stat") for e in rep["effects"]}
    finally:
        diagnosis._GlsBase = plain
    for name in rows["plain"]:
        print(f"| {name} | {_fmt(rows['plain'][name], 4)} | {_fmt(rows['settling'][name], 4)} |")
    print()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20, help="seeds per synthetic cell")
    ap.add_argument("--n-sim", type=int, default=10, help="simulated replicates on the 84-h record")
    ap.add_argument("--skip-record", action="store_true", help="skip sections 1-2 (the 84-h record)")
    args = ap.parse_args(argv)
    if not args.skip_record:
        record_section(args.n_sim)
        residual_section()
        rule_section(max(args.n_sim // 2, 2))
        settling_section(args.n_sim)
    recovery_section(args.seeds)
    calls_section(args.seeds)
    effectgen_section(args.seeds)
    independence_section()
    return 0


if __name__ == "__main__":
    sys.exit(main())
