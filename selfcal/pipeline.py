"""Recording in, calibration out: the online calibrator run over a whole file.

Used by ``selfcal calibrate``, the benchmarks and the diagnosis. Recordings in g and
m/s² are converted exactly to g; raw counts (scale unknown) are first normalised
roughly from their percentiles, still windows are found, and a sphere fit of those
windows gives the counts-per-g scale and centre the calibrator then works in.
"""

from __future__ import annotations

import copy
import itertools
import sys
from dataclasses import dataclass, field

import numpy as np

from selfcal.calibrator import OnlineCalibrator
from selfcal.errors import InputError
from selfcal.fit import guess_normalizer, sphere_normalizer
from selfcal.io import Recording
from selfcal.models import ErrorModel, Normalizer

#: Samples per chunk when streaming a recording through the calibrator.
CHUNK_SAMPLES = 50_000


@dataclass
class CalibrationRun:
    """What :func:`calibrate_recording` produced.

    ``calibration`` is the contract JSON in the recording's unit (None if nothing
    was published); ``calibrator`` the online calibrator (normalised units, ~g);
    ``normalizer`` maps raw -> normalised units; ``events`` the refit outcomes.
    """

    calibration: dict | None
    status: str
    last_refit: dict | None
    calibrator: OnlineCalibrator
    normalizer: Normalizer
    n_windows: int
    events: list[dict]
    notes: list[str]
    unit: str = "g"
    meta: dict = field(default_factory=dict)  # the recording's preamble (device, sensor, rate, ...)


def _rough_counts_normalizers(acc: np.ndarray) -> list[Normalizer]:
    """Candidate counts -> roughly g maps for the detector, in the order they are tried
    (:func:`_counts_windows`; a sphere fit of the windows then refines the map chosen).

    * centre and half-spread between the 1st and 99th percentiles: right when the axes
      turn through +-1 g (a wrist), whatever the counts' offset;
    * signed about 0, the rows' median norm as the scale: right for a device that stays
      near one orientation (an insole: the first gave 1.5 counts/g where the truth was 256,
      and no still window passed the norm test).
    """
    lo, hi = np.percentile(acc, [1, 99], axis=0)
    out = []
    scale = float(np.median((hi - lo) / 2))
    if np.isfinite(scale) and scale > 0:
        out.append(Normalizer(tuple(float(c) for c in (hi + lo) / 2), scale))
    signed = float(np.median(np.linalg.norm(acc, axis=1)))
    if np.isfinite(signed) and signed > 0:
        out.append(Normalizer((0.0, 0.0, 0.0), signed))
    if not out:
        raise InputError("counts: the recording does not vary; cannot estimate counts per g")
    return out


def _counts_normalizer(means_counts: np.ndarray, rough: Normalizer) -> tuple[Normalizer, str]:
    """Counts per g from the still windows' means (counts): the sphere through them, unless
    they do not determine one (one orientation, as an insole's mostly are: the fit gave
    0.09 counts/g for 256), or its radius is not within a factor 2 of the ``rough`` map's
    scale; then the rough map itself. Returns ``(map, note)``."""
    try:
        sphere = sphere_normalizer(means_counts)
        if 0.5 <= sphere.scale / rough.scale <= 2.0:
            return sphere, (f"counts: sphere fit of {len(means_counts)} still windows gives {sphere.scale:.2f} "
                            f"counts/g, centre {np.round(sphere.center, 2).tolist()} counts")
        why = f"their sphere's radius {sphere.scale:.3g} counts is not near the rough {rough.scale:.3g}"
    except InputError as exc:
        why = str(exc).removeprefix("counts: ")
    return rough, (f"counts: {len(means_counts)} still windows do not determine a sphere ({why}): counts per g "
                   f"taken as {rough.scale:.2f} (the rows' median norm, signed counts), centre "
                   f"{np.round(rough.center, 2).tolist()}; the calibration refines both")


def _counts_windows(rec: Recording, cfg: dict):
    """The detector's still windows of a raw-counts recording under the first rough map (of
    :func:`_rough_counts_normalizers`, in their order) with which it finds enough of them
    for a sphere (4), else the one with which it finds the most: ``(map, windows)``. (The
    most windows is not the better map: a loose norm test passes more under a wrong scale.)"""
    best = None
    for rough in _rough_counts_normalizers(rec.acc):
        w = _windows_of(rough.to_u(rec.acc), rec, cfg)
        if len(w) >= 4:
            return rough, w
        if best is None or len(w) > len(best[1]):
            best = (rough, w)
    return best


def _detector_config(config: dict, rate_hz: float, loose_norm: bool) -> dict:
    cfg = copy.deepcopy(config or {})
    det = cfg.setdefault("detector", {})
    det["rate_hz"] = float(rate_hz)
    if loose_norm:
        det["norm_tol_raw_g"] = max(float(det.get("norm_tol_raw_g", 0.15)), 0.5)
    return cfg


