"""The online calibrator: detector -> pose buffer -> scheduler -> fit -> guard.

One object per device. Feed it samples (or ready-made still poses) in any chunking;
it detects still windows, keeps a diverse pose buffer, refits when the scheduler says
so, and publishes a new model only when the guard lets it. Its whole state
serialises to JSON and back exactly (:meth:`OnlineCalibrator.to_json`).

Update rule (observability-aware, no double counting)
-----------------------------------------------------
* First publication: a full MAP fit of every training pose in the buffer under the
  datasheet prior (``selfcal.fit.datasheet_prior``).
* Later refits are *sequential*: the prior is the published model with its
  covariance, inflated by process noise for the time elapsed (sensors drift), and
  the data are the poses not yet absorbed into it. Directions the new poses do not
  determine stay at the prior. A pose that has been absorbed is not fitted again,
  so the same information is never counted twice.
* If the new poses conflict with the prior (reduced chi² above
  ``scheduler.conflict_chi2``), the calibrator falls back to a full fit of the whole
  buffer under the datasheet prior.
* The guard compares the candidate with the current model on held-out poses (never
  fitted) and checks plausibility; a refused refit is typed and explained.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from selfcal.config import section
from selfcal.errors import InputError
from selfcal.fit import (
    FitConfig,
    FitResult,
    GuardConfig,
    GuardDecision,
    Prior,
    datasheet_prior,
    fit_poses,
    implausible,
    rms_mg,
)
from selfcal.models import ErrorModel, Normalizer
from selfcal.poses import PoseBuffer, PoseConfig

SECONDS_PER_DAY = 86400.0


class SchedulerConfig(BaseModel):
    """The ``[scheduler]`` section: when to refit, and how fast the prior ages."""

    model_config = ConfigDict(extra="forbid")

    min_poses_first: int = Field(6, ge=1, description="training poses needed before the first fit")
    update: str = Field(
        "sequential", pattern="^(sequential|full)$",
        description="'sequential': prior = published posterior, data = new poses; 'full': every refit fits the whole buffer under the datasheet prior",
    )
    refit_every_poses: int = Field(8, ge=1, description="refit after this many new poses")
    refit_every_hours: float = Field(24.0, gt=0, description="...or after this many hours with >= 1 new pose")
    conflict_chi2: float = Field(6.0, gt=0, description="sequential-update reduced chi2 above this: full refit")
    calibrated_min_poses: int = Field(12, ge=1, description="poses absorbed before status 'calibrated'")
    process_noise_bias_g_per_sqrt_day: float = Field(
        2e-4, ge=0, description="random-walk sd added to the offset prior per sqrt(day), g"
    )
    process_noise_scale_per_sqrt_day: float = Field(
        1e-4, ge=0, description="random-walk sd added to the scale prior per sqrt(day), relative"
    )
    process_noise_effect_per_sqrt_day: float = Field(
        0.0, ge=0, description="random-walk sd of effect parameters per sqrt(day) (relative to their prior sd)"
    )

    @classmethod
    def from_section(cls, section_: dict[str, Any] | None) -> "SchedulerConfig":
        """Validate the ``[scheduler]`` TOML section."""
        return cls(**(section_ or {}))


def _detector_module():
    from selfcal import detect  # local import: keeps this module importable alone

    return detect


class OnlineCalibrator:
    """Per-device online calibrator (inputs in g).

    Parameters
    ----------
    config : dict, optional
        Loaded configuration (``selfcal.config.load_config()``); sections
        ``detector``, ``poses``, ``fit``, ``guard``, ``scheduler``.
    model : str
        Error model name (``"affine9"``, ``"scale6"``, ``"affine9+temperature_bias"``...).
    initial_params_u : ndarray, shape (p,), optional
        An initial value for the first fit (as in the insole paper's protocol, which
        starts from a random value); the fit also considers its own initial values.
    """

    def __init__(self, config: dict | None = None, model: str = "affine9", initial_params_u=None):
        self.config = dict(config or {})
        self.model = ErrorModel(model)
        self.fit_cfg = FitConfig.from_section(section(self.config, "fit"))
        self.guard_cfg = GuardConfig.from_section(section(self.config, "guard"))
        self.sched_cfg = SchedulerConfig.from_section(section(self.config, "scheduler"))
        self.pose_cfg = PoseConfig.from_section(section(self.config, "poses"))
        detect = _detector_module()
        self.det_cfg = detect.DetectorConfig.from_section(section(self.config, "detector"))
        self.detector = detect.StaticDetector(self.det_cfg)
        self.buffer = PoseBuffer.empty(self.pose_cfg)
        self.initial_params_u = None if initial_params_u is None else np.asarray(initial_params_u, dtype=float)
        self.current: dict | None = None  # {"theta_u", "cov_u", "t_s", "version", "calibration"}
        self.last_refit: dict | None = None
        self.n_refits = 0
        self.new_since_refit = 0
        self.last_refit_t_s: float | None = None
        self.t_last_s: float | None = None
        self.n_samples = 0

    # ------------------------------------------------------------------ status
    @property
    def status(self) -> str:
        """``uncalibrated``, ``provisional`` or ``calibrated``."""
        if self.current is None:
            return "uncalibrated"
        cal = self.current["calibration"]
        base = set(self.model.param_names[: 9 if self.model.base != "scale6" else 6])
        if base.issubset(set(cal["determined"])) and cal["n_poses_absorbed"] >= self.sched_cfg.calibrated_min_poses:
            return "calibrated"
        return "provisional"

    def calibration(self) -> dict | None:
        """The published calibration (design-contract JSON) with status and version, or None."""
        if self.current is None:
            return None
        out = dict(self.current["calibration"])
        out["status"] = self.status
        out["version"] = self.current["version"]
        return out

    def apply(self, acc_g: np.ndarray, temp_c=None, t_s=None) -> np.ndarray:
        """Calibrate samples (n,3) g with the published model (identity if none)."""
        if self.current is None:
            return np.asarray(acc_g, dtype=float)
        return self.model.apply(np.asarray(self.current["theta_u"]), acc_g, temp_c, t_s)

    def _to_cal(self):
        if self.current is None:
            return None
        matrix, offset = self.model.linear(np.asarray(self.current["theta_u"]))

        def to_cal(x):
            return (np.asarray(x) - offset) @ matrix.T

        return to_cal

    # ------------------------------------------------------------------ feeding
    def feed_samples(self, t_s, acc_g, temp_c=None, pressure_kpa=None) -> list[dict]:
        """Feed a chunk of samples; returns the refit outcomes it triggered.

        Parameters
        ----------
        t_s : ndarray, shape (n,), s, non-decreasing across calls
        acc_g : ndarray, shape (n, 3), g (uncalibrated)
        temp_c : ndarray, shape (n,), degC, optional
        pressure_kpa : ndarray, shape (n, k), kPa, optional
        """
        t_s = np.asarray(t_s, dtype=float)
        acc_g = np.asarray(acc_g, dtype=float)
        if acc_g.ndim != 2 or acc_g.shape[1] != 3 or acc_g.shape[0] != t_s.shape[0]:
            raise InputError(f"feed_samples: acc_g must be (n, 3) with n = len(t_s); got {acc_g.shape}, {t_s.shape}")
        if t_s.size == 0:
            return []
        windows = self.detector.feed(t_s, acc_g, temp_c=temp_c, pressure_kpa=pressure_kpa, to_cal=self._to_cal())
        self.n_samples += int(t_s.size)
        self.t_last_s = float(t_s[-1])
        return self._take_windows(windows)

    def flush(self) -> list[dict]:
        """End of stream: close an open still window and refit if anything is new."""
        windows = self.detector.flush()
        events = self._take_windows(windows)
        if self.new_since_refit > 0:
            events.append(self.refit())
        # poses that only validated a publication are training data now: absorb them (whether
        # that publication happened here or earlier, inside feed_poses)
        if self.current is not None:
            pending = self.buffer.validated & ~self.buffer.absorbed
            if pending.any():
                self.new_since_refit = int(pending.sum())
                events.append(self.refit())
        return events

    def _take_windows(self, w) -> list[dict]:
        if len(w.n) == 0:
            return []
        t_mid = 0.5 * (np.asarray(w.t_start_s) + np.asarray(w.t_end_s))
        return self.feed_poses(w.mean_g, w.sd_g, w.n, t_mid, w.temp_c)

    def feed_poses(self, mean_g, sd_g, n, t_s, temp_c=None) -> list[dict]:
        """Feed still poses directly (a poses table); returns the refit outcomes.

        Parameters
        ----------
        mean_g, sd_g : ndarray, shape (k, 3), g
        n : ndarray, shape (k,) — samples per window
        t_s : ndarray, shape (k,), s — window centre times
        temp_c : ndarray, shape (k,), degC, optional
        """
        mean_g = np.atleast_2d(np.asarray(mean_g, dtype=float))
        t_s = np.atleast_1d(np.asarray(t_s, dtype=float))
        if mean_g.shape[0] == 0:
            return []
        stats = self.buffer.add(mean_g, sd_g, n, t_s, temp_c)
        self.new_since_refit += stats["new_info"]
        self.t_last_s = max(self.t_last_s or -np.inf, float(np.max(t_s)))
        if self._due():
            return [self.refit()]
        return []

    def _due(self) -> bool:
        if self.new_since_refit <= 0:
            return False
        if self.current is None:
            n_train = int(np.sum(~self._heldout()))
            return n_train >= self.sched_cfg.min_poses_first
        if self.new_since_refit >= self.sched_cfg.refit_every_poses:
            return True
        if self.last_refit_t_s is not None and self.t_last_s is not None:
            return (self.t_last_s - self.last_refit_t_s) >= self.sched_cfg.refit_every_hours * 3600.0
        return False

    # ------------------------------------------------------------------ refit
    def _aged_prior(self, t_now: float) -> Prior:
        cur = self.current
        cov = np.asarray(cur["cov_u"], dtype=float).copy()
        days = max(0.0, (t_now - cur["t_s"]) / SECONDS_PER_DAY)
        q = np.zeros(self.model.n_params)
        q[0:3] = self.sched_cfg.process_noise_bias_g_per_sqrt_day ** 2
        q[3:6] = self.sched_cfg.process_noise_scale_per_sqrt_day ** 2
        ds = np.diag(datasheet_prior(self.model, self.fit_cfg).cov)
        for eff in self.model.effects:
            sl = self.model.index(eff)
            q[sl] = (self.sched_cfg.process_noise_effect_per_sqrt_day ** 2) * ds[sl]
        cov[np.diag_indices_from(cov)] += q * days
        return Prior(np.asarray(cur["theta_u"], dtype=float), cov)

    def refit(self) -> dict:
        """Refit now (the scheduler calls this); returns the outcome dict."""
        t_now = float(self.t_last_s if self.t_last_s is not None else 0.0)
        self.n_refits += 1
        held = self._heldout()
        train = ~held
        mode = "full"
        fit: FitResult | None = None
        used = train
        try:
            if self.current is not None and self.sched_cfg.update == "sequential":
                new_train = train & ~self.buffer.absorbed
                if new_train.sum() == 0:
                    return self._refuse(t_now, "no_still_poses", "no new training pose since the last refit", "sequential")
                prior = self._aged_prior(t_now)
                fit = fit_poses(
                    self.model, self.buffer.pose_data(new_train), prior=prior,
                    theta0_u=prior.mean, cfg=self.fit_cfg,
                )
                mode, used = "sequential", new_train
                if fit.chi2_red > self.sched_cfg.conflict_chi2:
                    fit, mode, used = None, "full_after_conflict", train
            if fit is None:
                if train.sum() < self.guard_cfg.min_poses:
                    return self._refuse(
                        t_now, "insufficient_coverage" if len(self.buffer) else "no_still_poses",
                        f"{int(train.sum())} training pose(s); at least {self.guard_cfg.min_poses} are needed", mode,
                    )
                theta0 = self.initial_params_u if self.current is None else np.asarray(self.current["theta_u"])
                fit = fit_poses(
                    self.model, self.buffer.pose_data(train), prior=datasheet_prior(self.model, self.fit_cfg),
                    theta0_u=theta0, cfg=self.fit_cfg,
                )
        except InputError as exc:
            return self._refuse(t_now, "insufficient_coverage", str(exc), mode)

        decision = self._guard(fit, held, first=mode != "sequential")
        if not decision.publish:
            return self._refuse(t_now, decision.reason, decision.message, mode, fit, decision)
        return self._publish(t_now, fit, used, mode, decision)

    def _heldout(self) -> np.ndarray:
        """Held-out mask: every k-th pose id, not yet absorbed, once the buffer is large enough."""
        if len(self.buffer) < self.guard_cfg.heldout_min_poses:
            return np.zeros(len(self.buffer), dtype=bool)
        return self.buffer.heldout(self.guard_cfg.heldout_every) & ~self.buffer.absorbed & ~self.buffer.validated

    def _guard(self, fit: FitResult, held: np.ndarray, first: bool = True) -> GuardDecision:
        g = self.guard_cfg
        if not fit.success:
            return GuardDecision(False, "not_converged", f"LM did not converge: {fit.message}")
        why = implausible(self.model, fit.theta_u, g)
        if why:
            return GuardDecision(False, "implausible", why)
        if fit.residual_rms_mg > g.max_residual_rms_mg:
            return GuardDecision(
                False, "implausible",
                f"fit residual RMS {fit.residual_rms_mg:.2f} mg exceeds {g.max_residual_rms_mg} mg",
            )
        if first and fit.n_determined_directions < g.min_determined:
            return GuardDecision(False, "insufficient_coverage", "the poses determine no parameter direction")
        cur_theta = np.asarray(self.current["theta_u"]) if self.current else self.model.nominal()
        ident = Normalizer()
        if held.sum() >= g.min_heldout:
            ref = self.buffer.pose_data(held)
            where = f"{int(held.sum())} held-out poses"
        else:
            ref = self.buffer.pose_data()
            where = f"all {len(self.buffer)} poses (too few held out)"
        new = rms_mg(self.model, fit.theta_u, ident, ref)
        cur = rms_mg(self.model, cur_theta, ident, ref)
        label = "current model" if self.current else "uncalibrated (nominal) model"
        if new > cur * (1 + g.tolerance_rel) + g.tolerance_mg:
            return GuardDecision(
                False, "worse_than_current",
                f"held-out RMS {new:.3f} mg on {where} is worse than the {label}'s {cur:.3f} mg", new, cur,
            )
        return GuardDecision(True, None, f"held-out RMS {new:.3f} mg vs {label} {cur:.3f} mg on {where}", new, cur)

    def _refuse(self, t_now, reason, message, mode, fit=None, decision=None) -> dict:
        self.new_since_refit = 0  # wait for new poses before trying again
        self.last_refit_t_s = t_now
        self.last_refit = {
            "t_s": t_now, "published": False, "reason": reason, "message": message, "mode": mode,
            "n_poses": len(self.buffer),
            "fit_ms": None if fit is None else fit.fit_ms,
            "heldout_rms_mg_new": None if decision is None else decision.heldout_rms_mg_new,
            "heldout_rms_mg_current": None if decision is None else decision.heldout_rms_mg_current,
        }
        return dict(self.last_refit, calibration=None)

    def _cumulative_determined(self, cov_u: np.ndarray) -> np.ndarray:
        ds = np.diag(datasheet_prior(self.model, self.fit_cfg).cov)
        return np.sqrt(np.diag(cov_u) / ds) < self.fit_cfg.determined_ratio

    def _publish(self, t_now, fit: FitResult, used: np.ndarray, mode: str, decision: GuardDecision) -> dict:
        version = (self.current["version"] if self.current else 0) + 1
        self.buffer.mark_absorbed(self.buffer.pose_id[used], t_now)
        self.buffer.mark_validated(self.buffer.pose_id[self._heldout()])
        cal = fit.to_calibration(unit="g")
        det = self._cumulative_determined(fit.cov_u)
        names = self.model.param_names
        cal["determined_this_refit"] = cal.pop("determined")
        cal["undetermined_this_refit"] = cal.pop("undetermined")
        cal["determined"] = [n for n, d in zip(names, det) if d]
        cal["undetermined"] = [n for n, d in zip(names, det) if not d]
        all_poses = self.buffer.pose_data()
        cal["residual_rms_mg"] = rms_mg(self.model, fit.theta_u, Normalizer(), all_poses)
        cal["n_poses"] = len(self.buffer)
        cal["n_poses_absorbed"] = int(self.buffer.absorbed.sum())
        cal["refit_mode"] = mode
        cal["t_s"] = t_now
        cal["provenance"] = self.buffer.summary()
        cal["heldout_rms_mg"] = decision.heldout_rms_mg_new
        self.current = {
            "theta_u": fit.theta_u.tolist(),
            "cov_u": fit.cov_u.tolist(),
            "t_s": t_now,
            "version": version,
            "calibration": cal,
        }
        self.new_since_refit = 0
        self.last_refit_t_s = t_now
        self.last_refit = {
            "t_s": t_now, "published": True, "reason": None, "message": decision.message, "mode": mode,
            "n_poses": len(self.buffer), "fit_ms": fit.fit_ms, "version": version,
            "heldout_rms_mg_new": decision.heldout_rms_mg_new,
            "heldout_rms_mg_current": decision.heldout_rms_mg_current,
        }
        return dict(self.last_refit, calibration=self.calibration())

    def seed_calibration(self, params: dict[str, float], std: dict[str, float] | None = None, t_s: float = 0.0) -> None:
        """Install a factory calibration (params in g units) as the published model."""
        theta = self.model.from_dict(params)
        sd = np.sqrt(np.diag(datasheet_prior(self.model, self.fit_cfg).cov))
        if std:
            sd = np.array([float(std.get(n, s)) for n, s in zip(self.model.param_names, sd)])
        if np.any(~np.isfinite(sd)) or np.any(sd <= 0):
            raise InputError("std: every standard deviation must be finite and > 0")
        cov = np.diag(sd**2)
        matrix, offset = self.model.linear(theta)
        det = self._cumulative_determined(cov)
        names = self.model.param_names
        cal = {
            "format": "selfcal-calibration", "format_version": 1, "model": self.model.name, "unit": "g",
            "params": self.model.to_dict(theta), "std": {n: float(s) for n, s in zip(names, sd)},
            "determined": [n for n, d in zip(names, det) if d],
            "undetermined": [n for n, d in zip(names, det) if not d],
            "n_poses": len(self.buffer), "n_poses_absorbed": 0, "residual_rms_mg": None,
            "matrix": matrix.tolist(), "offset": offset.tolist(), "refit_mode": "seeded", "t_s": t_s,
            "temp_ref_c": self.model.temp_ref_c, "t_ref_s": self.model.t_ref_s,
        }
        version = (self.current["version"] if self.current else 0) + 1
        self.current = {"theta_u": theta.tolist(), "cov_u": cov.tolist(), "t_s": t_s, "version": version, "calibration": cal}

    # ------------------------------------------------------------------ state
    def state(self) -> dict:
        """The whole state as a JSON-serialisable dict."""
        return {
            "format": "selfcal-calibrator-state",
            "format_version": 1,
            "config": self.config,
            "model": self.model.name,
            "temp_ref_c": self.model.temp_ref_c,
            "t_ref_s": self.model.t_ref_s,
            "initial_params_u": None if self.initial_params_u is None else self.initial_params_u.tolist(),
            "detector": self.detector.state_dict(),
            "buffer": self.buffer.to_json(),
            "current": self.current,
            "last_refit": self.last_refit,
            "n_refits": self.n_refits,
            "new_since_refit": self.new_since_refit,
            "last_refit_t_s": self.last_refit_t_s,
            "t_last_s": self.t_last_s,
            "n_samples": self.n_samples,
        }

    def to_json(self) -> str:
        """Serialise the whole state to a JSON string (exact round trip)."""
        return json.dumps(self.state(), allow_nan=True, separators=(",", ":"))

    @classmethod
    def from_json(cls, text: str | dict) -> "OnlineCalibrator":
        """Rebuild a calibrator from :meth:`to_json` output."""
        d = json.loads(text) if isinstance(text, (str, bytes)) else text
        if d.get("format") != "selfcal-calibrator-state" or d.get("format_version") != 1:
            raise InputError("calibrator state: unknown format or version")
        obj = cls(d["config"], d["model"], d["initial_params_u"])
        obj.model = ErrorModel(d["model"], d["temp_ref_c"], d["t_ref_s"])
        obj.detector = _detector_module().StaticDetector.from_state(obj.det_cfg, d["detector"])
        obj.buffer = PoseBuffer.from_json(d["buffer"])
        obj.current = d["current"]
        obj.last_refit = d["last_refit"]
        obj.n_refits = d["n_refits"]
        obj.new_since_refit = d["new_since_refit"]
        obj.last_refit_t_s = d["last_refit_t_s"]
        obj.t_last_s = d["t_last_s"]
        obj.n_samples = d["n_samples"]
        return obj
