"""Refit speed for 48 still poses: selfcal's LM vs the seed-LM port vs scipy.

Prints median wall times (ms) measured in this one run and the ratios, plus the
accuracy each reaches (calibrated-norm RMS over the whole sphere, mg), so that speed
is never bought with accuracy. Usage: ``python bench/fit_speed.py [--trials N]``.

What is timed (same pose sets, same machine, same process):

* ``selfcal refit``     — ``selfcal.fit.fit_poses`` warm-started from the previous model
                          (what the online calibrator does on every refit)
* ``selfcal cold``      — ``fit_poses`` from scratch (prior mean, LS, quadric candidates)
* ``selfcal lm only``   — the LM loop alone (``lm_solve``) from the warm start
* ``scipy default``     — ``scipy.optimize.least_squares`` with its defaults (trf,
                          2-point finite-difference Jacobian) on the same residual
* ``scipy lm+jac``      — ``least_squares(method='lm')`` with selfcal's analytic Jacobian
* ``seed LM port``      — ``selfcal.baselines.seed_lm`` (the seed's loop, defects included)
* ``online refit``      — the whole ``OnlineCalibrator.refit()`` over a store holding the
                          same poses: robust MAP fit, variance components and refit, the
                          held-out-fold fit of the guard, status and predicted sphere error
                          (warm: the second refit after the first publication)

``python bench/fit_speed.py --poses 240`` is the online calibrator's acceptance figure
(a refit over 240 poses, median <= 5 ms).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from posegen import poses_from_truth, random_truth, sphere_rms_mg, spread_directions  # noqa: E402

from selfcal.baselines import seed_lm  # noqa: E402
from selfcal.calibrator import OnlineCalibrator  # noqa: E402
from selfcal.fit import FitConfig, datasheet_prior, fit_poses, lm_solve, pose_sigma  # noqa: E402
from selfcal.models import ErrorModel  # noqa: E402

A9 = ErrorModel("affine9")


def timed(fn, repeat=1):
    t0 = time.perf_counter()
    for _ in range(repeat):
        out = fn()
    return (time.perf_counter() - t0) / repeat * 1e3, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--poses", type=int, default=48)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(48)
    cfg = FitConfig()
    rows = {k: ([], []) for k in ["selfcal refit", "selfcal cold", "selfcal lm only", "scipy default", "scipy lm+jac", "seed LM port", "online refit"]}
    for trial in range(args.trials):
        truth = random_truth(rng)
        poses = poses_from_truth(rng, A9, truth, spread_directions(rng, args.poses))
        previous = truth + rng.normal(0, 1e-3, 9)  # last refit's model, close to the truth
        prior = datasheet_prior(A9, cfg)
        sigma = pose_sigma(poses.mean, poses.sd, poses.count, cfg)

        def add(name, ms, theta):
            rows[name][0].append(ms)
            rows[name][1].append(sphere_rms_mg(A9, theta, truth, n=500, seed=trial))

        ms, r = timed(lambda: fit_poses(A9, poses, prior=prior, theta0_u=previous, cfg=cfg))
        add("selfcal refit", ms, r.theta_u)
        ms, r = timed(lambda: fit_poses(A9, poses, prior=prior, cfg=cfg))
        add("selfcal cold", ms, r.theta_u)
        ms, r = timed(lambda: lm_solve(A9, previous, poses.mean, sigma, prior, cfg=cfg))
        add("selfcal lm only", ms, r.x)

        def fun(th):
            return A9.residuals(th, poses.mean) / sigma

        def jac(th):
            return A9.residual_jac(th, poses.mean)[1] / sigma[:, None]

        ms, r = timed(lambda: least_squares(fun, A9.nominal()))
        add("scipy default", ms, r.x)
        ms, r = timed(lambda: least_squares(fun, previous, jac=jac, method="lm"))
        add("scipy lm+jac", ms, r.x)
        ms, r = timed(lambda: seed_lm(poses.mean, g=1.0))
        theta = A9.from_linear(r.matrix, r.offset)
        add("seed LM port", ms, theta)
        cal = OnlineCalibrator({"scheduler": {"min_poses_first": 10**9, "refit_every_poses": 10**9}})
        t_pose = 600.0 * np.arange(len(poses.mean))  # ten minutes apart: every pose its own cell
        cal.feed_poses(poses.mean, poses.sd, poses.count, t_pose)
        cal.refit()
        ms, ev = timed(cal.refit)
        add("online refit", ms, np.asarray(cal.current["theta_u"]) if cal.current else A9.nominal())
    seed_med = np.median(rows["seed LM port"][0])
    ours = np.median(rows["selfcal refit"][0])
    print(f"refit of {args.poses} poses, {args.trials} pose sets (median over sets)")
    print(f"{'method':<18}{'median ms':>10}{'p90 ms':>9}{'sphere RMS mg (median)':>24}{'seed/this':>11}")
    for name, (ms, err) in rows.items():
        print(f"{name:<18}{np.median(ms):10.3f}{np.percentile(ms, 90):9.3f}{np.median(err):24.4f}{seed_med / np.median(ms):11.1f}")
    print(f"\nselfcal refit median {ours:.3f} ms (goal <= 2 ms); speed-up vs seed LM port: {seed_med / ours:.0f}x (goal >= 100x)")
    print(f"online refit (whole calibrator step) over {args.poses} poses: median "
          f"{np.median(rows['online refit'][0]):.2f} ms (goal <= 5 ms at 240 poses)")
    print(f"scipy default / selfcal refit: {np.median(rows['scipy default'][0]) / ours:.1f}x; "
          f"scipy lm+jac / selfcal lm only: {np.median(rows['scipy lm+jac'][0]) / np.median(rows['selfcal lm only'][0]):.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
