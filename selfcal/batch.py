"""Many recordings at once: each file in its own process, one summary table, nothing stops the run.

Used by ``selfcal calibrate FILE... [--jobs N] [--summary summary.csv] [--out-dir DIR]``.
Every file gets a calibration JSON (``DIR/<name>.cal.json``) and a summary row; a file
that cannot be read or calibrated gets a row with its error, and the run goes on. Files
are streamed (bounded memory per process); duration and temperature range are those of
the still windows. The
summary is written as CSV and, as GGIR users expect, as a Markdown report with one plot
(the still-pose error before against after, per file).
"""

from __future__ import annotations

import csv
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

#: Columns of the summary table (units in the names).
SUMMARY_COLUMNS = (
    "file", "device", "status", "refusal_reason", "error", "n_poses", "n_windows", "residual_before_mg",
    "residual_after_mg", "predicted_sphere_rms_mg", "model", "temp_min_c", "temp_max_c", "duration_h",
    "calibration", "seconds",
)


def _device_name(meta: dict) -> str | None:
    return meta.get("device") or meta.get("sensor") or meta.get("format")


def calibrate_one(path: str, model: str, config_path: str | None, out_dir: str, columns: list[str] | None = None,
                  fixed_model: bool = False) -> dict:
    """Calibrate one file; never raises: an error becomes the row's ``error``."""
    from selfcal.config import load_config
    from selfcal.errors import SelfcalError
    from selfcal.io import iter_recording
    from selfcal.pipeline import calibrate_path

    t0 = time.perf_counter()
    row: dict = {k: None for k in SUMMARY_COLUMNS}
    row.update(file=path, model=model)
    try:
        cfg = load_config(config_path)
        if fixed_model:
            cfg.setdefault("selection", {})["enabled"] = False
        run = calibrate_path(path, model, cfg, columns=columns)  # streamed: bounded memory
        row["device"] = _device_name(run.meta)
        row["model"] = run.calibrator.model.name  # model selection may have extended the one asked for
        store = run.calibrator.store
        summ = store.summary()
        if summ["t_span_s"]:
            row["duration_h"] = round((summ["t_span_s"][1] - summ["t_span_s"][0]) / 3600.0, 4)
        if summ["temp_range_c"]:
            row["temp_min_c"], row["temp_max_c"] = (round(x, 2) for x in summ["temp_range_c"])
        row["n_poses"] = len(store)
        row["n_windows"] = int(store.window_counts().sum()) if len(store) else 0
        if len(store):
            poses = store.pose_data()
            before = np.linalg.norm(poses.mean, axis=1) - 1.0
            row["residual_before_mg"] = round(float(np.sqrt(np.mean(before**2)) * 1e3), 4)
        if run.calibration is None:
            last = run.last_refit or {}
            row["status"] = "uncalibrated"
            row["refusal_reason"] = last.get("reason") or "no_still_poses"
        else:
            cal = run.calibration
            row["status"] = cal["status"]
            row["predicted_sphere_rms_mg"] = round(float(cal["predicted_sphere_rms_mg"]), 4)
            model_now = run.calibrator.model
            with_temp = np.isfinite(store.mean_temp()) if model_now.uses_temperature else np.ones(len(store), bool)
            if with_temp.any():  # a temperature model scores the cells that have a temperature
                theta = np.asarray(run.calibrator.current["theta_u"])
                p = store.pose_data(with_temp)
                after = model_now.residuals(theta, p.mean, p.temp_c, p.t_s)
                row["residual_after_mg"] = round(float(np.sqrt(np.mean(after**2)) * 1e3), 4)
            target = Path(out_dir) / (Path(path).name + ".cal.json")
            tmp = target.with_name(target.name + ".tmp")
            tmp.write_text(json.dumps(cal, indent=2) + "\n", encoding="utf-8")
            os.replace(tmp, target)
            row["calibration"] = str(target)
    except SelfcalError as exc:
        row["status"] = "error"
        row["error"] = str(exc)
    except Exception as exc:  # noqa: BLE001 - one bad file never stops the run; the row says why
        row["status"] = "error"
        row["error"] = f"{type(exc).__name__}: {exc}"
    if row["status"] == "error":  # the device name, if the file's preamble can be read at all
        try:
            row["device"] = _device_name(next(iter_recording(path, block_rows=1, columns=columns)).meta)
        except Exception:  # noqa: BLE001 - the row already says what went wrong
            pass
    row["seconds"] = round(time.perf_counter() - t0, 3)
    return row


