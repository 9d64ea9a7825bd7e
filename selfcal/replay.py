"""Long-horizon replay: the online calibrator over simulated wear, measured against the truth.

The insole paper's protocol (``refit_every_days > 0``): 30 days of normal use, a
refit every 3 days from the poses collected in those days, the first from a random
initial value in [0, 1] per parameter, each later one warm-started from the previous
(selfcal's sequential MAP update). The calibrator's own scheduler is switched off; the
replay calls ``refit()`` at each boundary. With ``refit_every_days = 0`` the
calibrator runs as shipped, with its own scheduler.

Levels:

* ``poses`` (default): the simulator's still windows are fed with ``feed_poses``
  (the detector is skipped; windows whose per-axis sd exceeds the detector's
  ``sd_max_g`` are dropped as the detector would). 30 days take seconds.
* ``samples``: the full 20 Hz stream goes through the detector with ``feed_samples``
  (about 2.5 µs per sample; 30 days ≈ 52 M samples take minutes).

Metrics (every refit, and the initial model), against the simulation truth:

* ``param_rel_error``: mean over the 9 base parameters of ``|est − true| / |true|``,
  the paper's measure. The truth is in the canonical identifiable form (QR factor).
* ``sphere_norm_rms_mg``: RMS of ``‖a_cal‖ − 1 g`` over 2000 directions spread on the
  whole sphere, for the true sensor at the reference temperature, at the refit time.
* ``tilt_error_deg``: RMS roll/pitch error over every still pose of the replay,
  calibrated vs true. The reference is the truth in the sensor's canonical frame
  (``R_true (raw − b_true)``). The mounting rotation that norms cannot see (method.md
  §1) is excluded; it needs a reference direction and is not a calibration error.
* ``n_poses``, ``fit_ms``, ``status``, the refit outcome.

A recorded file (:func:`replay_recording`, ``selfcal replay --recording FILE``) is
streamed in blocks through the online calibrator as shipped, exactly as ``selfcal
calibrate`` streams it, and every version it publishes is scored against the truth
``selfcal simulate --out FILE`` wrote beside it (:mod:`selfcal.scoring`, the scores of
``bench/consistency.py``).
"""

from __future__ import annotations

import contextlib
import copy
import json
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from selfcal import model_numba, sums_numba
from selfcal.attitude import roll_pitch_deg
from selfcal.calibrator import OnlineCalibrator
from selfcal.config import section
from selfcal.errors import InputError
from selfcal.fit import sphere_directions
from selfcal.models import ErrorModel
from selfcal.sim import SimConfig, Simulation, canonical_qr, plan_numba, sensor_mean
from selfcal.soak import find_soaks

SECONDS_PER_DAY = 86400.0
_AFFINE9 = ErrorModel("affine9")
BASE_NAMES = _AFFINE9.param_names


#: Tilt is scored on at most this many still windows, evenly spaced in time (a month
#: has ~260 000): the RMS of 20 000 has a relative standard error of ~0.5 %, and the
#: cost of a row no longer grows with the replay's length.
TILT_WINDOWS_MAX = 20_000


class TruthMetrics:
    """Metrics of a model (normalised = g units) against a simulated sensor's truth."""

    def __init__(self, sim: Simulation, poses, max_windows: int = TILT_WINDOWS_MAX, rows: np.ndarray | None = None):
        """``rows`` (int, ascending): the windows of ``poses`` that count (default all); the
        tilt is scored on every ``ceil(len(rows) / max_windows)``-th of them."""
        self.sensor = sim.truth.sensor
        self.truth_params = np.array([self.sensor.params()[n] for n in BASE_NAMES])
        q, _ = canonical_qr(self.sensor.matrix)
        self.q = q
        self.dirs = sphere_directions()
        rows = np.arange(len(poses.t_s)) if rows is None else np.asarray(rows)
        stride = max(1, -(-len(rows) // max_windows))
        pick = rows[::stride]
        poses = SimpleNamespace(**{k: getattr(poses, k)[pick] for k in ("mean_g", "temp_c", "t_s", "a_true_g")})
        self.poses = poses
        # reference for tilt: the truth in the sensor's canonical frame
        self.a_ref = poses.a_true_g @ q  # rows: Q^T a
        self.roll_ref, self.pitch_ref = roll_pitch_deg(self.a_ref)

    def __call__(self, model: ErrorModel, theta_u: np.ndarray, t_s: float) -> dict[str, float]:
        theta_u = np.asarray(theta_u, dtype=float)
        # another base (seed9, scale6) as the affine9 parameters of the same linear map
        base = theta_u[: len(BASE_NAMES)] if model.base == "affine9" else _AFFINE9.from_linear(*model.linear(theta_u))
        truth_params = self.truth_params
        if np.isfinite(self.sensor.step_at_s) and t_s >= self.sensor.step_at_s:  # the sensor as it now is
            truth_params = np.array([self.sensor.params_at(t_s)[n] for n in BASE_NAMES])
        rel = np.abs(base[:9] - truth_params) / np.maximum(np.abs(truth_params), 1e-12)
        n = len(self.dirs)
        temp = np.full(n, self.sensor.temp_ref_c)
        tt = np.full(n, float(t_s))
        raw = sensor_mean(self.sensor, self.dirs, temp, tt)
        a = model.apply(theta_u, raw, temp, tt)
        sphere = float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - 1) ** 2)) * 1e3)
        p = self.poses
        a_cal = model.apply(theta_u, p.mean_g, p.temp_c, p.t_s)
        roll, pitch = roll_pitch_deg(a_cal)
        droll = (roll - self.roll_ref + 180) % 360 - 180
        dpitch = pitch - self.pitch_ref
        tilt = float(np.sqrt(np.mean(np.concatenate([droll, dpitch]) ** 2)))
        return {"param_rel_error": float(np.mean(rel)), "sphere_norm_rms_mg": sphere, "tilt_error_deg": tilt}


