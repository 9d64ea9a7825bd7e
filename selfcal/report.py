"""Markdown report with plots for ``selfcal diagnose --report DIR``."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _fmt(x, nd=3):
    if x is None:
        return "–"
    if isinstance(x, float):
        return f"{x:.{nd}g}" if abs(x) < 1e4 else f"{x:.3e}"
    return str(x)


def _noise_model_lines(nm: dict | None) -> list[str]:
    """Markdown lines of the report's ``noise_model`` section (empty without one)."""
    if not nm or not nm.get("estimated"):
        return []
    sd = nm.get("std") or {}

    def pm(key):
        return f"{_fmt(nm.get(key))}" + (f" ± {_fmt(sd[key])}" if sd.get(key) is not None else "")

    rule = nm.get("bout_rule") or {}
    test = nm.get("independence_test") or {}
    lines = [
        "## Noise model",
        "",
        f"Still bouts: consecutive windows at most {_fmt(rule.get('gap_s'))} s apart, turning at most "
        f"{_fmt(rule.get('angle_deg'))}° between windows: {nm['n_bouts']} bouts, {nm['n_multi_window_bouts']} of two "
        f"windows or more ({nm['n_windows_in_multi_window_bouts']} windows). Independence within bouts: "
        f"χ² {_fmt(test.get('chi2'))} for {test.get('dof')} bouts, p = {_fmt(test.get('p'))}.",
        "",
    ]
    if nm.get("correlated_var_mg2"):
        tau = sd.get("tau_s_16_84")
        lines += [
            "| term | value |",
            "|---|---|",
            f"| measured noise per window (rms) | {_fmt(nm.get('measured_noise_mg'))} mg |",
            f"| shared by a bout | {pm('sigma_bout_mg')} mg |",
            f"| AR(1) within a bout | {pm('sigma_ar_mg')} mg, τ {_fmt(nm.get('tau_s'))} s"
            + (f" (16–84 %: {_fmt(tau[0])}–{_fmt(tau[1])} s)" if tau else "") + " |",
            f"| independent excess | {pm('sigma_white_mg')} mg |",
            f"| correlated share of the variance | {_fmt(nm.get('correlated_share'))} |",
            "",
            "The simulation draws the bout and AR(1) terms; the F statistics are divided by each effect's design "
            "effect, and the cross-validation holds out whole bouts.",
            "",
        ]
    else:
        lines += [nm.get("why", "No correlated part: the windows are treated as independent."), ""]
    return lines


