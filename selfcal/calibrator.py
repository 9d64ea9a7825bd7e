"""The online calibrator: detector -> pose store -> scheduler -> robust MAP refit -> guard -> publication.

One object per device. Feed it samples (or ready-made still poses) in any chunking;
it detects still windows, keeps every one of them in a compressed pose store
(:mod:`selfcal.poses`), refits when the scheduler says so, and publishes a new model
only when the guard lets it and the model has changed significantly. Its whole state
serialises to JSON and back exactly (:meth:`OnlineCalibrator.to_json`).

Why it is consistent by construction (docs/internals.md has the measurements)
---------------------------------------------------------------------------
* **Nothing is absorbed.** Every refit is one MAP problem over the whole pose store
  under the datasheet prior (or a factory calibration the operator installed),
  re-linearised at every refit and warm-started from the published model. A pose is
  never folded into a Gaussian linearised at an early, wrong estimate.
* **Repeats do not average down.** The store pools repeats of one pose into a cell
  whose systematic floor counts once; its noise is the cell's own scatter, not a
  datasheet guess.
* **Robust.** A Huber loss on whitened residuals, and a model-free gate inside each
  cell: a "still" window that was not still cannot lock the device in.
* **Guard without lock-in.** "Worse" is decided on held-out cells that *neither*
  model was fitted to: the candidate is refitted without one fold (rotating), and is
  compared with the published model on the cells of that fold that appeared after
  the published model was fitted.
* **Status is a promise.** Every version carries ``predicted_sphere_rms_mg``, the
  calibrated-norm RMS error over the whole sphere that its covariance predicts, with
  what the candidate effects the model lacks could add as far as the cells do not
  determine them (:meth:`OnlineCalibrator._unmodelled`), and, while the recent cells
  show an offset jump not yet named, that jump.
  ``calibrated`` means that this is at most ``calibrated_max_sphere_mg`` *and* the
  data determine every base parameter *and* the cells since the last version agree
  with the fit (no offset jump at their start: a bias step not yet named);
  ``provisional`` is anything published short of that.
* **Publication on significant change only**: a status change, a parameter change
  that is significant against the new covariance (chi² quantile), or a predicted
  sphere error that improved by a factor; never more often than
  ``publish_min_interval_s`` of data time except for a status change.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.special import chdtri as _chi2_isf  # chi2.ppf(q, k) = chdtri(k, 1 - q); scipy.stats costs 0.5 s to import

from selfcal.checkpoint import CheckpointBase, apply_patch, field_digests, make_patch
from selfcal.checkpoint import base_of as checkpoint_base_of
from selfcal.config import section
from selfcal.errors import InputError
from selfcal.fit import (
    FitConfig,
    FitResult,
    GuardConfig,
    GuardDecision,
    PoseData,
    Prior,
    datasheet_prior,
    fit_poses,
    implausible,
    predicted_sphere_rms_mg,
    unmodelled_sphere_rms_mg,
    variance_components,
)
from selfcal.models import SECONDARY_EFFECTS, ErrorModel, Normalizer
from selfcal.poses import PoseConfig, PoseStore
from selfcal.selection import (
    Comparison,
    SelectionConfig,
    change_record,
    compare,
    extend_prior,
    rounded,
    stops_paying,
    supports,
    wald_far_below,
    wald_not_significant_to_keep,
    wald_significant,
)
from selfcal.selection import applicable as selection_applicable
from selfcal.steps import jump_score, latest_jump, refine_time, scan_step, step_times, whitened_basis

SECONDS_PER_DAY = 86400.0
STATE_FORMAT_VERSION = 2
#: The smallest standard deviation a seeded (factory) calibration may give a parameter (g, or
#: relative for scales): below it the prior's covariance is numerically singular.
SEED_STD_MIN = 1e-7
#: The largest (the service's bound): its square stays far from overflow in the prior.
SEED_STD_MAX = 1e6


class SchedulerConfig(BaseModel):
    """The ``[scheduler]`` section: when to refit, when to publish, what ``calibrated`` means."""

    model_config = ConfigDict(extra="forbid")

    min_poses_first: int = Field(6, ge=1, description="pose cells needed before the first fit")
    refit_every_poses: int = Field(8, ge=1, description="refit after this many new pose cells")
    refit_every_windows: int = Field(720, ge=1, description="...or after this many new still windows")
    refit_every_hours: float = Field(6.0, gt=0, description="...or after this many hours with >= 1 new window")
    refit_every_fraction: float = Field(
        0.05, ge=0, description="...but at least this fraction of the stored cells (windows) must be new: refits "
                                "come when the information has grown by that much, not on a fixed count")
    calibrated_min_poses: int = Field(12, ge=1, description="pose cells needed before status 'calibrated'")
    calibrated_max_sphere_mg: float = Field(
        2.0, gt=0, description="'calibrated' needs a predicted whole-sphere norm RMS error at most this, mg"
    )
    predict_unmodelled: bool = Field(
        False, description="the predicted whole-sphere error includes what the [selection] candidates the model "
                          "lacks could add, at their datasheet size as far as the cells do not determine them")
    recent_check_alpha: float = Field(
        1e-4, ge=0, lt=1, description="'calibrated' also needs the cells since the last version to agree with the "
                                      "fit: their offset is tested for a jump at this level (0: no test)")
    recent_check_min_cells: int = Field(12, ge=1, description="...when at least this many cells are new")
    publish_chi2_quantile: float = Field(
        0.99, gt=0, lt=1, description="a parameter change is significant beyond this chi2 quantile (new covariance)"
    )
    publish_improve_factor: float = Field(
        1.25, gt=1, description="...or when the predicted sphere error shrinks by this factor"
    )
    publish_max_shift_mg: float = Field(
        0.5, ge=0, description="a calibrated version published because it is more certain (not because the data say the "
                               "published one is wrong) may move the whole-sphere calibration by at most this, mg")
    publish_final_chi2_quantile: float = Field(
        0.99, gt=0, lt=1, description="at the end of a stream (flush), a change beyond this chi2 quantile is published")
    publish_final_max_shift_mg: float = Field(
        1000.0, ge=0, description="at the end of a stream the most certain fit is what the user keeps: the "
                                  "bound on its whole-sphere shift, mg (1 g: none)")
    publish_final_improve_factor: float = Field(
        1.05, gt=1, description="...or one whose predicted sphere error shrank by this factor (and that moves the "
                                "calibration by at most publish_final_max_shift_mg)")
    publish_min_interval_s: float = Field(
        1800.0, ge=0, description="at most one version per this much data time (a status change is always published), s"
    )
    cell_floor_g: float = Field(
        1e-4, gt=0, description="shared error of one pose cell (repeats in a cell do not average it down) until "
                                "the residuals of enough cells measure it (variance components), g")
    cell_floor_min_g: float = Field(
        1e-5, gt=0, description="least cell floor the variance components may set, g")
    cell_floor_max_g: float = Field(
        1e-2, gt=0, description="largest cell floor the variance components may set, g")
    process_noise_bias_g_per_sqrt_day: float = Field(
        0.0, ge=0, description="random-walk sd of the offsets per sqrt(day): older cells weigh less, g"
    )
    process_noise_scale_per_sqrt_day: float = Field(
        0.0, ge=0, description="random-walk sd of the scales per sqrt(day), relative"
    )

    @classmethod
    def from_section(cls, section_: dict[str, Any] | None) -> "SchedulerConfig":
        """Validate the ``[scheduler]`` TOML section."""
        return cls(**(section_ or {}))


def _detector_module():
    from selfcal import detect  # local import: keeps this module importable alone

    return detect


def _clipped_rms_mg(model: ErrorModel, theta_u: np.ndarray, poses: PoseData, clip_g: float) -> float:
    """RMS norm residual (mg) with each residual clipped at ``clip_g`` (one wild pose cannot decide)."""
    r = model.residuals(theta_u, poses.mean, poses.temp_c, poses.t_s)
    r = np.clip(r, -clip_g, clip_g)
    return float(np.sqrt(np.mean(r * r)) * 1e3)


class OnlineCalibrator:
    """Per-device online calibrator (inputs in g, or normalised units ~g).

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
        self.sel_cfg = SelectionConfig.from_section(section(self.config, "selection"))
        detect = _detector_module()
        self.det_cfg = detect.DetectorConfig.from_section(section(self.config, "detector"))
        self.detector = detect.StaticDetector(self.det_cfg)
        self.store = PoseStore.empty(self.pose_cfg)
        self.initial_params_u = None if initial_params_u is None else np.asarray(initial_params_u, dtype=float)
        self.current: dict | None = None  # {"theta_u", "cov_u", "t_s", "version", "calibration"}
        self.seeded_prior: dict | None = None  # a factory calibration installed as the prior
        self.last_refit: dict | None = None
        self.n_refits = 0
        self.new_since_refit = 0  # new pose cells
        self.windows_since_refit = 0
        self.last_refit_t_s: float | None = None
        self.t_last_s: float | None = None
        self.n_samples = 0
        # online model selection: when it last looked, which effects it added, its recent checks
        self.selection: dict = {"last_check_t_s": None, "added": [], "checks": [], "n_checks": 0}
        # the last refit's fit settings (its measured cell noise floor): the bias step's
        # re-estimate and the guard's held-out fit use them; kept in the state
        self._fit_cfg_now: FitConfig | None = None

    # ------------------------------------------------------------------ status
    @property
    def buffer(self) -> PoseStore:
        """The pose store (old name, kept for callers that count poses)."""
        return self.store

    @property
    def status(self) -> str:
        """``uncalibrated``, ``provisional`` or ``calibrated`` (of the published model)."""
        if self.current is None:
            return "uncalibrated"
        return str(self.current["calibration"].get("status", "provisional"))

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
        events: list[dict] = []
        k_now = self.detector.state_.n_pressure
        k_new = 0 if pressure_kpa is None else (np.shape(pressure_kpa)[1] if np.ndim(pressure_kpa) == 2 else None)
        if k_now is not None and k_new is not None and k_new != k_now:
            # the device's pressure channels changed (a firmware, a gateway): the detector's
            # stream ends here (its open still window closed) and a new one starts
            events = self._take_windows(self.detector.flush())
        # no model-dependent gate: the poses that could refute the model are never filtered by it
        windows = self.detector.feed(t_s, acc_g, temp_c=temp_c, pressure_kpa=pressure_kpa, to_cal=None)
        return events + self.feed_windows(windows, int(t_s.size))

    def feed_windows(self, windows, n_samples: int = 0) -> list[dict]:
        """Feed still windows that a detector with this calibrator's ``[detector]`` settings
        found (``StillWindows``); returns the refit outcomes. ``feed_samples`` is the detector
        followed by this; a replay that runs two calibrators on one stream detects once.

        n_samples : int — samples the windows were detected in (counted in ``n_samples``)
        """
        self.n_samples += int(n_samples)
        # the calibrator's clock is the still windows' (not the chunk's last sample): refit
        # times, and so every published version, do not depend on how a stream is chunked
        return self._take_windows(windows)

    def flush(self) -> list[dict]:
        """End of stream: close an open still window and refit if anything is new."""
        events = self._take_windows(self.detector.flush())
        if self.windows_since_refit > 0:
            events.append(self.refit(final=True))
        return events

    def _take_windows(self, w) -> list[dict]:
        if len(w.n) == 0:
            return []
        t_mid = 0.5 * (np.asarray(w.t_start_s) + np.asarray(w.t_end_s))
        return self.feed_poses(w.mean_g, w.sd_g, w.n, t_mid, w.temp_c)

    def feed_poses(self, mean_g, sd_g, n, t_s, temp_c=None, until=None) -> list[dict]:
        """Feed still poses directly (a poses table); returns the refit outcomes.

        Poses are taken in time order, and the scheduler may refit between them, so
        the result does not depend on how a poses table is split into calls.

        Parameters
        ----------
        mean_g, sd_g : ndarray, shape (k, 3), g (sd may be None)
        n : ndarray, shape (k,) — samples per window
        t_s : ndarray, shape (k,), s — window centre times
        temp_c : ndarray, shape (k,), degC, optional
        until : callable (outcome dict) -> bool, optional — stop after the first refit
            outcome it is true of: the poses after that refit are not fed (the calibrator
            is then as if the table had ended there)
        """
        mean_g = np.atleast_2d(np.asarray(mean_g, dtype=float))
        k = mean_g.shape[0]
        if k == 0:
            return []
        t_s = np.broadcast_to(np.asarray(t_s, dtype=float), (k,))
        sd = None if sd_g is None else np.broadcast_to(np.asarray(sd_g, dtype=float), (k, 3))
        n = np.broadcast_to(np.asarray(n, dtype=float), (k,))
        temp = None if temp_c is None else np.broadcast_to(np.asarray(temp_c, dtype=float), (k,))
        events: list[dict] = []
        i = 0
        while i < k:
            # add up to the window where the scheduler could fire: few steps, same result
            room, need_cells = self._room(t_s[i:])
            j = min(k, i + room)
            stats = self.store.add(mean_g[i:j], None if sd is None else sd[i:j], n[i:j], t_s[i:j],
                                   None if temp is None else temp[i:j], rate_hz=self.det_cfg.rate_hz,
                                   max_new_cells=need_cells)
            j = i + stats["consumed"]
            self.new_since_refit += stats["new_info"]
            self.windows_since_refit += stats["added"]
            if np.isfinite(stats["t_max"]):  # the windows stored move the clock; invalid ones (NaN, n = 0) do not
                self.t_last_s = max(self.t_last_s if self.t_last_s is not None else -np.inf, stats["t_max"])
            if self._due():
                events.append(self.refit())
                if until is not None and until(events[-1]):
                    break
            i = j
        return events

    def _room(self, t_s: np.ndarray) -> tuple[int, int]:
        """(windows of this batch that can be added before the scheduler could fire on a
        count of windows or on time, >= 1; new cells after which it could fire, >= 1: the
        pose store stops there, outlier twins included)."""
        s = self.sched_cfg
        k = len(t_s)
        if self.current is None:
            need_cells = max(1 - self.new_since_refit, s.min_poses_first - int(self._usable().sum()), 1)
            room = k
        else:
            cells, windows = self._refit_needs()
            need_cells = max(cells - self.new_since_refit, 1)
            room = max(windows - self.windows_since_refit, 1)
            if self.last_refit_t_s is not None:
                late = np.flatnonzero(t_s - self.last_refit_t_s >= s.refit_every_hours * 3600.0)
                if late.size:
                    room = min(room, int(late[0]) + 1)
        return int(max(1, min(room, k))), int(need_cells)

    def _refit_needs(self) -> tuple[int, int]:
        """New cells and new windows that make a refit due (the larger of the count and the fraction)."""
        s = self.sched_cfg
        n_windows = float(self.store.stats[:, 0].sum()) if len(self.store) else 0.0
        return (max(s.refit_every_poses, int(np.ceil(s.refit_every_fraction * len(self.store)))),
                max(s.refit_every_windows, int(np.ceil(s.refit_every_fraction * n_windows))))

    def _due(self) -> bool:
        s = self.sched_cfg
        if self.windows_since_refit <= 0:
            return False
        if self.current is None:
            return self.new_since_refit > 0 and int(self._usable().sum()) >= s.min_poses_first
        need_cells, need_windows = self._refit_needs()
        if self.new_since_refit >= need_cells or self.windows_since_refit >= need_windows:
            return True
        if self.last_refit_t_s is not None and self.t_last_s is not None:
            return (self.t_last_s - self.last_refit_t_s) >= s.refit_every_hours * 3600.0
        return False

    # ------------------------------------------------------------------ refit
    def _usable(self) -> np.ndarray:
        """Cells the model can use (temperature models need cells with a temperature)."""
        if self.model.uses_temperature:
            return np.isfinite(self.store.mean_temp())
        return np.ones(len(self.store), dtype=bool)

    def prior(self) -> Prior:
        """The prior of every refit: the datasheet, or the installed factory calibration."""
        if self.seeded_prior is not None:
            return Prior(np.asarray(self.seeded_prior["mean"], float), np.asarray(self.seeded_prior["cov"], float))
        return datasheet_prior(self.model, self.fit_cfg)

    def _age_var(self) -> float:
        s = self.sched_cfg
        return s.process_noise_bias_g_per_sqrt_day**2 + s.process_noise_scale_per_sqrt_day**2

    def refit(self, final: bool = False) -> dict:
        """Refit now (the scheduler calls this); returns the outcome dict.

        ``final`` (end of a stream): publish any change that is not negligible, without
        waiting for the minimum interval.
        """
        t_now = float(self.t_last_s if self.t_last_s is not None else 0.0)
        self.n_refits += 1
        usable = self._usable()
        n_cells = int(usable.sum())
        if n_cells < self.guard_cfg.min_poses:
            reason = "insufficient_coverage" if len(self.store) else "no_still_poses"
            return self._refuse(t_now, reason, f"{n_cells} pose cell(s); at least {self.guard_cfg.min_poses} are needed")
        checked: dict = {}
        if self._selection_due(t_now, n_cells):
            switched = self._select(t_now, checked)
            if switched is not None:
                return switched
            usable = self._usable()
            n_cells = int(usable.sum())
        prior = self.prior()
        done = checked.get(self.model.uses_temperature)
        if done is not None and np.array_equal(done[0], usable):
            # the check fitted this model to these cells from this start (the published
            # value) with this state: the same fit, not done twice
            _, data, cfg, _, fit, c_noise = done
        else:
            data = self._pose_data(usable, t_now)
            theta0 = self.initial_params_u if self.current is None else np.asarray(self.current["theta_u"])
            try:
                fit, data, cfg, c_noise = self._fit_store(data, usable, prior, theta0)
            except InputError as exc:
                return self._refuse(t_now, "insufficient_coverage", str(exc))
        fit.extra["noise_scale"] = {"cell_floor_g": float(cfg.sigma_floor_g), "cell_noise_factor": float(c_noise)}
        self._fit_cfg_now = cfg
        screened = self._screen(fit)
        if screened is not None:
            return self._refuse(t_now, screened.reason, screened.message, fit, screened)
        # a candidate the publish rule holds back (no significant change: most refits) is
        # refused before its held-out refit, which only decides whether a candidate that
        # would be published may be: the same versions, one robust fit fewer a held refit
        cal = self._describe(fit, t_now, n_cells, GuardDecision(True, None, ""))
        self._check_recent(cal, fit, data, usable)
        hold = self._hold(fit, cal, t_now, final)
        if hold:
            return self._refuse(t_now, "no_significant_change", hold, fit)
        decision = self._heldout(fit, data, usable, prior)
        if not decision.publish:
            return self._refuse(t_now, decision.reason, decision.message, fit, decision)
        cal["heldout_rms_mg"] = decision.heldout_rms_mg_new
        return self._publish(t_now, fit, cal, decision)

    def _pose_data(self, mask: np.ndarray, t_now: float) -> PoseData:
        """The store's cells ``mask`` as poses to fit: aged (process noise), and, once a bias
        step was found, the cells from before it brought to today's offset.

        A cell whose windows all came before a step has the step's size added to its mean
        (raw unit: the step is a jump of the offset): it keeps telling the scale and the
        axes. The last step's size is refitted with the cells at every fit
        (:meth:`_fit_store`); before an earlier step, a cell's sd also grows by ``[selection]
        step_downweight`` times that step's sd. A cell with windows from both sides
        (coarsened before the step was found) is neither: its sd grows by
        ``step_downweight`` times the step's size."""
        data = self.store.pose_data(mask, t_now, self._age_var())
        steps = self.selection.get("steps") or []
        if not steps:
            return data
        t_first, t_last = self.store.t_first[mask], self.store.t_last[mask]
        shift = np.zeros((len(t_first), 3))
        var = np.zeros(len(t_first))
        for i, st in enumerate(steps):
            tau = float(st["t_step_s"])
            size = np.asarray(st["size_mg"], float) * 1e-3
            sd2 = float(np.sum(np.square(st["sd_mg"]))) * 1e-6
            before = t_last < tau
            mixed = (t_first < tau) & ~before
            shift += before[:, None] * size
            # the last step's size is refitted with the cells (_fit_store); an earlier one's is fixed
            var += (i < len(steps) - 1) * before * sd2 + mixed * (float(size @ size) + sd2)
        if not np.any(var > 0):
            return PoseData(data.mean + shift, data.sd, data.count, data.t_s, data.temp_c)
        k = self.sel_cfg.step_downweight
        sd = np.sqrt(data.sd**2 + (k**2 * var)[:, None])
        return PoseData(data.mean + shift, sd, data.count, data.t_s, data.temp_c)

    def _fit_store(self, data: PoseData, usable: np.ndarray, prior: Prior, theta0) -> tuple:
        """The robust MAP fit of the cells, with the noise the data show; returns
        ``(fit, data, fit_cfg, cell_noise_factor)`` (data with the noise rescaled)."""
        s = self.sched_cfg
        floor = s.cell_floor_g
        cfg = self.fit_cfg.model_copy(update={"sigma_floor_g": floor})
        clusters = self.store.clusters()[usable]
        fit, data = self._fit_with_step(data, usable, prior, theta0, cfg, clusters)
        # the noise the data show: the shared floor as the residuals measure it (between
        # cell_floor_min_g and cell_floor_max_g), the cells' noise scaled (never below the model)
        bounds = (((s.cell_floor_min_g / floor) ** 2, (s.cell_floor_max_g / floor) ** 2), (1.0, 10.0))
        c_floor, c_noise = variance_components(self.model, fit, data, floor, bounds=bounds,
                                               reject_z=self.fit_cfg.reject_z)
        if c_floor != 1.0 or c_noise > 1.0:
            cfg = self.fit_cfg.model_copy(update={"sigma_floor_g": floor * np.sqrt(c_floor)})
            data = PoseData(data.mean, None if data.sd is None else data.sd * np.sqrt(c_noise),
                            data.count, data.t_s, data.temp_c)
            fit, data = self._fit_with_step(data, usable, prior, fit.theta_u, cfg, clusters)
        return fit, data, cfg, c_noise

    def _fit_with_step(self, data: PoseData, usable: np.ndarray, prior: Prior, theta0, cfg: FitConfig,
                       clusters: np.ndarray) -> tuple[FitResult, PoseData]:
        """The robust fit of the current model; after a bias step, jointly with its size.

        ``data`` comes from :meth:`_pose_data` (the cells from before the last step shifted
        by its recorded size). With a step, the model plus ``bias_step`` at its time is fitted
        to the cells as they were; the cells from before it are shifted by that fit's size
        instead, and the current model fitted to them has exactly the joint fit's residuals.
        Its covariance is the joint fit's, mapped to today's offset (offset + step), so the
        step's uncertainty is in the published one. Returns ``(fit, data)``."""
        steps = self.selection.get("steps") or []
        if not steps or not self.model.takes("bias_step"):
            return fit_poses(self.model, data, prior=prior, theta0_u=theta0, cfg=cfg, robust=True,
                             clusters=clusters), data
        tau = float(steps[-1]["t_step_s"])
        recorded = np.asarray(steps[-1]["size_mg"], float) * 1e-3
        before = (self.store.t_last[usable] < tau)[:, None]
        as_was = PoseData(data.mean - before * recorded, data.sd, data.count, data.t_s, data.temp_c)
        large = self._step_model(tau)
        sl = large.index("bias_step")
        start = large.extend_theta(np.asarray(theta0, float), self.model)
        start[sl] = recorded
        joint = fit_poses(large, as_was, prior=self._prior_of(large), theta0_u=start, cfg=cfg, robust=True,
                          clusters=clusters)
        size = joint.theta_u[sl] if joint.success else recorded
        data = PoseData(as_was.mean + before * size, data.sd, data.count, data.t_s, data.temp_c)
        offset = self.model.index("b")
        if joint.success:  # today's offset: the offset before the step plus the step
            small = joint.theta_u[: self.model.n_params].copy()
            small[offset] += size
        else:
            small = theta0
        fit = fit_poses(self.model, data, prior=prior, theta0_u=small, cfg=cfg, robust=True, clusters=clusters)
        if joint.success:
            a = np.zeros((self.model.n_params, large.n_params))
            a[:, : self.model.n_params] = np.eye(self.model.n_params)
            a[np.arange(offset.start, offset.stop), np.arange(sl.start, sl.stop)] = 1.0
            fit.cov_u = a @ joint.cov_u @ a.T
            fit.cov = fit.normalizer.cov_to_raw(self.model, fit.cov_u)
            fit.std = np.sqrt(np.maximum(np.diag(fit.cov), 0.0))
            fit.extra["bias_step_size_mg"] = (size * 1e3).tolist()
        return fit, data

    # ------------------------------------------------------------------ model selection
    def _selection_due(self, t_now: float, n_cells: int) -> bool:
        """A check of the model is due: selection on, a published model, enough cells, and
        ``every_hours`` of data since the last check (or since the first cell)."""
        c = self.sel_cfg
        if not c.enabled or self.current is None or n_cells < c.min_cells or not len(self.store):
            return False
        last = self.selection.get("last_check_t_s")
        since = float(self.store.t_first.min()) if last is None else float(last)
        return t_now - since >= c.every_hours * 3600.0

    def set_selection(self, section_: dict | None) -> None:
        """Replace the ``[selection]`` settings (a service applies its current ones to a
        restored device); the selection history is kept. None: the defaults, and no
        ``selection`` section in the state, as a calibrator made without one has."""
        self.sel_cfg = SelectionConfig.from_section(section_)
        if section_ is None:
            self.config.pop("selection", None)
        else:
            self.config["selection"] = dict(section_)

    def _prior_of(self, target: ErrorModel) -> Prior:
        """The prior of another model: this one's (datasheet or installed) for the shared terms."""
        return extend_prior(self.prior(), self.model, target, datasheet_prior(target, self.fit_cfg))

    def _candidate(self, effect: str) -> ErrorModel:
        """This model with ``effect`` added; a new time drift is referred to the first cell's
        time (an epoch-based clock would otherwise put t_ref decades away)."""
        names = self.model.effects + (effect,)
        t_ref = self.model.t_ref_s
        if effect == "time_drift_bias" and "time_drift_bias" not in self.model.effects and len(self.store):
            t_ref = float(self.store.t_first.min())
        return ErrorModel("+".join((self.model.base,) + names), self.model.temp_ref_c, t_ref)

    def _select(self, t_now: float, prepared: dict | None = None) -> dict | None:
        """One check of the model (see :mod:`selfcal.selection`); the switch event, or None.

        Depends only on the pose store and the published model (not on what an earlier
        refit left in memory), so a calibrator restored from its state decides the same.
        ``prepared`` (filled when given): the current model's fits the check made, by
        whether the cells need a temperature, ``(mask, data, fit config, cross-validation
        cache, fit, cell noise factor)`` as :meth:`_fit_store` gives them; when the check
        changes nothing, the refit that follows is the one of the same mask."""
        c = self.sel_cfg
        self.selection["last_check_t_s"] = t_now
        self.selection["n_checks"] = int(self.selection.get("n_checks", 0)) + 1
        theta = np.asarray(self.current["theta_u"], float)
        temps = self.store.mean_temp()
        folds_all = self.store.folds()
        clusters_all = self.store.clusters()
        clip = c.clip_mg * 1e-3
        results: list[tuple[str, Comparison]] = []
        prepared = {} if prepared is None else prepared

        def cells(with_temp: bool) -> tuple:
            """(mask, data with the noise the current model's fit shows, fit config, small-model CV cache,
            the current model's fit on them)."""
            if with_temp not in prepared:
                mask = np.isfinite(temps) if with_temp else np.ones(len(self.store), dtype=bool)
                other = prepared.get(not with_temp)
                if other is not None and np.array_equal(other[0], mask):
                    # every cell has a temperature: the same cells, so the same fits (and
                    # held-out residuals) as the other key's, not made twice
                    prepared[with_temp] = other
                else:
                    data = self._pose_data(mask, t_now)
                    fit, data, cfg, c_noise = self._fit_store(data, mask, self.prior(), theta)
                    prepared[with_temp] = (mask, data, cfg, {}, fit, c_noise)
            return prepared[with_temp][:5]

        try:
            self._reestimate_step(t_now)
            # drop: an effect selection added that no longer pays
            for e in [x for x in self.selection.get("added", []) if x in self.model.effects]:
                small = self.model.with_effects(tuple(x for x in self.model.effects if x != e))
                mask, data, cfg, _, _ = cells(self.model.uses_temperature)
                comp = compare(small, self.model, data, folds_all[mask], prior_small=self._prior_of(small),
                               prior_large=self.prior(), theta_small=small.extend_theta(theta, self.model),
                               fit_cfg=cfg, clip_g=clip, clusters=clusters_all[mask],
                               cv_only_if=wald_not_significant_to_keep(c))
                results.append(("drop", comp))
                if stops_paying(comp, c):
                    return self._switch(small, comp, "dropped", t_now, results)
            # add: the best supported candidate
            supported: list[Comparison] = []
            for e in c.candidates:
                if e in self.model.effects or not self.model.takes(e):
                    continue
                large = self._candidate(e)
                mask, data, cfg, cv_small, small_fit = cells(large.uses_temperature)
                if mask.sum() < c.min_cells or selection_applicable(e, data, c):
                    continue
                comp = compare(self.model, large, data, folds_all[mask], prior_small=self.prior(),
                               prior_large=self._prior_of(large), theta_small=theta, fit_cfg=cfg, clip_g=clip,
                               cv_small=cv_small, clusters=clusters_all[mask], cv_only_if=wald_significant(c),
                               small_fit=small_fit, screen_if=wald_far_below(c))
                results.append(("add", comp))
                if supports(comp, c):
                    supported.append(comp)
            # did the offset jump? A step imitates a drift (and a drift a step): both are
            # asked, and the one with the larger held-out gain is taken
            step = self._test_step(cells, folds_all, clusters_all, clip, theta, results) if c.step else None
        except (InputError, np.linalg.LinAlgError) as exc:  # a check that cannot be made is logged, never raised
            self._log_check(t_now, results, f"not decided: {exc}")
            return None
        if step is not None and (not supported or step[1].gain_rel > max(x.gain_rel for x in supported)):
            found = self._step_found(step[0], step[1], t_now, results)
            if found is not None:
                return found
        if not supported:
            self._log_check(t_now, results, None)
            return None
        # the largest relative held-out gain wins. Two can be supported at once (a temperature
        # bias and a scale on flat poses): waiting for data that separate them would leave the
        # device on the base model, which predicts worse than either, so the better one goes in
        # now, and a rival that went in first is dropped once the other has joined
        # a secondary effect (the cross-axis tempcos: on flat poses nearly a copy of a
        # temperature bias) goes in when no primary one is supported, or when its terms'
        # evidence (Wald chi2) beats the best primary's by secondary_margin_chi2
        primary = [x for x in supported if x.effect not in SECONDARY_EFFECTS]
        best = max(primary or supported, key=lambda x: x.gain_rel)
        if primary:
            bar = max(p.wald_chi2 for p in primary) + c.secondary_margin_chi2
            strong = [x for x in supported if x.effect in SECONDARY_EFFECTS and x.wald_chi2 >= bar]
            if strong:
                best = max(strong, key=lambda x: x.gain_rel)
        return self._switch(ErrorModel(best.large, self.model.temp_ref_c, self._candidate(best.effect).t_ref_s),
                            best, "added", t_now, results)

    def _step_model(self, tau: float) -> ErrorModel:
        """This model plus ``bias_step`` at ``tau`` (s)."""
        return ErrorModel(f"{self.model.name}+bias_step", self.model.temp_ref_c, self.model.t_ref_s, float(tau))

    def _reestimate_step(self, t_now: float, force: bool = False) -> None:
        """The size of the last step found, refitted on the cells since the step before it at
        their own weights (a step found soon after it happened is known from few cells; the
        down-weighting of the cells before it follows what the data say now). Cells with
        windows from both sides of the step are left out, and a refit less precise than the
        size recorded is not taken (the store drops its oldest cells when it is full) unless
        ``force`` (the step just found: its first size came from every cell)."""
        steps = self.selection.get("steps") or []
        if not steps or not self.model.takes("bias_step"):
            return
        last = steps[-1]
        since = float(steps[-2]["t_step_s"]) if len(steps) > 1 else -np.inf
        # cells with windows from both sides of the step (coarsened before it was found) are
        # neither the old offset nor the new: they would pull the size towards zero
        usable = self._usable() & (self.store.t_first >= since) & ~self.store.straddles(float(last["t_step_s"]))
        if usable.sum() < self.sel_cfg.min_cells:
            return
        large = self._step_model(float(last["t_step_s"]))
        data = self.store.pose_data(usable, t_now, self._age_var())
        theta0 = large.extend_theta(np.asarray(self.current["theta_u"], float), self.model)
        theta0[large.index("bias_step")] = np.asarray(last["size_mg"], float) * 1e-3
        fit = fit_poses(large, data, prior=self._prior_of(large), theta0_u=theta0, cfg=self._fit_cfg_now or self.fit_cfg,
                        robust=True)
        if not fit.success:
            return
        sl = large.index("bias_step")
        if not force and np.sum(np.diag(fit.cov_u)[sl]) > np.sum((np.asarray(last["sd_mg"], float) * 1e-3) ** 2):
            return  # less precise than the size recorded (the cells from before the step were coarsened away)
        last["size_mg"] = [round(float(x), 4) for x in fit.theta_u[sl] * 1e3]
        last["sd_mg"] = [round(float(x), 4) for x in np.sqrt(np.diag(fit.cov_u)[sl]) * 1e3]
        last["reestimated_t_s"] = float(t_now)

    def _test_step(self, cells, folds_all, clusters_all, clip: float, theta: np.ndarray,
                   results: list) -> tuple[float, Comparison] | None:
        """One question of a check: did the offset jump (a shock, a battery change) since the
        last step found? The best of ``step_times`` candidate times (:mod:`selfcal.steps`)
        is tested like an effect (:func:`compare`: Wald test of the step at ``alpha /
        step_times``, held-out cells). ``(step time s, comparison)`` when supported, else None."""
        c = self.sel_cfg
        if not self.model.takes("bias_step"):  # seed9 (a demonstration model) takes nothing
            return None
        mask, data, cfg, cv_small, small = cells(self.model.uses_temperature)
        steps = self.selection.get("steps") or []
        recent = data.t_s > (float(steps[-1]["t_step_s"]) if steps else -np.inf)
        if recent.sum() < c.min_cells or float(np.ptp(data.t_s[recent])) < c.min_time_span_days * 86400.0:
            return None
        times = step_times(data.t_s[recent], c)
        if len(times) == 0:
            return None
        sigma, q = whitened_basis(small, data.mean, data.temp_c, data.t_s)
        tau, _ = scan_step(small, data.mean, data.temp_c, data.t_s, sigma, q, times)
        large = self._step_model(tau)
        level = c.model_copy(update={"alpha": c.alpha / len(times)})
        comp = compare(self.model, large, data, folds_all[mask], prior_small=self.prior(),
                       prior_large=self._prior_of(large), theta_small=theta, fit_cfg=cfg, clip_g=clip,
                       cv_small=cv_small, clusters=clusters_all[mask], cv_only_if=wald_significant(level),
                       small_fit=small, screen_if=wald_far_below(level))
        results.append(("step", comp))
        if not supports(comp, level):
            return None
        return refine_time(small, data.mean, data.temp_c, data.t_s, sigma, q, times, tau), comp

    def _step_found(self, tau: float, comp: Comparison, t_now: float, results: list) -> dict | None:
        """Record a bias step at ``tau`` (s), refit the current model jointly with the step's
        size (:meth:`_fit_with_step`), and publish that as a version; None if it does not fit."""
        fit_l = comp.large_fit
        sl = fit_l.model.index("bias_step")
        size, cov = fit_l.theta_u[sl], fit_l.cov_u[sl, sl]
        record = {"change": "bias_step", "t_step_s": float(tau), "found_t_s": float(t_now),
                  "size_mg": [round(float(x), 4) for x in size * 1e3],
                  "sd_mg": [round(float(x), 4) for x in np.sqrt(np.diag(cov)) * 1e3],
                  "heldout_rms_mg_before": rounded(comp.heldout_rms_small_mg, 4),
                  "heldout_rms_mg_after": rounded(comp.heldout_rms_large_mg, 4),
                  "heldout_z": rounded(comp.heldout_z, 3), "n_heldout_cells": comp.n_heldout, "wald_chi2": round(comp.wald_chi2, 3)}
        before = list(self.selection.get("steps") or [])
        self.selection["steps"] = before + [dict(record)]  # re-estimated later; the version keeps this
        # the test's fit had every cell, those with windows from both sides too: the size the
        # history is corrected by comes from the others
        self._reestimate_step(t_now, force=True)
        fit, cfg, c_noise, n_cells, why = self._refit_for_change(t_now, np.asarray(self.current["theta_u"], float))
        if why:
            self.selection["steps"] = before  # the history stays as it was: the refit did not fit
            self._log_check(t_now, results, f"bias step at {tau / 3600:.1f} h: not taken ({why})")
            return None
        self._log_check(t_now, results, f"bias step at {tau / 3600:.1f} h")
        self.store.add_barrier(tau)
        message = (f"bias step of ({', '.join(f'{x:.2f}' for x in record['size_mg'])}) mg at {tau / 3600:.1f} h: "
                   f"the cells from before it are fitted with the step (held-out RMS {record['heldout_rms_mg_before']} -> "
                   f"{record['heldout_rms_mg_after']} mg on {comp.n_heldout} cells with the step, z "
                   f"{comp.heldout_z:.1f}; step chi2 {comp.wald_chi2:.1f} on 3)")
        return self._publish_change(fit, cfg, c_noise, t_now, n_cells, message, record, "bias_step", "bias_step")

    def _refit_for_change(self, t_now: float, theta0: np.ndarray) -> tuple:
        """Refit the store under the current model (jointly with the last bias step) for a change a
        check decided; ``(fit, fit config, cell noise factor, cells, why not)``, ``why not``
        None when the fit converged and is plausible."""
        try:
            usable = self._usable()
            fit, _, cfg, c_noise = self._fit_store(self._pose_data(usable, t_now), usable, self.prior(), theta0)
        except (InputError, np.linalg.LinAlgError) as exc:
            return None, None, 1.0, 0, str(exc)
        why = None if fit.success else f"the fit did not converge: {fit.message}"
        return fit, cfg, c_noise, int(usable.sum()), why or implausible(self.model, fit.theta_u, self.guard_cfg)

    def _publish_change(self, fit: FitResult, cfg: FitConfig, c_noise: float, t_now: float, n_cells: int,
                        message: str, record: dict, key: str, mode: str) -> dict:
        """Publish a refit that a model check decided (a switch, a bias step) at once: the
        version carries ``record`` under ``key`` and the event says ``mode``."""
        fit.extra["noise_scale"] = {"cell_floor_g": float(cfg.sigma_floor_g), "cell_noise_factor": float(c_noise)}
        self._fit_cfg_now = cfg
        decision = GuardDecision(True, None, message, record["heldout_rms_mg_after"], record["heldout_rms_mg_before"])
        cal = self._describe(fit, t_now, n_cells, decision)
        cal[key] = record
        event = self._publish(t_now, fit, cal, decision)
        event["mode"] = self.last_refit["mode"] = mode
        event[key] = self.last_refit[key] = record
        return event

    def _log_check(self, t_now: float, results: list, decision: str | None) -> None:
        """Keep the last 10 checks: ``{"t_s", "decision" (None: no change), "tested": [comparison dicts]}``."""
        self.selection["checks"] = (self.selection.get("checks", []) + [{
            "t_s": t_now, "decision": decision,
            "tested": [dict(comp.to_dict(), test=kind) for kind, comp in results]}])[-10:]

    def _switch(self, target: ErrorModel, comp: Comparison, what: str, t_now: float, results: list) -> dict | None:
        """Refit the store under ``target`` and publish it as a model change; None if it cannot be."""
        old_model, old_seed = self.model, self.seeded_prior
        if self.seeded_prior is not None:
            p = self._prior_of(target)
            self.seeded_prior = {"mean": p.mean.tolist(), "cov": p.cov.tolist()}
        theta0 = target.extend_theta(np.asarray(self.current["theta_u"], float), self.model)
        self.model = target
        try:
            fit, cfg, c_noise, n_cells, why = self._refit_for_change(t_now, theta0)
        except BaseException:
            self.model, self.seeded_prior = old_model, old_seed  # stay, whatever went wrong
            raise
        if why:
            self.model, self.seeded_prior = old_model, old_seed  # stay: the switch did not fit
            self._log_check(t_now, results, f"{what} {comp.effect}: not switched ({why})")
            return None
        self._log_check(t_now, results, f"{what} {comp.effect}")
        added = [x for x in self.selection.get("added", []) if x in target.effects]
        if what == "added":
            added.append(comp.effect)
        self.selection["added"] = added
        record = change_record(comp, what, old_model.name, target.name)
        message = (f"model {old_model.name} -> {target.name}: {comp.effect} {what} (held-out RMS "
                   f"{record['heldout_rms_mg_before']} -> {record['heldout_rms_mg_after']} mg on {comp.n_heldout} "
                   f"cells, z {comp.heldout_z:.1f} for the larger model; effect terms chi2 {comp.wald_chi2:.1f} "
                   f"on {comp.wald_dof})")
        return self._publish_change(fit, cfg, c_noise, t_now, n_cells, message, record, "model_change",
                                    "model_switch")

    def _screen(self, fit: FitResult) -> GuardDecision | None:
        """The guard's checks of the fit alone (converged, plausible parameters and
        residuals, a determined direction for a first version): the refusal, or None."""
        g = self.guard_cfg
        if not fit.success:
            return GuardDecision(False, "not_converged", f"LM did not converge: {fit.message}")
        why = implausible(self.model, fit.theta_u, g)
        if why:
            return GuardDecision(False, "implausible", why)
        inl = np.abs(fit.residuals_g / fit.sigma_g) <= self.fit_cfg.reject_z
        rms_in = float(np.sqrt(np.mean(fit.residuals_g[inl] ** 2)) * 1e3) if inl.any() else np.inf
        if rms_in > g.max_residual_rms_mg:
            return GuardDecision(
                False, "implausible", f"fit residual RMS {rms_in:.2f} mg exceeds {g.max_residual_rms_mg} mg")
        if self.current is None and fit.n_determined_directions < g.min_determined:
            return GuardDecision(False, "insufficient_coverage", "the poses determine no parameter direction")
        return None

    def _heldout(self, fit: FitResult, data: PoseData, usable: np.ndarray, prior: Prior) -> GuardDecision:
        """The guard's held-out comparison: the candidate refitted without one fold of the
        cells that came after the published model, and that fold's clipped RMS against
        the published model's (a robust fit: the costly half of the guard)."""
        g = self.guard_cfg
        # held out: one fold (rotating), and only cells that appeared after the published
        # model was fitted, so that neither model has seen them
        fold = self.n_refits % self.pose_cfg.folds
        t_first = self.store.t_first[usable]
        held = self.store.folds()[usable] == fold
        if self.current is not None:
            held &= t_first > float(self.current.get("t_data_s", self.current["t_s"]))
        label = "published model" if self.current else "uncalibrated (nominal) model"
        if held.sum() < g.min_heldout or (~held).sum() < g.min_poses:
            return GuardDecision(True, None, f"{int(held.sum())} unseen held-out cell(s): no comparison", None, None)
        cur_theta = np.asarray(self.current["theta_u"]) if self.current else self.model.nominal()
        try:
            cv = fit_poses(self.model, data.subset(~held), prior=prior, theta0_u=fit.theta_u,
                           cfg=self._fit_cfg_now.model_copy(update={"curvature_cov": False}), robust=True)
        except InputError as exc:
            return GuardDecision(False, "insufficient_coverage", f"held-out refit: {exc}")
        ref = data.subset(held)
        clip = g.max_residual_rms_mg * 1e-3
        new = _clipped_rms_mg(self.model, cv.theta_u, ref, clip)
        cur = _clipped_rms_mg(self.model, cur_theta, ref, clip)
        where = f"{int(held.sum())} held-out cells (fold {fold}) that neither model was fitted to"
        if new > cur * (1 + g.tolerance_rel) + g.tolerance_mg:
            return GuardDecision(
                False, "worse_than_current", f"held-out RMS {new:.3f} mg on {where} is worse than the {label}'s {cur:.3f} mg",
                new, cur)
        return GuardDecision(True, None, f"held-out RMS {new:.3f} mg vs {label} {cur:.3f} mg on {where}", new, cur)

    def _check_recent(self, cal: dict, fit: FitResult, data: PoseData, usable: np.ndarray) -> None:
        """A ``calibrated`` candidate stays so only if the cells that came since the last
        version agree with it: the score statistic of an offset jump at the start of those
        cells (3 dof, at the fit, with the fitted model's columns projected out and the
        whitened residuals clipped at ``reject_z``) must be below the chi2 quantile of
        ``recent_check_alpha``. A bias step is seen here within hours, long before a model
        check can name it (it needs 15 % of the cells after it); until then the device is
        ``provisional``, with the reason in ``status_reason`` and the test in
        ``recent_jump``, and its ``predicted_sphere_rms_mg`` includes the jump those cells
        show (its estimate and covariance on the offsets, from where among them it fits
        best: :func:`selfcal.steps.latest_jump`). After a flagged version the
        cells are counted from where its check counted, so the flag holds until a version
        passes that test (a model check that names the step fits it away)."""
        s = self.sched_cfg
        if cal["status"] != "calibrated" or self.current is None or s.recent_check_alpha <= 0:
            return
        # a published version this check flagged: count the cells from where its check did,
        # so that a refit a few hours later (too few cells of its own to test) does not
        # turn the same disagreement back into 'calibrated'
        flag = self.current["calibration"].get("recent_jump")
        t_prev = float(flag["since_t_s"]) if flag else float(self.current.get("t_data_s", self.current["t_s"]))
        recent = self.store.t_first[usable] > t_prev
        n = int(recent.sum())
        threshold = float(_chi2_isf(3, s.recent_check_alpha))
        score = None
        if not (n < s.recent_check_min_cells or n == len(recent) or len(fit.residuals_g) != len(recent)):
            jac = fit.model.residual_jac(fit.theta_u, data.mean, data.temp_c, data.t_s)[1] / fit.sigma_g[:, None]
            q, _ = np.linalg.qr(jac)
            rw = np.clip(fit.residuals_g / fit.sigma_g, -self.fit_cfg.reject_z, self.fit_cfg.reject_z)
            try:
                score = jump_score(jac[:, 0:3], q, rw, recent)
            except np.linalg.LinAlgError:
                score = None
        if score is None:
            if flag:  # nothing can clear the flag yet: as published
                cal["status"] = "provisional"
                cal["status_reason"] = self.current["calibration"].get("status_reason")
                cal["recent_jump"] = dict(flag)
            return
        if score > threshold:
            # until a model check names the step, the promise covers the jump these cells show,
            # from where among them it fits best (a step after most of them is not averaged
            # over all of them: the sensor as it is now)
            _, jump, jump_cov = latest_jump(jac[:, 0:3], q, rw, self.store.t_first[usable], recent)
            cov = np.zeros((self.model.n_params, self.model.n_params))
            cov[0:3, 0:3] = np.outer(jump, jump) + jump_cov
            jump_mg = predicted_sphere_rms_mg(self.model, fit.theta_u, cov, cal["t_s"])
            cal["predicted_sphere_rms_mg"] = float(np.hypot(cal["predicted_sphere_rms_mg"], jump_mg))
            cal["status"] = "provisional"
            cal["status_reason"] = (f"the {n} cells since the last version that agreed disagree with the model (offset jump "
                                    f"chi2 {score:.1f} on 3 > {threshold:.1f}): a bias step?")
            cal["recent_jump"] = {"since_t_s": t_prev, "chi2": score, "threshold": threshold,
                                  "sphere_rms_mg": jump_mg}

    def _determined(self, cov_u: np.ndarray) -> np.ndarray:
        """Parameters whose sd is below ``determined_ratio`` of the datasheet's, (p,) bool."""
        ds = np.diag(datasheet_prior(self.model, self.fit_cfg).cov)
        return np.sqrt(np.diag(cov_u) / ds) < self.fit_cfg.determined_ratio

    def _status_of(self, det: np.ndarray, predicted_mg: float, n_cells: int) -> str:
        n_base = 6 if self.model.base == "scale6" else 9
        ok = bool(det[:n_base].all()) and predicted_mg <= self.sched_cfg.calibrated_max_sphere_mg
        return "calibrated" if ok and n_cells >= self.sched_cfg.calibrated_min_poses else "provisional"

    def _describe(self, fit: FitResult, t_now: float, n_cells: int, decision: GuardDecision) -> dict:
        cal = fit.to_calibration(unit="g")
        det = self._determined(fit.cov_u)
        names = self.model.param_names
        cal["determined"] = [n for n, d in zip(names, det) if d]
        cal["undetermined"] = [n for n, d in zip(names, det) if not d]
        predicted_model = predicted_sphere_rms_mg(self.model, fit.theta_u, fit.cov_u, t_now)
        undetermined, determined, effects = self._unmodelled(fit, t_now)
        unmodelled = float(np.hypot(undetermined, determined))
        predicted = float(np.hypot(predicted_model, unmodelled))
        cal["predicted_sphere_rms_mg"] = predicted
        cal["predicted_sphere_rms_mg_model"] = predicted_model
        cal["unmodelled"] = {"effects": effects, "sphere_rms_mg": unmodelled, "undetermined_mg": undetermined,
                             "determined_mg": determined}
        cal["status"] = self._status_of(det, predicted, n_cells)
        cal["n_poses"] = n_cells
        cal["n_windows"] = int(self.store.window_counts().sum())
        cal["n_rejected"] = int(fit.extra.get("n_rejected", 0))
        cal["refit_mode"] = "full"
        cal["noise_scale"] = fit.extra.get("noise_scale")
        cal["t_s"] = t_now
        cal["provenance"] = self.store.summary()
        cal["heldout_rms_mg"] = decision.heldout_rms_mg_new
        return cal

    def _unmodelled(self, fit: FitResult, t_now: float) -> tuple[float, float, list[str]]:
        """What the candidate effects this model lacks could add to the whole-sphere error
        (mg, :func:`selfcal.fit.unmodelled_sphere_rms_mg`: what the cells leave open, what
        they say the effects are), and their names.

        The promise of a version (``predicted_sphere_rms_mg``) holds for the sensor as it
        may be, not only for the model: an effect that no pose of this device can tell
        apart (a quadratic nonlinearity when every pose is near an axis) stays at its
        datasheet size in it. A temperature effect counts when every cell has a
        temperature; ``[scheduler] predict_unmodelled = false`` leaves them all out."""
        if not self.sched_cfg.predict_unmodelled or fit.cells_u is None or fit.poses is None:
            return 0.0, 0.0, []
        _, temp, _ = fit.cells_u
        has_temp = temp is not None and bool(np.all(np.isfinite(temp)))
        effects = []
        for e in self.sel_cfg.candidates:
            if e in self.model.effects or e in effects or (e.startswith("temperature") and not has_temp):
                continue
            if self.model.takes(e):  # (seed9 takes none, the cross-axis tempcos need affine9)
                effects.append(e)
        if not effects:
            return 0.0, 0.0, []
        t_ref = self.model.t_ref_s
        if "time_drift_bias" in effects and len(self.store):
            t_ref = float(self.store.t_first.min())  # as a candidate drift is referred (_candidate)
        extended = ErrorModel("+".join((self.model.base,) + self.model.effects + tuple(effects)),
                              self.model.temp_ref_c, t_ref)
        prior = self._prior_of(extended)
        undetermined, determined = unmodelled_sphere_rms_mg(fit, extended, self.prior(), prior, t_now,
                                                            self._fit_cfg_now or self.fit_cfg)
        if not (np.isfinite(undetermined) and np.isfinite(determined)):
            # (a singular information or a failed fit: the prior alone, as if no pose told anything)
            undetermined = predicted_sphere_rms_mg(extended, extended.extend_theta(fit.theta_u, self.model), prior.cov,
                                                   t_now)
            determined = 0.0
        return float(undetermined), float(determined), effects

    def _hold(self, fit: FitResult, cal: dict, t_now: float, final: bool = False) -> str | None:
        """Why a passing candidate is not published (no significant change), or None."""
        if self.current is None:
            return None
        if cal["status"] != self.status:
            return None
        s = self.sched_cfg
        since = t_now - float(self.current["t_s"])
        if since < s.publish_min_interval_s and not final:
            return f"last version {since:.0f} s ago (at most one per {s.publish_min_interval_s:g} s of data)"
        d = fit.theta_u - np.asarray(self.current["theta_u"], float)
        try:
            d2 = float(d @ np.linalg.solve(fit.cov_u, d))
        except np.linalg.LinAlgError:
            d2 = np.inf
        thr = float(_chi2_isf(self.model.n_params, 1.0 - (s.publish_final_chi2_quantile if final
                                                           else s.publish_chi2_quantile)))
        if d2 > thr:  # the data say the published model is off
            return None
        # more certain: the model's own prediction (the unmodelled effects' share shrinks
        # only as the cells come to determine them, and is no better estimate of the model)
        current = self.current["calibration"]
        pred_cur = current.get("predicted_sphere_rms_mg_model", current.get("predicted_sphere_rms_mg"))
        pred_new = cal.get("predicted_sphere_rms_mg_model", cal["predicted_sphere_rms_mg"])
        factor = s.publish_final_improve_factor if final else s.publish_improve_factor
        improved = pred_cur is None or pred_new * factor <= float(pred_cur)
        # more certain, but not significantly different: a calibrated model is replaced only
        # if the new one moves it little over the whole sphere (shift = the published model's
        # sphere error were the new one the truth), so that a calibrated version can never be
        # worse than the one it replaces by more than that (triangle inequality of the sphere
        # RMS). A provisional model is expected to move: it is replaced by any better one.
        shift = predicted_sphere_rms_mg(self.model, fit.theta_u, np.outer(d, d), t_now) if np.all(np.isfinite(d)) else np.inf
        max_shift = s.publish_final_max_shift_mg if final else s.publish_max_shift_mg
        if improved and (cal["status"] != "calibrated" or shift <= max_shift):
            return None
        return (f"change chi2 {d2:.1f} <= {thr:.1f}; predicted sphere error (the model's) {pred_new:.3f} mg "
                f"vs published {float(pred_cur):.3f} mg, whole-sphere shift {shift:.3f} mg")

    def _refuse(self, t_now, reason, message, fit=None, decision=None) -> dict:
        self.new_since_refit = 0  # wait for new poses before trying again
        self.windows_since_refit = 0
        self.last_refit_t_s = t_now
        self.last_refit = {
            "t_s": t_now, "published": False, "reason": reason, "message": message, "mode": "full",
            "n_poses": len(self.store),
            "fit_ms": None if fit is None else fit.fit_ms,
            "heldout_rms_mg_new": None if decision is None else decision.heldout_rms_mg_new,
            "heldout_rms_mg_current": None if decision is None else decision.heldout_rms_mg_current,
        }
        return dict(self.last_refit, calibration=None)

    def _publish(self, t_now, fit: FitResult, cal: dict, decision: GuardDecision) -> dict:
        version = (self.current["version"] if self.current else 0) + 1
        self.current = {
            "theta_u": fit.theta_u.tolist(),
            "cov_u": fit.cov_u.tolist(),
            "t_s": t_now,
            "t_data_s": float(self.store.t_last.max()) if len(self.store) else t_now,
            "version": version,
            "calibration": cal,
        }
        self.new_since_refit = 0
        self.windows_since_refit = 0
        self.last_refit_t_s = t_now
        self.last_refit = {
            "t_s": t_now, "published": True, "reason": None, "message": decision.message, "mode": "full",
            "n_poses": len(self.store), "fit_ms": fit.fit_ms, "version": version,
            "heldout_rms_mg_new": decision.heldout_rms_mg_new,
            "heldout_rms_mg_current": decision.heldout_rms_mg_current,
        }
        return dict(self.last_refit, calibration=self.calibration())

    def seed_calibration(self, params: dict[str, float], std: dict[str, float] | None = None, t_s: float = 0.0) -> None:
        """Install a factory calibration (params in g units) as the published model and the prior of later refits."""
        theta = self.model.from_dict(params)
        bad = [n for n, v in zip(self.model.param_names, theta) if not np.isfinite(v)]
        if bad:  # (a NaN parameter was installed: NaN predictions, every later refit refused)
            raise InputError(f"params: {', '.join(bad)} not finite")
        sd = np.sqrt(np.diag(datasheet_prior(self.model, self.fit_cfg).cov))
        if std:
            unknown = sorted(set(std) - set(self.model.param_names))
            if unknown:
                raise InputError(f"std: unknown names {unknown} (model {self.model.name}: "
                                 f"{list(self.model.param_names)})")
            sd = np.array([float(std.get(n, s)) for n, s in zip(self.model.param_names, sd)])
        # a smaller sd squared underflows or makes the prior's covariance singular: every later
        # refit raised (LinAlgError) and the device's batches were all rejected
        # a larger one squared overflows: the refits' eigen-decompositions then failed
        if np.any(~np.isfinite(sd)) or np.any(sd < SEED_STD_MIN) or np.any(sd > SEED_STD_MAX):
            raise InputError(f"std: every standard deviation must be finite, >= {SEED_STD_MIN:g} and "
                             f"<= {SEED_STD_MAX:g}")
        cov = np.diag(sd**2)
        matrix, offset = self.model.linear(theta)
        det = self._determined(cov)
        names = self.model.param_names
        predicted = predicted_sphere_rms_mg(self.model, theta, cov, t_s)
        cal = {
            "format": "selfcal-calibration", "format_version": 1, "model": self.model.name, "unit": "g",
            "params": self.model.to_dict(theta), "std": {n: float(s) for n, s in zip(names, sd)},
            "determined": [n for n, d in zip(names, det) if d],
            "undetermined": [n for n, d in zip(names, det) if not d],
            "n_poses": len(self.store), "n_windows": int(self.store.window_counts().sum()), "residual_rms_mg": None,
            "matrix": matrix.tolist(), "offset": offset.tolist(), "refit_mode": "seeded", "t_s": t_s,
            "temp_ref_c": self.model.temp_ref_c, "t_ref_s": self.model.t_ref_s,
            "predicted_sphere_rms_mg": predicted,
            "status": self._status_of(det, predicted, self.sched_cfg.calibrated_min_poses),
        }
        version = (self.current["version"] if self.current else 0) + 1
        self.seeded_prior = {"mean": theta.tolist(), "cov": cov.tolist()}
        self.current = {"theta_u": theta.tolist(), "cov_u": cov.tolist(), "t_s": t_s, "t_data_s": t_s,
                        "version": version, "calibration": cal}

    # ------------------------------------------------------------------ state
    def state(self, store_rows: bool = True) -> dict:
        """The whole state as a JSON-serialisable dict (``store_rows=False``: without the
        pose store's per-cell fields, for a checkpoint patch)."""
        return {
            "format": "selfcal-calibrator-state",
            "format_version": STATE_FORMAT_VERSION,
            "config": self.config,
            "model": self.model.name,
            "temp_ref_c": self.model.temp_ref_c,
            "t_ref_s": self.model.t_ref_s,
            "initial_params_u": None if self.initial_params_u is None else self.initial_params_u.tolist(),
            "detector": self.detector.state_dict(),
            "store": self.store.to_json(rows=store_rows),
            "current": self.current,
            "seeded_prior": self.seeded_prior,
            "last_refit": self.last_refit,
            "n_refits": self.n_refits,
            "new_since_refit": self.new_since_refit,
            "windows_since_refit": self.windows_since_refit,
            "last_refit_t_s": self.last_refit_t_s,
            "t_last_s": self.t_last_s,
            "n_samples": self.n_samples,
            "selection": self.selection,
            "fit_sigma_floor_g_now": None if self._fit_cfg_now is None else float(self._fit_cfg_now.sigma_floor_g),
        }

    def to_json(self) -> str:
        """Serialise the whole state to a JSON string (exact round trip)."""
        return json.dumps(self.state(), allow_nan=True, separators=(",", ":"))

    def checkpoint_base(self, text: str) -> CheckpointBase:
        """What a checkpoint writer keeps of the full state ``text`` (this calibrator's
        :meth:`to_json`, just written as a base) to patch it later."""
        return checkpoint_base_of(text, self.store, field_digests(self.state(store_rows=False)))

    def checkpoint_patch(self, base: CheckpointBase) -> str:
        """The state as a patch against ``base`` (text; usually a few % of the full state)."""
        return make_patch(self.state(store_rows=False), self.store, base)

    @classmethod
    def from_checkpoint(cls, base_text: str, patch_text: str | None = None) -> tuple["OnlineCalibrator", CheckpointBase]:
        """A calibrator from a stored base and its latest patch (None: the base alone), and
        the base's :class:`CheckpointBase` for the next patches."""
        if patch_text is None:
            d = json.loads(base_text)
            fields = field_digests(d)  # as stored (before from_json reads d)
            obj = cls.from_json(d)
            # a patch is made against the rows of the text; a state of format 1 has none
            # (its poses are re-filed on load): its next checkpoint is in full
            return obj, (checkpoint_base_of(base_text, obj.store, fields)
                         if d.get("format_version") == STATE_FORMAT_VERSION else None)
        state, base = apply_patch(base_text, patch_text, encode=False)
        return cls.from_json(state), base

    @classmethod
    def from_json(cls, text: str | dict) -> "OnlineCalibrator":
        """Rebuild a calibrator from :meth:`to_json` output (format 2; format 1 states are migrated).

        A state that is not JSON, lacks a field, or whose parts do not fit together (a
        model's parameters of another length, a pose store of another config) is an
        InputError naming what is wrong, not a late failure at the first refit."""
        try:
            d = json.loads(text) if isinstance(text, (str, bytes)) else text
        except (ValueError, UnicodeDecodeError) as exc:
            raise InputError(f"calibrator state: not JSON ({exc})") from None
        if not isinstance(d, dict) or d.get("format") != "selfcal-calibrator-state" or d.get(
                "format_version") not in (1, STATE_FORMAT_VERSION):
            raise InputError("calibrator state: unknown format or version")
        try:
            obj = cls._from_state(d)
        except InputError:
            raise
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise InputError(f"calibrator state: corrupt or incomplete ({type(exc).__name__}: {exc})") from None
        n = obj.model.n_params
        if obj.current is not None and (len(obj.current.get("theta_u", ())) != n
                                        or np.shape(obj.current.get("cov_u")) != (n, n)):
            raise InputError(f"calibrator state: the current fit does not have the {n} parameters of model "
                             f"{obj.model.name}")
        if d["format_version"] != 1 and obj.store.config != obj.pose_cfg:
            raise InputError("calibrator state: its pose store was written under another [poses] config than "
                             "the state's own")
        return obj

    @classmethod
    def _from_state(cls, d: dict) -> "OnlineCalibrator":
        obj = cls(d["config"], d["model"], d["initial_params_u"])
        obj.model = ErrorModel(d["model"], d["temp_ref_c"], d["t_ref_s"])
        obj.detector = _detector_module().StaticDetector.from_state(obj.det_cfg, d["detector"])
        obj.current = d["current"]
        obj.last_refit = d["last_refit"]
        obj.n_refits = d["n_refits"]
        obj.new_since_refit = d["new_since_refit"]
        obj.last_refit_t_s = d["last_refit_t_s"]
        obj.t_last_s = d["t_last_s"]
        obj.n_samples = d["n_samples"]
        if d["format_version"] == 1:  # pose buffer of the sequential calibrator: re-file its poses
            b = d["buffer"]

            def arr(x):
                return np.array([[np.nan if v is None else v for v in row] for row in x], dtype=float).reshape(-1, 3)

            temps = np.array([np.nan if v is None else v for v in b["temp_c"]], dtype=float)
            if b["mean"]:
                obj.store.add(arr(b["mean"]), arr(b["sd"]), np.asarray(b["count"], float), np.asarray(b["t_s"], float), temps)
            obj.windows_since_refit = obj.new_since_refit
            if obj.current is not None:
                obj.current["calibration"].setdefault("status", "provisional")
            return obj
        obj.store = PoseStore.from_json(d["store"])
        obj.seeded_prior = d.get("seeded_prior")
        obj.windows_since_refit = d["windows_since_refit"]
        obj.selection = d.get("selection") or {"last_check_t_s": None, "added": [], "checks": [], "n_checks": 0}
        floor = d.get("fit_sigma_floor_g_now")  # (states written before it was kept: None)
        obj._fit_cfg_now = None if floor is None else obj.fit_cfg.model_copy(update={"sigma_floor_g": float(floor)})
        return obj


__all__ = ["OnlineCalibrator", "SchedulerConfig", "Normalizer"]