class StageClock:
    """Wall time by stage of one replay (s): ``with clock("name"): ...`` adds the block's
    time to ``name``. The stages of :func:`replay`: ``simulation`` (the plan, the still
    windows, and at the samples level the 20 Hz stream), ``detector`` (the one detection
    both calibrators share at the samples level), ``protocol`` (the protocol calibrator's
    feeds and refits, its model checks included), ``as_shipped`` (the calibrator as shipped,
    until it says ``calibrated``) and ``scores`` (the metrics against the truth). Wall
    time: a process that waits for a core counts the wait in the stage it is in. The
    stages start with the simulation, and the result's ``wall_s`` after it (and after the
    truth's scorer is built), so the stages can add up to more than ``wall_s``."""

    STAGES = ("simulation", "detector", "protocol", "as_shipped", "scores")

    def __init__(self):
        self._s = dict.fromkeys(self.STAGES, 0.0)

    @contextlib.contextmanager
    def __call__(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._s[name] += time.perf_counter() - t0

    def seconds(self) -> dict[str, float]:
        """``{stage: s}``, every stage of :data:`STAGES`."""
        return dict(self._s)


def _protocol_config(config: dict, refit_every_days: float) -> dict:
    cfg = copy.deepcopy(config or {})
    if refit_every_days > 0:  # the replay decides when to refit
        sched = cfg.setdefault("scheduler", {})
        sched.update(refit_every_poses=10**9, refit_every_windows=10**9, refit_every_hours=1e9, min_poses_first=10**9)
    return cfg


def _calibrated(ev: dict) -> bool:
    return bool(ev["published"] and ev["calibration"]["status"] == "calibrated")


def first_calibrated_h_of(cal: OnlineCalibrator, mean_g, sd_g, n, t_s, temp_c, piece: int | None = None) -> float | None:
    """Feed poses to ``cal`` in order until a refit publishes ``calibrated``; the time of
    that refit (h), or None if none did.

    The poses go in one call that stops at that refit (``feed_poses(until=...)``), so the
    refits after it, which nothing reads, are not made. ``piece``: feed them that many at
    a time instead (the same hour: a calibrator's outcomes do not depend on how its poses
    are split into calls; pieces of 256 were the replay's way before ``until``, and cost
    an add to the pose store each).

    Parameters
    ----------
    mean_g, sd_g : ndarray, shape (k, 3), g; n : (k,) samples; t_s : (k,) s; temp_c : (k,) degC
    """
    step = len(t_s) if piece is None else int(piece)
    for i in range(0, len(t_s), max(step, 1)):
        sl = slice(i, i + max(step, 1))
        for ev in cal.feed_poses(mean_g[sl], sd_g[sl], n[sl], t_s[sl], temp_c[sl], until=_calibrated):
            if _calibrated(ev):
                return float(ev["t_s"]) / 3600.0
    return None


def period_ends(days: float, refit_every_days: float) -> np.ndarray:
    """The replay's period ends (days): every ``refit_every_days`` (1 day with 0, the
    calibrator's own scheduler), and ``days`` itself when the last period is shorter (its
    poses are fed and refitted too)."""
    step = refit_every_days if refit_every_days > 0 else 1.0
    ends = np.arange(step, days + 1e-9, step)
    if len(ends) == 0 or ends[-1] < days - 1e-9:
        ends = np.r_[ends, days]
    return ends


def _config_digest(config: dict | None) -> str:
    """SHA-256 of a configuration (its JSON, keys sorted): tells a checkpoint's run apart."""
    import hashlib

    return hashlib.sha256(json.dumps(config or {}, sort_keys=True, default=str).encode()).hexdigest()


def read_checkpoint(path: Path, run_key: dict[str, Any]) -> dict[str, Any]:
    """A replay checkpoint written by a run with the inputs ``run_key``; InputError naming the
    file and what differs otherwise (a checkpoint of another run is never resumed, nor
    silently overwritten)."""
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"--checkpoint {path}: not a readable replay checkpoint ({type(exc).__name__}: {exc})") from None
    keys = ("run", "done_until", "refits", "first_calibrated_h", "calibrator", "online")
    if not isinstance(state, dict) or not all(k in state for k in keys) or not isinstance(state["run"], dict):
        raise InputError(f"--checkpoint {path}: not a replay checkpoint of this selfcal version (it lacks "
                         f"{', '.join(k for k in keys if not isinstance(state, dict) or k not in state) or 'run'}); "
                         "delete it or choose another file")
    differ = [f"{k} {state['run'].get(k)!r} there, {v!r} now" for k, v in run_key.items() if state["run"].get(k) != v]
    if differ:
        raise InputError(f"--checkpoint {path}: written by another run ({'; '.join(differ)}); resume it with the "
                         "same options, or choose another file")
    return state


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def replay(
    days: float = 30.0,
    refit_every_days: float = 3.0,
    seed: int = 0,
    *,
    config: dict | None = None,
    effects: tuple[str, ...] = (),
    model: str = "affine9",
    level: str = "poses",
    random_init: bool = True,
    checkpoint: str | Path | None = None,
    progress: bool = False,
    soaks: bool = True,
) -> dict[str, Any]:
    """Replay one simulated device; returns ``{"initial": {...}, "refits": [...], ...}``.

    Parameters
    ----------
    days : float — simulated days of wear
    refit_every_days : float — the paper's protocol period; 0 = the calibrator's own scheduler
    seed : int — simulation (and random initial value) seed
    config : dict — loaded configuration (sections ``sim`` and the calibrator's)
    effects : names of sensor effects the simulator switches on
    model : str — the calibrator's model
    level : ``"poses"`` or ``"samples"``
    random_init : bool — start from a random value in [0, 1] per parameter (the paper's test)
    checkpoint : path — JSON checkpoint written after every refit; resumed if it exists
    progress : bool — progress bar on stderr
    soaks : bool — False drops every still window that belongs to a thermal soak
        (:func:`selfcal.soak.find_soaks`: one orientation while the temperature changes by
        ≥ 1 °C), to measure what soaks bring; only at the ``poses`` level

    Besides the base metrics, every row carries the model's effect terms (``effect_terms``:
    estimate, sd and whether determined, in the recording's unit per °C or per day), and
    the result has, per term, the truth, the first day it was determined and its final
    error (``effect_summary``).
    """
    if level not in ("poses", "samples"):
        raise ValueError(f"level: expected 'poses' or 'samples', got {level!r}")
    if not (np.isfinite(days) and days > 0):
        raise InputError(f"days = {days!r}: must be a finite number > 0")
    if not (np.isfinite(refit_every_days) and refit_every_days >= 0):
        raise InputError(f"refit_every_days = {refit_every_days!r}: must be a finite number >= 0 (0: the "
                         "calibrator's own scheduler)")
    config = config or {}
    sim_cfg = SimConfig.from_section(section(config, "sim"))
    if effects:
        sim_cfg = sim_cfg.with_effects(list(effects))
    clock = StageClock()
    if days >= plan_numba.LOAD_FOR_DAYS:  # the fits' and the store's kernels pay for their load over a run this long
        model_numba.load()
        sums_numba.load()
    rng = np.random.default_rng(seed)
    with clock("simulation"):
        sim = Simulation(sim_cfg, rng, days=days, seed=seed)
        poses = sim.poses(pressure=False)  # (no calibrator takes a window's pressure)
    cal_cfg = _protocol_config(config, refit_every_days)
    sd_max = float(section(cal_cfg, "detector").get("sd_max_g", 0.010))
    keep = np.all(poses.sd_g <= sd_max, axis=1)

    soak_info = {"dropped": not soaks, "n_soaks": 0, "n_windows": 0}
    if not soaks:
        if level != "poses":
            raise ValueError("soaks=False works at the poses level (the detector's windows are not filtered)")
        keep_idx = np.flatnonzero(keep)
        keep_idx = keep_idx[np.argsort(poses.t_s[keep_idx], kind="stable")]
        runs = find_soaks(poses.t_s[keep_idx] + poses.duration_s[keep_idx] / 2, poses.mean_g[keep_idx],
                          poses.temp_c[keep_idx])
        for run in runs:
            keep[keep_idx[run]] = False
        soak_info.update(n_soaks=len(runs), n_windows=int(sum(r.stop - r.start for r in runs)))
    # the windows kept are taken period by period (below), not copied into a second table
    # of the whole run (a year's is ~0.5 GB, most of its cost memory touched for the first time)
    kept = np.flatnonzero(keep)
    with clock("scores"):
        metrics = TruthMetrics(sim, poses, rows=kept)
    init_rng = np.random.default_rng([seed, 1])
    theta0 = init_rng.uniform(0.0, 1.0, ErrorModel(model).n_params) if random_init else None
    cal = OnlineCalibrator(cal_cfg, model, initial_params_u=theta0)
    online = OnlineCalibrator(config, model)  # as shipped: for the time to 'calibrated'
    start_theta = theta0 if theta0 is not None else cal.model.nominal()
    initial = dict(day=0.0, **metrics(cal.model, start_theta, 0.0), n_poses=0, fit_ms=None,
                   status="uncalibrated", published=None, reason=None)
    refits: list[dict] = []
    first_calibrated_h = None
    boundaries = period_ends(days, refit_every_days)
    done_until = 0.0
    ckpt = Path(checkpoint) if checkpoint else None
    run_key = {"seed": seed, "days": days, "refit_every_days": refit_every_days, "level": level, "model": model,
               "random_init": random_init, "soaks": soaks, "effects": sorted(effects),
               "config_sha256": _config_digest(config)}
    if ckpt and ckpt.exists():
        state = read_checkpoint(ckpt, run_key)
        cal = OnlineCalibrator.from_json(state["calibrator"])
        online = OnlineCalibrator.from_json(state["online"])
        refits, done_until, first_calibrated_h = state["refits"], state["done_until"], state["first_calibrated_h"]
    bar = None
    if progress:
        from tqdm import tqdm

        # the periods a resumed run had done count as done, not as this run's speed (ETA)
        bar = tqdm(total=len(boundaries), initial=int(np.sum(boundaries <= done_until + 1e-9)),
                   desc=f"replay seed {seed}", unit="period", file=sys.stderr)
    t0_wall = time.perf_counter()
    base_name = ErrorModel(model).base
    last_cal = cal.calibration()
    # (the calibrators take what a device sends: the truth columns are not streamed)
    sample_iter = sim.iter_samples(chunk_s=3600, truth=False) if level == "samples" else None
    # resumed: the periods done took every chunk that starts before their end; the
    # simulation streams them again from its start, and they are not fed twice
    fed_until_s = done_until * SECONDS_PER_DAY
    shared_detector = cal.det_cfg == online.det_cfg
    pending = None
    prev = 0.0
    # in time order, a period's windows are a slice of the table (two searches, not two
    # passes over the run), of which the kept ones are fed; else a mask picks the same rows
    in_time_order = bool(np.all(np.diff(poses.t_s) >= 0))
    for b in boundaries:
        lo, hi, prev = prev * SECONDS_PER_DAY, b * SECONDS_PER_DAY, b
        if b <= done_until + 1e-9:
            continue
        if in_time_order:
            i0, i1 = np.searchsorted(poses.t_s, [lo, hi], side="left")
            sel = int(i0) + np.flatnonzero(keep[int(i0):int(i1)])
        else:
            sel = keep & (poses.t_s >= lo) & (poses.t_s < hi)
        if level == "poses":
            args = (poses.mean_g[sel], poses.sd_g[sel], poses.n[sel], poses.t_s[sel] + poses.duration_s[sel] / 2,
                    poses.temp_c[sel])
            with clock("protocol"):
                events = cal.feed_poses(*args)
            if first_calibrated_h is None:  # the as-shipped calibrator is only timed to 'calibrated'
                with clock("as_shipped"):
                    first_calibrated_h = first_calibrated_h_of(online, *args)
        else:
            events = []
            while True:
                if pending:
                    chunk = pending
                else:
                    with clock("simulation"):
                        chunk = next(sample_iter, None)
                pending = None
                if chunk is None:
                    break
                if len(chunk) == 0 or chunk.t_s[-1] < fed_until_s:
                    continue
                if chunk.t_s[0] < fed_until_s:  # resumed: its rows before the periods done were fed
                    chunk = chunk.split(fed_until_s)[1]
                if chunk.t_s[0] >= hi:
                    pending = chunk
                    break
                if chunk.t_s[-1] >= hi:  # a chunk holds whole segments: its rows from hi on are the next period's
                    chunk, pending = chunk.split(hi)
                if first_calibrated_h is None and shared_detector:
                    # one detection for both calibrators (the same [detector] settings): the
                    # as-shipped one gets the protocol calibrator's windows
                    with clock("detector"):
                        windows = cal.detector.feed(chunk.t_s, chunk.acc_g, temp_c=chunk.temp_c,
                                                    pressure_kpa=chunk.pressure_kpa, to_cal=None)
                    with clock("protocol"):
                        events += cal.feed_windows(windows, len(chunk.t_s))
                    with clock("as_shipped"):
                        online.feed_windows(windows, len(chunk.t_s))
                else:  # each calibrator's own detector (its time is in that calibrator's)
                    with clock("protocol"):
                        events += cal.feed_samples(chunk.t_s, chunk.acc_g, chunk.temp_c, chunk.pressure_kpa)
                    if first_calibrated_h is None:
                        with clock("as_shipped"):
                            online.feed_samples(chunk.t_s, chunk.acc_g, chunk.temp_c, chunk.pressure_kpa)
                if first_calibrated_h is None and online.status == "calibrated":
                    first_calibrated_h = float(chunk.t_s[-1]) / 3600.0
                if pending is not None:  # the period ends inside this chunk
                    break
        cal.t_last_s = hi
        if refit_every_days > 0:
            with clock("protocol"):
                events = [cal.refit()]
        for ev in events:
            if ev["published"]:  # the effect terms as published at this event (rows' other metrics: period end)
                last_cal = ev["calibration"]
            cur = cal.current
            theta = np.asarray(cur["theta_u"]) if cur else start_theta
            with clock("scores"):
                scores = metrics(cal.model, theta, ev["t_s"])
            row = dict(day=float(ev["t_s"] / SECONDS_PER_DAY), **scores,
                       n_poses=len(cal.buffer), fit_ms=ev.get("fit_ms"), status=cal.status,
                       published=ev["published"], reason=ev["reason"], mode=ev.get("mode"),
                       effect_terms=_effect_terms(last_cal, base_name), model=(last_cal or {}).get("model", model))
            if ev.get("model_change"):
                row["model_change"] = ev["model_change"]
            if ev.get("bias_step"):
                row["bias_step"] = ev["bias_step"]
            refits.append(row)
        done_until = b
        if ckpt:
            _atomic_write(ckpt, json.dumps({
                "run": run_key, "seed": seed, "days": days, "effects": list(effects), "done_until": done_until,
                "refits": refits, "first_calibrated_h": first_calibrated_h,
                "calibrator": cal.to_json(), "online": online.to_json()}))
        if bar:
            bar.update(1)
    if bar:
        bar.close()
    truth = sim.truth.sensor
    final = cal.calibration()
    return {
        "seed": seed,
        "days": days,
        "refit_every_days": refit_every_days,
        "level": level,
        "model": model,
        "effects": list(effects),
        "initial": initial,
        "refits": refits,
        "time_to_calibrated_h": first_calibrated_h,
        "n_still_windows": int(len(kept)),
        "wall_s": time.perf_counter() - t0_wall,
        "stage_s": clock.seconds(),
        "truth": {"params": truth.params(), "effects": truth.model_params(),
                  "bias_step": None if not np.isfinite(truth.step_at_s) else {
                      "t_s": truth.step_at_s, "day": truth.step_at_s / SECONDS_PER_DAY,
                      "size_mg": truth.effects["bias_step"].tolist()}},
        "soaks": soak_info,
        "model_final": cal.model.name,
        "selection_checks": int(cal.selection.get("n_checks", 0)),
        "model_switches": [dict(r["model_change"], day=r["day"]) for r in refits if r.get("model_change")],
        "bias_steps": [dict(r["bias_step"], day=r["day"]) for r in refits if r.get("bias_step")],
        "bias_steps_final": [dict(x) for x in cal.selection.get("steps", [])],
        "effect_summary": effect_summary(refits, truth.model_params()),
        "final": None if final is None else {k: final[k] for k in ("params", "std", "status", "version", "undetermined")},
    }


