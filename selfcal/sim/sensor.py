"""The simulated accelerometer: per-device truth draw and the forward error model.

Forward model (truth convention of ``docs/internals.md``, effects of
``docs/simulation.md``), for true specific force ``a`` (g, foot frame), true sensor
temperature ``T`` (degC) and time ``t`` (s since the start of the simulation)::

    dT   = T - temp_ref_c                     t_day = t / 86400
    l    = a + 1e-3 * q * a**2                              scale_nonlinearity (mg/g^2)
    M(T) = diag(1 + 1e-6 * ts * dT) @ matrix_true           temperature_scale (ppm/degC)
    M(T) = Q diag(s) (U + 1e-6 * dT * N(tn))                temperature_cross (ppm/degC)
    raw  = offset_true + 1e-3 * tb * dT + 1e-3 * db * t_day + inv(M(T)) @ l + noise
    raw  = clip(lsb * round(raw / lsb), -range, +range)

``tb`` temperature_bias (mg/degC), ``db`` time_drift_bias (mg/day); products are per axis.
``matrix_true = Q diag(s) U`` (``canonical_qr``), ``U`` unit upper triangular with the
cross-axis terms ``nxy, nxz, nyz``; ``N(tn)`` is strictly upper triangular with their
tempcos ``tn = (tnxy, tnxz, tnyz)``. With both temperature effects on, the scale tempco
acts on ``l`` first.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from selfcal.sim.config import EFFECT_NAMES, EVENT_EFFECTS, SimConfig
from selfcal.sim.draw_numba import standard_normal

#: Unit of each effect coefficient in the config and in the truth (``coefficients``).
EFFECT_UNITS = {
    "temperature_bias": "mg/degC",
    "temperature_scale": "ppm/degC",
    "time_drift_bias": "mg/day",
    "scale_nonlinearity": "mg/g^2",
    "temperature_cross": "ppm/degC",
    "bias_step": "mg",
}

#: The same coefficient in the units and parameter names of ``selfcal.models``
#: (raw unit = g): factor from the config unit, parameter names.
EFFECT_MODEL_PARAMS = {
    "temperature_bias": (1e-3, ("tbx", "tby", "tbz")),      # g/degC
    "temperature_scale": (1e-6, ("tsx", "tsy", "tsz")),     # 1/degC
    "time_drift_bias": (1e-3, ("dbx", "dby", "dbz")),       # g/day
    "scale_nonlinearity": (1e-3, ("qx", "qy", "qz")),       # 1/g
    "temperature_cross": (1e-6, ("tnxy", "tnxz", "tnyz")),  # 1/degC
    "bias_step": (1e-3, ("sbx", "sby", "sbz")),             # g, from step_at_s on
}

#: Effects drawn from the device's own stream of random numbers (the first four). Effects
#: added later draw from a generator seeded by the device's drawn values, so a seed still
#: draws the same device, and the same later draws, as before they existed.
_STREAM_EFFECTS = ("temperature_bias", "temperature_scale", "time_drift_bias", "scale_nonlinearity")

SECONDS_PER_DAY = 86400.0


def _rot(axis: int, angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.eye(3)
    r[i, i] = r[j, j] = c
    r[i, j], r[j, i] = -s, s
    return r


def canonical_params(matrix: np.ndarray, offset: np.ndarray) -> dict[str, float]:
    """The 9 identifiable parameters of a sensor ``matrix`` (QR, positive diagonal).

    Parameters
    ----------
    matrix : ndarray, shape (3, 3), g per raw unit
        Calibration matrix: ``a = matrix @ (raw - offset)``.
    offset : ndarray, shape (3,), raw unit

    Returns
    -------
    dict
        ``bx, by, bz`` (raw unit), ``sx, sy, sz`` (g per raw unit), ``nxy, nxz, nyz``
        (dimensionless) with ``R = diag(s) @ [[1, nxy, nxz], [0, 1, nyz], [0, 0, 1]]``
        and ``matrix = Q @ R``, ``Q`` a rotation (unobservable from norms).
    """
    _, r = canonical_qr(matrix)
    s = np.diag(r)
    u = r / s[:, None]
    off = np.asarray(offset, float)
    return {
        "bx": float(off[0]), "by": float(off[1]), "bz": float(off[2]),
        "sx": float(s[0]), "sy": float(s[1]), "sz": float(s[2]),
        "nxy": float(u[0, 1]), "nxz": float(u[0, 2]), "nyz": float(u[1, 2]),
    }


def canonical_qr(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """QR of ``matrix`` with ``R`` having a positive diagonal.

    Returns
    -------
    q : ndarray, shape (3, 3)
        Orthogonal factor.
    r : ndarray, shape (3, 3), g per raw unit
        Upper-triangular factor; ``R @ (raw - offset)`` has the norm of ``a``.
    """
    q, r = np.linalg.qr(np.asarray(matrix, float))
    sign = np.sign(np.diag(r))
    sign[sign == 0] = 1.0
    return q * sign[None, :], r * sign[:, None]


@dataclass
class SensorTruth:
    """Ground truth of one simulated device.

    Attributes
    ----------
    matrix : ndarray, shape (3, 3), g per raw unit
        ``matrix_true``: calibration matrix including misalignment
        (``a = matrix @ (raw - offset)`` without effects).
    offset : ndarray, shape (3,), g (raw unit)
    effects : dict
        name -> ndarray shape (3,) coefficients in :data:`EFFECT_UNITS`; zero when the
        effect is disabled.
    enabled : tuple of str
        Effects switched on.
    temp_ref_c : float
        Reference temperature of the temperature effects (degC).
    step_at_s : float
        When the bias step (``effects["bias_step"]``, mg) happens, s since the start;
        ``inf`` when there is none.
    """

    matrix: np.ndarray
    offset: np.ndarray
    effects: dict[str, np.ndarray]
    enabled: tuple[str, ...]
    temp_ref_c: float
    noise_sd_g: np.ndarray = field(default_factory=lambda: np.zeros(3))
    lsb_g: float = 0.0
    range_g: float = np.inf
    step_at_s: float = np.inf

    def params(self) -> dict[str, float]:
        """Canonical identifiable parameters (see :func:`canonical_params`) at the start."""
        return canonical_params(self.matrix, self.offset)

    def offset_at(self, t_s: float) -> np.ndarray:
        """The offset (g, raw unit, shape (3,)) at time ``t_s``: with the bias step once it happened."""
        if "bias_step" in self.enabled and float(t_s) >= self.step_at_s:
            return self.offset + 1e-3 * self.effects["bias_step"]
        return self.offset

    def params_at(self, t_s: float) -> dict[str, float]:
        """:meth:`params` of the sensor as it is at time ``t_s`` (s): the offset after a bias step."""
        return canonical_params(self.matrix, self.offset_at(t_s))

    def model_params(self) -> dict[str, float]:
        """Enabled effect coefficients in ``selfcal.models`` names and units."""
        out = {}
        for name in self.enabled:
            if name in EVENT_EFFECTS:  # not a term of a continuous model: see offset_at, step_at_s
                continue
            factor, names = EFFECT_MODEL_PARAMS[name]
            for k, v in zip(names, self.effects[name]):
                out[k] = float(v) * factor
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (lists of floats)."""
        _, r = canonical_qr(self.matrix)
        return {
            "matrix": self.matrix.tolist(),
            "offset": self.offset.tolist(),
            "params": self.params(),
            "matrix_canonical": r.tolist(),
            "temp_ref_c": self.temp_ref_c,
            "time_origin_s": 0.0,
            "effects": {
                n: {
                    "enabled": n in self.enabled,
                    "coefficients": self.effects[n].tolist(),
                    "unit": EFFECT_UNITS[n],
                }
                for n in EFFECT_NAMES
            },
            "effect_params": self.model_params(),
            "noise_sd_g": self.noise_sd_g.tolist(),
            "lsb_g": self.lsb_g,
            "range_g": self.range_g,
            "step_at_s": self.step_at_s if np.isfinite(self.step_at_s) else None,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SensorTruth":
        """Inverse of :meth:`to_dict`."""
        # a truth written before an effect existed has it off
        eff = {n: np.asarray(d["effects"][n]["coefficients"], float) if n in d["effects"] else np.zeros(3)
               for n in EFFECT_NAMES}
        enabled = tuple(n for n in EFFECT_NAMES if n in d["effects"] and d["effects"][n]["enabled"])
        return cls(
            matrix=np.asarray(d["matrix"], float),
            offset=np.asarray(d["offset"], float),
            effects=eff,
            enabled=enabled,
            temp_ref_c=float(d["temp_ref_c"]),
            noise_sd_g=np.asarray(d.get("noise_sd_g", [0, 0, 0]), float),
            lsb_g=float(d.get("lsb_g", 0.0)),
            range_g=float(d.get("range_g", np.inf)),
            step_at_s=float(np.inf if d.get("step_at_s") is None else d["step_at_s"]),
        )


def draw_sensor_truth(config: SimConfig, rng: np.random.Generator) -> SensorTruth:
    """Draw one device: matrix, offset and effect coefficients.

    Every quantity is drawn whatever the switches, so enabling an effect never changes
    the other draws of the same seed. Limits are uniform ``+-limit``; effect
    coefficients are ``sign * U(0.5, 1) * magnitude`` per axis (clearly present when
    enabled), unless ``coefficients`` are given explicitly.

    Parameters
    ----------
    config : SimConfig
    rng : numpy.random.Generator

    Returns
    -------
    SensorTruth
    """
    sc = config.sensor
    scale = 1.0 + rng.uniform(-sc.scale_rel, sc.scale_rel, 3)
    nonorth = np.deg2rad(rng.uniform(-sc.nonorth_deg, sc.nonorth_deg, 3))
    mis = np.deg2rad(rng.uniform(-sc.misalign_deg, sc.misalign_deg, 3))
    offset = 1e-3 * rng.uniform(-sc.offset_mg, sc.offset_mg, 3)
    upper = np.eye(3)
    upper[0, 1], upper[0, 2], upper[1, 2] = nonorth
    rotation = _rot(0, mis[0]) @ _rot(1, mis[1]) @ _rot(2, mis[2])
    matrix = rotation @ np.diag(scale) @ upper
    effects = {}
    side = np.random.default_rng(np.frombuffer(hashlib.sha256(
        np.concatenate([scale, nonorth, mis, offset]).tobytes()).digest(), dtype=np.uint32))
    for name in EFFECT_NAMES:
        ec = getattr(config.effects, name)
        draw = rng if name in _STREAM_EFFECTS else side
        sign = draw.choice([-1.0, 1.0], 3)
        frac = draw.uniform(0.5, 1.0, 3)
        coef = sign * frac * np.asarray(ec.magnitude, float)
        if ec.coefficients is not None:
            coef = np.asarray(ec.coefficients, float)
        effects[name] = coef if ec.enabled else np.zeros(3)
    enabled = tuple(n for n in EFFECT_NAMES if getattr(config.effects, n).enabled)
    return SensorTruth(
        matrix=matrix,
        offset=offset,
        effects=effects,
        enabled=enabled,
        temp_ref_c=config.effects.temp_ref_c,
        noise_sd_g=1e-3 * np.asarray(sc.noise_sd_mg, float),
        lsb_g=1e-3 * sc.lsb_mg,
        range_g=sc.range_g,
        step_at_s=config.effects.bias_step.at_day * SECONDS_PER_DAY if "bias_step" in enabled else np.inf,
    )


def sensor_mean(truth: SensorTruth, a_true_g: np.ndarray, temp_c: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Noise-free, unquantised sensor output (the forward model without noise).

    Parameters
    ----------
    truth : SensorTruth
    a_true_g : ndarray, shape (n, 3), g
        True specific force in the foot frame (any memory layout: the simulator passes
        a view of its (3, n) array by axis).
    temp_c : ndarray, shape (n,), degC
        True sensor temperature.
    t_s : ndarray, shape (n,), s
        Time since the start of the simulation.

    Returns
    -------
    ndarray, shape (n, 3), g (raw unit)
    """
    a = np.asarray(a_true_g, float)
    eff = truth.effects
    on = truth.enabled
    if "scale_nonlinearity" in on:
        a = a + 1e-3 * eff["scale_nonlinearity"] * a * a
    minv = np.linalg.inv(truth.matrix)
    d_temp = np.asarray(temp_c, float) - truth.temp_ref_c
    if "temperature_scale" in on:
        # inv(diag(1 + k dT) M) l = inv(M) @ (l / (1 + k dT))
        a = a / (1.0 + d_temp[:, None] * (1e-6 * eff["temperature_scale"]))
    if "temperature_cross" in on:
        # M(T) = Q diag(s) U(T), U(T) = U + dT N (N strictly upper: the tempcos of nxy, nxz, nyz),
        # so inv(M(T)) = inv(U(T)) diag(1/s) Q^T: rotate and unscale here, invert U(T) per row
        q, r = canonical_qr(truth.matrix)
        s = np.diag(r)
        nt = r[[0, 0, 1], [1, 2, 2]] / s[[0, 0, 1]] + d_temp[:, None] * (1e-6 * eff["temperature_cross"])
        # diag(1/s) Q^T a, row-wise, each axis written out as ((a0 q0j + a1 q1j) + a2 q2j) / s_j:
        # a matmul's rounding depends on how many rows it is given (one row differed from
        # a block of them), and the simulator computes its rows in blocks of any length
        cols = np.ascontiguousarray(a.T)
        w = np.empty((len(a), 3))
        for j in range(3):
            w[:, j] = (cols[0] * q[0, j] + cols[1] * q[1, j] + cols[2] * q[2, j]) / s[j]
        y = w  # solve U(T) y = w in place (back substitution, unit diagonal)
        y[:, 1] -= nt[:, 2] * y[:, 2]
        y[:, 0] -= nt[:, 0] * y[:, 1] + nt[:, 1] * y[:, 2]
        return y + truth.offset + _additive(truth, d_temp, t_s)
    # inv(M) @ a + offset row-wise: each output axis as ((a0 m0 + a1 m1) + a2 m2) + b on
    # contiguous columns (a (n, 3) broadcast runs an inner loop of 3 per row, ~7x slower;
    # a matmul adds in another order, so other bits)
    cols = np.ascontiguousarray(a.T)
    raw_t = np.empty_like(cols)
    term = np.empty(len(a))
    for i in range(3):
        out = raw_t[i]
        np.multiply(cols[0], minv[i, 0], out=out)
        out += np.multiply(cols[1], minv[i, 1], out=term)
        out += np.multiply(cols[2], minv[i, 2], out=term)
        out += truth.offset[i]
    return np.ascontiguousarray(raw_t.T) + _additive(truth, d_temp, t_s)


def _additive(truth: SensorTruth, d_temp: np.ndarray, t_s: np.ndarray) -> np.ndarray | float:
    """The offset effects (temperature bias, time drift, bias step), raw unit: (n, 3), or 0.0."""
    eff, on = truth.effects, truth.enabled
    out: np.ndarray | float = 0.0
    if "temperature_bias" in on:
        out = out + 1e-3 * d_temp[:, None] * eff["temperature_bias"]
    if "time_drift_bias" in on:
        out = out + 1e-3 * (np.asarray(t_s, float)[:, None] / SECONDS_PER_DAY) * eff["time_drift_bias"]
    if "bias_step" in on:
        out = out + 1e-3 * (np.asarray(t_s, float)[:, None] >= truth.step_at_s) * eff["bias_step"]
    return out


def read_out(truth: SensorTruth, raw_mean_g: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
    """Add white noise (per-axis sd), quantise and clip.

    Parameters
    ----------
    truth : SensorTruth
    raw_mean_g : ndarray, shape (n, 3), g
        Output of :func:`sensor_mean`.
    rng : numpy.random.Generator or None
        Noise source; ``None`` or zero ``noise_sd_g`` adds no noise.

    Returns
    -------
    ndarray, shape (n, 3), g (raw unit), multiples of ``lsb_g`` when ``lsb_g > 0``
    """
    raw = np.array(raw_mean_g, dtype=float, copy=True)
    if rng is not None and np.any(truth.noise_sd_g > 0):
        noise = standard_normal(rng, raw.shape)
        noise *= truth.noise_sd_g
        raw += noise
    if truth.lsb_g > 0:
        raw /= truth.lsb_g
        np.round(raw, out=raw)
        raw *= truth.lsb_g
    if np.isfinite(truth.range_g):
        np.clip(raw, -truth.range_g, truth.range_g, out=raw)
    return raw
