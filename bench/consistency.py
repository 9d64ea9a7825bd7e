"""Consistency of the online calibrator, scored publication by publication against the truth.

For each seed: ``selfcal simulate --days D --kind poses --effects E`` (in-process, the
same code), then ``selfcal calibrate SIM.csv --model M --history H.jsonl``. Every
version in the history is scored against the simulator's truth:

* parameter errors in reported sds (``|est - true| / std``), every parameter;
* true whole-sphere calibrated-norm RMS error (2000 directions, true sensor at the
  reference temperature, at the version's time) against the version's
  ``predicted_sphere_rms_mg``;
* jumps: consecutive versions whose true error exceeds 1.5 x the previous + 0.5 mg;
* versions per week; time to the first ``calibrated``;
* the final error against the Cramér-Rao sphere error of the same week's poses: the
  Fisher information of every window of the recording at the truth, each independent
  with its *true* noise (the simulator's variance of the window mean; the simulation is
  re-run with the same seed to get it), plus the datasheet prior, propagated to the sphere
  exactly as ``predicted_sphere_rms_mg`` is;
* beside it, an efficient oracle: the MAP fit of the same windows weighted by their true
  noise (``selfcal.scoring.efficient_reference``). No calibrator can know that noise; the
  oracle shows how often even an efficient estimator's final error exceeds the target
  (the error is one draw, and with one weak direction it is half-normal).

The acceptance figures (issue "Honest online estimation") are computed over the
``calibrated`` versions pooled across seeds, and printed with PASS/FAIL.

    python bench/consistency.py --seeds 0-9                       # effects none, affine9
    python bench/consistency.py --seeds 100-104 --effects all     # each effect + its model
    python bench/consistency.py --seeds 0-9 --json --markdown OUT.md
"""

from __future__ import annotations

import argparse
import contextlib
import os
import json
import multiprocessing as mp
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from selfcal.scoring import (  # noqa: E402  (the scoring is the library's: selfcal replay --recording too)
    TruthScorer, consistency_figures, crlb_from_information, efficient_reference, load_truth, poses_file_information,
    run_figures, truth_path,
)

EFFECTS = ("temperature_bias", "temperature_scale", "time_drift_bias", "scale_nonlinearity")


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        if "-" in part:
            a, b = part.split("-")
            out += list(range(int(a), int(b) + 1))
        elif part.strip():
            out.append(int(part))
    return out


def run_one(job: dict) -> dict:
    """Simulate, calibrate with --history, score. ``job``: seed, days, effect, model, tmp."""
    from selfcal.cli import main as cli_main

    seed, days, effect, model_name = job["seed"], job["days"], job["effect"], job["model"]
    tmp = Path(job["tmp"])
    rec_path = tmp / f"sim-{effect}-{seed}.csv"
    hist_path = tmp / f"hist-{effect}-{seed}.jsonl"
    t0 = time.perf_counter()
    config = []
    if effect == "bias_step":  # the step half way through the recording; the calibrator looks for it
        cfg_path = tmp / f"step-{effect}-{seed}.toml"
        cfg_path.write_text(f"[sim.effects.bias_step]\nat_day = {days / 2!r}\n")
        config = ["--config", str(cfg_path)]
    argv = ["simulate", "--days", str(days), "--kind", "poses", "--effects", effect, "--seed", str(seed),
            "--out", str(rec_path), *config]
    with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
        ok = cli_main(argv) == 0
    if not ok:
        raise RuntimeError(f"simulate failed: {argv}")
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
        code = cli_main(["calibrate", str(rec_path), "--model", model_name, "--history", str(hist_path), "--json",
                         *config])
    t_cal = time.perf_counter() - t0
    scorer = TruthScorer(load_truth(truth_path(rec_path)), model_name)
    history = [json.loads(line) for line in hist_path.read_text().splitlines()] if hist_path.exists() else []
    versions = scorer.score_all(history)
    info, n_poses, rec_last_t = poses_file_information(rec_path, scorer.model, scorer.truth_u)
    last_t = versions[-1]["t_s"] if versions else rec_last_t
    crlb_model_noise = crlb_from_information(scorer.model, scorer.truth_u, info, last_t)
    # the same week's windows again from the simulator (same seed), with their true noise:
    # the Cramer-Rao bound of the data, and an efficient estimator's final error on them
    ref = efficient_reference(model_name, scorer.truth, _simulated_poses(seed, days, effect), last_t)
    for p in tmp.glob(f"*-{effect}-{seed}*"):
        p.unlink()
    return {"seed": seed, "effect": effect, "model": model_name, "days": days, "exit_code": code,
            "versions": versions, "crlb_sphere_mg": ref["crlb_mg"], "crlb_model_noise_mg": crlb_model_noise,
            "oracle_final_mg": ref["oracle_mg"], "n_poses": n_poses, "sim_s": t_sim, "calibrate_s": t_cal}


def _simulated_poses(seed: int, days: float, effect: str):
    """The windows ``selfcal simulate --kind poses`` wrote for this seed (the simulator is deterministic)."""
    import numpy as np

    from selfcal.config import load_config, section
    from selfcal.sim import SimConfig, Simulation

    cfg = SimConfig.from_section(section(load_config(None), "sim"))
    if effect == "bias_step":
        cfg = cfg.updated(effects={"bias_step": {"at_day": days / 2}})
    cfg = cfg.with_effects([] if effect == "none" else [effect])
    return Simulation(cfg, np.random.default_rng(seed), days=days, seed=seed).poses()