def write_report(report: dict, out_dir: str | Path) -> Path:
    """Write ``report.md`` and PNG plots into ``out_dir``; returns the Markdown path.

    ``report`` is :func:`selfcal.diagnosis.diagnose_poses` output made with
    ``keep_arrays=True``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    arr = report.get("_arrays") or {}
    days = (arr["t_s"] - arr["t_s"].min()) / 86400.0 if arr else None
    figs = []
    if arr:
        panels = [("time_days", days, "time since start (days)")]
        if arr["temp_c"] is not None:
            panels.insert(0, ("temp_c", arr["temp_c"], "temperature (°C)"))
        fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
        for ax, (_, x, label) in zip(axes[0], panels):
            ax.plot(x, arr["res_base_mg"], ".", ms=2, alpha=0.5, label=f"measured, {report['base_model']['model']}")
            if arr["res_sim_mg"] is not None:
                ax.plot(x, arr["res_sim_mg"], ".", ms=2, alpha=0.5, label="simulated under the base model")
            if arr["res_ext_mg"] is not None:
                ax.plot(x, arr["res_ext_mg"], ".", ms=2, alpha=0.5, label=f"measured, + {report['cause']}")
            ax.set_xlabel(label)
            ax.set_ylabel("norm residual (mg)")
            ax.grid(alpha=0.3)
        axes[0][0].legend(fontsize=8, markerscale=4)
        fig.tight_layout()
        fig.savefig(out / "residual_vs_temp_time.png", dpi=90)
        plt.close(fig)
        figs.append(("Residual against temperature and time", "residual_vs_temp_time.png"))

        fig, axes = plt.subplots(1, 3, figsize=(15, 4))
        for i, ax in enumerate(axes):
            ax.plot(arr["gdir"][:, i], arr["res_base_mg"], ".", ms=2, alpha=0.5, label="measured")
            if arr["res_sim_mg"] is not None:
                ax.plot(arr["gdir"][:, i], arr["res_sim_mg"], ".", ms=2, alpha=0.5, label="simulated")
            ax.set_xlabel(f"gravity component {'xyz'[i]} (g)")
            ax.set_ylabel("norm residual (mg)")
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8, markerscale=4)
        fig.tight_layout()
        fig.savefig(out / "residual_vs_axis.png", dpi=90)
        plt.close(fig)
        figs.append(("Residual against orientation (per axis)", "residual_vs_axis.png"))

        fig, ax = plt.subplots(figsize=(6, 4))
        bins = np.linspace(*np.percentile(arr["res_base_mg"], [0.5, 99.5]), 60)
        ax.hist(arr["res_base_mg"], bins=bins, alpha=0.6, density=True, label="measured")
        if arr["res_sim_mg"] is not None:
            ax.hist(arr["res_sim_mg"], bins=bins, alpha=0.6, density=True, label="simulated")
        ax.set_xlabel("norm residual (mg)")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "residual_hist.png", dpi=90)
        plt.close(fig)
        figs.append(("Measured vs simulated residual distribution", "residual_hist.png"))

    b = report["base_model"]
    d = report["discrepancy"]
    g = report["gain"]
    lines = [
        f"# selfcal diagnose: {report.get('recording') or 'poses'}",
        "",
        f"{report['n_poses']} still poses, unit `{report.get('unit', 'g')}`.",
        "",
        "## Verdict",
        "",
        f"**Cause: {report['cause'] or 'none beyond the base model'}**"
        + (f" (ambiguous with {', '.join(report['ambiguous'])})" if report.get("ambiguous") else ""),
        "",
        f"Held-out RMS ({g['split']}): before {_fmt(g['heldout_rms_mg_before'])} mg → after "
        f"{_fmt(g['heldout_rms_mg_after'])} mg ("
        + (f"{g['n_fit']} poses fitted, {g['n_heldout']} held out)." if g["n_fit"] is not None
           else f"each of the {g['n_heldout']} poses held out once)."),
        "",
        "## Base model",
        "",
        f"`{b['model']}`: residual RMS {_fmt(b['residual_rms_mg'])} mg. "
        + (f"Not determined by these poses: {', '.join(b['undetermined'])}." if b["undetermined"] else "All parameters determined."),
        "",
        "## What the simulation gets wrong",
        "",
        "We simulate this same recording under the base model: the same poses, times, temperatures, and each pose's"
        " measured noise. We then compare the measured residual statistics with the spread of "
        "the simulated ones. A |z| well above 3 is structure that the model and its noise do not produce.",
        "",
        "| statistic | measured | simulated (mean ± sd) | z |",
        "|---|---|---|---|",
    ]
    for k, v in d.items():
        if isinstance(v, dict):
            lines.append(f"| {k} | {_fmt(v['measured'])} | {_fmt(v['simulated_mean'])} ± {_fmt(v['simulated_sd'])} | {_fmt(v['z'])} |")
    lines += [
        "",
        f"Measured / simulated RMS: {_fmt(d.get('rms_ratio_measured_over_simulated'))}; per-pose noise level "
        f"{_fmt(d.get('noise_level_mg'))} mg.",
        "",
        *_noise_model_lines(report.get("noise_model")),
        "## Candidate effects",
        "",
        "| effect | supported | selected | F | held-out gain (time, pose) | estimate (x, y, z) ± sd | evidence |",
        "|---|---|---|---|---|---|---|",
    ]
    for e in report["effects"]:
        est = e.get("estimate")
        est_s = "–"
        if est:
            est_s = ", ".join(f"{est['value'][a]:.3g}±{est['std'][a]:.2g}" for a in "xyz") + f" {est['unit']}"
        gains = f"{_fmt(e.get('gain_time'))}, {_fmt(e.get('gain_pose'))}" if "gain_time" in e else "–"
        lines.append(f"| {e['name']} | {e.get('supported', False)} | {e['selected']} | {_fmt(e.get('f_stat'))} | {gains} | {est_s} | {e['evidence']} |")
    if report.get("extended_model"):
        em = report["extended_model"]
        lines += ["", "## Extended model", "", f"`{em['model']}` (reference temperature {em['temp_ref_c']:.1f} °C), "
                  f"residual RMS {_fmt(em['residual_rms_mg'])} mg.", ""]
    for title, fn in figs:
        lines += ["", f"## {title}", "", f"![{title}]({fn})"]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
