"""What the base model (affine9) does with each sensor effect switched on in the simulator.

For each effect (and none), replays the paper's 30-day protocol for a few wearers and
prints the final sphere RMS, tilt error, held-in residual and the parameter bias (final
estimate minus truth, in units of the reported sd). This is the input of the diagnosis:
an effect the base model cannot represent shows up as residual growth and biased
parameters. Usage: ``python bench/replay_effects.py [--seeds 3] [--days 30]``.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from selfcal.config import load_config
from selfcal.replay import replay_fleet
from selfcal.sim import EFFECT_NAMES


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--days", type=float, default=30.0)
    args = ap.parse_args(argv)
    cfg = load_config()
    print(f"{'effect':<20}{'final sphere mg':>17}{'tilt deg':>10}{'max |bias|/sd':>15}  worst parameter")
    for eff in (None,) + tuple(EFFECT_NAMES):
        res = replay_fleet(args.seeds, seed=200, workers=2, days=args.days, refit_every_days=3, config=cfg,
                           effects=() if eff is None else (eff,))
        sph = np.median([r["refits"][-1]["sphere_norm_rms_mg"] for r in res])
        tilt = np.median([r["refits"][-1]["tilt_error_deg"] for r in res])
        worst = (0.0, "")
        for r in res:
            f, t = r["final"], r["truth"]["params"]
            for k in t:
                z = abs(f["params"][k] - t[k]) / f["std"][k]
                worst = max(worst, (z, k))
        print(f"{eff or 'none':<20}{sph:17.3f}{tilt:10.3f}{worst[0]:15.1f}  {worst[1]}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