def _poses_detector_config(config: dict, rate_hz: float) -> dict:
    """The configuration for a poses table of windows taken at ``rate_hz``: the detector never
    runs on it (its rate gives each window's duration), so ``max_gap_s`` is widened to two
    intervals when a slower rate would have the detector's own checks refuse it."""
    from selfcal.detect import DetectorConfig

    cfg = _detector_config(config, rate_hz, False)
    det = cfg["detector"]
    det["max_gap_s"] = max(float(det.get("max_gap_s", DetectorConfig().max_gap_s)), 2.0 / rate_hz)
    return cfg


def _pressure_kpa(rec: Recording) -> np.ndarray | None:
    """Pressure in kPa when the recording has cells in a known unit, else None."""
    return rec.pressure_kpa() if rec.pressure is not None and rec.pressure_unit in ("kpa", "ncm2") else None


def _chunks(rec: Recording, normalizer: Normalizer):
    """``(t_s, acc_u, temp_c, pressure_kpa)`` pieces of CHUNK_SAMPLES, normalised piece by piece
    (no whole-file float64 copy of the acceleration)."""
    pres = _pressure_kpa(rec)
    for i in range(0, len(rec.t_s), CHUNK_SAMPLES):
        sl = slice(i, i + CHUNK_SAMPLES)
        yield (rec.t_s[sl], normalizer.to_u(rec.acc[sl]), None if rec.temp_c is None else rec.temp_c[sl],
               None if pres is None else pres[sl])


def _windows_to_poses(w, normalizer: Normalizer) -> dict:
    """Still windows (normalised units) as a poses dict in the recording's unit."""
    return {
        "mean": w.mean_g * normalizer.scale + np.asarray(normalizer.center),
        "sd": w.sd_g * normalizer.scale,
        "count": w.n.astype(float),
        "t_s": 0.5 * (w.t_start_s + w.t_end_s),
        "temp_c": w.temp_c if np.any(np.isfinite(w.temp_c)) else None,
    }


def _windows_of(rec_u_acc, rec: Recording, cfg: dict):
    from selfcal.detect import StaticDetector, DetectorConfig, StillWindows

    det = StaticDetector(DetectorConfig.from_section(cfg.get("detector")))
    pres = _pressure_kpa(rec)
    parts = []
    for i in range(0, len(rec.t_s), CHUNK_SAMPLES):
        sl = slice(i, i + CHUNK_SAMPLES)
        parts.append(det.feed(rec.t_s[sl], rec_u_acc[sl], None if rec.temp_c is None else rec.temp_c[sl],
                              None if pres is None else pres[sl]))
    parts.append(det.flush())
    return StillWindows.concat(parts)


def recording_poses(rec: Recording, config: dict | None = None) -> tuple[dict, Normalizer, list[str]]:
    """Still poses of a recording in its own unit, and the normaliser to ~g.

    Samples tables: the still windows found by the detector (raw counts are first
    normalised roughly, then by a sphere fit of the windows). Poses tables: the rows.

    Returns
    -------
    poses : dict with ``mean``, ``sd`` (n, 3) raw unit; ``count``, ``t_s`` (window
        centre, s), ``temp_c`` (n,) or None
    normalizer : Normalizer
    notes : list of str
    """
    notes: list[str] = []
    if rec.kind == "samples":
        cfg = _detector_config(config or {}, rec.rate_hz(), rec.unit == "counts")
        if rec.unit == "counts":
            rough, w = _counts_windows(rec, cfg)
        else:
            rough = guess_normalizer(rec.unit)
            w = _windows_of(rough.to_u(rec.acc), rec, cfg)
        if len(w) == 0:
            raise InputError(f"{rec.path}: no still window found")
        poses = _windows_to_poses(w, rough)
        if rec.unit == "counts":
            normalizer, note = _counts_normalizer(poses["mean"], rough)
            return poses, normalizer, [note]
    else:
        if rec.n is not None:
            count = rec.n.astype(float)
        else:
            rate = float(rec.meta.get("rate_hz", 50.0))
            count = np.maximum(1.0, (rec.duration_s if rec.duration_s is not None else np.ones(len(rec))) * rate)
            notes.append(f"poses table without n: samples per window assumed = duration_s x {rate:g} Hz")
        poses = {"mean": rec.acc, "sd": rec.sd, "count": count, "t_s": rec.t_s, "temp_c": rec.temp_c}
    normalizer = sphere_normalizer(poses["mean"]) if rec.unit == "counts" else guess_normalizer(rec.unit)
    return poses, normalizer, notes


