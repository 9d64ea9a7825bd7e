"""Power curve of `selfcal diagnose` against a plain BIC reference, with false alarms.

Hidden-effect pose sets are drawn as in ``tests/effectgen.py`` (insole-like poses over 8
days: on the foot at 28-33 degC, off the foot at 15-25 degC; a general affine sensor;
one effect in its forward form on a random axis with a random sign). The **strength**
of a case is the effect's coefficient as a fraction of the top of its realistic range
(``EFFECT_RANGES``, ``SECONDARY_RANGES``, ``EVENT_RANGES``): strength 0.5 is 0.15 mg/degC
of temperature bias, 112 ppm/degC of temperature scale, 0.3 mg/day of drift, 2 mg/g^2 of
nonlinearity, 150 ppm/degC of cross-axis tempco or a bias step of 2.5 mg (at a time in
the middle half of the 8 days).

For every case, in the same run:

* ``diagnose``: ``selfcal.diagnosis.diagnose_poses`` with the shipped configuration
  (its decision rule: F-test at its alpha under the noise model, a held-out gain on
  time blocks and pose folds, the separability check); its ``cause``;
* **plain BIC**: the base model and the base model plus each effect, each fitted by
  weighted least squares with an essentially flat prior; the model of least
  ``n ln(WRSS / n) + k ln n`` is named ("none" when the base model wins).

Printed: named / wrong / none per effect and strength with 95 % Wilson intervals of the
named rate, the false-alarm rate on effect-free sets (with its interval), and whether
diagnose beats or matches BIC in every cell (named rate at least BIC's, or inside BIC's
interval). Usage::

    python bench/diagnose_power.py                                 # 50 seeds per cell, 400 clean
    python bench/diagnose_power.py --seeds 30 --clean 200 --markdown power.md
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

from bout_noise import wilson  # noqa: E402  (the 95 % Wilson interval the other diagnose bench prints)
from effectgen import EFFECT_RANGES, EVENT_RANGES, SECONDARY_RANGES, hidden_effect_case  # noqa: E402

SEED_BASE = 31_000_000  # distinct from the seeds of tests/test_diagnose.py
RANGES = {**EFFECT_RANGES, **SECONDARY_RANGES, **EVENT_RANGES}  # every effect diagnose tests


def bic_cause(poses: dict) -> str | None:
    """Plain BIC over the base model and base + each effect diagnose tests, the secondary
    cross-axis tempcos included (weighted LS, flat prior). The bias step is fitted at each
    of diagnose's candidate times, its time counted as one more parameter."""
    from selfcal.diagnosis import DiagnoseConfig, step_times
    from selfcal.fit import FitConfig, PoseData, datasheet_prior, fit_poses, pose_sigma
    from selfcal.models import ErrorModel

    mean = np.asarray(poses["mean"], float)
    n = len(mean)
    data = PoseData(mean, poses["sd"], poses["count"], poses["t_s"], poses["temp_c"])
    cfg = FitConfig(sigma_floor_g=0.0)
    sigma = pose_sigma(mean, np.asarray(poses["sd"], float), np.asarray(poses["count"], float), cfg)
    best, best_bic = None, np.inf
    models = [(e, ErrorModel("affine9" if e is None else f"affine9+{e}", 25.0, 0.0), 0)
              for e in (None, *RANGES) if e not in EVENT_RANGES]
    models += [("bias_step", ErrorModel("affine9+bias_step", 25.0, 0.0, tau), 1)
               for tau in step_times(np.asarray(poses["t_s"], float), DiagnoseConfig())]
    for effect, model, extra in models:
        fit = fit_poses(model, data, prior=datasheet_prior(model, cfg, inflate=1e3), cfg=cfg)
        r, _ = model.residual_jac(fit.theta_u, mean, data.temp_c, data.t_s)
        wrss = float(np.sum((r / sigma) ** 2))
        bic = n * np.log(wrss / n) + (model.n_params + extra) * np.log(n)
        if bic < best_bic:
            best, best_bic = effect, bic
    return best


def run_case(job: tuple) -> dict:
    """One seeded case: (effect or None, strength, seed, n_poses, diagnose overrides) -> both answers."""
    from selfcal.diagnosis import diagnose_poses

    effect, strength, seed, n_poses, overrides = job
    rng = np.random.default_rng(seed)
    magnitude = None if effect is None else strength * RANGES[effect][1]
    poses, truth = hidden_effect_case(rng, effect, magnitude, n_poses=n_poses)
    rep = diagnose_poses(poses["mean"], poses["sd"], poses["count"], poses["t_s"], poses["temp_c"],
                         config={"diagnose": overrides} if overrides else None)
    return {"effect": effect, "strength": strength, "seed": seed, "diagnose": rep["cause"], "bic": bic_cause(poses)}


