"""Simulated insole vs real foot data: print the figures of docs/simulation.md, save plots.

Run: ``.venv/bin/python bench/sim_vs_real.py [--out docs/img] [--seed 1] [--days 1]``

Real data (read-only, ``data/``): Moticon OpenGo insoles (100 Hz, 16 cells)
and the gaitmap shoe-mounted NilsPod (204.8 Hz). Still moments are found with
``selfcal.detect.StaticDetector`` (``[detector]`` defaults, ``rate_hz`` set to the
data's rate) on both the real and the simulated streams. Walking samples are those
whose 1 s moving sd of ``|a|`` exceeds 0.1 g (both sides alike). Everything printed is
measured here; nothing is copied from elsewhere.
"""

from __future__ import annotations

import argparse
import glob
import time
from pathlib import Path

import numpy as np

from selfcal.detect import DetectorConfig, StaticDetector, StillWindows
from selfcal.io import read_recording
from selfcal.sim import SimConfig, Simulation
from selfcal.sim.wearer import OFF, SIT, STAIRS, STAND, WALK

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data"


def block_mean(t_s: np.ndarray, x: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Average samples into bins of ``dt_s`` (the 20 Hz sensor's sample average)."""
    b = np.floor((t_s - t_s[0]) / dt_s).astype(int)
    starts = np.flatnonzero(np.r_[True, np.diff(b) != 0])
    counts = np.diff(np.r_[starts, len(b)])
    xs = np.add.reduceat(x, starts, axis=0) / counts.reshape(-1, *([1] * (x.ndim - 1)))
    return b[starts] * dt_s + t_s[0], xs


def walking_mask(acc_g: np.ndarray, rate_hz: float) -> np.ndarray:
    """Samples whose centred 1 s moving sd of |a| exceeds 0.1 g."""
    n = np.linalg.norm(acc_g, axis=1)
    w = max(2, int(round(rate_hz)))
    k = np.ones(w) / w
    m1 = np.convolve(n, k, "same")
    m2 = np.convolve(n * n, k, "same")
    return np.sqrt(np.maximum(m2 - m1 * m1, 0)) > 0.1


def gait_cycle_s(norm: np.ndarray, rate_hz: float) -> float:
    """Stride time from the autocorrelation of |a| (first peak in 0.7-1.6 s)."""
    x = norm - norm.mean()
    ac = np.correlate(x, x, "full")[len(x) - 1:]
    lo, hi = int(0.7 * rate_hz), int(1.6 * rate_hz)
    return (lo + int(np.argmax(ac[lo:hi]))) / rate_hz


def detect(t_s, acc_g, rate_hz, pressure_kpa=None) -> StillWindows:
    det = StaticDetector(DetectorConfig(rate_hz=rate_hz))
    return StillWindows.concat([det.feed(t_s, acc_g, pressure_kpa=pressure_kpa), det.flush()])


def load_real():
    moticon = []
    for f in sorted(glob.glob(str(DATA / "moticon-insole" / "*.csv"))):
        r = read_recording(f)
        ok = np.all(np.isfinite(r.acc), axis=1)
        moticon.append((Path(f).stem, r.t_s[ok], r.acc_g()[ok], 10.0 * r.pressure[ok], r.extra.get("total_force_n")[ok]))
    gaitmap = []
    for f in sorted(glob.glob(str(DATA / "gaitmap-shoe-walking" / "*.csv"))):
        r = read_recording(f)
        gaitmap.append((Path(f).stem, r.t_s, r.acc_g()))
    return moticon, gaitmap


def pct(x, q=(50, 75, 95, 99)):
    return np.percentile(x, q).round(2).tolist()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "img"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--days", type=float, default=1.0)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    moticon, gaitmap = load_real()
    cfg = SimConfig()

    # --- generation speed -------------------------------------------------------
    t0 = time.perf_counter()
    sim = Simulation(cfg, np.random.default_rng(args.seed), days=args.days, seed=args.seed)
    c = sim.samples()
    el = time.perf_counter() - t0
    print(f"[speed] {args.days:g} day(s) at 20 Hz: {sim.schedule.n_samples} samples in {el:.2f} s "
          f"({sim.schedule.n_samples / el / 1e6:.2f} M samples/s)")

    # --- walking acceleration -------------------------------------------------------
    print("\n[walking |a| percentiles p50/p75/p95/p99, g]")
    sim_hi = {}
    for rate in (100.0, 204.8):
        s2 = Simulation(cfg.updated(ble={"rate_hz": rate, "packet_loss_rate": 0.0},
                                    day={"wear_start_h": 0.05, "wear_start_sd_h": 0.0, "breaks_per_day": 0.0},
                                    activity={"from_stand": {"walk": 1.0}, "from_walk": {"stand": 1.0},
                                              "stand": {"median_s": 5, "gsd": 1.5, "min_s": 3, "max_s": 20}}),
                        np.random.default_rng(args.seed), days=0.03)
        cc = s2.samples()
        sim_hi[rate] = cc
    rows = []
    for name, t, a, *_ in moticon:
        m = walking_mask(a, 100.0)
        if m.sum() > 200:
            rows.append(("moticon " + name, 100.0, np.linalg.norm(a[m], axis=1), t, a))
    for name, t, a in gaitmap:
        m = walking_mask(a, 204.8)
        rows.append(("gaitmap " + name, 204.8, np.linalg.norm(a[m], axis=1), t, a))
    real_20 = []
    for name, rate, nrm, t, a in rows:
        tb, ab = block_mean(t, a, 0.05)
        m20 = walking_mask(ab, 20.0)
        n20 = np.linalg.norm(ab[m20], axis=1)
        real_20.append(n20)
        print(f"  real {name:38s} native {rate:5.1f} Hz {pct(nrm)}   20 Hz {pct(n20)}")
    for rate, cc in sim_hi.items():
        m = walking_mask(cc.acc_g, rate) & (cc.activity == WALK)
        print(f"  sim  walking bouts                        native {rate:5.1f} Hz {pct(np.linalg.norm(cc.acc_g[m], axis=1))}")
    walk = (c.activity == WALK) & walking_mask(c.acc_g, 20.0)
    sim_walk20 = np.linalg.norm(c.acc_g[walk], axis=1)
    print(f"  sim  day, walking (20 Hz)                                  20 Hz {pct(sim_walk20)}")

    # gait cycle
    print("\n[gait cycle from the autocorrelation of |a|, s]")
    for name, rate, nrm, t, a in rows:
        m = walking_mask(a, rate)
        print(f"  real {name:38s} {gait_cycle_s(np.linalg.norm(a[m], axis=1), rate):.2f}")
    cc = sim_hi[100.0]
    w = cc.activity == WALK
    print(f"  sim  (100 Hz walking)                        {gait_cycle_s(np.linalg.norm(cc.acc_g[w], axis=1), 100.0):.2f}"
          f"   (config cycle_s = {cfg.gait.cycle_s})")

    # --- still moments -------------------------------------------------------------
    print("\n[still windows, StaticDetector defaults]")
    real_still = []
    for name, t, a, p, force in moticon:
        win = detect(t, a, 100.0, p)
        dur_rec = t[-1] - t[0]
        real_still.append((name, win, dur_rec))
        wm = walking_mask(a, 100.0)
        print(f"  real moticon {name:32s} {dur_rec:5.1f} s rec, walking {wm.mean():4.0%}: "
              f"{len(win)} windows, still {win.duration_s.sum():5.1f} s, durations {np.round(win.duration_s, 1).tolist()}")
    for name, t, a in gaitmap:
        win = detect(t, a, 204.8)
        print(f"  real gaitmap {name:32s} {t[-1] - t[0]:5.1f} s rec: {len(win)} windows, "
              f"still {win.duration_s.sum():.1f} s, max {win.duration_s.max() if len(win) else 0:.1f} s")
    win = detect(c.t_s, c.acc_g, 20.0, c.pressure_kpa)
    t_mid = 0.5 * (win.t_start_s + win.t_end_s)
    idx = np.clip(np.searchsorted(c.t_s, t_mid), 0, len(c) - 1)
    act = c.activity[idx]
    worn_h = np.isin(c.activity, (SIT, STAND, WALK, STAIRS)).sum() / 20.0 / 3600
    on = act != OFF
    # merge consecutive windows (split at max_window_s) into still runs
    gap = np.r_[True, win.t_start_s[1:] - win.t_end_s[:-1] > 0.3]
    run_id = np.cumsum(gap) - 1
    run_dur = np.bincount(run_id, weights=win.duration_s + 1 / 20.0)
    run_act = act[gap]
    print(f"  sim day: {len(win)} windows ({on.sum()} on the foot); worn {worn_h:.1f} h; "
          f"{np.sum(run_act != OFF) / worn_h:.0f} still runs per worn hour")
    for code, nm in ((STAND, "stand"), (SIT, "sit"), (OFF, "off_foot")):
        d = run_dur[run_act == code]
        if len(d):
            print(f"    {nm:8s} runs {len(d):5d}, duration p10/p50/p90 {np.percentile(d, [10, 50, 90]).round(1).tolist()} s")
    walk_win = np.sum(act == WALK)
    print(f"    windows during walking bouts: {walk_win}")
    truth_on = c.still & (c.activity != OFF)
    print(f"    true still fraction of worn time {truth_on.sum() / 20.0 / 3600 / worn_h:.2f}; "
          f"detected {win.duration_s[on].sum() / 3600 / worn_h:.2f}")

    # --- orientation spread ----------------------------------------------------------
    print("\n[orientation of still windows: pitch = asin(ax/|a|), roll = atan2(ay, az), deg]")
    for name, wn, _ in real_still:
        if len(wn):
            m = wn.mean_g
            pitch = np.rad2deg(np.arcsin(m[:, 0] / np.linalg.norm(m, axis=1)))
            roll = np.rad2deg(np.arctan2(m[:, 1], m[:, 2]))
            print(f"  real moticon {name:32s} pitch {pitch.round(1).tolist()} roll {roll.round(1).tolist()}")
    m = win.mean_g
    s_pitch = np.rad2deg(np.arcsin(np.clip(m[:, 0] / np.linalg.norm(m, axis=1), -1, 1)))
    s_roll = np.rad2deg(np.arctan2(m[:, 1], m[:, 2]))
    for code, nm in ((STAND, "stand"), (SIT, "sit"), (OFF, "off_foot")):
        k = act == code
        if k.any():
            print(f"  sim {nm:8s} pitch p5/p50/p95 {np.percentile(s_pitch[k], [5, 50, 95]).round(1).tolist()}  "
                  f"|roll| p50/p95 {np.percentile(np.abs(s_roll[k]), [50, 95]).round(1).tolist()}")

    # --- pressure --------------------------------------------------------------------
    print("\n[pressure]")
    for name, t, a, p, force in moticon:
        st = detect(t, a, 100.0, p)
        still = np.zeros(len(t), bool)
        for t0_, t1_ in zip(st.t_start_s, st.t_end_s):
            still |= (t >= t0_) & (t <= t1_)
        wm = walking_mask(a, 100.0)
        if still.any() and wm.any():
            f_st = force[still]
            print(f"  real moticon {name:32s} total force: still mean {f_st.mean():5.0f} N, CV {f_st.std() / f_st.mean():.2f}; "
                  f"walking CV {force[wm].std() / max(force[wm].mean(), 1e-9):.2f}, "
                  f"fraction of walking samples < 5 % of still mean {np.mean(force[wm] < 0.05 * f_st.mean()):.2f}")
    ps = c.pressure_kpa.sum(axis=1)
    still_stand = c.still & (c.activity == STAND)
    print(f"  sim  day, sum of 4 cells: standing still mean {ps[still_stand].mean():.0f} kPa, CV "
          f"{ps[still_stand].std() / ps[still_stand].mean():.2f}; walking CV {ps[walk].std() / ps[walk].mean():.2f}, "
          f"fraction of walking samples < 5 % of standing mean {np.mean(ps[walk] < 0.05 * ps[still_stand].mean()):.2f}")
    sit_still = c.still & (c.activity == SIT)
    off = c.activity == OFF
    print(f"  sim  sitting still mean {ps[sit_still].mean():.0f} kPa; off foot mean {ps[off].mean():.1f} kPa")

    # --- temperature -------------------------------------------------------------------
    print("\n[temperature] sim day: min {:.1f} / p50 {:.1f} / max {:.1f} degC".format(
        c.temp_c.min(), np.median(c.temp_c), c.temp_c.max()))

    # --- plots -------------------------------------------------------------------------
    plt.rcParams.update({"font.size": 8})
    fig, ax = plt.subplots(1, 2, figsize=(7, 2.8), dpi=90)
    for name, rate, nrm, t, a in rows[:1] + rows[-2:-1]:
        ax[0].plot(np.sort(nrm), np.linspace(0, 1, len(nrm)), label=f"real {name.split()[0]} ({rate:g} Hz)")
    for rate, cc in sim_hi.items():
        m = walking_mask(cc.acc_g, rate) & (cc.activity == WALK)
        x = np.sort(np.linalg.norm(cc.acc_g[m], axis=1))
        ax[0].plot(x, np.linspace(0, 1, len(x)), "--", label=f"sim ({rate:g} Hz)")
    ax[0].set(xlabel="|a| while walking [g]", ylabel="CDF", xlim=(0, 6), title="native rate")
    ax[0].legend(fontsize=6)
    allreal = np.concatenate(real_20)
    ax[1].plot(np.sort(allreal), np.linspace(0, 1, len(allreal)), label="real, 50 ms averages")
    ax[1].plot(np.sort(sim_walk20), np.linspace(0, 1, len(sim_walk20)), "--", label="sim 20 Hz")
    ax[1].set(xlabel="|a| while walking [g]", xlim=(0, 6), title="20 Hz")
    ax[1].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "sim_walk_norm_cdf.png")
    plt.close(fig)

    fig, ax = plt.subplots(2, 1, figsize=(7, 3.6), dpi=90, sharex=True)
    name, t, a = gaitmap[0]
    k = (t > 10) & (t < 15)
    ax[0].plot(t[k] - t[k][0], a[k])
    ax[0].set(ylabel="real gaitmap [g]")
    cc = sim_hi[204.8]
    i0 = np.flatnonzero(cc.activity == WALK)
    i0 = i0[len(i0) // 2]
    ts = cc.t_s[i0:i0 + int(5 * 204.8)]
    ax[1].plot(ts - ts[0], cc.acc_g[i0:i0 + len(ts)])
    ax[1].set(ylabel="sim (204.8 Hz) [g]", xlabel="s")
    ax[1].legend(["x (toes)", "y (left)", "z (up)"], fontsize=6, ncol=3)
    fig.tight_layout()
    fig.savefig(out / "sim_walk_trace.png")
    plt.close(fig)

    fig, ax = plt.subplots(1, 2, figsize=(7, 2.8), dpi=90)
    for code, nm in ((STAND, "stand"), (SIT, "sit")):
        d = run_dur[run_act == code]
        ax[0].hist(d, bins=np.logspace(0, 3.5, 30), alpha=0.6, label=f"sim {nm}")
    real_d = np.concatenate([wn.duration_s for _, wn, _ in real_still])
    ax[0].hist(real_d, bins=np.logspace(0, 3.5, 30), alpha=0.9, label="real moticon (trials)", histtype="step", color="k")
    ax[0].set(xscale="log", xlabel="still run duration [s]", ylabel="count", title="detected still runs (1 sim day)")
    ax[0].legend(fontsize=6)
    for code, nm in ((STAND, "stand"), (SIT, "sit"), (OFF, "off foot")):
        k = act == code
        ax[1].scatter(s_roll[k], s_pitch[k], s=3, alpha=0.4, label=nm)
    ax[1].set(xlabel="roll [deg]", ylabel="pitch [deg]", title="still-window orientation (sim)")
    ax[1].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "sim_still.png")
    plt.close(fig)

    fig, ax = plt.subplots(1, 2, figsize=(7, 2.6), dpi=90)
    name, t, a, p, force = moticon[2]
    ax[0].plot(t, force)
    ax[0].set(title=f"real moticon {name}", xlabel="s", ylabel="total force [N]")
    i0 = np.flatnonzero(np.diff((c.activity == WALK).astype(int)) == 1)[3] - 100
    ax[1].plot(c.t_s[i0:i0 + 400] - c.t_s[i0], c.pressure_kpa[i0:i0 + 400])
    ax[1].set(title="sim (standing -> walking)", xlabel="s", ylabel="kPa")
    ax[1].legend(["heel", "midfoot", "met1", "toe"], fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "sim_pressure.png")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 2.2), dpi=90)
    ax.plot(c.t_s[::200] / 3600, c.temp_c[::200])
    ax.set(xlabel="h", ylabel="temp [degC]", title="sim temperature, 1 day")
    fig.tight_layout()
    fig.savefig(out / "sim_temperature.png")
    plt.close(fig)
    print(f"\nplots written to {out}")


if __name__ == "__main__":
    main()