def run_batch(files: list[str], model: str, config_path: str | None, out_dir: str, jobs: int,
              summary: str | None, progress: bool = True, columns: list[str] | None = None,
              fixed_model: bool = False) -> list[dict]:
    """Calibrate ``files`` with ``jobs`` processes; write the summary; return the rows in input order."""
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    rows: dict[int, dict] = {}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(files), unit="file", desc="calibrate", file=sys.stderr)
    if jobs <= 1:
        for i, f in enumerate(files):
            rows[i] = calibrate_one(f, model, config_path, out_dir, columns, fixed_model)
            if bar:
                bar.update(1)
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futs = {pool.submit(calibrate_one, f, model, config_path, out_dir, columns, fixed_model): i
                    for i, f in enumerate(files)}
            for fut in as_completed(futs):
                rows[futs[fut]] = fut.result()
                if bar:
                    bar.update(1)
    if bar:
        bar.close()
    out = [rows[i] for i in range(len(files))]
    if summary:
        write_summary(out, summary)
    return out


def write_summary(rows: list[dict], path: str) -> tuple[Path, Path]:
    """Write the summary CSV and its Markdown report (with a before/after plot when matplotlib is there)."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    with tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=SUMMARY_COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r[k]) for k in SUMMARY_COLUMNS})
    os.replace(tmp, p)
    md = p.with_suffix(".md")
    fig = p.with_suffix(".png")
    have_plot = _plot(rows, fig)
    ok = [r for r in rows if r["status"] in ("provisional", "calibrated")]
    lines = [f"# selfcal calibration summary: {len(rows)} files", "",
             f"{sum(r['status'] == 'calibrated' for r in rows)} calibrated, "
             f"{sum(r['status'] == 'provisional' for r in rows)} provisional, "
             f"{sum(r['status'] == 'uncalibrated' for r in rows)} refused, "
             f"{sum(r['status'] == 'error' for r in rows)} errors.", ""]
    if have_plot:
        lines += [f"![still-pose error before and after calibration]({fig.name})", ""]
    lines += ["| file | status | reason / error | poses | before (mg) | after (mg) | predicted sphere (mg) | temp (°C) | hours |",
              "|---|---|---|---:|---:|---:|---:|---|---:|"]

    def f(x):
        return "" if x is None else str(x)

    for r in rows:
        temp = "" if r["temp_min_c"] is None else f"{r['temp_min_c']}–{r['temp_max_c']}"
        why = (r["refusal_reason"] or r["error"] or "").replace("|", "/")
        lines.append(f"| {Path(r['file']).name} | {r['status']} | {why} | {f(r['n_poses'])} | {f(r['residual_before_mg'])} | "
                     f"{f(r['residual_after_mg'])} | {f(r['predicted_sphere_rms_mg'])} | {temp} | {f(r['duration_h'])} |")
    if ok:
        after = [r["residual_after_mg"] for r in ok if r["residual_after_mg"] is not None]
        if after:
            lines += ["", f"Median still-pose error after calibration: {np.median(after):.3f} mg over {len(after)} files."]
    md.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p, md


def _plot(rows: list[dict], path: Path) -> bool:
    pts = [(r["residual_before_mg"], r["residual_after_mg"]) for r in rows
           if r["residual_before_mg"] is not None and r["residual_after_mg"] is not None]
    if not pts:
        return False
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    b, a = np.asarray(pts).T
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    ax.loglog(b, a, "o", ms=5)
    lim = [min(b.min(), a.min()) * 0.8, max(b.max(), a.max()) * 1.25]
    ax.plot(lim, lim, "k--", lw=0.8, label="no change")
    ax.set_xlabel("still-pose |a|-1 g RMS before (mg)")
    ax.set_ylabel("after calibration (mg)")
    ax.set_title("per file")
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True