def _effect_terms(c: dict | None, base: str) -> dict[str, dict]:
    """A published calibration's effect terms: ``{name: {"est", "sd", "determined"}}`` (recording unit)."""
    if c is None:
        return {}
    names = [n for n in c["params"] if n not in ErrorModel(base).param_names]
    det = set(c.get("determined", []))
    return {n: {"est": float(c["params"][n]), "sd": float(c["std"][n]), "determined": n in det} for n in names}


def effect_summary(rows: list[dict], truth_effects: dict[str, float]) -> dict[str, dict]:
    """Per effect term of the replayed model: the truth, the first day it was determined
    (None: never), and the final estimate's error, absolute and in its reported sd."""
    out: dict[str, dict] = {}
    names = list(rows[-1].get("effect_terms", {})) if rows else []
    for n in names:
        first = next((r["day"] for r in rows if r.get("effect_terms", {}).get(n, {}).get("determined")), None)
        last = rows[-1]["effect_terms"][n]
        true = float(truth_effects.get(n, 0.0))
        err = last["est"] - true
        out[n] = {"true": true, "first_determined_day": first, "final": last["est"], "final_sd": last["sd"],
                  "final_error": err, "final_error_sd": abs(err) / last["sd"] if last["sd"] > 0 else float("nan")}
    return out


