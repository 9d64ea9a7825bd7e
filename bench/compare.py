"""selfcal against the baselines, on the same pose sets (simulated with truth, and real).

Usage::

    python bench/compare.py [--quick] [--json] [--plots DIR] [--markdown FILE ...]

``--markdown`` may be repeated (``--markdown docs/compare.md --markdown README.md``): every
file gets the same generated block between its ``compare:begin``/``compare:end`` markers,
with the figure links (from ``--plots DIR``) relative to that file.

Every method gets exactly the same poses (``bench/compare_data.py`` builds them) and
returns ``a_cal_g = matrix @ (raw - offset)`` (+ a temperature term for GGIR). Metrics
(definitions in ``docs/compare.md``):

* ``sphere_norm_rms_mg`` — simulated sets: RMS over 2000 directions spread on the whole
  sphere of ``||calibrated(raw(a))|| - 1 g`` (mg), ``raw(a)`` the true sensor's reading
  (with effects: in the temperatures/times of the set's poses); median over sets.
* ``heldout_rms_mg`` — fit on part, RMS norm residual (mg) on the rest, mean of two
  splits: by pose (every 5th pose held out) and by time (first 60 % / last 40 %);
  median over the real sets (both splits are also reported).
* ``crlb_efficiency`` — geometric mean over identifiable parameters of CRLB variance /
  Monte-Carlo mean squared error (repeated noise draws of one set) on ``sim_spread``
  (``crlb_efficiency_min``: the smallest ratio).
* ``poses_needed`` — smallest prefix of a well-spread sequence at which the median
  sphere RMS (over seeds) is below 1 mg.
* ``fit_ms`` — median wall time of the fit (best of 3 runs when under 60 ms); ``speedup_vs_seed_lm`` = median seed_lm
  time / median selfcal fit time on the same sets.

A method that raises (e.g. six_face without six faces) or declines (GGIR without sphere
coverage, selfcal's guard refusing) leaves the sensor uncalibrated: it is scored with
the nominal model and counted in ``n_failed``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_data import (  # noqa: E402
    PoseSet,
    growing_spread,
    real_sets,
    sim_flat,
    sim_mix,
    sim_spread,
    sphere_points,
)

from selfcal.baselines import BASELINES  # noqa: E402
from selfcal.calibrator import OnlineCalibrator  # noqa: E402
from selfcal.fit import FitConfig, PoseData, cramer_rao_std, datasheet_prior, fit_poses  # noqa: E402
from selfcal.models import ErrorModel  # noqa: E402

A9 = ErrorModel("affine9")
S6 = ErrorModel("scale6")
G_MPS2 = 9.80665

#: row order of the report (selfcal first, then the issue's order). ``selfcal_engine`` is a
#: diagnostic row: the same fit on every pose, without the online guard's hold-out.
METHOD_ORDER = ["selfcal", "selfcal_engine", "seed_lm", "lm_fixed", "lm_random_init", "insole_lm_ls", "ellipsoid6", "quadric9",
                "six_face", "twelve_position", "da_lm", "ggir_autocal", "ggir_actipy", "imu_tk_style"]
#: methods whose calibration has only offset + per-axis scale (6 parameters)
SIX_PARAM = {"ellipsoid6", "six_face", "ggir_autocal", "ggir_actipy"}
POSES_GRID = [6, 8, 10, 12, 15, 18, 24, 30, 40, 48, 60]
THRESHOLD_MG = 1.0


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- running a method


@dataclass
class Cal:
    """A calibration in the set's raw unit, and how it was obtained."""

    matrix: np.ndarray
    offset: np.ndarray
    temp_coef: np.ndarray | None = None
    temp_ref_c: float = 0.0
    fit_ms: float = float("nan")
    e2e_ms: float = float("nan")
    failed: bool = False
    message: str = ""

    def apply(self, raw: np.ndarray, temp_c: np.ndarray | None = None) -> np.ndarray:
        out = (raw - self.offset) @ self.matrix.T
        if self.temp_coef is not None and temp_c is not None:
            out = out + np.multiply.outer(np.asarray(temp_c, float) - self.temp_ref_c, self.temp_coef)
        return out

    def norm_err_mg(self, raw, temp_c=None) -> np.ndarray:
        return (np.linalg.norm(self.apply(raw, temp_c), axis=1) - 1.0) * 1e3


def nominal_cal(ps: PoseSet, message: str, ms: float = float("nan")) -> Cal:
    """The uncalibrated sensor: only the nominal unit conversion of the set."""
    nz = ps.normalizer
    return Cal(np.eye(3) / nz.scale, np.asarray(nz.center, float), fit_ms=ms, e2e_ms=ms, failed=True, message=message)


def _rng_for(name: str) -> int:
    return zlib.crc32(name.encode()) & 0x7FFFFFFF


