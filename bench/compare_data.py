"""Pose sets for ``bench/compare.py``: simulated (truth known) and real (truth unknown).

Every method of the comparison receives exactly the same :class:`PoseSet` (pose means,
per-axis sd, sample counts, times, temperatures, in the set's raw unit).

Simulated sets (all built on the simulator's sensor model ``selfcal.sim``: a device
drawn by ``draw_sensor_truth`` with misalignment, non-orthogonality, scale and offset
errors, white noise and 3.90625 mg quantisation; noise-free readings by ``sensor_mean``):

* ``sim_flat``   — flat-heavy insole wear: the simulator's pose-level output
  (``simulate_poses``: standing, sitting, shoe off, a few days), thinned to distinct
  poses (one per 3 deg direction cell and 2 degC temperature cell, as the insole
  paper's diversity rule does) and capped at ``max_poses`` (random, kept in time order);
* ``sim_spread`` — a well-spread set: 48 directions uniform on the sphere, 5-s stills
  (100 samples at 20 Hz), times over 3 days, temperatures 15-35 degC;
* ``sim_mix``    — the insole paper's mix: 6 near-axis poses (O_cor, tilted ~3 deg)
  and 18 others (``tests/posegen.insole_like_directions``);
* the suffix ``+fx`` enables the simulator's continuous effects (temperature bias and
  scale, time drift of the bias, scale non-linearity, cross-axis tempcos) at their
  default magnitudes (not the bias step, an event).

Real sets (``data/``): the 84-h GGIR wrist poses table, and the still windows
(``selfcal.detect.StaticDetector``, rate from the recording, as ``selfcal.pipeline``
does; raw counts first normalised roughly with a loose norm test) of the Xsens
multi-pose, NilsPod six-face, Axivity and Moticon insole recordings.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from selfcal.fit import guess_normalizer, sphere_normalizer
from selfcal.models import Normalizer
from selfcal.sim import SimConfig, draw_sensor_truth, sensor_mean, simulate_poses
from selfcal.sim.config import CONTINUOUS_EFFECTS

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from posegen import insole_like_directions, spread_directions  # noqa: E402

DATA_DIR = Path(__file__).resolve().parents[1] / "data"


@dataclass
class PoseSet:
    """One set of still poses, in the raw unit ``unit``.

    Simulated sets also carry the truth: ``truth`` (a ``SensorTruth``), ``clean`` (the
    noise-free readings of the poses), ``a_true`` (their true specific force),
    ``temp_true``, and ``noise`` (per-axis sd of each pose mean, for new noise draws).
    """

    name: str
    family: str
    kind: str  # "sim" | "real"
    unit: str
    mean: np.ndarray
    sd: np.ndarray
    n: np.ndarray
    t_s: np.ndarray
    temp_c: np.ndarray | None
    normalizer: Normalizer = field(default_factory=Normalizer)
    truth: object | None = None
    clean: np.ndarray | None = None
    a_true: np.ndarray | None = None
    temp_true: np.ndarray | None = None
    noise: np.ndarray | None = None
    effects: bool = False
    note: str = ""

    def __len__(self) -> int:
        return len(self.mean)

    def subset(self, idx) -> "PoseSet":
        """The poses at ``idx`` (bool mask or integer indices), same metadata."""
        def s(x):
            return None if x is None else x[idx]
        return replace(self, mean=self.mean[idx], sd=self.sd[idx], n=self.n[idx], t_s=self.t_s[idx],
                       temp_c=s(self.temp_c), clean=s(self.clean), a_true=s(self.a_true),
                       temp_true=s(self.temp_true), noise=s(self.noise))

    def redraw(self, rng: np.random.Generator) -> "PoseSet":
        """Same poses, truth and noise level; a new draw of the pose-mean noise (sim only)."""
        mean = self.clean + self.noise * rng.standard_normal(self.clean.shape)
        return replace(self, mean=mean)


# --------------------------------------------------------------------------- simulated


def _sim_config(effects: bool) -> SimConfig:
    cfg = SimConfig()
    return cfg.with_effects(list(CONTINUOUS_EFFECTS)) if effects else cfg


def thin_poses(a_dir: np.ndarray, temp_c: np.ndarray | None, angle_deg: float = 3.0, temp_step_c: float = 2.0) -> np.ndarray:
    """Indices of the first pose in each (direction cell, temperature cell), time order kept.

    Directions are binned on an equal-angle grid of ``angle_deg`` (elevation and
    azimuth scaled by cos(elevation)); temperatures in ``temp_step_c`` bins.
    """
    d = a_dir / np.linalg.norm(a_dir, axis=1, keepdims=True)
    el = np.arcsin(np.clip(d[:, 2], -1, 1))
    az = np.arctan2(d[:, 1], d[:, 0])
    step = np.deg2rad(angle_deg)
    ie = np.floor(el / step).astype(np.int64)
    ia = np.floor(az * np.maximum(np.cos(el), 1e-3) / step).astype(np.int64)
    it = np.zeros_like(ie) if temp_c is None else np.floor(np.asarray(temp_c) / temp_step_c).astype(np.int64)
    key = np.stack([ie, ia, it], axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    return np.sort(first)


def sim_flat(seed: int, effects: bool = False, days: float = 3.0, max_poses: int = 120) -> PoseSet:
    """Flat-heavy insole wear from the simulator (see module docstring)."""
    cfg = _sim_config(effects)
    rng = np.random.default_rng(seed)
    pt, truth = simulate_poses(cfg, rng, days=days, seed=seed)
    # diversity thinning on what a device can see (the raw reading), like the paper's delta3
    keep = thin_poses(pt.mean_g, pt.temp_c)
    if len(keep) > max_poses:
        keep = np.sort(np.random.default_rng(seed + 1000).choice(keep, max_poses, replace=False))
    sens = truth.sensor
    t_mid = pt.t_s + 0.5 * pt.duration_s
    clean = sensor_mean(sens, pt.a_true_g[keep], pt.temp_true_c[keep], t_mid[keep])
    n = pt.n[keep].astype(float)
    sd = pt.sd_g[keep]
    return PoseSet(
        name=f"sim_flat{'+fx' if effects else ''}/s{seed}", family=f"sim_flat{'+fx' if effects else ''}",
        kind="sim", unit="g", mean=pt.mean_g[keep], sd=sd, n=n, t_s=t_mid[keep], temp_c=pt.temp_c[keep],
        truth=sens, clean=clean, a_true=pt.a_true_g[keep], temp_true=pt.temp_true_c[keep],
        noise=sd / np.sqrt(n)[:, None], effects=effects,
        note=f"{len(pt)} simulated windows over {days:g} days -> {len(keep)} distinct poses",
    )


def _synthetic(name: str, family: str, seed: int, directions: np.ndarray, effects: bool, rng: np.random.Generator,
               count: int = 100) -> PoseSet:
    cfg = _sim_config(effects)
    sens = draw_sensor_truth(cfg, np.random.default_rng(seed + 7919))
    m = len(directions)
    t = np.sort(rng.uniform(0, 3 * 86400.0, m))
    temp = rng.uniform(15.0, 35.0, m)
    clean = sensor_mean(sens, directions, temp, t)
    sd1 = np.sqrt(sens.noise_sd_g**2 + sens.lsb_g**2 / 12.0)
    sd = np.tile(sd1, (m, 1))
    n = np.full(m, float(count))
    noise = sd / np.sqrt(n)[:, None]
    mean = clean + noise * rng.standard_normal((m, 3))
    temp_rep = temp + 0.1 * rng.standard_normal(m)
    return PoseSet(name=name, family=family, kind="sim", unit="g", mean=mean, sd=sd, n=n, t_s=t, temp_c=temp_rep,
                   truth=sens, clean=clean, a_true=directions, temp_true=temp, noise=noise, effects=effects,
                   note=f"{m} poses, {count} samples each")


def sim_spread(seed: int, effects: bool = False, n_poses: int = 48) -> PoseSet:
    """Well-spread poses (uniform on the sphere) on a simulator-drawn device."""
    rng = np.random.default_rng(seed)
    fam = f"sim_spread{'+fx' if effects else ''}"
    return _synthetic(f"{fam}/s{seed}", fam, seed, spread_directions(rng, n_poses), effects, rng)


def sim_mix(seed: int, effects: bool = False) -> PoseSet:
    """The insole paper's mix: 6 near-axis poses + 18 others."""
    rng = np.random.default_rng(seed)
    fam = f"sim_mix{'+fx' if effects else ''}"
    return _synthetic(f"{fam}/s{seed}", fam, seed, insole_like_directions(rng, 6, 18), effects, rng)