def step_summary(results: list[dict]) -> dict:
    """Bias steps found by the replays of a fleet, against the simulated ones.

    A device with a true step has it *found* when a step is published after the true time;
    a step published before it (or on a device without one) is *false*. For the devices
    where it is found: the delay (days from the step to the first publication), the error
    of the step's time (h) and of its size (mg, the largest axis; and whether every axis is
    within 2 of its reported sds), as re-estimated at the end of the replay.
    """
    delays, t_err, size_err, size_z, size_sd, false, with_step, found = [], [], [], [], [], 0, 0, 0
    for r in results:
        true = (r.get("truth") or {}).get("bias_step")
        pubs = r.get("bias_steps", [])
        if true is None:
            false += len(pubs) > 0
            continue
        with_step += 1
        false += any(p["found_t_s"] < true["t_s"] for p in pubs)
        after = [p for p in pubs if p["found_t_s"] >= true["t_s"]]
        if not after:
            continue
        found += 1
        delays.append((after[0]["found_t_s"] - true["t_s"]) / SECONDS_PER_DAY)
        final = min(r.get("bias_steps_final") or after, key=lambda p: abs(p["t_step_s"] - true["t_s"]))
        t_err.append(abs(final["t_step_s"] - true["t_s"]) / 3600.0)
        err = np.subtract(final["size_mg"], true["size_mg"])
        size_err.append(float(np.max(np.abs(err))))
        size_sd.append(float(np.max(final["sd_mg"])))
        with np.errstate(divide="ignore"):
            size_z.append(float(np.max(np.abs(err) / np.asarray(final["sd_mg"], float))))
    med = lambda x: float(np.median(x)) if x else None  # noqa: E731
    return {"devices": len(results), "with_step": with_step, "found": found, "false": int(false),
            "median_delay_days": med(delays), "median_time_error_h": med(t_err),
            "median_size_error_mg": med(size_err), "max_size_error_mg": max(size_err) if size_err else None,
            "size_within_2sd": int(sum(z <= 2.0 for z in size_z)), "median_size_sd_mg": med(size_sd)}