def run_selfcal(ps: PoseSet, model: str = "affine9") -> Cal:
    """The online calibrator as shipped, but with the model fixed (this comparison scores
    matrix/offset plus a temperature bias, not an effect model selection might add):
    feed_poses then flush, calibration() -> matrix/offset."""
    nz = ps.normalizer
    t0 = time.perf_counter()
    cal = OnlineCalibrator({"selection": {"enabled": False}}, model=model)
    events = cal.feed_poses(nz.to_u(ps.mean), ps.sd / nz.scale, ps.n, ps.t_s, ps.temp_c)
    events += cal.flush()
    c = cal.calibration()
    e2e = (time.perf_counter() - t0) * 1e3
    fit_ms = float(sum(e["fit_ms"] for e in events if e.get("fit_ms") is not None))
    if c is None:
        last = cal.last_refit or {}
        return nominal_cal(ps, f"nothing published: {last.get('reason')}: {last.get('message')}", e2e)
    m_u, o_u = np.asarray(c["matrix"], float), np.asarray(c["offset"], float)
    matrix, offset = m_u / nz.scale, np.asarray(nz.center, float) + nz.scale * o_u
    temp_coef = None
    if "temperature_bias" in cal.model.effects:
        # a = M (u - (b + tb dT)) = M(u - b) - M tb dT: an additive term in g
        th = np.asarray(cal.current["theta_u"], float)
        temp_coef = -(m_u @ th[cal.model.index("temperature_bias")])
    return Cal(matrix, offset, temp_coef, cal.model.temp_ref_c, fit_ms=fit_ms, e2e_ms=e2e,
               message=f"{c['status']} v{c['version']}, {c['n_windows']} still windows in {c['n_poses']} pose cells")


def run_engine(ps: PoseSet) -> Cal:
    """Diagnostic row: selfcal's fit (``fit_poses``, datasheet prior) on *every* pose, no guard hold-out."""
    nz = ps.normalizer
    t0 = time.perf_counter()
    fr = fit_poses(A9, PoseData(nz.to_u(ps.mean), ps.sd / nz.scale, ps.n, ps.t_s, ps.temp_c))
    ms = (time.perf_counter() - t0) * 1e3
    m_u, o_u = fr.linear()
    return Cal(m_u / nz.scale, np.asarray(nz.center, float) + nz.scale * o_u, fit_ms=ms, e2e_ms=ms,
               message=fr.message if hasattr(fr, "message") else "")


def run_baseline(name: str, ps: PoseSet, quick: bool) -> Cal:
    f = BASELINES[name]
    kw: dict = {}
    mean = ps.mean
    back = 1.0
    if name == "seed_lm":
        # the seed works in m/s^2 with g = 9.8 and lambda tied to those magnitudes
        if ps.unit == "g":
            mean, back = ps.mean * G_MPS2, G_MPS2
        elif ps.unit == "counts":
            kw = {"prescale": True}  # the seed has no way to handle counts
    elif name in ("lm_random_init", "da_lm"):
        kw = {"rng": _rng_for(ps.name)}
        if name == "da_lm":
            kw["quick"] = quick
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = f(mean, ps.sd if name != "seed_lm" else None, ps.n, ps.t_s, ps.temp_c, **kw)
    except Exception as exc:  # noqa: BLE001 - a refusal is a result
        return nominal_cal(ps, f"{type(exc).__name__}: {exc}", (time.perf_counter() - t0) * 1e3)
    ms = (time.perf_counter() - t0) * 1e3
    matrix, offset = np.asarray(r.matrix, float) * back, np.asarray(r.offset, float) / back
    if not (np.all(np.isfinite(matrix)) and np.all(np.isfinite(offset))):
        return nominal_cal(ps, f"non-finite result: {r.message}", ms)
    declined = name.startswith("ggir") and not bool(r.extra.get("recalibrated", r.converged))
    return Cal(matrix, offset, None if r.temp_coef is None else np.asarray(r.temp_coef, float), float(r.temp_ref_c),
               fit_ms=ms, e2e_ms=ms, failed=declined, message=r.message)


#: plausibility of any result, in the set's normalised (~g) frame: singular values of the
#: matrix within [0.5, 2] and |offset| <= 0.5 g. Outside, the fit has run off to a
#: degenerate solution (e.g. bias -> infinity, scale -> 0 maps every reading to one
#: unit vector: a perfect *norm* and no calibration at all), scored as uncalibrated.
SV_RANGE = (0.5, 2.0)
MAX_OFFSET_G = 0.5


def degenerate(ps: PoseSet, cal: Cal) -> str | None:
    nz = ps.normalizer
    sv = np.linalg.svd(cal.matrix * nz.scale, compute_uv=False)
    off = np.abs((cal.offset - np.asarray(nz.center, float)) / nz.scale)
    if sv.min() < SV_RANGE[0] or sv.max() > SV_RANGE[1] or off.max() > MAX_OFFSET_G:
        return (f"degenerate result (singular values {np.round(sv, 3).tolist()}, max |offset| {off.max():.3g} g): "
                f"{cal.message}")
    return None