def tally(rows: list[dict], method: str, effect: str | None) -> tuple[int, int, int]:
    """(named, wrong, none) of one method over ``rows``."""
    named = sum(r[method] == effect for r in rows) if effect is not None else 0
    wrong = sum(r[method] is not None and r[method] != effect for r in rows)
    return named, wrong, len(rows) - named - wrong


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50, help="cases per effect and strength (>= 30)")
    ap.add_argument("--clean", type=int, default=400, help="effect-free sets (>= 200)")
    ap.add_argument("--strengths", default="0.06,0.12,0.25,0.5")
    ap.add_argument("--poses", type=int, default=240, help="poses per set")
    ap.add_argument("--workers", type=int, default=min(2, mp.cpu_count()))
    ap.add_argument("--markdown", metavar="FILE", help="write the tables here too")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a [diagnose] setting (e.g. min_gain_rel=0), to measure another operating point")
    args = ap.parse_args(argv)
    overrides = {k: float(v) for k, v in (x.split("=", 1) for x in args.set)}
    strengths = [float(x) for x in args.strengths.split(",")]
    jobs = [(e, s, SEED_BASE + 100_000 * k + 1000 * j + i, args.poses, overrides)
            for k, e in enumerate(RANGES) for j, s in enumerate(strengths) for i in range(args.seeds)]
    jobs += [(None, 0.0, SEED_BASE + 900_000 + i, args.poses, overrides) for i in range(args.clean)]
    t0 = time.perf_counter()
    rows = []
    with mp.get_context("spawn").Pool(args.workers) as pool:
        for i, r in enumerate(pool.imap_unordered(run_case, jobs, chunksize=8), 1):
            rows.append(r)
            if i % 100 == 0 or i == len(jobs):
                el = time.perf_counter() - t0
                print(f"[{i}/{len(jobs)}] {el:.0f} s, ETA {el / i * (len(jobs) - i):.0f} s", file=sys.stderr, flush=True)
    lines = [f"{args.seeds} sets per cell of {args.poses} poses, {args.clean} effect-free sets"
             + (f", diagnose with {overrides}" if overrides else "") + "; "
             f"cells: named / wrong / none, named rate [95 % Wilson interval]", "",
             "| effect | strength | magnitude | diagnose | BIC | diagnose >= BIC |", "|---|---:|---|---|---|---|"]
    units = {"temperature_bias": "mg/°C", "temperature_scale": "ppm/°C", "time_drift_bias": "mg/day",
             "scale_nonlinearity": "mg/g²", "temperature_cross": "ppm/°C", "bias_step": "mg"}
    all_match = True
    at_012 = {}
    for e in RANGES:
        for s in strengths:
            cell = [r for r in rows if r["effect"] == e and r["strength"] == s]
            n = len(cell)
            d, b = tally(cell, "diagnose", e), tally(cell, "bic", e)
            lo_b, hi_b = wilson(b[0], n)
            ok = d[0] >= b[0] or d[0] / n >= lo_b
            all_match &= ok
            if abs(s - 0.12) < 1e-9:
                at_012[e] = d[0] / n
            fmt = lambda t: f"{t[0]}/{t[1]}/{t[2]}, {t[0] / n:.0%} [{wilson(t[0], n)[0]:.0%}, {wilson(t[0], n)[1]:.0%}]"
            lines.append(f"| {e} | {s:g} | {s * RANGES[e][1]:.3g} {units[e]} | {fmt(d)} | {fmt(b)} | "
                         f"{'yes' if ok else 'NO'} |")
    clean = [r for r in rows if r["effect"] is None]
    fa_d = sum(r["diagnose"] is not None for r in clean)
    fa_b = sum(r["bic"] is not None for r in clean)
    lines += ["", f"False alarms on {len(clean)} effect-free sets: diagnose {fa_d} = {fa_d / len(clean):.1%} "
                  f"[{wilson(fa_d, len(clean))[0]:.1%}, {wilson(fa_d, len(clean))[1]:.1%}]; "
                  f"BIC {fa_b} = {fa_b / len(clean):.1%} [{wilson(fa_b, len(clean))[0]:.1%}, "
                  f"{wilson(fa_b, len(clean))[1]:.1%}]."]
    checks = {
        "false alarms <= 5 % (upper interval <= 8 %)": fa_d / len(clean) <= 0.05 and wilson(fa_d, len(clean))[1] <= 0.08,
        "at strength 0.12, >= 80 % named on every effect": bool(at_012) and min(at_012.values()) >= 0.8,
        "diagnose beats or matches BIC in every cell": all_match,
    }
    lines.append("")
    lines += [f"* {'PASS' if ok else 'FAIL'}  {name}" for name, ok in checks.items()]
    lines.append(f"\nelapsed {time.perf_counter() - t0:.0f} s")
    # speed on a 10 000-pose table (default config)
    from selfcal.diagnosis import diagnose_poses

    poses, _ = hidden_effect_case(np.random.default_rng(5), "temperature_bias", 0.2, n_poses=10_000, days=30)
    t1 = time.perf_counter()
    rep = diagnose_poses(poses["mean"], poses["sd"], poses["count"], poses["t_s"], poses["temp_c"])
    lines.append(f"diagnose on 10 000 poses (default config): {time.perf_counter() - t1:.2f} s, cause {rep['cause']}")
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        Path(args.markdown).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