def _replay_one(kwargs: dict) -> dict:
    """One device's replay, as every engine runs it: with one BLAS thread (restored after).

    A replay's linear algebra is on small matrices (a few thousand rows by ~12), where
    OpenBLAS's extra threads bring nothing and busy-wait between calls; with one replay
    process per core they took the cores the other replays needed (4 devices x 10 days on
    2 processes, 2 cores: 6.7-7.3 device-days/s with OpenBLAS's default of a thread per
    core, 9.7-10.7 with one; the same results). A process pool forks after numpy has
    loaded OpenBLAS, and a Ray or Dask worker is already running, so environment
    variables would come too late: threadpoolctl sets the loaded libraries' thread counts.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        try:
            return replay(**kwargs)
        except Exception as exc:  # the fleet's error names the device that failed
            exc.add_note(f"(the replay of the device with seed {kwargs.get('seed')})")
            raise


ENGINES = ("processes", "dask", "ray")


def check_engine(engine: str) -> None:
    """InputError unless ``engine`` is one of :data:`ENGINES` and its package is installed."""
    if engine not in ENGINES:
        raise InputError(f"--engine {engine!r}: choose one of {', '.join(ENGINES)}")
    import importlib.util

    if engine == "dask" and importlib.util.find_spec("distributed") is None:
        raise InputError("--engine dask needs dask's distributed scheduler (pip install 'selfcal[fleet]')")
    if engine == "ray" and importlib.util.find_spec("ray") is None:
        raise InputError("--engine ray needs ray (pip install 'selfcal[ray]')")


def replay_fleet(devices: int, seed: int, workers: int | None = None, progress: bool = False, *,
                 engine: str = "processes", scheduler: str | None = None, **kwargs) -> list[dict]:
    """Replay ``devices`` independent devices (seeds ``seed .. seed+devices-1``) in parallel.

    ``engine``: ``processes`` (a local process pool, the default), ``dask`` (a
    ``distributed`` cluster: the one at ``scheduler`` address, else a local cluster of
    ``workers`` single-threaded worker processes) or ``ray`` (the Ray cluster at ``scheduler``,
    else a local Ray of ``workers`` CPUs; extra ``ray``).
    Each device's replay is the same function with the same seed on every engine, so
    the results are identical (only the wall times ``wall_s``, ``stage_s`` and
    ``fit_ms`` differ). Returns the results in seed
    order; the progress bar (stderr) counts devices and shows the ETA.
    """
    check_engine(engine)
    if workers is not None and workers < 1:
        raise InputError(f"--workers {workers}: must be >= 1")
    jobs = [dict(kwargs, seed=seed + i, progress=False) for i in range(devices)]
    workers = workers or min(devices, os.cpu_count() or 1)
    results: list[dict | None] = [None] * devices
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=devices, desc=f"devices ({engine})", unit="device", file=sys.stderr)

    def done(i: int, result: dict) -> None:
        results[i] = result
        if bar:
            bar.update(1)

    if engine == "dask":
        _run_dask(jobs, workers, scheduler, done)
    elif engine == "ray":
        _run_ray(jobs, workers, scheduler, done)
    elif workers <= 1:
        for i, job in enumerate(jobs):
            done(i, _replay_one(job))
    else:
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # loaded once here, the simulator planner's kernels (and at the samples level the
        # detector's and the stream's draws') come to every forked process; otherwise each
        # loads and checks them, or all compile them into an empty numba cache at once
        plan_numba.kernels(float(kwargs.get("days", 30.0)) * devices / workers)
        if float(kwargs.get("days", 30.0)) * devices / workers >= plan_numba.LOAD_FOR_DAYS:
            model_numba.load()  # the fits' and the store's kernels, likewise
            sums_numba.load()
        if kwargs.get("level") == "samples":
            from selfcal.detect_numba import kernels_now
            from selfcal.sim import draw_numba

            kernels_now()
            draw_numba.load()  # the stream's draws
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futs = {pool.submit(_replay_one, job): i for i, job in enumerate(jobs)}
            try:
                for fut in as_completed(futs):
                    done(futs[fut], fut.result())
            except BaseException:  # a device failed, or Ctrl-C: the devices not started are not run
                pool.shutdown(wait=False, cancel_futures=True)
                raise
    if bar:
        bar.close()
    return results  # type: ignore[return-value]


def _run_dask(jobs: list[dict], workers: int, scheduler: str | None, done) -> None:
    """Run the jobs on a Dask ``distributed`` cluster (a local one unless ``scheduler`` is given)."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise InputError("--engine dask needs dask's distributed scheduler "
                         "(pip install 'selfcal[fleet]')") from None
    cluster = None
    if scheduler:
        client = Client(scheduler)
    else:
        cluster = local_dask_cluster(workers)
        client = Client(cluster)
    try:
        futs = client.map(_replay_one, jobs, pure=False)
        index = {f.key: i for i, f in enumerate(futs)}
        for fut in as_completed(futs):
            done(index[fut.key], fut.result())
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def local_dask_cluster(workers: int):
    """A local Dask ``distributed`` cluster for replays: ``workers`` single-threaded worker
    processes (the replay is CPU-bound Python, one per core).

    Dask's nannies set MALLOC_TRIM_THRESHOLD_=65536 in their workers by default; glibc then
    returns freed memory at once, and the replay's many numpy temporaries cost mmap/munmap
    each: 1.5x slower per device, measured. Workers keep glibc's own policy (and their BLAS
    runs one thread during a replay: :func:`_replay_one`)."""
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.nanny.pre-spawn-environ": {}}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                            dashboard_address=None, silence_logs=40)