def growing_spread(seed: int, n_max: int = 60) -> PoseSet:
    """A well-spread sequence whose prefixes are the 'poses needed' test (no effects)."""
    rng = np.random.default_rng(10_000 + seed)
    return _synthetic(f"growing/s{seed}", "growing", seed, spread_directions(rng, n_max), False, rng)


def sphere_points(ps: PoseSet, n: int = 2000, seed: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
    """Raw readings of ``n`` directions spread over the whole sphere, and their temperatures.

    Without effects the conditions do not matter (reference temperature, t = 0). With
    effects each direction is paired with the (true temperature, time) of a random pose
    of the set: the sphere is evaluated in the conditions the data were taken in.
    """
    rng = np.random.default_rng(seed)
    d = spread_directions(rng, n)
    sens = ps.truth
    if ps.effects:
        k = rng.integers(0, len(ps), n)
        temp, t = ps.temp_true[k], ps.t_s[k]
    else:
        temp, t = np.full(n, sens.temp_ref_c), np.zeros(n)
    return sensor_mean(sens, d, temp, t), temp


# --------------------------------------------------------------------------- real


def _windows(rec, acc_u: np.ndarray, loose: bool):
    from selfcal.detect import DetectorConfig, StaticDetector, StillWindows

    det_cfg = {"rate_hz": float(rec.rate_hz())}
    if loose:
        det_cfg["norm_tol_raw_g"] = 0.5
    det = StaticDetector(DetectorConfig.from_section(det_cfg))
    pres = rec.pressure_kpa() if rec.pressure is not None and rec.pressure_unit in ("kpa", "ncm2") else None
    parts = []
    step = 50_000
    for i in range(0, len(rec.t_s), step):
        sl = slice(i, i + step)
        parts.append(det.feed(rec.t_s[sl], acc_u[sl], None if rec.temp_c is None else rec.temp_c[sl],
                              None if pres is None else pres[sl]))
    parts.append(det.flush())
    return StillWindows.concat(parts)


def real_set(path: Path, name: str, max_poses: int | None = None) -> PoseSet | None:
    """Still poses of a real recording in its own unit; None if it has fewer than 12."""
    from selfcal.io import read_recording

    rec = read_recording(str(path))
    if rec.kind == "poses":
        mean, sd = rec.acc, rec.sd if rec.sd is not None else np.full_like(rec.acc, np.nan)
        rate = float(rec.meta.get("rate_hz", 50.0))
        n = rec.n.astype(float) if rec.n is not None else np.maximum(1.0, rec.duration_s * rate)
        t, temp = rec.t_s, rec.temp_c
        normalizer = sphere_normalizer(mean) if rec.unit == "counts" else guess_normalizer(rec.unit)
        note = f"poses table, {len(rec)} windows"
    else:
        if rec.unit == "counts":
            lo, hi = np.percentile(rec.acc, [1, 99], axis=0)
            rough = Normalizer(tuple(float(c) for c in (hi + lo) / 2), float(np.median((hi - lo) / 2)))
            w = _windows(rec, rough.to_u(rec.acc), loose=True)
            mean = w.mean_g * rough.scale + np.asarray(rough.center)
            sd = w.sd_g * rough.scale
            normalizer = sphere_normalizer(mean) if len(w) >= 4 else rough
        else:
            normalizer = guess_normalizer(rec.unit)
            w = _windows(rec, normalizer.to_u(rec.acc), loose=False)
            mean = w.mean_g * normalizer.scale + np.asarray(normalizer.center)
            sd = w.sd_g * normalizer.scale
        n = w.n.astype(float)
        t = 0.5 * (w.t_start_s + w.t_end_s)
        temp = None if rec.temp_c is None else np.asarray(w.temp_c, float)
        note = f"{len(rec)} samples at {rec.rate_hz():.4g} Hz -> {len(w)} still windows"
    if temp is not None and not np.all(np.isfinite(temp)):
        temp = None
    if len(mean) < 12:
        return None
    ps = PoseSet(name=name, family=name, kind="real", unit=rec.unit, mean=np.asarray(mean, float),
                 sd=np.asarray(sd, float), n=np.asarray(n, float), t_s=np.asarray(t, float), temp_c=temp,
                 normalizer=normalizer, note=note)
    if max_poses is not None and len(ps) > max_poses:
        idx = np.unique(np.linspace(0, len(ps) - 1, max_poses).round().astype(int))
        ps = ps.subset(idx)
        ps.note += f" (every {len(rec) // max_poses}th kept: {len(ps)})" if rec.kind == "poses" else f" ({len(ps)} kept)"
    return ps


REAL_FILES = [
    ("ggir_wrist_84h", "ggir-wrist-84h/poses.csv"),
    ("imutk_xsens", "imutk-xsens-multipose/samples.csv"),
    ("nilspod_ferraris", "imucal-nilspod-ferraris/samples.csv"),
    ("axivity_ax3_ggir", "axivity-wrist/ggirread_ax3_testfile.csv"),
    ("axivity_ax6_ggir", "axivity-wrist/ggirread_ax6_testfile.csv"),
    ("axivity_ax3_skdh", "axivity-wrist/skdh_ax3_sample.csv"),
    ("axivity_ax6_skdh", "axivity-wrist/skdh_ax6_sample.csv"),
    ("moticon_102114_left", "moticon-insole/230927_102114_left.csv"),
    ("moticon_102137_left", "moticon-insole/230927_102137_left.csv"),
]


def real_sets(max_poses: int | None = None, data_dir: Path = DATA_DIR, log=None) -> tuple[list[PoseSet], list[str]]:
    """Every real set with at least 12 still poses; and notes on the ones skipped."""
    out, skipped = [], []
    for name, rel in REAL_FILES:
        p = data_dir / rel
        if not p.exists():
            skipped.append(f"{name}: {rel} not found")
            continue
        ps = real_set(p, name, max_poses)
        if ps is None:
            skipped.append(f"{name}: fewer than 12 still windows")
            continue
        if log:
            log(f"  {name}: {ps.note}")
        out.append(ps)
    return out, skipped