def score(runs: list[dict]) -> dict:
    """Pooled acceptance figures over the calibrated versions of ``runs``."""
    per_seed = [{"seed": r["seed"], "effect": r["effect"],
                 **run_figures(r["versions"], r["days"], r["crlb_sphere_mg"]), "calibrate_s": r["calibrate_s"],
                 "oracle_final_mg": r["oracle_final_mg"]}
                for r in runs]
    for p in per_seed:
        p["oracle_ok"] = p["oracle_final_mg"] <= p["final_target_mg"]
    out = {
        "calibrated_versions": int(sum(p["calibrated_versions"] for p in per_seed)),
        **consistency_figures(r["versions"] for r in runs),
        "max_versions_per_week": max(p["versions_per_week"] for p in per_seed),
        "final_ok_all": all(p["final_ok"] for p in per_seed),
        "final_ok_seeds": int(sum(bool(p["final_ok"]) for p in per_seed)),
        "oracle_ok_seeds": int(sum(p["oracle_ok"] for p in per_seed)),
        "per_seed": per_seed,
    }
    checks = {
        ">= 93 % of parameter errors within 2 sd": out["within_2sd"] is not None and out["within_2sd"] >= 0.93,
        "no parameter error beyond 5 sd": out["max_abs_z"] is not None and out["max_abs_z"] <= 5,
        "true <= 2.5 x predicted + 0.05 mg in >= 90 %": out["sphere_ratio_ok"] is not None and out["sphere_ratio_ok"] >= 0.9,
        "< 1 % jumps (true > 1.5 x previous + 0.5 mg)": out["jump_fraction"] < 0.01,
        "<= 150 versions per week": out["max_versions_per_week"] <= 150,
        "final <= max(0.5 mg, 2 x CRLB) on every seed": out["final_ok_all"],
    }
    out["checks"] = checks
    return out


def markdown(title: str, s: dict) -> str:
    """A Markdown table of one scored set."""
    f = lambda x, d=2: "—" if x is None else f"{x:.{d}f}"  # noqa: E731
    lines = [f"**{title}**: {s['calibrated_versions']} calibrated versions; "
             f"{100 * (s['within_2sd'] or 0):.1f} % of parameter errors within 2 sd, max {f(s['max_abs_z'])} sd; "
             f"true ≤ 2.5 × predicted + 0.05 mg in {100 * (s['sphere_ratio_ok'] or 0):.1f} %; "
             f"jumps {s['jumps']}/{s['pairs']}; at most {s['max_versions_per_week']:.0f} versions/week.", "",
             "| seed | effect | versions | calibrated | first calibrated (h) | final true (mg) | final predicted (mg) | CRLB (mg) | target (mg) | ok | efficient oracle (mg) |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    for p in s["per_seed"]:
        lines.append(f"| {p['seed']} | {p['effect']} | {p['versions']} | {p['calibrated_versions']} | "
                     f"{f(p['first_calibrated_h'], 1)} | {f(p['final_true_mg'], 3)} | {f(p['final_predicted_mg'], 3)} | "
                     f"{f(p['crlb_sphere_mg'], 3)} | {f(p['final_target_mg'], 2)} | {'yes' if p['final_ok'] else 'NO'} | "
                     f"{f(p['oracle_final_mg'], 3)}{'' if p['oracle_ok'] else ' (over)'} |")
    n = len(s["per_seed"])
    lines.append("")
    lines.append(f"Final error within max(0.5 mg, 2 x CRLB): selfcal {s['final_ok_seeds']}/{n} seeds; the efficient "
                 f"oracle (true noise weights, same windows) {s['oracle_ok_seeds']}/{n}.")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-9", help="seeds, e.g. 0-9 or 1,5,7")
    ap.add_argument("--days", type=float, default=7.0)
    ap.add_argument("--effects", default="none",
                    help="'none' (model affine9), 'all' (each effect with affine9+effect), or one effect name; "
                         "'bias_step' puts the step half way through and keeps affine9 (the calibrator looks for it)")
    ap.add_argument("--workers", type=int, default=min(2, mp.cpu_count()))
    ap.add_argument("--json", metavar="FILE", help="write the full results here")
    ap.add_argument("--markdown", metavar="FILE", help="write the Markdown tables here")
    args = ap.parse_args(argv)
    effects = list(EFFECTS) if args.effects == "all" else [args.effects]
    t0 = time.perf_counter()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [{"seed": s, "days": args.days, "effect": e, "tmp": tmp,
                 "model": "affine9" if e in ("none", "bias_step") else f"affine9+{e}"}
                for e in effects for s in _seeds(args.seeds)]
        done = 0
        with mp.get_context("spawn").Pool(args.workers) as pool:
            runs = []
            for r in pool.imap_unordered(run_one, jobs):
                runs.append(r)
                done += 1
                print(f"[{done}/{len(jobs)}] seed {r['seed']} {r['effect']}: {len(r['versions'])} versions, "
                      f"calibrate {r['calibrate_s']:.1f} s", file=sys.stderr, flush=True)
    texts = []
    all_ok = True
    for e in effects:
        rs = sorted([r for r in runs if r["effect"] == e], key=lambda r: r["seed"])
        s = score(rs)
        results[e] = {"score": s, "runs": rs}
        title = f"effects {e}, model {rs[0]['model']}, seeds {args.seeds}, {args.days:g} days"
        texts.append(markdown(title, s))
        print(texts[-1])
        for name, ok in s["checks"].items():
            print(f"  {'PASS' if ok else 'FAIL'}  {name}")
            all_ok &= ok
        print()
    print(f"elapsed {time.perf_counter() - t0:.0f} s; {'all checks pass' if all_ok else 'SOME CHECKS FAIL'}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))
    if args.markdown:
        Path(args.markdown).write_text("\n\n".join(texts) + "\n")
    return 0 if all_ok else 1


if __name__ == "__main__":
    sys.exit(main())
