"""Power curve of `selfcal diagnose`: detection rate vs effect magnitude, false alarms, speed.

For each effect, cases are drawn as in tests/effectgen.py (120 insole-like poses over 8
days, random axis and sign) at a fraction of the realistic magnitude range (0.25x,
0.5x, 1x, 1.5x); the rate of correct naming, of wrong naming and of "no cause" is
printed. Also: false alarms with no effect, and the wall time of one diagnose call on a
10 000-pose table. Usage: ``python bench/diagnose_power.py [--cases N]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from effectgen import EFFECT_RANGES, hidden_effect_case  # noqa: E402

from selfcal.diagnosis import diagnose_poses  # noqa: E402

CFG = {"diagnose": {"n_sim": 2}}


def run(poses):
    return diagnose_poses(poses["mean"], poses["sd"], poses["count"], poses["t_s"], poses["temp_c"], config=CFG)["cause"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=50, help="cases per effect and magnitude")
    args = ap.parse_args(argv)
    fractions = (0.25, 0.5, 1.0, 1.5)
    print(f"{'effect':<20}" + "".join(f"{f'x{f:g}':>16}" for f in fractions) + "   (named / wrong / none, of N)")
    for k, eff in enumerate(EFFECT_RANGES):
        lo, hi = EFFECT_RANGES[eff]
        cells = []
        for f in fractions:
            named = wrong = 0
            for s in range(args.cases):
                rng = np.random.default_rng(777_000 + 1000 * k + s)
                cause = run(hidden_effect_case(rng, eff, rng.uniform(lo * f, hi * f))[0])
                named += cause == eff
                wrong += cause is not None and cause != eff
            cells.append(f"{named}/{wrong}/{args.cases - named - wrong}")
            print(f"  {eff} x{f:g}: named {named / args.cases:.0%}", file=sys.stderr, flush=True)
        print(f"{eff:<20}" + "".join(f"{c:>16}" for c in cells))
    fa = sum(run(hidden_effect_case(np.random.default_rng(888_000 + s), None)[0]) is not None for s in range(args.cases))
    print(f"no effect: false alarms {fa}/{args.cases}")
    # speed on a 10 000-pose table (default config: 10 simulated replicates)
    rng = np.random.default_rng(5)
    poses, _ = hidden_effect_case(rng, "temperature_bias", 0.2, n_poses=10_000, days=30)
    t0 = time.perf_counter()
    rep = diagnose_poses(poses["mean"], poses["sd"], poses["count"], poses["t_s"], poses["temp_c"])
    print(f"diagnose on 10 000 poses (default config): {time.perf_counter() - t0:.2f} s, cause {rep['cause']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