def path_poses(path, config: dict | None = None, block_rows: int = 100_000,
               progress: bool = False) -> tuple[dict, Normalizer, list[str], str]:
    """:func:`recording_poses` of a file, streaming a samples table in blocks (bounded memory).

    Returns ``(poses, normalizer, notes, unit)``. Poses tables, device files and raw
    counts are read whole (as :func:`calibrate_path` does). ``progress``: a bar on stderr
    by bytes read.
    """
    from selfcal.detect import DetectorConfig, StaticDetector, StillWindows
    from selfcal.io import iter_recording, read_recording

    bar = ByteProgress(path, "still windows", progress)
    blocks = iter_recording(path, block_rows, progress=bar)
    first = next(blocks)
    if first.kind != "samples" or first.unit == "counts" or len(first) < 2:
        bar.close(done=False)
        rec = read_recording(path)
        poses, normalizer, notes = recording_poses(rec, config)
        return poses, normalizer, notes, rec.unit
    normalizer = guess_normalizer(first.unit)
    cfg = _detector_config(config or {}, first.rate_hz(), loose_norm=False)
    det = StaticDetector(DetectorConfig.from_section(cfg.get("detector")))
    parts = [det.feed(*piece) for rec in itertools.chain([first], blocks) for piece in _chunks(rec, normalizer)]
    parts.append(det.flush())
    bar.close()
    w = StillWindows.concat(parts)
    if len(w) == 0:
        raise InputError(f"{path}: no still window found")
    return _windows_to_poses(w, normalizer), normalizer, [], first.unit


def calibrate_recording(
    rec: Recording,
    model: str = "affine9",
    config: dict | None = None,
    progress: bool = False,
) -> CalibrationRun:
    """Run the online calibrator over a recording (samples or poses table).

    Parameters
    ----------
    rec : Recording — any unit (g, m/s², counts)
    model : str — error model name
    config : dict — loaded configuration (``selfcal.config.load_config``)
    progress : bool — show a progress bar on stderr

    Returns
    -------
    CalibrationRun
    """
    config = copy.deepcopy(config or {})
    notes: list[str] = []
    if len(rec) == 0:
        raise InputError(f"{rec.path}: no rows")
    if rec.kind == "samples":
        rate = rec.rate_hz()
        if rec.unit == "counts":
            rough, w = _counts_windows(rec, _detector_config(config, rate, loose_norm=True))
            if len(w) == 0:
                raise InputError(f"{rec.path}: raw counts with no still window: cannot find the counts-per-g scale")
            normalizer, note = _counts_normalizer(w.mean_g * rough.scale + np.asarray(rough.center), rough)
            notes.append(note)
        else:
            normalizer = guess_normalizer(rec.unit)
        cfg = _detector_config(config, rate, loose_norm=False)
        cal = OnlineCalibrator(cfg, model)
        events: list[dict] = []
        n = len(rec.t_s)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=n, unit="sample", file=sys.stderr, desc="calibrate")
        n_windows = 0
        for piece in _chunks(rec, normalizer):
            before = cal.buffer.n_seen
            events += cal.feed_samples(*piece)
            n_windows += cal.buffer.n_seen - before
            if bar:
                bar.update(len(piece[0]))
        before = cal.buffer.n_seen
        events += cal.flush()
        n_windows += cal.buffer.n_seen - before
        if bar:
            bar.close()
    else:  # poses table
        poses, normalizer, notes = recording_poses(rec, config)
        try:
            rate = float(rec.meta.get("rate_hz", 0) or 0)
        except ValueError:
            rate = 0.0
        cal = OnlineCalibrator(_poses_detector_config(config, rate) if rate > 0 else config, model)
        sd_u = None if poses["sd"] is None else poses["sd"] / normalizer.scale
        events = cal.feed_poses(normalizer.to_u(poses["mean"]), sd_u, poses["count"], poses["t_s"], poses["temp_c"])
        events += cal.flush()
        n_windows = len(rec)
    return CalibrationRun(
        calibration=to_raw_calibration(cal, normalizer, rec.unit),
        status=cal.status,
        last_refit=cal.last_refit,
        calibrator=cal,
        normalizer=normalizer,
        n_windows=n_windows,
        events=events,
        notes=notes,
        unit=rec.unit,
        meta=dict(rec.meta),
    )


class ByteProgress:
    """A progress bar on stderr over the bytes of the file at ``path`` (``enabled`` False:
    nothing is shown); called with the bytes read so far, as :func:`selfcal.io.iter_recording`'s
    ``progress`` callback."""

    def __init__(self, path, desc: str, enabled: bool):
        import os

        self.size = max(os.path.getsize(path), 1) if enabled and os.path.isfile(path) else 1
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=self.size, unit="B", unit_scale=True, file=sys.stderr, desc=desc)

    def __call__(self, n_bytes: int) -> None:
        if self.bar is not None:
            self.bar.update(max(0, min(n_bytes, self.size) - self.bar.n))

    def close(self, done: bool = True) -> None:
        """End the bar (``done``: at 100 %)."""
        if self.bar is not None:
            if done:
                self.bar.update(self.size - self.bar.n)
            self.bar.close()
            self.bar = None