def run(name: str, ps: PoseSet, quick: bool) -> Cal:
    if name == "selfcal":
        cal = run_selfcal(ps)
    elif name == "selfcal_engine":
        cal = run_engine(ps)
    elif name == "selfcal+effect":
        cal = run_selfcal(ps, ps.__dict__.get("_diag_model", "affine9"))
    else:
        cal = run_baseline(name, ps, quick)
    if not cal.failed:
        why = degenerate(ps, cal)
        if why:
            out = nominal_cal(ps, why)
            out.fit_ms, out.e2e_ms = cal.fit_ms, cal.e2e_ms
            return out
    return cal


# --------------------------------------------------------------------------- metrics


_SPHERE_CACHE: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def sphere_rms(ps: PoseSet, cal: Cal) -> float:
    if ps.name not in _SPHERE_CACHE:
        _SPHERE_CACHE[ps.name] = sphere_points(ps)
    raw, temp = _SPHERE_CACHE[ps.name]
    e = cal.norm_err_mg(raw, temp)
    return float(np.sqrt(np.mean(e**2)))


def pose_dir_rms(ps: PoseSet, cal: Cal) -> float:
    """Truth-known error over the set's own pose directions and conditions (noise-free)."""
    e = cal.norm_err_mg(ps.clean, ps.temp_true)
    return float(np.sqrt(np.mean(e**2)))


def splits(ps: PoseSet) -> dict[str, np.ndarray]:
    """Held-out masks: every 5th pose; the last 40 % in time."""
    idx = np.arange(len(ps))
    by_pose = idx % 5 == 4
    order = np.argsort(ps.t_s, kind="stable")
    by_time = np.zeros(len(ps), bool)
    by_time[order[int(np.ceil(0.6 * len(ps))):]] = True
    return {"pose": by_pose, "time": by_time}


def heldout(name: str, ps: PoseSet, quick: bool) -> dict[str, float]:
    out = {}
    for split, held in splits(ps).items():
        cal = run(name, ps.subset(~held), quick)
        h = ps.subset(held)
        e = cal.norm_err_mg(h.mean, h.temp_c)
        out[split] = float(np.sqrt(np.mean(e**2)))
        out[split + "_failed"] = cal.failed
    return out


def theta_of(cal: Cal) -> np.ndarray:
    """Canonical affine9 parameters (g units) of a calibration's linear part."""
    return A9.from_linear(cal.matrix, cal.offset)


def crlb(ps: PoseSet) -> dict[str, np.ndarray]:
    """CRLB sd of the 9 (and 6) canonical parameters at the truth, and which are identifiable."""
    sens = ps.truth
    th = A9.from_linear(sens.matrix, sens.offset)
    gdir = ps.a_true / np.linalg.norm(ps.a_true, axis=1, keepdims=True)
    w = gdir @ sens.matrix  # d||a|| / d raw
    sigma = np.sqrt(np.sum((w * ps.noise) ** 2, axis=1))
    j9 = A9.residual_jac(th, ps.clean)[1]
    sd9 = cramer_rao_std(j9, sigma)
    th6 = S6.nominal()
    th6[:] = th[:6]
    j6 = S6.residual_jac(th6, ps.clean)[1]
    sd6 = cramer_rao_std(j6, sigma)
    prior_sd = np.sqrt(np.diag(datasheet_prior(A9, FitConfig()).cov))
    ident9 = np.isfinite(sd9) & (sd9 < 0.5 * prior_sd)
    ident6 = np.isfinite(sd6) & (sd6 < 0.5 * prior_sd[:6])
    return {"theta": th, "sd9": sd9, "sd6": sd6, "ident9": ident9, "ident6": ident6}