def _run_ray(jobs: list[dict], workers: int, scheduler: str | None, done) -> None:
    """Run the jobs as Ray tasks, one CPU each: on the cluster at ``scheduler``
    (``ray.init(address=...)``), in the Ray this process already joined, or else on a local
    Ray of ``workers`` CPUs, which is shut down when the jobs are done (as a local Dask
    cluster is)."""
    try:
        import ray
    except ImportError:
        raise InputError("--engine ray needs ray (pip install 'selfcal[ray]')") from None
    started = not ray.is_initialized()
    if started:
        local = {} if scheduler else {"num_cpus": workers, "include_dashboard": False}
        ray.init(address=scheduler, log_to_driver=False, **local)
    remote = ray.remote(num_cpus=1)(_replay_one)
    refs = [remote.remote(job) for job in jobs]
    index = {r: i for i, r in enumerate(refs)}
    pending = list(refs)
    try:
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for r in ready:
                done(index[r], ray.get(r))
    except BaseException:  # a device failed, or Ctrl-C: the others are cancelled
        for r in pending:
            ray.cancel(r)
        raise
    finally:
        if started:
            ray.shutdown()


def replay_recording(
    path: str | Path,
    model: str = "affine9",
    *,
    config: dict | None = None,
    truth: dict | None = None,
    progress: bool = False,
    block_rows: int = 100_000,
) -> dict[str, Any]:
    """Replay a recorded file through the online calibrator; score every published version.

    The file is streamed in blocks exactly as ``selfcal calibrate`` streams it
    (:func:`selfcal.pipeline.calibrate_path`): a samples table in g or m/s² is never read
    whole, so memory does not grow with its length (poses tables, device files and raw
    counts are read whole, as ``calibrate`` reads them). See :func:`score_recording_run`
    for the result.

    Parameters
    ----------
    path : recording file (selfcal CSV, samples or poses; a device file)
    model : str — the calibrator's model
    config : dict — loaded configuration
    truth : dict — the simulation truth (:func:`selfcal.scoring.load_truth`), or None
    progress : bool — progress bar by bytes read on stderr
    block_rows : int — rows per block read
    """
    from selfcal.pipeline import calibrate_path

    t0 = time.perf_counter()
    run = calibrate_path(path, model, config, progress=progress, block_rows=block_rows)
    out = score_recording_run(run, path, truth, block_rows=block_rows)
    out["wall_s"] = time.perf_counter() - t0
    return out