def calibrate_path(
    path,
    model: str = "affine9",
    config: dict | None = None,
    progress: bool = False,
    block_rows: int = 100_000,
    columns: list[str] | None = None,
) -> CalibrationRun:
    """Calibrate a recording file, streaming a samples table in blocks (bounded memory).

    A samples table in g or m/s² is read block by block (:func:`selfcal.io.iter_recording`)
    straight into the online calibrator: only still poses stay in memory, whatever the
    file's length. The result equals :func:`calibrate_recording` on the whole file (test:
    ``tests/test_streaming.py``). Poses tables (small), device files (decoded whole) and
    raw-counts tables (their counts-per-g scale needs every still window first) are read
    whole. Progress is by bytes read.
    """
    import os

    from selfcal.io import iter_recording, read_recording

    config = copy.deepcopy(config or {})
    bar = ByteProgress(path, "calibrate", progress)
    blocks = iter_recording(path, block_rows, progress=bar, columns=columns)
    first = next(blocks)
    if first.kind != "samples" or first.unit == "counts" or len(first) == 0:
        bar.close(done=False)
        if columns is not None:  # a plain CSV in counts (the scale needs every still window): gather it
            parts = [first, *blocks]
            temp = None if first.temp_c is None else np.concatenate([b.temp_c for b in parts])
            whole = Recording(kind="samples", unit=first.unit, t_s=np.concatenate([b.t_s for b in parts]),
                              acc=np.vstack([b.acc for b in parts]), temp_c=temp, path=str(path),
                              meta=dict(first.meta))
            return calibrate_recording(whole, model, config, progress=False)
        return calibrate_recording(read_recording(path), model, config, progress=False)
    normalizer = guess_normalizer(first.unit)
    rate = first.rate_hz() if len(first) > 1 else 20.0
    cal = OnlineCalibrator(_detector_config(config, rate, loose_norm=False), model)
    events: list[dict] = []
    for rec in itertools.chain([first], blocks):
        for piece in _chunks(rec, normalizer):
            events.extend(cal.feed_samples(*piece))
    events.extend(cal.flush())
    bar.close()
    notes: list[str] = []
    return CalibrationRun(
        calibration=to_raw_calibration(cal, normalizer, first.unit), status=cal.status, last_refit=cal.last_refit,
        calibrator=cal, normalizer=normalizer, n_windows=int(cal.store.n_seen), events=events, notes=notes,
        unit=first.unit, meta=dict(first.meta),
    )


def published_versions(run: CalibrationRun) -> list[dict]:
    """Every version a run published, in time order, each in the recording's unit (``--history``)."""
    return [version_in_unit(ev["calibration"], None, run.normalizer, run.unit)
            for ev in run.events if ev.get("published") and ev.get("calibration") is not None]


def to_raw_calibration(cal: OnlineCalibrator, normalizer: Normalizer, unit: str) -> dict | None:
    """The calibrator's published model expressed in the recording's unit (contract JSON)."""
    cur = cal.calibration()
    if cur is None:
        return None
    return version_in_unit(cur, cal.model, normalizer, unit)


def version_in_unit(calibration: dict, model: ErrorModel | None, normalizer: Normalizer, unit: str) -> dict:
    """A published calibration (normalised units, ~g) expressed in the recording's unit.

    ``params``, ``std``, ``crlb_std``, ``matrix`` and ``offset`` are converted;
    ``predicted_sphere_rms_mg`` is in mg of the calibrated output and is unchanged.
    ``model``: None takes the version's own (``calibration["model"]``: online model
    selection may change the model between versions).
    """
    if model is None or calibration.get("model", model.name) != model.name:
        model = ErrorModel(calibration["model"], calibration.get("temp_ref_c", 25.0), calibration.get("t_ref_s", 0.0))
    names = model.param_names
    theta_u = model.from_dict(calibration["params"])
    f = normalizer.param_scale(model)
    params = normalizer.theta_to_raw(model, theta_u)
    matrix, offset = model.linear(params)
    out = dict(calibration)
    out["unit"] = unit
    out["params"] = model.to_dict(params)
    out["std"] = {n: float(calibration["std"][n]) * float(k) for n, k in zip(names, f)}
    if isinstance(calibration.get("crlb_std"), dict):
        fd = dict(zip(names, f))
        out["crlb_std"] = {k: (None if v is None else float(v) * fd[k]) for k, v in calibration["crlb_std"].items()}
    out["matrix"] = matrix.tolist()
    out["offset"] = offset.tolist()
    out["normalizer"] = {"center": list(normalizer.center), "scale": normalizer.scale}
    return out