def efficiency(ps: PoseSet, methods: list[str], draws: int, quick: bool, seed: int = 0) -> dict[str, dict]:
    """CRLB variance / Monte-Carlo MSE per identifiable parameter (mean and min over them)."""
    cr = crlb(ps)
    rng = np.random.default_rng(seed)
    est = {m: [] for m in methods}
    failed = {m: 0 for m in methods}
    for _ in range(draws):
        d = ps.redraw(rng)
        for m in methods:
            cal = run(m, d, quick)
            failed[m] += cal.failed
            est[m].append(theta_of(cal))
    out = {}
    for m in methods:
        th = np.array(est[m])
        six = m in SIX_PARAM
        k = 6 if six else 9
        ident = cr["ident6"] if six else cr["ident9"]
        sd = cr["sd6"] if six else cr["sd9"]
        if not ident.any():
            out[m] = {"mean": None, "min": None, "note": "no identifiable parameter"}
            continue
        err = th[:, :k] - cr["theta"][:k]
        mse = np.mean(err**2, axis=0)
        var = np.var(th[:, :k], axis=0, ddof=1)
        ratio = (sd**2 / np.maximum(mse, 1e-300))[ident]
        ratio_var = (sd**2 / np.maximum(var, 1e-300))[ident]
        out[m] = {
            # geometric mean: a constant that happens to sit on the truth of one parameter
            # (ratio >> 1) cannot lift a method that ignores the data
            "mean": float(np.exp(np.mean(np.log(ratio)))), "min": float(np.min(ratio)),
            "arith_mean": float(np.mean(ratio)), "geo_mean_var_only": float(np.exp(np.mean(np.log(ratio_var)))),
            "params": [n for n, i in zip(A9.param_names[:k], ident) if i], "n_failed_draws": failed[m],
            "note": ("6-parameter model: CRLB of offset+scale (scale6) at the truth's offset/scale"
                     if six else "affine9 CRLB"),
        }
    return out


# --------------------------------------------------------------------------- report


def fmt(x, nd=2, fail=False) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "—"
    s = f"{x:.{nd}f}" if abs(x) < 1e4 else f"{x:.3g}"
    return s + ("*" if fail else "")


