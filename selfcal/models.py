"""Accelerometer error models: parameters, apply, analytic Jacobian of the norm residual.

Every model maps a raw reading ``raw`` (shape ``(n, 3)``, in the recording's unit) to
calibrated specific force ``a`` in **g**. Its linear part at the reference conditions is
``a = matrix @ (raw - offset)`` (design contract). The fit minimises the norm residual
``r = ||a|| - 1`` (g), whose Jacobian each model gives analytically.

Base models
-----------
``scale6``   offset ``bx, by, bz`` (raw unit) and per-axis scale ``sx, sy, sz``
             (g per raw unit): ``matrix = diag(s)``.
``affine9``  ``scale6`` plus upper-triangular non-orthogonality ``nxy, nxz, nyz``
             (dimensionless, ~rad): ``matrix = diag(s) @ [[1, nxy, nxz], [0, 1, nyz],
             [0, 0, 1]]``. Every invertible sensor matrix is ``Q @ R`` with ``Q`` a
             rotation and ``R`` upper triangular; norms see only ``R``, so these 9
             parameters are exactly what gravity norms can determine.
``seed9``    the seed document's form ``a = T K (raw + b)`` with
             ``T = [[1, psi, -theta], [-psi, 1, phi], [theta, -phi, 1]]`` (first-order
             rotation). Kept to demonstrate that its three angles are not determined by
             norms (a rotation does not change ``||a||`` at first order).

Effects (extensions; each adds 3 per-axis parameters)
-----------------------------------------------------
``temperature_bias``   ``tbx, tby, tbz`` raw unit per degC: offset ``b + tb (T - T_ref)``
``temperature_scale``  ``tsx, tsy, tsz`` 1/degC: scale ``s (1 + ts (T - T_ref))``
``time_drift_bias``    ``dbx, dby, dbz`` raw unit per day: offset ``b + db (t - t_ref)/86400``
``scale_nonlinearity`` ``qx, qy, qz`` 1/g: ``a_i = l_i - q_i l_i**2`` where ``l`` is the
                       linear calibrated value (g); ``q = 0.002`` is 2 mg/g².
``temperature_cross``  ``tnxy, tnxz, tnyz`` 1/degC (affine9 only): the cross-axis terms
                       ``n + tn (T - T_ref)`` (a package that bends as it warms couples
                       the axes; ``tn = 1e-5`` is 10 ppm/degC of cross-axis coupling)

Event (a change at one time ``t_step_s``, which the model takes as a constant)
---------------------------------------------------------------------------
``bias_step``          ``sbx, sby, sbz`` raw unit: offset ``b + sb`` from ``t_step_s`` on (a
                       shock or a battery change moves the bias at once). ``selfcal
                       diagnose`` scans for the time; no calibrator runs this model (the
                       online answer to a step is to down-weight what came before it).

The simulator (``selfcal.sim``) produces the same effects in the forward direction;
the forms here are their first-order inverses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from selfcal.errors import InputError

SECONDS_PER_DAY = 86400.0

BASE_PARAMS = {
    "scale6": ("bx", "by", "bz", "sx", "sy", "sz"),
    "affine9": ("bx", "by", "bz", "sx", "sy", "sz", "nxy", "nxz", "nyz"),
    "seed9": ("bx", "by", "bz", "sx", "sy", "sz", "psi", "theta", "phi"),
}

EFFECT_PARAMS = {
    "temperature_bias": ("tbx", "tby", "tbz"),
    "temperature_scale": ("tsx", "tsy", "tsz"),
    "time_drift_bias": ("dbx", "dby", "dbz"),
    "scale_nonlinearity": ("qx", "qy", "qz"),
    "temperature_cross": ("tnxy", "tnxz", "tnyz"),
}

#: Events: effects of a change at one time (the model's ``t_step_s``), found by diagnose's
#: scan over candidate times. Not in EFFECT_PARAMS: no calibrator switches to them.
EVENT_PARAMS = {
    "bias_step": ("sbx", "sby", "sbz"),
}
_ALL_EFFECT_PARAMS = {**EFFECT_PARAMS, **EVENT_PARAMS}

#: Effects diagnose and online selection take only when they clearly beat the others: a
#: cross-axis tempco into z looks like a temperature bias on mostly flat poses, and a
#: bias is the far more common effect (docs/diagnose.md).
SECONDARY_EFFECTS = ("temperature_cross", "bias_step")

#: Units of each parameter family, for documentation and reports ("raw" = recording unit).
PARAM_UNITS = {
    "b": "raw", "s": "g/raw", "n": "1", "psi": "rad", "theta": "rad", "phi": "rad",
    "tb": "raw/degC", "ts": "1/degC", "db": "raw/day", "q": "1/g", "tn": "1/degC", "sb": "raw",
}

_UPPER = ((0, 1), (0, 2), (1, 2))  # positions of nxy, nxz, nyz


def parse_model_name(name: str) -> tuple[str, tuple[str, ...]]:
    """Split ``"affine9+temperature_bias+..."`` into the base name and effect names."""
    parts = [p.strip() for p in str(name).split("+") if p.strip()]
    if not parts or parts[0] not in BASE_PARAMS:
        raise InputError(
            f"model: unknown base model {parts[0] if parts else name!r}; "
            f"choose one of {sorted(BASE_PARAMS)} (optionally +effect)"
        )
    effects = tuple(parts[1:])
    for eff in effects:
        if eff not in _ALL_EFFECT_PARAMS:
            raise InputError(f"model: unknown effect {eff!r}; choose from {sorted(EFFECT_PARAMS)}")
    if len(set(effects)) != len(effects):
        raise InputError(f"model: effect repeated in {name!r}")
    if parts[0] == "seed9" and effects:
        raise InputError("model: seed9 is a demonstration model and takes no effects")
    if "temperature_cross" in effects and parts[0] != "affine9":
        raise InputError(f"model: temperature_cross varies the cross-axis terms of affine9; {parts[0]} has none")
    # canonical order, so that names compare equal
    effects = tuple(e for e in _ALL_EFFECT_PARAMS if e in effects)
    return parts[0], effects


@dataclass(frozen=True)
class ErrorModel:
    """An accelerometer error model: a base form plus optional effects.

    Parameters
    ----------
    name : str
        ``"scale6"``, ``"affine9"`` or ``"seed9"``, optionally followed by
        ``"+effect"`` terms (``"affine9+temperature_bias"``).
    temp_ref_c : float
        Reference temperature (degC) of the temperature effects.
    t_ref_s : float
        Time origin (s) of the drift effect.
    t_step_s : float
        Time (s, the clock of ``t_s``) of the ``bias_step`` event; required by it.
    """

    name: str = "affine9"
    temp_ref_c: float = 25.0
    t_ref_s: float = 0.0
    t_step_s: float = float("nan")
    base: str = field(init=False)
    effects: tuple[str, ...] = field(init=False)
    param_names: tuple[str, ...] = field(init=False)
    # the first index of each effect's parameters in the kernel's order (bias_step,
    # temperature_bias, time_drift_bias, temperature_scale, scale_nonlinearity,
    # temperature_cross), -1 without it: found once, not at every kernel call
    _kernel_index: tuple[int, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        base, effects = parse_model_name(self.name)
        object.__setattr__(self, "base", base)
        object.__setattr__(self, "effects", effects)
        names = BASE_PARAMS[base] + tuple(n for e in effects for n in _ALL_EFFECT_PARAMS[e])
        object.__setattr__(self, "param_names", names)
        object.__setattr__(self, "name", "+".join((base,) + effects))
        object.__setattr__(self, "_kernel_index", tuple(
            self.index(e).start if e in effects else -1
            for e in ("bias_step", "temperature_bias", "time_drift_bias", "temperature_scale",
                      "scale_nonlinearity", "temperature_cross")))
        if "bias_step" in effects and not np.isfinite(self.t_step_s):
            raise InputError("model: bias_step needs the time of the step (t_step_s); `selfcal diagnose` scans "
                             "for it, and the online calibrator finds a step at its model checks and fits the "
                             "history before it jointly with the step's size (give a base model, e.g. affine9)")

    # ------------------------------------------------------------------ basics
    @property
    def uses_temperature(self) -> bool:
        """Whether the model needs a temperature (degC) for every pose."""
        return any(e.startswith("temperature") for e in self.effects)

    @property
    def n_params(self) -> int:
        """Number of parameters."""
        return len(self.param_names)

    def index(self, effect: str) -> slice:
        """Slice of the 3 parameters of ``effect`` (or ``"b"``, ``"s"``, ``"n"``)."""
        if effect == "b":
            return slice(0, 3)
        if effect == "s":
            return slice(3, 6)
        if effect == "n":
            if self.base == "scale6":
                raise KeyError("scale6 has no non-orthogonality")
            return slice(6, 9)
        start = len(BASE_PARAMS[self.base])
        for e in self.effects:
            if e == effect:
                return slice(start, start + 3)
            start += 3
        raise KeyError(effect)

    def nominal(self) -> np.ndarray:
        """Nominal parameters: zero offset, unit scale, no axis error, no effects."""
        theta = np.zeros(self.n_params)
        theta[3:6] = 1.0
        return theta

    def to_dict(self, theta: np.ndarray) -> dict[str, float]:
        """Parameter vector (p,) -> ``{name: value}``."""
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (self.n_params,):
            raise InputError(f"params: expected {self.n_params} values for {self.name}, got {theta.shape}")
        return {k: float(v) for k, v in zip(self.param_names, theta)}

    def from_dict(self, params: dict[str, float]) -> np.ndarray:
        """``{name: value}`` -> parameter vector; missing effect terms default to 0."""
        theta = self.nominal()
        unknown = set(params) - set(self.param_names)
        if unknown:
            raise InputError(f"params: unknown names {sorted(unknown)} for model {self.name}")
        for i, n in enumerate(self.param_names):
            if n in params:
                theta[i] = float(params[n])
            elif i < len(BASE_PARAMS[self.base]):
                raise InputError(f"params: missing {n!r} for model {self.name}")
        return theta

    def takes(self, effect: str) -> bool:
        """Whether ``effect`` can be added to this base model (the rules of
        :func:`parse_model_name`: seed9 takes none, cross-axis terms need affine9)."""
        try:
            parse_model_name(f"{self.base}+{effect}")
        except InputError:
            return False
        return True

    def with_effects(self, effects: tuple[str, ...]) -> "ErrorModel":
        """The same base model with a different set of effects."""
        return ErrorModel("+".join((self.base,) + tuple(effects)), self.temp_ref_c, self.t_ref_s,
                          self.t_step_s if "bias_step" in effects else float("nan"))

    def extend_theta(self, theta: np.ndarray, other: "ErrorModel") -> np.ndarray:
        """Map ``theta`` of ``other`` into this model (shared names copied, new ones 0)."""
        d = other.to_dict(theta)
        out = self.nominal()
        for i, n in enumerate(self.param_names):
            if n in d:
                out[i] = d[n]
        return out

    # ------------------------------------------------------------------ linear part
    def upper(self, theta: np.ndarray) -> np.ndarray:
        """The unit upper-triangular (affine9), identity (scale6) or T (seed9) matrix."""
        if self.base == "affine9":
            u = np.eye(3)
            u[0, 1], u[0, 2], u[1, 2] = theta[6], theta[7], theta[8]
            return u
        if self.base == "seed9":
            psi, th, phi = theta[6], theta[7], theta[8]
            return np.array([[1.0, psi, -th], [-psi, 1.0, phi], [th, -phi, 1.0]])
        return np.eye(3)

    def linear(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Linear part at the reference conditions: ``(matrix (3,3), offset (3,) raw unit)``.

        ``a_cal_g = matrix @ (raw - offset)``. Nonlinearity is not part of it.
        """
        theta = np.asarray(theta, dtype=float)
        s = theta[3:6]
        if self.base == "seed9":
            return self.upper(theta) @ np.diag(s), -theta[0:3].copy()
        return np.diag(s) @ self.upper(theta), theta[0:3].copy()

    def from_linear(self, matrix: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """Parameters whose linear part reproduces the norms of ``matrix @ (raw - offset)``.

        ``matrix`` is reduced to its identifiable upper-triangular factor (QR with a
        positive diagonal); the rotation it may contain is dropped (norms cannot see it).
        Effect parameters are set to zero.
        """
        matrix = np.asarray(matrix, dtype=float)
        offset = np.asarray(offset, dtype=float)
        if matrix.shape != (3, 3) or offset.shape != (3,):
            raise InputError("from_linear: matrix must be (3, 3) and offset (3,)")
        _, r = np.linalg.qr(matrix)
        r = np.sign(np.diag(r))[:, None] * r
        theta = self.nominal()
        s = np.diag(r).copy()
        if self.base == "seed9":
            theta[0:3] = -offset
            theta[3:6] = s  # T = I: the angles stay at 0 (unobservable)
            return theta
        theta[0:3] = offset
        theta[3:6] = s
        if self.base == "affine9":
            u = r / s[:, None]
            theta[6], theta[7], theta[8] = u[0, 1], u[0, 2], u[1, 2]
        return theta

    # ------------------------------------------------------------------ forward map
    def _covariates(self, n: int, temp_c, t_s) -> tuple[np.ndarray | None, np.ndarray | None]:
        dtemp = dtime = None
        if not self.effects:
            return dtemp, dtime
        if self.uses_temperature:
            if temp_c is None:
                raise InputError(f"model {self.name} needs temp_c (degC) for every row")
            dtemp = np.asarray(temp_c, dtype=float).reshape(n) - self.temp_ref_c
            if not np.all(np.isfinite(dtemp)):
                raise InputError(f"model {self.name}: temp_c has NaN/inf values")
        if "time_drift_bias" in self.effects:
            if t_s is None:
                raise InputError(f"model {self.name} needs t_s (s) for every row")
            dtime = (np.asarray(t_s, dtype=float).reshape(n) - self.t_ref_s) / SECONDS_PER_DAY
        return dtemp, dtime

    def _after_step(self, n: int, t_s) -> np.ndarray:
        """1.0 for rows at or after ``t_step_s``, else 0.0, (n,)."""
        if t_s is None:
            raise InputError(f"model {self.name} needs t_s (s) for every row")
        return (np.asarray(t_s, dtype=float).reshape(n) >= self.t_step_s).astype(float)

    def _forward(self, theta, raw, temp_c, t_s):
        theta = np.asarray(theta, dtype=float)
        raw = np.asarray(raw, dtype=float)
        n = raw.shape[0]
        dtemp, dtime = self._covariates(n, temp_c, t_s)
        b = theta[0:3]  # (3,) broadcasts; (n, 3) once an effect makes it per-sample
        if "bias_step" in self.effects:
            b = b + self._after_step(n, t_s)[:, None] * theta[self.index("bias_step")]
        if "temperature_bias" in self.effects:
            b = b + dtemp[:, None] * theta[self.index("temperature_bias")]
        if "time_drift_bias" in self.effects:
            b = b + dtime[:, None] * theta[self.index("time_drift_bias")]
        s_eff = theta[3:6]
        if "temperature_scale" in self.effects:
            s_eff = s_eff * (1.0 + dtemp[:, None] * theta[self.index("temperature_scale")])
        u = None
        if self.base == "seed9":
            u = self.upper(theta)
            y = raw + b
            z = s_eff * y
            lin = z @ u.T
        elif "temperature_cross" in self.effects:
            y = raw - b
            nt = theta[6:9] + dtemp[:, None] * theta[self.index("temperature_cross")]  # (n, 3) per row
            u = nt  # the per-row cross-axis terms (the Jacobian reads them from here)
            z = y.copy()  # z = U(T) y, U unit upper triangular
            z[:, 0] += nt[:, 0] * y[:, 1] + nt[:, 1] * y[:, 2]
            z[:, 1] += nt[:, 2] * y[:, 2]
            lin = s_eff * z
        elif self.base == "affine9":
            # z = U y, U unit upper triangular, written out (not a matrix product, whose
            # rounding is the BLAS library's): the order of :mod:`selfcal._model_jit`'s kernel
            y = raw - b
            u = theta[6:9]  # (nxy, nxz, nyz): the Jacobian reads them from here
            z = y.copy()
            z[:, 0] += u[0] * y[:, 1] + u[1] * y[:, 2]
            z[:, 1] += u[2] * y[:, 2]
            lin = s_eff * z
        else:  # scale6: U = I
            y = raw - b
            z = y
            lin = s_eff * z
        if "scale_nonlinearity" in self.effects:
            q = theta[self.index("scale_nonlinearity")]
            a = lin - q * lin**2
        else:
            a = lin
        return a, (y, z, lin, s_eff, u, dtemp, dtime)

    def apply(self, theta: np.ndarray, raw: np.ndarray, temp_c=None, t_s=None) -> np.ndarray:
        """Calibrated specific force.

        Parameters
        ----------
        theta : ndarray, shape (p,)
        raw : ndarray, shape (n, 3), recording unit
        temp_c : ndarray, shape (n,), degC, needed by temperature effects
        t_s : ndarray, shape (n,), s, needed by the drift effect

        Returns
        -------
        ndarray, shape (n, 3), g
        """
        raw = np.asarray(raw, dtype=float)
        if raw.ndim != 2 or raw.shape[1] != 3:
            raise InputError(f"raw: expected shape (n, 3), got {raw.shape}")
        return self._forward(theta, raw, temp_c, t_s)[0]

    def residuals(self, theta, raw, temp_c=None, t_s=None) -> np.ndarray:
        """Norm residuals ``||a|| - 1`` (g), shape (n,)."""
        return _norm(self.apply(theta, raw, temp_c, t_s)) - 1.0

    def residual_jac(self, theta, raw, temp_c=None, t_s=None, accelerate=None) -> tuple[np.ndarray, np.ndarray]:
        """Norm residuals (n,) in g and their analytic Jacobian (n, p).

        ``accelerate``: None uses the numba kernel of :mod:`selfcal.model_numba` when it is
        there (the same values bit for bit), False the numpy code; or a kernel to use.
        """
        theta = np.asarray(theta, dtype=float)
        raw = np.asarray(raw, dtype=float)
        if self.base != "seed9" and accelerate is not False:
            if accelerate is None:
                from selfcal.model_numba import kernel

                accelerate = kernel(raw.shape[0] if raw.ndim == 2 else 0)
            if accelerate is not None and raw.ndim == 2 and raw.shape[1] == 3:
                return self._residual_jac_kernel(accelerate, theta, raw, temp_c, t_s)
        a, (y, z, lin, s_eff, u, dtemp, dtime) = self._forward(theta, raw, temp_c, t_s)
        norm = _norm(a)
        nhat = a / norm[:, None]
        r = norm - 1.0
        n = raw.shape[0]
        jac = np.empty((n, self.n_params))
        if "scale_nonlinearity" in self.effects:
            sl = self.index("scale_nonlinearity")
            q = theta[sl]
            w = nhat * (1.0 - 2.0 * q * lin)  # dr/d(lin)
            jac[:, sl] = -nhat * lin**2
        else:
            w = nhat
        if self.base == "seed9":
            # lin = T z, z = s_eff * y, y = raw + b
            tw = w @ u  # (T^T w) as rows
            ds = tw * y
            jac[:, 0:3] = tw * s_eff
            jac[:, 6] = w[:, 0] * z[:, 1] - w[:, 1] * z[:, 0]  # psi
            jac[:, 7] = -w[:, 0] * z[:, 2] + w[:, 2] * z[:, 0]  # theta
            jac[:, 8] = w[:, 1] * z[:, 2] - w[:, 2] * z[:, 1]  # phi
            jac[:, 3:6] = ds
            return r, jac
        # lin = s_eff * z, z = U y, y = raw - b_eff
        ws = w * s_eff
        if self.base == "affine9":  # u: (nxy, nxz, nyz), per row with temperature_cross
            v = ws.copy()  # dr/dy = ws^T U, rows, written out as z is
            v[:, 1] += ws[:, 0] * u[..., 0]
            v[:, 2] += ws[:, 0] * u[..., 1] + ws[:, 1] * u[..., 2]
        else:  # scale6: U = I
            v = ws
        jac[:, 0:3] = -v
        scale_factor = 1.0
        if "temperature_scale" in self.effects:
            ts = theta[self.index("temperature_scale")]
            scale_factor = 1.0 + dtemp[:, None] * ts
            jac[:, self.index("temperature_scale")] = w * z * theta[3:6] * dtemp[:, None]
        jac[:, 3:6] = w * z * scale_factor
        if self.base == "affine9":
            jac[:, 6] = ws[:, 0] * y[:, 1]
            jac[:, 7] = ws[:, 0] * y[:, 2]
            jac[:, 8] = ws[:, 1] * y[:, 2]
            if "temperature_cross" in self.effects:
                jac[:, self.index("temperature_cross")] = jac[:, 6:9] * dtemp[:, None]
        if "temperature_bias" in self.effects:
            jac[:, self.index("temperature_bias")] = -v * dtemp[:, None]
        if "time_drift_bias" in self.effects:
            jac[:, self.index("time_drift_bias")] = -v * dtime[:, None]
        if "bias_step" in self.effects:
            jac[:, self.index("bias_step")] = -v * self._after_step(n, t_s)[:, None]
        return r, jac

    def _residual_jac_kernel(self, kern, theta, raw, temp_c, t_s) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`residual_jac` by the kernel ``kern`` (scale6, affine9)."""
        n = raw.shape[0]
        r = np.empty(n)
        jac = np.empty((n, self.n_params))
        kern(*self._kernel_inputs(theta, raw, temp_c, t_s), r, jac)
        return r, jac

    def _whitened_kernel(self, kern, theta, raw, temp_c, t_s, var_axis, floor2) -> tuple:
        """``(r, jac, r / sigma, d(r / sigma) / d theta)`` by the whitening kernel ``kern``
        (:func:`selfcal._model_jit.whitened_residual_jac`; scale6, affine9): ``sigma``
        from ``var_axis`` (n, 3) and ``floor2`` (g²) as :class:`selfcal.fit.NoiseModel` has it."""
        raw = np.asarray(raw, dtype=float)
        if raw.ndim != 2 or raw.shape[1] != 3:
            raise InputError(f"raw: expected shape (n, 3), got {raw.shape}")
        n = raw.shape[0]
        r, rw = np.empty(n), np.empty(n)
        jac, jw = np.empty((n, self.n_params)), np.empty((n, self.n_params))
        kern(*self._kernel_inputs(theta, raw, temp_c, t_s), np.ascontiguousarray(var_axis, dtype=float),
             float(floor2), r, jac, rw, jw)
        return r, jac, rw, jw

    def _kernel_inputs(self, theta, raw, temp_c, t_s) -> tuple:
        """The kernels' leading arguments for readings ``raw`` (n, 3): parameters, readings,
        the covariates (empty where the model has no effect that reads them), the step
        indicator, whether the cross-axis terms are there, and the effects' indices."""
        n = raw.shape[0]
        dtemp, dtime = self._covariates(n, temp_c, t_s)
        after = self._after_step(n, t_s) if "bias_step" in self.effects else None
        none = np.zeros(0)
        return (np.ascontiguousarray(theta, dtype=float), np.ascontiguousarray(raw, dtype=float),
                none if dtemp is None else np.ascontiguousarray(dtemp, dtype=float),
                none if dtime is None else np.ascontiguousarray(dtime, dtype=float),
                none if after is None else after, self.base == "affine9", *self._kernel_index)


def _norm(a: np.ndarray) -> np.ndarray:
    """Row norms of ``a`` (n, 3): ``sqrt((a0² + a1²) + a2²)``, in that order (the kernel's)."""
    sq = a * a
    return np.sqrt(sq[:, 0] + sq[:, 1] + sq[:, 2])


def available_models() -> list[str]:
    """Names of the base models and effects (combine as ``base+effect+...``)."""
    return list(BASE_PARAMS) + [f"affine9+{e}" for e in EFFECT_PARAMS]


@dataclass(frozen=True)
class Normalizer:
    """Affine change of unit ``u = (raw - center) / scale`` applied before fitting.

    Keeps every parameter O(1) whatever the recording's unit (g, m/s², counts), so
    that one prior and one set of tolerances serve all. ``scale`` is in raw units per
    g (1 for g, 9.80665 for m/s², ~counts per g for counts); ``center`` in raw units.
    """

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0

    def to_u(self, raw: np.ndarray) -> np.ndarray:
        """Raw (n,3), raw unit -> normalised (n,3), ~g."""
        return (np.asarray(raw, dtype=float) - np.asarray(self.center)) / self.scale

    def param_scale(self, model: ErrorModel) -> np.ndarray:
        """Per-parameter factor d(theta_raw)/d(theta_u), shape (p,)."""
        f = np.ones(model.n_params)
        f[0:3] = self.scale
        f[3:6] = 1.0 / self.scale
        for eff in ("temperature_bias", "time_drift_bias", "bias_step"):
            if eff in model.effects:
                f[model.index(eff)] = self.scale
        return f

    def theta_to_raw(self, model: ErrorModel, theta_u: np.ndarray) -> np.ndarray:
        """Parameters fitted on normalised data -> parameters in the raw unit."""
        out = np.asarray(theta_u, dtype=float) * self.param_scale(model)
        c = np.asarray(self.center)
        out[0:3] += -c if model.base == "seed9" else c
        return out

    def theta_to_u(self, model: ErrorModel, theta_raw: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`theta_to_raw`."""
        t = np.asarray(theta_raw, dtype=float).copy()
        c = np.asarray(self.center)
        t[0:3] -= -c if model.base == "seed9" else c
        return t / self.param_scale(model)

    def cov_to_raw(self, model: ErrorModel, cov_u: np.ndarray) -> np.ndarray:
        """Covariance (p,p) of normalised parameters -> raw-unit parameters."""
        f = self.param_scale(model)
        return cov_u * f[:, None] * f[None, :]