def score_recording_run(run, path: str | Path, truth: dict | None = None, block_rows: int = 100_000) -> dict[str, Any]:
    """A :class:`selfcal.pipeline.CalibrationRun` of ``path``: its versions, scored when ``truth`` is given.

    Returns ``{"recording", "model", "unit", "status", "n_windows", "notes", "versions",
    "summary"}``. Each of ``versions`` (in time order, as ``calibrate --history`` writes
    them) has ``version``, ``t_s``, ``status``, ``predicted_mg``, ``params`` and ``std``
    (the recording's unit); with a truth also ``true_mg`` and ``z`` (see
    :mod:`selfcal.scoring`). ``summary``: :func:`selfcal.scoring.run_figures` (over the
    truth's ``days``; the CRLB and the final target for a poses file, whose rows are the
    still windows, each with the noise model's variance: the recording does not hold the
    simulator's true noise, which ``bench/consistency.py`` takes from the simulator) and, with a truth, :func:`selfcal.scoring.consistency_figures`.
    """
    from selfcal.errors import InputError
    from selfcal.pipeline import published_versions
    from selfcal.scoring import (TruthScorer, consistency_figures, crlb_from_information, poses_file_information,
                                 run_figures, version_row)

    calibrations = published_versions(run)
    notes = list(run.notes)
    days = crlb = None
    if truth is None:
        rows = [version_row(c) for c in calibrations]
    else:
        if run.unit != truth.get("unit", "g"):
            raise InputError(f"{path}: the recording is in {run.unit}, its truth in {truth.get('unit', 'g')}; "
                             "a truth scores the simulated recording it was written with")
        if truth.get("recording") and truth["recording"] != Path(path).name:
            notes.append(f"the truth was written for {truth['recording']!r}, not {Path(path).name!r}")
        scorer = TruthScorer(truth, run.calibrator.model.name)
        rows = scorer.score_all(calibrations)
        days = truth.get("days")
        info = poses_file_information(path, scorer.model, scorer.truth_u, block_rows)
        if info is not None and info[1] > 0:
            last_t = rows[-1]["t_s"] if rows else info[2]
            crlb = crlb_from_information(scorer.model, scorer.truth_u, info[0], last_t)
    for row, c in zip(rows, calibrations):
        row["params"], row["std"] = c["params"], c["std"]
    summary = run_figures(rows, days, crlb)
    if truth is not None:
        summary.update(consistency_figures([rows]))
    return {
        "recording": str(path), "model": run.calibrator.model.name, "unit": run.unit, "status": run.status,
        "n_windows": int(run.n_windows), "notes": notes, "versions": rows, "summary": summary,
    }
