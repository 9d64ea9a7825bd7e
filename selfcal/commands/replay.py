"""``selfcal replay``: long-horizon replay of simulated wear, or of a recorded file, against the truth.

* ``selfcal replay --days D --refit-every-days R --seed S [--devices N] [--json]``: simulate
  wear and replay it (:func:`selfcal.replay.replay`).
* ``selfcal replay --recording FILE [--truth T.json] [--history H.jsonl] [--json]``: stream
  a recorded file through the online calibrator exactly as ``selfcal calibrate`` does and
  score every published version against ``FILE.truth.json`` (written by ``selfcal
  simulate --out FILE``) when there is one (:func:`selfcal.replay.replay_recording`).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from selfcal.config import load_config
from selfcal.errors import CalibrationError, InputError
from selfcal.sim import EFFECT_NAMES

#: The simulation's options and their defaults (None in the parser: a given one is seen).
SIM_DEFAULTS = {"days": 30.0, "refit_every_days": 3.0, "seed": 0, "devices": 1, "workers": None, "effects": "",
                "level": "poses", "no_random_init": False, "checkpoint": None, "engine": None, "scheduler": None,
                "soaks": "with"}


def add_arguments(parser) -> None:
    rec = parser.add_argument_group("replay a recorded file")
    rec.add_argument("--recording", metavar="FILE",
                     help="replay this file instead of simulating: streamed in blocks as calibrate does, every "
                          "published version scored against FILE.truth.json when there is one")
    rec.add_argument("--truth", metavar="T.json",
                     help="the truth file (default: the one selfcal simulate --out FILE wrote beside it)")
    rec.add_argument("--history", metavar="FILE.jsonl",
                     help="write every published version here, as calibrate --history does")
    sim = parser.add_argument_group("simulate wear (not with --recording)")
    sim.add_argument("--days", type=float, default=None, help="simulated days of wear (default 30)")
    sim.add_argument("--refit-every-days", type=float, default=None,
                     help="the insole paper's protocol period (default 3; 0: the calibrator's own scheduler)")
    sim.add_argument("--seed", type=int, default=None, help="simulation seed (default 0)")
    sim.add_argument("--devices", type=int, default=None,
                     help="independent devices (seeds seed..seed+N-1), across processes (default 1)")
    sim.add_argument("--workers", type=int, default=None, help="processes for --devices (default: CPU count)")
    sim.add_argument("--engine", choices=["processes", "dask", "ray"], default=None,
                     help="where the devices run: a local process pool (default), a Dask distributed cluster "
                          "(local, or --scheduler ADDRESS) or Ray; results are identical")
    sim.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="--engine dask: the scheduler (tcp://host:8786); ray: the cluster address")
    sim.add_argument("--effects", default=None, help=f"comma-separated sensor effects to simulate: {', '.join(EFFECT_NAMES)}")
    sim.add_argument("--level", choices=("poses", "samples"), default=None,
                     help="feed still windows (fast, the default) or the full 20 Hz stream through the detector")
    sim.add_argument("--no-random-init", action="store_true", help="start from the nominal model, not random [0, 1]")
    sim.add_argument("--checkpoint", metavar="FILE", help="checkpoint after every refit; resume from it")
    sim.add_argument("--soaks", choices=("with", "without", "both"), default=None,
                     help="thermal soaks (still windows in one orientation while the temperature changes): keep "
                          "them (default), drop them, or run both and compare what the model's temperature terms "
                          "gain (poses level)")
    parser.add_argument("--model", default="affine9",
                        help="the calibrator's model to start from (online model selection may change it)")
    parser.add_argument("--fixed-model", action="store_true",
                        help="keep --model (no online model selection: [selection] enabled = false)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def run(args) -> int:
    from selfcal.replay import replay, replay_fleet, step_summary

    given = [k for k in SIM_DEFAULTS if getattr(args, k) is not None and getattr(args, k) is not False]  # 0 is given
    if args.recording is not None:
        if given:
            flags = ", ".join("--" + k.replace("_", "-") for k in given)
            raise InputError(f"--recording replays a file; the simulation's options ({flags}) do not apply to it")
        return run_recording(args)
    for flag in ("truth", "history"):
        if getattr(args, flag) is not None:
            raise InputError(f"--{flag} takes --recording FILE (a simulated replay knows its truth)")
    for k, default in SIM_DEFAULTS.items():
        if getattr(args, k) is None:
            setattr(args, k, default)
    effects = tuple(e for e in args.effects.split(",") if e)
    bad = [e for e in effects if e not in EFFECT_NAMES]
    if bad:
        raise InputError(f"--effects: unknown {bad}; choose from {list(EFFECT_NAMES)}")
    import math

    from selfcal.commands.simulate import MAX_DAYS, MIN_DAYS

    if not (math.isfinite(args.days) and MIN_DAYS <= args.days <= MAX_DAYS) or not (
            math.isfinite(args.refit_every_days) and args.refit_every_days >= 0) or args.devices < 1:
        raise InputError(f"--days {args.days:g}, --refit-every-days {args.refit_every_days:g}, --devices "
                         f"{args.devices}: --days must be a finite number from {MIN_DAYS:g} to {MAX_DAYS:g}, "
                         "--refit-every-days a finite number >= 0, --devices >= 1")
    if args.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {args.seed}")
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers {args.workers}: must be >= 1")
    from selfcal.replay import check_engine

    check_engine(args.engine or "processes")  # (one device runs here, whatever the engine: checked all the same)
    if args.checkpoint:
        from selfcal.commands.calibrate import check_writable

        check_writable(args.checkpoint)
    if args.soaks != "with" and args.level != "poses":
        raise InputError("--soaks without|both works at --level poses (the detector's windows are not filtered)")
    cfg = load_config(args.config)
    if args.fixed_model or args.soaks == "both":  # --soaks both compares the same model's terms
        cfg.setdefault("selection", {})["enabled"] = False
    kw = dict(days=args.days, refit_every_days=args.refit_every_days, config=cfg, effects=effects,
              model=args.model, level=args.level, random_init=not args.no_random_init)
    progress = not args.no_progress and (sys.stderr.isatty() or args.devices > 1)
    if args.soaks == "both":
        if args.checkpoint:
            raise InputError("--checkpoint works with one run, not --soaks both")
        return run_soak_comparison(args, kw, progress)
    kw["soaks"] = args.soaks == "with"
    t0 = time.perf_counter()
    if args.devices == 1:
        out = replay(seed=args.seed, checkpoint=args.checkpoint, progress=progress, **kw)
    else:
        if args.checkpoint:
            raise InputError("--checkpoint works with one device")
        results = replay_fleet(args.devices, args.seed, workers=args.workers, progress=progress,
                               engine=args.engine or "processes", scheduler=args.scheduler, **kw)
        wall = time.perf_counter() - t0
        last = [r["refits"][-1] for r in results if r["refits"]]
        out = {
            "devices": args.devices, "days": args.days, "wall_s": wall,
            "device_days_per_s": args.devices * args.days / wall,
            "final_sphere_norm_rms_mg": {  # None: no device refitted (too short for its scheduler)
                "median": float(np.median([x["sphere_norm_rms_mg"] for x in last])),
                "max": float(np.max([x["sphere_norm_rms_mg"] for x in last])),
            } if last else None,
            "time_to_calibrated_h": [r["time_to_calibrated_h"] for r in results],
            "model_selection": selection_summary(results),
            "bias_steps": step_summary(results),
            "results": results,
        }
    if args.json:
        print(json.dumps(out))
        return 0
    if args.devices > 1:
        final = out["final_sphere_norm_rms_mg"]
        print(f"{args.devices} devices x {args.days:g} days in {out['wall_s']:.1f} s: "
              f"{out['device_days_per_s']:.1f} simulated device-days/s; "
              + (f"final sphere RMS median {final['median']:.3f} mg, max {final['max']:.3f} mg" if final
                 else "no refit in any device"))
        sel = out["model_selection"]
        day = f"median day of the first switch {sel['median_first_switch_day']:.2f}" \
            if sel["median_first_switch_day"] is not None else "no switch"
        print(f"model selection: {sel['switched']}/{args.devices} devices switched ({day}); final models "
              + ", ".join(f"{m} x{n}" for m, n in sel["final_models"].items()))
        print_step_summary(out["bias_steps"])
        return 0
    first = (f"first 'calibrated' after {out['time_to_calibrated_h']:.1f} h" if out["time_to_calibrated_h"] is not None
             else "never 'calibrated'")
    print(f"replay seed {out['seed']}: {out['days']:g} days, refit every {out['refit_every_days']:g} days, "
          f"level {out['level']}, effects {out['effects'] or 'none'}; {first}")
    print(f"{'day':>5} {'param rel err':>14} {'sphere RMS mg':>14} {'tilt deg':>9} {'poses':>6} {'fit ms':>7}  outcome")
    for row in [out["initial"]] + out["refits"]:
        fit = f"{row['fit_ms']:7.2f}" if row.get("fit_ms") is not None else "      -"
        outcome = "initial" if row.get("published") is None else ("published" if row["published"] else row["reason"])
        print(f"{row['day']:5.1f} {row['param_rel_error']:14.4f} {row['sphere_norm_rms_mg']:14.3f} "
              f"{row['tilt_error_deg']:9.3f} {row['n_poses']:6d} {fit}  {outcome}")
    for sw in out["model_switches"]:
        print(f"model switch on day {sw['day']:.2f}: {sw['from_model']} -> {sw['to_model']} ({sw['change']} "
              f"{sw['effect']}: held-out z {sw['heldout_z_larger_model']}, RMS {sw['heldout_rms_mg_before']} -> "
              f"{sw['heldout_rms_mg_after']} mg, effect terms chi2 {sw['wald_chi2']} on {sw['wald_dof']})")
    true = (out.get("truth") or {}).get("bias_step")
    if true:
        print(f"simulated bias step on day {true['day']:.2f}: ({', '.join(f'{x:.3f}' for x in true['size_mg'])}) mg")
    for st in out.get("bias_steps_final", []):
        print(f"bias step found at {st['t_step_s'] / 86400:.2f} days: ({', '.join(f'{x:.3f}' for x in st['size_mg'])})"
              f" +- ({', '.join(f'{x:.3f}' for x in st['sd_mg'])}) mg (re-estimated at the end)")
    for name, e in out["effect_summary"].items():
        day = f"determined on day {e['first_determined_day']:.2f}" if e["first_determined_day"] is not None \
            else "never determined"
        print(f"{name}: {day}; final {_term(name, e['final'])} +- {_term(name, e['final_sd'])}, true "
              f"{_term(name, e['true'])}, error {_term(name, e['final_error'])} ({e['final_error_sd']:.2f} sd)")
    return 0


def print_step_summary(st: dict) -> None:
    """One line on the bias steps of a fleet replay (:func:`selfcal.replay.step_summary`)."""
    line = f"bias steps: {st['false']}/{st['devices']} devices with a false step"
    if st["with_step"]:
        line += f"; found on {st['found']}/{st['with_step']} devices with a simulated step"
        if st["found"]:
            line += (f" (median {st['median_delay_days']:.2f} days after it; time error median "
                     f"{st['median_time_error_h']:.2f} h; size error median {st['median_size_error_mg']:.3f} mg, "
                     f"max {st['max_size_error_mg']:.3f} mg, within 2 sd on {st['size_within_2sd']}/{st['found']})")
    print(line)


def selection_summary(results: list[dict]) -> dict:
    """How many devices changed their model, when, and to what (``model_switches`` of each replay)."""
    firsts = [r["model_switches"][0]["day"] for r in results if r.get("model_switches")]
    finals: dict[str, int] = {}
    for r in results:
        finals[r.get("model_final", r["model"])] = finals.get(r.get("model_final", r["model"]), 0) + 1
    return {"switched": len(firsts), "devices": len(results),
            "median_first_switch_day": float(np.median(firsts)) if firsts else None,
            "switches": sum(len(r.get("model_switches", [])) for r in results), "final_models": finals}


def _term(name: str, value: float) -> str:
    """An effect term in display units: offsets per degC or per day in mg, scales per degC in ppm."""
    if name.startswith("ts"):
        return f"{value * 1e6:.1f} ppm/degC"
    if name.startswith("db"):
        return f"{value * 1e3:.4f} mg/day"
    if name.startswith("q"):
        return f"{value * 1e3:.4f} 1e-3/g"
    return f"{value * 1e3:.4f} mg/degC"


def run_soak_comparison(args, kw: dict, progress: bool) -> int:
    """``--soaks both``: every device replayed with and without its soaks; per effect term, the
    day it is determined and its final error, side by side (model selection off: the same
    model's terms are compared)."""
    from selfcal.replay import replay_fleet

    t0 = time.perf_counter()
    runs = {}
    for label, keep in (("with", True), ("without", False)):
        runs[label] = replay_fleet(args.devices, args.seed, workers=args.workers, progress=progress,
                                   engine=args.engine or "processes", scheduler=args.scheduler, soaks=keep, **kw)
    terms = list(runs["with"][0]["effect_summary"])
    table = []
    for i in range(args.devices):
        for n in terms:
            w, wo = runs["with"][i]["effect_summary"][n], runs["without"][i]["effect_summary"][n]
            table.append({"seed": args.seed + i, "term": n, "true": w["true"],
                          "soaks_dropped": runs["without"][i]["soaks"]["n_soaks"],
                          "soak_windows_dropped": runs["without"][i]["soaks"]["n_windows"],
                          "with": w, "without": wo})
    summary = {}
    for n in terms:
        summary[n] = {}
        for label in ("with", "without"):
            rows = [r[label] for r in table if r["term"] == n]
            days = [r["first_determined_day"] for r in rows if r["first_determined_day"] is not None]
            summary[n][label] = {
                "determined": len(days), "devices": len(rows),
                "median_first_determined_day": float(np.median(days)) if days else None,
                "median_abs_final_error": float(np.median([abs(r["final_error"]) for r in rows])),
                "within_2sd": int(sum(r["final_error_sd"] <= 2 for r in rows)),
            }
    out = {"devices": args.devices, "days": args.days, "model": args.model, "wall_s": time.perf_counter() - t0,
           "summary": summary, "table": table}
    if args.json:
        print(json.dumps(out))
        return 0
    if not terms:
        print(f"model {args.model} has no effect terms: nothing for soaks to determine")
        return 0
    print(f"{args.devices} devices x {args.days:g} days, model {args.model}, effects {list(kw['effects']) or 'none'}: "
          f"with and without thermal soaks ({out['wall_s']:.0f} s)")
    print(f"{'seed':>4} {'term':<5} {'soaks':>5} {'true':>18} | {'with: day':>9} {'final error':>20} {'sd':>5} |"
          f" {'without: day':>12} {'final error':>20} {'sd':>5}")
    for r in table:
        w, wo = r["with"], r["without"]
        fd = lambda e: f"{e['first_determined_day']:.2f}" if e["first_determined_day"] is not None else "never"  # noqa: E731
        print(f"{r['seed']:>4} {r['term']:<5} {r['soaks_dropped']:>5} {_term(r['term'], r['true']):>18} | "
              f"{fd(w):>9} {_term(r['term'], w['final_error']):>20} {w['final_error_sd']:5.2f} | "
              f"{fd(wo):>12} {_term(r['term'], wo['final_error']):>20} {wo['final_error_sd']:5.2f}")
    for n, s in summary.items():
        for label in ("with", "without"):
            x = s[label]
            day = f"{x['median_first_determined_day']:.2f}" if x["median_first_determined_day"] is not None else "-"
            print(f"{n} {label + ' soaks':<13}: determined on {x['determined']}/{x['devices']} devices, median day "
                  f"{day}; median |final error| {_term(n, x['median_abs_final_error'])}; within 2 sd "
                  f"{x['within_2sd']}/{x['devices']}")
    return 0


def run_recording(args) -> int:
    """``--recording FILE``: the file through the online calibrator, every published version scored."""
    from selfcal.commands.calibrate import check_writable, write_history
    from selfcal.models import ErrorModel
    from selfcal.pipeline import calibrate_path
    from selfcal.replay import score_recording_run
    from selfcal.scoring import load_truth, truth_path

    rec = args.recording
    ErrorModel(args.model)  # every check before the work, none after it
    cfg = load_config(args.config)
    if args.fixed_model:
        cfg.setdefault("selection", {})["enabled"] = False
    if Path(rec).is_dir():
        raise InputError(f"{rec}: is a directory, not a recording file")
    if not Path(rec).exists():
        raise InputError(f"{rec}: no such file")
    if args.history:
        check_writable(args.history, [rec] + ([args.truth] if args.truth else []))
    tp = Path(args.truth) if args.truth else truth_path(rec)
    truth = load_truth(tp) if args.truth or tp.exists() else None
    t0 = time.perf_counter()
    # streamed in blocks, as calibrate: only the still poses stay in memory, whatever the file's length
    run = calibrate_path(rec, args.model, cfg, progress=not args.no_progress and sys.stderr.isatty())
    if args.history and run.calibration is not None:  # a run that published nothing keeps the file as it was
        write_history(args.history, run)
    out = score_recording_run(run, rec, truth)
    out["truth"] = None if truth is None else str(tp)
    if truth is None:
        out["notes"].append(f"no truth found (looked for {tp}): the version history only; selfcal simulate "
                            "--out FILE writes FILE.truth.json beside the recording (or give --truth)")
    out["wall_s"] = time.perf_counter() - t0
    failure = None
    if not out["versions"]:
        reason = run.last_refit["reason"] if run.last_refit else "no_still_poses"
        message = run.last_refit["message"] if run.last_refit else "no still window was found"
        out.update(reason=reason, message=message)
        failure = CalibrationError(reason, f"{rec}: no calibration published: {message}")
    if args.json:
        print(json.dumps(out))
    else:
        print_recording_replay(out)
    if failure:
        raise failure
    return 0


def print_recording_replay(out: dict) -> None:
    """The human-readable report of ``replay --recording``."""
    s, rows, scored = out["summary"], out["versions"], out["truth"] is not None
    first = (f"first 'calibrated' after {s['first_calibrated_h']:.1f} h" if s["first_calibrated_h"] is not None
             else "never 'calibrated'")
    print(f"replay of {out['recording']} (model {out['model']}): {s['versions']} versions published from "
          f"{out['n_windows']} still windows; {first}; final status {out['status']}")
    if scored:
        print(f"truth: {out['truth']}")
    for note in out["notes"]:
        print(f"  note: {note}")
    if not rows:
        return
    print(f"{'version':>7} {'day':>7}  {'status':<12} {'predicted mg':>12}" + (f" {'true mg':>9} {'max |z|':>8}" if scored else ""))
    for r in rows:
        line = f"{r['version']:>7} {r['t_s'] / 86400:7.2f}  {r['status']:<12} {r['predicted_mg']:12.3f}"
        if scored:
            line += f" {r['true_mg']:9.3f} {max(abs(z) for z in r['z']):8.2f}"
        print(line)
    if not scored:
        return
    final = f"final: true {s['final_true_mg']:.3f} mg, predicted {s['final_predicted_mg']:.3f} mg"
    if s["crlb_sphere_mg"] is not None:
        final += (f"; CRLB (noise model) {s['crlb_sphere_mg']:.3f} mg, target {s['final_target_mg']:.2f} mg: "
                  f"{'within' if s['final_ok'] else 'ABOVE'}")
    print(final)
    if s["versions_per_week"] is not None:
        print(f"{s['versions_per_week']:.1f} versions per week")
    if s["calibrated_versions"]:
        print(f"{s['calibrated_versions']} calibrated versions: {100 * s['within_2sd']:.1f} % of parameter errors "
              f"within 2 sd (max {s['max_abs_z']:.2f} sd); true <= 2.5 x predicted + 0.05 mg in "
              f"{100 * s['sphere_ratio_ok']:.1f} %; jumps {s['jumps']}/{s['pairs']}")