def markdown(report: dict) -> str:
    rows = report["rows"]
    lines = []
    lines.append("| method | sphere RMS, sim (mg) | held-out RMS, real (mg) | fit (ms) | CRLB eff. | poses needed | failed |")
    lines.append("|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        lines.append(f"| `{r['method']}` | {fmt(r['sphere_norm_rms_mg'])} | {fmt(r['heldout_rms_mg'])} | "
                     f"{fmt(r['fit_ms'], 2)} | {fmt(r['crlb_efficiency'])} | "
                     f"{r['poses_needed'] if r['poses_needed'] is not None else '—'} | {r['n_failed']}/{r['n_sets']} |")
    lines.append("")
    lines.append(f"speed-up of selfcal's fit vs seed_lm (median times, same sets): "
                 f"**{report['speedup_vs_seed_lm']:.0f}x** (whole online calibrator incl. pose buffer and guard: "
                 f"{report['speedup_end_to_end_vs_seed_lm']:.1f}x)")
    lines.append("")
    fams = report["sim_families"]
    lines.append("Sphere RMS (mg) per simulated family, median over seeds (* = failed/declined on some seed):")
    lines.append("")
    lines.append("| method | " + " | ".join(f"`{f}`" for f in fams) + " |")
    lines.append("|---|" + "---:|" * len(fams))
    for r in rows:
        cells = []
        for f in fams:
            d = r["by_dataset"].get(f, {})
            cells.append(fmt(d.get("sphere_norm_rms_mg"), 2, d.get("n_failed", 0) > 0))
        lines.append(f"| `{r['method']}` | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("Error over the set's *own* pose directions and conditions (truth known, noise-free; mg), "
                 "median over seeds — what the device actually sees:")
    lines.append("")
    lines.append("| method | " + " | ".join(f"`{f}`" for f in fams) + " |")
    lines.append("|---|" + "---:|" * len(fams))
    for r in rows:
        cells = []
        for f in fams:
            d = r["by_dataset"].get(f, {})
            cells.append(fmt(d.get("pose_dir_rms_mg"), 2, d.get("n_failed", 0) > 0))
        lines.append(f"| `{r['method']}` | " + " | ".join(cells) + " |")
    lines.append("")
    reals = report["real_sets"]
    lines.append("Held-out RMS (mg) per real set: by pose / by time (* = failed/declined, scored uncalibrated):")
    lines.append("")
    lines.append("| method | " + " | ".join(f"`{f}`" for f in reals) + " |")
    lines.append("|---|" + "---:|" * len(reals))
    for r in rows:
        cells = []
        for f in reals:
            d = r["by_dataset"].get(f, {})
            cells.append(f"{fmt(d.get('heldout_pose_rms_mg'), 2, d.get('pose_failed'))} / "
                         f"{fmt(d.get('heldout_time_rms_mg'), 2, d.get('time_failed'))}")
        lines.append(f"| `{r['method']}` | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("CRLB efficiency per clean simulated family (geometric mean over identifiable parameters; min in brackets):")
    lines.append("")
    eff_fams = report["efficiency_families"]
    lines.append("| method | " + " | ".join(f"`{f}`" for f in eff_fams) + " |")
    lines.append("|---|" + "---:|" * len(eff_fams))
    for r in rows:
        cells = []
        for f in eff_fams:
            e = r["by_dataset"].get(f, {}).get("crlb")
            cells.append("—" if not e or e.get("mean") is None else f"{e['mean']:.2f} ({e['min']:.2f})")
        lines.append(f"| `{r['method']}` | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("Best per data set: " + "; ".join(f"`{k}`: {v}" for k, v in report["best"].items()))
    return "\n".join(lines) + "\n"


BEGIN, END = "<!-- compare:begin (generated by bench/compare.py, do not edit) -->", "<!-- compare:end -->"
#: the figures ``plots`` writes, with their captions (linked from the generated block)
FIGURES = [("compare_sphere_rms.png", "sphere RMS per method and family"),
           ("compare_vs_poses.png", "RMS vs number of poses"),
           ("compare_heldout_real.png", "held-out RMS on real recordings")]


def check_markdown_target(path: Path) -> str | None:
    """Why ``path`` cannot receive the block (None if it can): a file that exists must hold both markers
    (the block replaces only what lies between them; nothing else in the file is ever overwritten)."""
    if not path.exists():
        return None if path.parent.is_dir() else f"{path}: directory {path.parent} does not exist"
    text = path.read_text()
    if BEGIN not in text or END not in text or text.index(END) < text.index(BEGIN):
        return f"{path}: exists but has no {BEGIN} ... {END} markers (refusing to overwrite it)"
    return None


def figure_links(path: Path, img_dir: Path | None) -> str:
    """Image links to the figures in ``img_dir``, relative to the directory of ``path`` (the target file)."""
    if img_dir is None:
        return ""
    import os

    base = Path(os.path.abspath(path)).parent
    out = []
    for name, caption in FIGURES:
        rel = Path(os.path.relpath(Path(os.path.abspath(img_dir)) / name, base)).as_posix()
        out.append(f"![{caption}]({rel})")
    return "\n".join(out) + "\n\n"


def write_markdown(path: Path, tables: str, report: dict, argv, img_dir: Path | None = None) -> None:
    """Write the block into ``path``: between the BEGIN/END markers if the file has them, or a new file.

    The figure links (when ``img_dir`` is given) are relative to ``path``'s own directory, so the same
    block works in ``docs/compare.md`` and in ``README.md``."""
    cmd = "python bench/compare.py " + " ".join(sys.argv[1:] if argv is None else argv)
    block = (f"{BEGIN}\n\nGenerated by `{cmd}` in {report['wall_s']:.0f} s "
             f"(seeds {report['config']['seeds']}, {report['config']['mc_draws']} Monte-Carlo draws).\n\n"
             f"{figure_links(path, img_dir)}{tables}\n{END}")
    why = check_markdown_target(path)
    if why:
        raise ValueError(why)
    if path.exists():
        text = path.read_text()
        a, b = text.index(BEGIN), text.index(END) + len(END)
        path.write_text(text[:a] + block + text[b:])
        return
    path.write_text(block + "\n")


def text_table(report: dict) -> str:
    out = [f"{'method':<16}{'sphere mg':>11}{'heldout mg':>12}{'fit ms':>9}{'CRLB eff':>10}{'poses':>7}{'failed':>8}"]
    for r in report["rows"]:
        out.append(f"{r['method']:<16}{fmt(r['sphere_norm_rms_mg']):>11}{fmt(r['heldout_rms_mg']):>12}"
                   f"{fmt(r['fit_ms']):>9}{fmt(r['crlb_efficiency']):>10}"
                   f"{(r['poses_needed'] if r['poses_needed'] is not None else '—'):>7}"
                   f"{str(r['n_failed']) + '/' + str(r['n_sets']):>8}")
    out.append(f"speedup_vs_seed_lm: {report['speedup_vs_seed_lm']:.1f}x (fit); "
               f"{report['speedup_end_to_end_vs_seed_lm']:.1f}x (whole online calibrator)")
    out.append("best: " + "; ".join(f"{k}: {v}" for k, v in report["best"].items()))
    return "\n".join(out)


def plots(report: dict, curves: dict, outdir: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    outdir.mkdir(parents=True, exist_ok=True)
    rows = report["rows"]
    methods = [r["method"] for r in rows]
    fams = report["sim_families"]
    written = []
    fig, ax = plt.subplots(figsize=(11, 4.8))
    width = 0.8 / len(fams)
    x = np.arange(len(methods))
    for i, f in enumerate(fams):
        v = [r["by_dataset"].get(f, {}).get("sphere_norm_rms_mg") or np.nan for r in rows]
        ax.bar(x + (i - (len(fams) - 1) / 2) * width, v, width, label=f)
    ax.set_yscale("log")
    ax.set_xticks(x, methods, rotation=40, ha="right")
    ax.set_ylabel("sphere norm RMS (mg), median over seeds")
    ax.axhline(THRESHOLD_MG, color="k", lw=0.6, ls=":")
    ax.set_title("Calibrated-norm error over the whole sphere, simulated sets (lower is better)")
    ax.legend(fontsize=8, ncol=3)
    fig.tight_layout()
    p = outdir / "compare_sphere_rms.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(str(p))

    fig, ax = plt.subplots(figsize=(8, 5))
    for m, (ns, v) in curves.items():
        ax.plot(ns, v, marker="o", ms=3, lw=2.2 if m == "selfcal" else 1.0, label=m,
                color="k" if m == "selfcal" else None)
    ax.set_yscale("log")
    ax.axhline(THRESHOLD_MG, color="k", lw=0.6, ls=":")
    ax.set_xlabel("number of poses (prefix of a well-spread sequence)")
    ax.set_ylabel("sphere norm RMS (mg), median over seeds")
    ax.set_title("Error vs number of poses")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    p = outdir / "compare_vs_poses.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(str(p))

    reals = report["real_sets"]
    fig, ax = plt.subplots(figsize=(11, 4.8))
    width = 0.8 / max(len(reals), 1)
    for i, f in enumerate(reals):
        v = [r["by_dataset"].get(f, {}).get("heldout_rms_mg") or np.nan for r in rows]
        ax.bar(x + (i - (len(reals) - 1) / 2) * width, v, width, label=f)
    ax.set_yscale("log")
    ax.set_xticks(x, methods, rotation=40, ha="right")
    ax.set_ylabel("held-out norm RMS (mg), mean of 2 splits")
    ax.set_title("Real recordings: held-out calibrated-norm error (lower is better)")
    ax.legend(fontsize=8, ncol=3)
    fig.tight_layout()
    p = outdir / "compare_heldout_real.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(str(p))
    return written


# --------------------------------------------------------------------------- main


def _median(v):
    v = [x for x in v if x is not None and np.isfinite(x)]
    return float(np.median(v)) if v else None


def build_report(args) -> tuple[dict, dict]:
    t_start = time.perf_counter()
    quick = args.quick
    seeds = list(range(args.seeds if args.seeds else (2 if quick else 5)))
    draws = args.draws if args.draws else (50 if quick else 300)
    grow_seeds = list(range(1 if args.tiny else (3 if quick else 10)))
    methods = [m for m in METHOD_ORDER if m.startswith("selfcal") or m in BASELINES]
    if args.methods:
        methods = [m for m in methods if m in args.methods.split(",") or m == "selfcal"]
    if "ggir_actipy" in methods and importlib.util.find_spec("actipy") is None:
        methods.remove("ggir_actipy")
        log("actipy is not installed (opt-in extra 'compare', Academic Use Licence): ggir_actipy skipped")
    if "ggir_actipy" in methods:  # warm-up: the first call imports pandas/statsmodels
        warm = sim_spread(99)
        run_baseline("ggir_actipy", warm, quick)

    # ---- data
    log(f"building data sets (seeds {seeds})")
    sims: list[PoseSet] = []
    families = ["sim_spread", "sim_spread+fx", "sim_mix", "sim_flat", "sim_flat+fx"]
    if args.tiny:
        families = ["sim_spread", "sim_flat+fx"]
    for s in seeds:
        for fam in families:
            fx = fam.endswith("+fx")
            base = fam.replace("+fx", "")
            ps = {"sim_spread": sim_spread, "sim_mix": sim_mix, "sim_flat": sim_flat}[base](s, fx)
            sims.append(ps)
    reals, skipped = ([], []) if args.no_real else real_sets(max_poses=400 if quick else None, log=log)
    if args.tiny:
        reals = reals[:1]

    # optional: selfcal with the model selfcal.diagnose selects, on the hidden-effect sets
    diag_ok = False
    if args.effect_row:
        try:
            from selfcal.diagnosis import diagnose_poses  # noqa: F401

            diag_ok = True
        except Exception as exc:  # noqa: BLE001
            log(f"selfcal.diagnose not usable ({exc}); no selfcal+effect row")
    if diag_ok:
        from selfcal.diagnosis import diagnose_poses

        for ps in sims:
            if ps.effects:
                try:
                    rep = diagnose_poses(ps.mean, ps.sd, ps.n, ps.t_s, ps.temp_c)
                    cause = rep.get("cause")
                    ps.__dict__["_diag_model"] = "affine9" + (f"+{cause}" if isinstance(cause, str) else "")
                except Exception as exc:  # noqa: BLE001
                    log(f"diagnose failed on {ps.name}: {exc}")
        methods = methods[:1] + ["selfcal+effect"] + methods[1:]

    res: dict[str, dict[str, dict]] = {m: {} for m in methods}  # method -> set name -> metrics
    # ---- accuracy on every set (one fit each) + held-out splits
    for ps in sims + reals:
        log(f"{ps.name}: {len(ps)} poses ({ps.note})")
        for m in methods:
            if m == "selfcal+effect" and not ps.effects:
                continue
            cal = run(m, ps, quick)
            if cal.fit_ms < 60:  # timing: best of 3 (the machine is shared); slow methods once
                for _ in range(2):
                    again = run(m, ps, quick)
                    cal.fit_ms, cal.e2e_ms = min(cal.fit_ms, again.fit_ms), min(cal.e2e_ms, again.e2e_ms)
            d = {"fit_ms": cal.fit_ms, "e2e_ms": cal.e2e_ms, "failed": cal.failed, "message": cal.message[:200]}
            if ps.kind == "sim":
                d["sphere_norm_rms_mg"] = sphere_rms(ps, cal)
                d["pose_dir_rms_mg"] = pose_dir_rms(ps, cal)
            if ps.kind == "real" or not args.no_sim_heldout:
                h = heldout(m, ps, quick)
                d.update(heldout_pose_rms_mg=h["pose"], heldout_time_rms_mg=h["time"],
                         pose_failed=h["pose_failed"], time_failed=h["time_failed"],
                         heldout_rms_mg=0.5 * (h["pose"] + h["time"]))
            res[m][ps.name] = d

    # ---- CRLB efficiency (clean sim families, Monte Carlo over noise draws)
    eff_sets = [ps for ps in sims if not ps.effects and (ps.name.endswith("/s0") or not quick)]
    eff: dict[str, dict[str, dict]] = {m: {} for m in methods}
    for ps in eff_sets:
        log(f"CRLB efficiency on {ps.name}: {draws} noise draws x {len(methods)} methods")
        ms = [m for m in methods if m != "selfcal+effect"]
        for m, e in efficiency(ps, ms, draws, quick, seed=_rng_for(ps.name)).items():
            eff[m][ps.name] = e

    # ---- poses needed (growing prefixes of well-spread sequences)
    log(f"poses needed: prefixes {POSES_GRID} x {len(grow_seeds)} seeds")
    grow = [growing_spread(s, max(POSES_GRID)) for s in grow_seeds]
    curves = {}
    needed = {}
    for m in methods:
        if m == "selfcal+effect":
            continue
        med = []
        for k in POSES_GRID:
            v = []
            for g in grow:
                sub = g.subset(np.arange(k))
                sub.name = f"{g.name}"  # same sphere points for every prefix
                v.append(sphere_rms(sub, run(m, sub, quick)))
            med.append(float(np.median(v)))
        curves[m] = (POSES_GRID, med)
        below = [k for k, v in zip(POSES_GRID, med) if v < THRESHOLD_MG]
        needed[m] = below[0] if below else None

    # ---- summary rows
    sim_fams = list(dict.fromkeys(ps.family for ps in sims))
    rows = []
    for m in methods:
        r = res[m]
        by: dict[str, dict] = {}
        for fam in sim_fams:
            names = [ps.name for ps in sims if ps.family == fam and ps.name in r]
            if not names:
                continue
            by[fam] = {
                "sphere_norm_rms_mg": _median([r[n]["sphere_norm_rms_mg"] for n in names]),
                "pose_dir_rms_mg": _median([r[n]["pose_dir_rms_mg"] for n in names]),
                "heldout_rms_mg": _median([r[n].get("heldout_rms_mg") for n in names]),
                "fit_ms": _median([r[n]["fit_ms"] for n in names]),
                "n_failed": int(sum(r[n]["failed"] for n in names)),
                "n_sets": len(names),
                "messages": sorted({r[n]["message"] for n in names if r[n]["failed"]})[:3],
            }
            e = [eff[m][ps.name] for ps in eff_sets if ps.family == fam and ps.name in eff.get(m, {})]
            if e:
                by[fam]["crlb"] = e[0] if len(e) == 1 else {
                    "mean": _median([x["mean"] for x in e]), "min": _median([x["min"] for x in e]),
                    "note": e[0]["note"] + f" (median over {len(e)} seeds)"}
        for ps in reals:
            if ps.name in r:
                by[ps.name] = {k: r[ps.name][k] for k in ("heldout_rms_mg", "heldout_pose_rms_mg", "heldout_time_rms_mg",
                                                          "pose_failed", "time_failed", "fit_ms", "failed", "message")}
        sim_names = [ps.name for ps in sims if ps.name in r]
        real_names = [ps.name for ps in reals if ps.name in r]
        spread_eff = by.get("sim_spread", {}).get("crlb") or {}
        rows.append({
            "method": m,
            "sphere_norm_rms_mg": _median([r[n]["sphere_norm_rms_mg"] for n in sim_names]),
            "pose_dir_rms_mg": _median([r[n]["pose_dir_rms_mg"] for n in sim_names]),
            "heldout_rms_mg": _median([r[n]["heldout_rms_mg"] for n in real_names]) if real_names else None,
            "heldout_pose_rms_mg": _median([r[n]["heldout_pose_rms_mg"] for n in real_names]) if real_names else None,
            "heldout_time_rms_mg": _median([r[n]["heldout_time_rms_mg"] for n in real_names]) if real_names else None,
            "fit_ms": _median([r[n]["fit_ms"] for n in sim_names + real_names]),
            "end_to_end_ms": _median([r[n]["e2e_ms"] for n in sim_names + real_names]),
            "crlb_efficiency": spread_eff.get("mean"),
            "crlb_efficiency_min": spread_eff.get("min"),
            "crlb_efficiency_note": spread_eff.get("note", "not computed (effect sets only)"),
            "poses_needed": needed.get(m),
            "n_failed": int(sum(r[n]["failed"] for n in sim_names + real_names)),
            "n_sets": len(sim_names + real_names),
            "by_dataset": by,
        })
    common = [ps.name for ps in sims + reals if ps.name in res["selfcal"] and ps.name in res.get("seed_lm", {})]
    seed_ms = _median([res["seed_lm"][n]["fit_ms"] for n in common]) if "seed_lm" in res else None
    self_ms = _median([res["selfcal"][n]["fit_ms"] for n in common])
    self_e2e = _median([res["selfcal"][n]["e2e_ms"] for n in common])
    best = {}
    for fam in sim_fams:
        cand = [(r["by_dataset"][fam]["sphere_norm_rms_mg"], r["method"]) for r in rows if fam in r["by_dataset"]]
        best[fam] = min(cand)[1]
    for ps in reals:
        cand = [(r["by_dataset"][ps.name]["heldout_rms_mg"], r["method"]) for r in rows if ps.name in r["by_dataset"]]
        best[ps.name] = min(cand)[1]
    report = {
        "rows": rows,
        "speedup_vs_seed_lm": (seed_ms / self_ms) if seed_ms and self_ms else None,
        "speedup_end_to_end_vs_seed_lm": (seed_ms / self_e2e) if seed_ms and self_e2e else None,
        "seed_lm_fit_ms": seed_ms, "selfcal_fit_ms": self_ms, "selfcal_end_to_end_ms": self_e2e,
        "best": best,
        "sim_families": sim_fams,
        "real_sets": [ps.name for ps in reals],
        "efficiency_families": list(dict.fromkeys(ps.family for ps in eff_sets)),
        "datasets": [{"name": ps.name, "kind": ps.kind, "unit": ps.unit, "n_poses": len(ps), "note": ps.note}
                     for ps in sims + reals],
        "skipped_datasets": skipped,
        "config": {"quick": quick, "seeds": seeds, "mc_draws": draws, "growing_seeds": grow_seeds,
                   "poses_grid": POSES_GRID, "threshold_mg": THRESHOLD_MG,
                   "selfcal_effect_row": diag_ok},
        "poses_curves": {m: v[1] for m, v in curves.items()},
        "wall_s": None,
    }
    report["wall_s"] = time.perf_counter() - t_start
    return report, curves


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="few seeds, 30 MC draws, quick DA (< 3 min)")
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    ap.add_argument("--plots", metavar="DIR", help="write compare_*.png into DIR")
    ap.add_argument("--markdown", metavar="FILE", action="append", default=[],
                    help="write the results block (tables + figure links) between the compare:begin/end markers "
                         "of FILE, or into a new FILE; repeat for several files (e.g. docs/compare.md and README.md)")
    ap.add_argument("--seeds", type=int, help="seeds per simulated family (default 2 quick, 5 full)")
    ap.add_argument("--draws", type=int, help="Monte-Carlo noise draws for the CRLB efficiency (50 quick, 300 full)")
    ap.add_argument("--methods", help="comma-separated subset of baselines (selfcal always runs)")
    ap.add_argument("--no-real", action="store_true", help="skip the real recordings")
    ap.add_argument("--no-sim-heldout", action="store_true", help="held-out splits on real sets only")
    ap.add_argument("--effect-row", action="store_true",
                    help="add selfcal+effect (model chosen by selfcal.diagnose) on the hidden-effect sets")
    ap.add_argument("--tiny", action="store_true", help=argparse.SUPPRESS)  # smoke test
    args = ap.parse_args(argv)
    bad = [why for why in (check_markdown_target(Path(m)) for m in args.markdown) if why]
    if bad:  # before the (minutes-long) run, not after
        for why in bad:
            log(f"error: --markdown {why}")
        return 2
    report, curves = build_report(args)
    if args.plots:
        for p in plots(report, curves, Path(args.plots)):
            log(f"wrote {p}")
    tables = markdown(report) if args.markdown else ""
    for target in dict.fromkeys(args.markdown):  # each file once, same block, its own image paths
        write_markdown(Path(target), tables, report, argv, Path(args.plots) if args.plots else None)
        log(f"wrote {target}")
    if args.json:
        print(json.dumps(report, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else str(o)))
    else:
        print(text_table(report))
    log(f"wall time {report['wall_s']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
