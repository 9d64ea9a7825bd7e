"""The most any test can name at a false-alarm rate: power bounds on diagnose_power's cases.

For every case of ``bench/diagnose_power.py`` (the same seeds, poses and truth), the
case's noise-free means are fitted by the base model (weighted least squares, flat prior,
the poses' own noise as weights). What the base model cannot absorb is the effect's
signal; its whitened squared norm ``lam`` is the noncentrality of the likelihood-ratio
test of the base model against the base model plus that effect (the noise is white and
Gaussian, so this is exact to first order).

Two bounds on the rate of finding the effect at false-alarm rate ``alpha``:

* ``NP``: the Neyman-Pearson test of the base model against the case's exact truth (it
  knows the effect, the axis, the sign and the size): power ``Phi(sqrt(lam) - z_{1-alpha})``.
  No test with that false-alarm rate does better on that case; a test that must also *name*
  the effect does worse.
* ``LR3``: the likelihood-ratio test that knows only which effect to test (3 extra
  parameters): ``P(chi2_3(lam) > chi2_3,1-alpha)``, the best a one-candidate test does.

diagnose asks about six candidates with Bonferroni and must name the right one, so its
named rate is below both. A cell whose ``NP`` bound is below 80 % is out of reach of every
method at that false-alarm rate. Usage::

    python bench/diagnose_power_bound.py [--seeds 50] [--alpha 0.05,0.012]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy import stats

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

from diagnose_power import RANGES, SEED_BASE  # noqa: E402  (the same cells and seeds)
from effectgen import hidden_effect_case  # noqa: E402


def noncentrality(effect: str, strength: float, seed: int, n_poses: int) -> float:
    """``lam`` of one case: the whitened squared residual of the base model's fit to its
    noise-free means (dimensionless)."""
    from selfcal.fit import FitConfig, PoseData, datasheet_prior, fit_poses, pose_sigma
    from selfcal.models import ErrorModel

    poses, _ = hidden_effect_case(np.random.default_rng(seed), effect, strength * RANGES[effect][1],
                                  n_poses=n_poses, noise=False)
    mean = np.asarray(poses["mean"], float)
    cfg = FitConfig(sigma_floor_g=0.0)
    data = PoseData(mean, poses["sd"], poses["count"], poses["t_s"], poses["temp_c"])
    model = ErrorModel("affine9", 25.0, 0.0)
    fit = fit_poses(model, data, prior=datasheet_prior(model, cfg, inflate=1e3), cfg=cfg)
    sigma = pose_sigma(mean, np.asarray(poses["sd"], float), np.asarray(poses["count"], float), cfg)
    r, _ = model.residual_jac(fit.theta_u, mean, data.temp_c, data.t_s)
    return float(np.sum((r / sigma) ** 2))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50, help="cases per effect and strength (diagnose_power's first ones)")
    ap.add_argument("--strengths", default="0.06,0.12,0.25,0.5")
    ap.add_argument("--poses", type=int, default=240)
    ap.add_argument("--alpha", default="0.05,0.012", help="false-alarm rates to bound the power at")
    args = ap.parse_args(argv)
    strengths = [float(x) for x in args.strengths.split(",")]
    alphas = [float(x) for x in args.alpha.split(",")]
    t0 = time.perf_counter()
    head = " | ".join(f"NP at {a:g} | LR3 at {a:g}" for a in alphas)
    print(f"{args.seeds} cases per cell of {args.poses} poses (diagnose_power's seeds); mean bound on the rate of "
          f"finding the effect, and the median noncentrality\n")
    print(f"| effect | strength | median lam | {head} |")
    print("|---|---:|---:|" + "---:|" * (2 * len(alphas)))
    below = []
    for k, e in enumerate(RANGES):
        for j, s in enumerate(strengths):
            lam = np.array([noncentrality(e, s, SEED_BASE + 100_000 * k + 1000 * j + i, args.poses)
                            for i in range(args.seeds)])
            cells = []
            for a in alphas:
                np_pow = float(np.mean(stats.norm.cdf(np.sqrt(lam) - stats.norm.isf(a))))
                lr3 = float(np.mean(stats.ncx2.sf(stats.chi2.isf(a, 3), 3, np.maximum(lam, 1e-12))))
                cells += [f"{np_pow:.0%}", f"{lr3:.0%}"]
                if abs(s - 0.12) < 1e-9 and np_pow < 0.8:
                    below.append(f"{e} (NP {np_pow:.0%} at alpha {a:g})")
            print(f"| {e} | {s:g} | {np.median(lam):.1f} | " + " | ".join(cells) + " |", flush=True)
    print()
    if below:
        print("At strength 0.12, out of reach of every test (NP bound < 80 %): " + "; ".join(below))
    else:
        print("At strength 0.12, the NP bound is >= 80 % on every effect at every alpha")
    print(f"\nelapsed {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
