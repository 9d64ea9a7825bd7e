"""Plot one thermal soak of a real recording: the still mean along gravity against temperature.

    python bench/soak_plot.py [REC] [--out docs/img/soak_ggir.png]

Finds the soaks of the recording's still windows (selfcal.soak, along-gravity frame),
takes the one with the most temperature information, and plots its windows' mean along
gravity (mg, relative to the soak's fitted value at its mean temperature) against
temperature, with the fitted slope g.tb and its ±2 sd band. Prints every soak's fit.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", nargs="?", default=str(REPO / "data" / "ggir-wrist-84h" / "poses.csv"))
    ap.add_argument("--out", default=str(REPO / "docs" / "img" / "soak_ggir.png"))
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from selfcal.diagnosis import window_mean_variance
    from selfcal.pipeline import path_poses
    from selfcal.soak import find_soaks, fit_soak

    poses, normalizer, _, _ = path_poses(args.recording)
    order = np.argsort(poses["t_s"], kind="stable")
    t = poses["t_s"][order]
    u = normalizer.to_u(poses["mean"])[order]
    temp = poses["temp_c"][order]
    var = window_mean_variance(u, None if poses["sd"] is None else poses["sd"][order], poses["count"][order], normalizer)
    runs = find_soaks(t, u, temp)
    print(f"{args.recording}: {len(runs)} soaks")
    best, best_info = None, -1.0
    for r in runs:
        f = fit_soak(temp[r], u[r], var[r], frame="norm")
        g = f.orientation / np.linalg.norm(f.orientation)
        sd_along = float(np.sqrt(g @ f.cov @ g)) * 1e3
        print(f"  {t[r.start] / 3600:6.2f}-{t[r.stop - 1] / 3600:6.2f} h  {f.dtemp_c:4.1f} degC  {f.n_windows:4d} windows  "
              f"g.tb {g @ f.coef * 1e3:+.3f} ± {sd_along:.3f} mg/degC  ({f.effect})")
        info = 1.0 / sd_along**2
        if info > best_info:
            best, best_info = (r, f, g), info
    if best is None:
        print("no soak to plot")
        return 1
    r, f, g = best
    along = (u[r] @ g) * 1e3
    dt = temp[r] - f.t_ref_c
    fitted0 = float(f.orientation @ g) * 1e3
    slope = float(g @ f.coef) * 1e3
    sd = float(np.sqrt(g @ f.cov @ g)) * 1e3
    x = np.linspace(dt.min(), dt.max(), 50)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    ax.scatter(temp[r], along - fitted0, s=8, alpha=0.6, label=f"{f.n_windows} still windows (mean along gravity)")
    ax.plot(x + f.t_ref_c, slope * x, "k-", label=f"fit: {slope:+.2f} ± {sd:.2f} mg/°C")
    ax.fill_between(x + f.t_ref_c, (slope - 2 * sd) * x, (slope + 2 * sd) * x, color="k", alpha=0.15, label="±2 sd")
    ax.set_xlabel("device temperature (°C)")
    ax.set_ylabel("still mean along gravity − fit at mean T (mg)")
    ax.set_title(f"{Path(args.recording).parent.name}: one soak, {f.dtemp_c:.1f} °C in "
                 f"{(t[r.stop - 1] - t[r.start]) / 60:.0f} min")
    ax.legend(fontsize=8)
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"plot: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
