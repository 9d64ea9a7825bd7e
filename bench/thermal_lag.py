"""Is the tempco disagreement on the 84-h wrist record a thermal lag? (README, thermal soaks)

Fits ``affine9+temperature_bias`` to every still window of ``data/ggir-wrist-84h`` (robust
least squares, in-sample) with the thermometer reading passed through a first-order lag
of time constant tau (negative tau: a lead, ``2 T - lag(T)``), and prints the mean
|‖a‖ − 1 g| and the tempcos for each tau; then the same record under the extended models.
A lag that explains the data would lower the mean below the unlagged fit's.

    python bench/thermal_lag.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import lfilter

from selfcal.models import ErrorModel

DATA = Path(__file__).resolve().parents[1] / "data" / "ggir-wrist-84h" / "poses.csv"
GRID_S = 10.0  # the record's epoch


def lagged(t_s: np.ndarray, temp_c: np.ndarray, tau_s: float) -> np.ndarray:
    """The temperature (degC, shape (n,)) through a first-order lag of ``tau_s`` s (a lead if < 0)."""
    if tau_s == 0:
        return temp_c.copy()
    grid = np.arange(t_s[0], t_s[-1] + GRID_S, GRID_S)
    tg = np.interp(grid, t_s, temp_c)
    a = np.exp(-GRID_S / abs(tau_s))
    y = lfilter([1 - a], [1, -a], tg - tg[0]) + tg[0]
    if tau_s < 0:
        y = 2 * tg - y
    return np.interp(t_s, grid, y)


def fit(model: ErrorModel, raw: np.ndarray, temp_c: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, float]:
    """Robust (soft-L1, 2 mg) least squares; returns theta and the mean |‖a‖ − 1 g| in mg."""
    r = least_squares(lambda th: model.residuals(th, raw, temp_c, t_s), model.nominal(), loss="soft_l1",
                      f_scale=0.002)
    a = model.apply(r.x, raw, temp_c, t_s)
    return r.x, float(np.mean(np.abs(np.linalg.norm(a, axis=1) - 1.0)) * 1e3)


def main() -> int:
    d = np.genfromtxt(DATA, delimiter=",", names=True, skip_header=4)
    t, temp = d["t_s"], d["temp_c"]
    raw = np.c_[d["ax_g"], d["ay_g"], d["az_g"]]
    model = ErrorModel("affine9+temperature_bias")
    print("| tau s | mean abs(norm - 1) mg | tbx | tby | tbz (mg/degC) |")
    print("|---:|---:|---:|---:|---:|")
    for tau in (-300, -120, 0, 60, 120, 300, 600, 1200, 3600):
        theta, mae = fit(model, raw, lagged(t, temp, tau), t)
        tb = theta[model.index("temperature_bias")] * 1e3
        print(f"| {tau} | {mae:.3f} | {tb[0]:+.3f} | {tb[1]:+.3f} | {tb[2]:+.3f} |", flush=True)
    print()
    for name in ("affine9+temperature_bias", "affine9+temperature_bias+temperature_scale",
                 "affine9+temperature_bias+time_drift_bias", "affine9+temperature_bias+temperature_scale+time_drift_bias"):
        _, mae = fit(ErrorModel(name), raw, temp, t)
        print(f"{name}: mean abs(norm - 1) {mae:.3f} mg", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
