"""Streaming static (still-pose) detector.

A *still window* is a stretch of samples during which the sensor does not move, so its
mean specific force is gravity alone: the raw material of every norm-based
calibration. The detector is fed chunks of any size (one sample to hours) and returns
exactly the windows one call on the whole stream would return.

Conditions (``docs/detector.md`` gives the numbers and why, and the insole paper's
version). Every sliding window of ``Twait`` seconds
(``W = round(twait_s * rate_hz)`` samples, stride one sample) is tested:

* per-axis sample sd ``<= sd_max_g`` (the motion test; it comes first because it does
  not depend on the calibration);
* per-axis sample sd ``>= sd_min_g`` (a flat-lined, idle-repeated or clipped axis has
  no sensor noise: it is not a still pose);
* no sample with ``|value| >= clip_abs_g`` on any axis (saturation);
* norm: without a model every sample has ``| ||raw|| - 1 g | < norm_tol_raw_g`` (the
  paper's condition 1, loose enough for a sensor whose raw norm is off by 100 mg);
  with a model ``to_cal`` the calibrated window mean has
  ``| ||to_cal(mean)|| - 1 g | <= norm_tol_cal_g`` instead;
* pressure (when given): every channel's sd over time ``<= pressure_sd_max_kpa``
  (the paper's condition 2, read as spread over time per channel);
* all values finite, and no time step inside the window that is ``<= 0`` or
  ``> max_gap_s`` (dropped rows within the tolerance do not break a window; steps and
  durations are compared with ``max_gap_s`` and ``min_duration_s`` to within a
  thousandth of a sample interval, so a step of whole intervals nominally on the
  threshold is decided by this rule, not by the rounding of large times).

A run of consecutive passing windows ``j = a..b`` covers the samples ``a..b+W-1``
(every ``W``-sample stretch inside passes). ``trim_s`` is cut from both ends (the
paper's "truncate the window edges"); a run never re-uses samples of the previous run.
The run is then cut into consecutive pieces of ``round(max_window_s * rate_hz)``
samples counted from its first sample (the last piece is the remainder), and each piece
of ``t_end_s - t_start_s >= min_duration_s`` is a still window.

Speed and chunk invariance. The statistics of a window are *defined* as those of its
own samples, copied to contiguous memory and reduced along it (two-pass mean and sd),
so they do not depend on where chunks were cut. Computing that for every sliding
window costs O(W) a sample; instead the sd tests use rolling sums (O(1) a sample,
prefix sums re-anchored every few thousand windows) with a rigorous bound on their
rounding error, and only the rare windows within that bound of a threshold are
reduced in full. The flags are therefore those of the definition, bit for bit
(``tests/test_detect_reference.py`` holds the fast detector to the old one,
``bench/detector_speed.py`` measures both). The output windows' statistics come from
the definition directly, pieces of one length reduced together. The carried state is
the last ``W - 1`` samples plus the open piece (bounded by ``max_window_s``), and it is
explicit: :func:`step` is the pure kernel ``step(state, chunk) -> (state, windows)``;
:class:`StaticDetector` is a thin shell.
"""

from __future__ import annotations

import base64
import functools
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from selfcal.detect_numba import IN, UNSURE, _kernel, kernels_now
from selfcal.errors import InputError

__all__ = [
    "DetectorConfig",
    "DetectorState",
    "StaticDetector",
    "StillWindows",
    "step",
    "flush_state",
]

#: Version tag of :meth:`StaticDetector.state_dict`.
STATE_VERSION = 2  # 2: buffers as base64 float64 (1: JSON lists, still read)

#: Calibration callable: ``(m, 3)`` raw acceleration in g -> ``(m, 3)`` calibrated g.
ToCal = Callable[[np.ndarray], np.ndarray]

# Largest number of float64 values materialised at once when copying sliding windows.
_BLOCK_VALUES = 1 << 20

# Windows per block of re-anchored prefix sums (bounds their rounding error).
_ROLL_BLOCK = 1 << 13

# Longer chunks are stepped through in pieces of this many samples (cache-sized).
_STEP_SAMPLES = 1 << 16

# Below this many new windows a call reduces each window directly (less overhead).
_SMALL_WINDOWS = 64

_UNIT_ROUNDOFF = np.finfo(float).eps / 2


# ----------------------------------------------------------------------------- config
class DetectorConfig(BaseModel):
    """Validated ``[detector]`` section.

    Attributes
    ----------
    rate_hz : float
        Nominal sample rate, Hz (the caller passes the recording's rate). Converts the
        durations below into sample counts.
    twait_s : float
        Length of the sliding test window, s (the paper's ``Twait``).
    trim_s : float
        Cut from both ends of a run of still samples, s.
    min_duration_s : float
        Shortest still window returned (``t_end_s - t_start_s``), s.
    max_window_s : float
        Longer runs are split into consecutive windows of this length, s.
    sd_max_g : float
        Largest per-axis sample sd over the test window, g.
    sd_min_g : float
        Smallest per-axis sample sd over the test window, g (flat-line floor).
    clip_abs_g : float or None
        A sample with ``|value| >=`` this on any axis is saturated, g. None (``false``
        in TOML): no test.
    norm_tol_raw_g : float
        Largest per-sample ``| ||raw|| - 1 |`` when no model is given, g.
    norm_tol_cal_g : float
        Largest ``| ||to_cal(window mean)|| - 1 |`` when a model is given, g.
    pressure_sd_max_kpa : float
        Largest per-channel pressure sd over the test window, kPa.
    max_gap_s : float
        A time step larger than this breaks a window, s.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    rate_hz: float = Field(20.0, gt=0, allow_inf_nan=False)
    twait_s: float = Field(1.0, gt=0, allow_inf_nan=False)
    trim_s: float = Field(0.2, ge=0, allow_inf_nan=False)
    min_duration_s: float = Field(1.0, gt=0, allow_inf_nan=False)
    max_window_s: float = Field(10.0, gt=0, allow_inf_nan=False)
    sd_max_g: float = Field(0.010, gt=0, allow_inf_nan=False)
    sd_min_g: float = Field(0.0002, ge=0, allow_inf_nan=False)
    clip_abs_g: float | None = Field(1.5, gt=0, allow_inf_nan=False)
    norm_tol_raw_g: float = Field(0.15, gt=0, allow_inf_nan=False)
    norm_tol_cal_g: float = Field(0.03, gt=0, allow_inf_nan=False)
    pressure_sd_max_kpa: float = Field(60.0, gt=0, allow_inf_nan=False)
    max_gap_s: float = Field(0.2, gt=0, allow_inf_nan=False)

    @field_validator("clip_abs_g", mode="before")
    @classmethod
    def _clip_off(cls, v: Any) -> Any:
        # TOML has no null: ``clip_abs_g = false`` switches the test off.
        if v is False:
            return None
        if v is True:
            raise ValueError("clip_abs_g: expected a number in g, or false to disable")
        return v

    @model_validator(mode="after")
    def _check_consistent(self) -> "DetectorConfig":
        if self.sd_min_g >= self.sd_max_g:
            raise ValueError(
                f"sd_min_g ({self.sd_min_g}) must be smaller than sd_max_g ({self.sd_max_g})"
            )
        if self.max_window_s < self.min_duration_s:
            raise ValueError(
                f"max_window_s ({self.max_window_s}) must be >= min_duration_s "
                f"({self.min_duration_s})"
            )
        if self.rate_hz * self.gap_limit_s < 1.0:  # (a step of one interval must pass, as in the detector)
            interval = 1.0 / self.rate_hz
            hint = " (are the times in milliseconds? t_s is in seconds)" if interval >= 1.0 else ""
            raise ValueError(
                f"the samples are {interval:g} s apart (rate_hz {self.rate_hz:g}){hint}: more than max_gap_s "
                f"({self.max_gap_s:g} s), so every time step would break a window (raise max_gap_s)"
            )
        if (self.max_window_samples - 1) / self.rate_hz < self.min_duration_s - self.time_tolerance_s:
            raise ValueError(
                f"max_window_s ({self.max_window_s:g}) is {self.max_window_samples} samples at {self.rate_hz:g} Hz, "
                f"which last {(self.max_window_samples - 1) / self.rate_hz:g} s: shorter than min_duration_s "
                f"({self.min_duration_s:g}), so no window could be kept (raise max_window_s)"
            )
        if self.window_samples < 2:
            raise ValueError(
                f"twait_s * rate_hz = {self.twait_s * self.rate_hz:g} samples: the test "
                "window needs at least 2 samples (raise twait_s)"
            )
        return self

    @classmethod
    def from_section(cls, section: dict[str, Any] | None) -> "DetectorConfig":
        """Build from the ``[detector]`` TOML section; unknown or bad keys -> InputError."""
        try:
            return cls(**(section or {}))
        except ValidationError as exc:
            msgs = "; ".join(
                f"{'.'.join(str(p) for p in err['loc']) or 'detector'}: {err['msg']}"
                for err in exc.errors()
            )
            raise InputError(f"config [detector]: {msgs}") from None

    @property
    def time_tolerance_s(self) -> float:
        """A thousandth of a sample interval, s: time steps and durations are compared
        with ``max_gap_s`` and ``min_duration_s`` to within it, so that a step of whole
        sample intervals nominally on the threshold (3 missing samples at 20 Hz against 0.2 s)
        is decided by the documented rule, not by the rounding of large times (1.7e9 s)."""
        return 1e-3 / self.rate_hz

    @property
    def gap_limit_s(self) -> float:
        """A step longer than this breaks a window: ``max_gap_s`` plus the time tolerance, s."""
        return self.max_gap_s + self.time_tolerance_s

    @property
    def duration_floor_s(self) -> float:
        """A piece lasting this long or more is kept: ``min_duration_s`` less the time tolerance, s."""
        return self.min_duration_s - self.time_tolerance_s

    # Derived sample counts (the ``_samples`` results of style principle 2).
    @property
    def window_samples(self) -> int:
        """``W``: samples in the sliding test window."""
        return int(round(self.twait_s * self.rate_hz))

    @property
    def trim_samples(self) -> int:
        """Samples cut from each end of a run."""
        return int(round(self.trim_s * self.rate_hz))

    @property
    def max_window_samples(self) -> int:
        """Samples in a full piece of a split run (at least 2)."""
        return max(2, int(round(self.max_window_s * self.rate_hz)))


# ---------------------------------------------------------------------------- results
@dataclass
class StillWindows:
    """A table of still windows (one row per window).

    Attributes
    ----------
    mean_g : ndarray, shape (m, 3), g
        Per-axis mean of the raw acceleration.
    sd_g : ndarray, shape (m, 3), g
        Per-axis sample standard deviation (ddof=1).
    n : ndarray, shape (m,), int
        Number of samples.
    t_start_s, t_end_s : ndarray, shape (m,), s
        Times of the first and last sample.
    temp_c : ndarray, shape (m,), °C
        Mean of the finite temperature readings (NaN if none).
    pressure_sd_kpa : ndarray, shape (m,), kPa
        Largest per-channel pressure sd over the window (NaN without pressure).
    """

    mean_g: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    sd_g: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    n: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    t_start_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    t_end_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    temp_c: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pressure_sd_kpa: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return int(self.n.shape[0])

    @property
    def duration_s(self) -> np.ndarray:
        """``t_end_s - t_start_s``, shape (m,), s."""
        return self.t_end_s - self.t_start_s

    @classmethod
    def concat(cls, parts: Sequence["StillWindows"]) -> "StillWindows":
        """Stack several tables in order (an empty list gives an empty table)."""
        parts = list(parts)
        if not parts:
            return cls()
        return cls(
            mean_g=np.concatenate([p.mean_g for p in parts], axis=0).reshape(-1, 3),
            sd_g=np.concatenate([p.sd_g for p in parts], axis=0).reshape(-1, 3),
            n=np.concatenate([p.n for p in parts]).astype(np.int64),
            t_start_s=np.concatenate([p.t_start_s for p in parts]),
            t_end_s=np.concatenate([p.t_end_s for p in parts]),
            temp_c=np.concatenate([p.temp_c for p in parts]),
            pressure_sd_kpa=np.concatenate([p.pressure_sd_kpa for p in parts]),
        )


# ------------------------------------------------------------------------------ state
@dataclass
class DetectorState:
    """Everything the detector carries between chunks (global sample indices).

    Attributes
    ----------
    n_seen : int
        Samples received so far in this stream.
    buf_start : int
        Global index of the first buffered sample.
    t_s : ndarray, shape (b,), s
    acc_g : ndarray, shape (b, 3), g
    temp_c : ndarray, shape (b,), °C (NaN where absent)
    pressure_kpa : ndarray, shape (b, k), kPa (``k = 0`` without pressure)
        The buffered samples: the last ``W - 1`` plus the open piece.
    n_pressure : int or None
        Pressure channels of this stream (None before the first sample).
    run_open : bool
        Whether the last evaluated test window passed.
    piece_start : int
        Global index of the first sample of the open piece (if ``run_open``).
    last_end : int
        Global index of the last sample of the previous run (-1: none).
    by_channel : ndarray, shape (4 + k, b), or None
        The buffered samples by channel (ax, ay, az in g, the ``k`` pressure channels in
        kPa, temperature in °C), of which ``acc_g``, ``pressure_kpa`` and ``temp_c`` are
        views, when :func:`step` made them (None: built from them when needed). Not part
        of :func:`state_to_dict` nor of equality.
    """

    n_seen: int = 0
    buf_start: int = 0
    t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    acc_g: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    temp_c: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pressure_kpa: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    n_pressure: int | None = None
    run_open: bool = False
    piece_start: int = 0
    last_end: int = -1
    by_channel: np.ndarray | None = field(default=None, repr=False, compare=False)


def _to_list(a: np.ndarray) -> list:
    """Array -> nested list of floats, non-finite values as None (strict JSON)."""
    obj = np.asarray(a, dtype=float).astype(object)
    obj[~np.isfinite(np.asarray(a, dtype=float))] = None
    return obj.tolist()


def _from_list(x: Any, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    try:
        arr = np.array(x if x is not None else [], dtype=float)  # None -> nan
    except (TypeError, ValueError) as exc:
        raise InputError(f"detector state: {name} is not a numeric array: {exc}") from None
    if arr.size == 0:
        return np.zeros((0, *shape_tail))
    if arr.shape[1:] != shape_tail:
        raise InputError(
            f"detector state: {name} has shape {arr.shape}, expected (b, *{shape_tail})"
        )
    return arr


def _to_b64(a: np.ndarray) -> str:
    """Array -> base64 of its float64 little-endian bytes, row-major (exact, NaN kept)."""
    return base64.b64encode(np.ascontiguousarray(a, dtype="<f8").tobytes()).decode("ascii")


def _from_b64(x: Any, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    try:
        raw = base64.b64decode(x, validate=True)
    except (TypeError, ValueError) as exc:
        raise InputError(f"detector state: {name} is not base64 float64 data: {exc}") from None
    width = 8 * int(np.prod(shape_tail, dtype=np.int64))
    if width and len(raw) % width:
        raise InputError(f"detector state: {name} holds {len(raw)} bytes, not rows of {shape_tail} float64")
    arr = np.frombuffer(raw, dtype="<f8").astype(float)
    return arr.reshape((-1, *shape_tail)) if width else np.zeros((0, *shape_tail))


def state_to_dict(state: DetectorState, config: DetectorConfig) -> dict[str, Any]:
    """JSON-serialisable form of a state: ints, and the buffered samples as base64 float64
    (exact, NaN kept; about 25 times faster to write as JSON than lists of floats)."""
    return {
        "version": STATE_VERSION,
        "config": config.model_dump(),
        "n_seen": int(state.n_seen),
        "buf_start": int(state.buf_start),
        "t_s": _to_b64(state.t_s),
        "acc_g": _to_b64(state.acc_g),
        "temp_c": _to_b64(state.temp_c),
        "pressure_kpa": _to_b64(state.pressure_kpa),
        "n_pressure": state.n_pressure,
        "run_open": bool(state.run_open),
        "piece_start": int(state.piece_start),
        "last_end": int(state.last_end),
    }


def state_from_dict(d: dict[str, Any], config: DetectorConfig) -> DetectorState:
    """Inverse of :func:`state_to_dict`; checks version and config."""
    if not isinstance(d, dict):
        raise InputError(f"detector state: expected a dict, got {type(d).__name__}")
    if d.get("version") not in (1, STATE_VERSION):
        raise InputError(
            f"detector state: version {d.get('version')!r} is not supported "
            f"(expected 1 or {STATE_VERSION})"
        )
    arrays = _from_list if d.get("version") == 1 else _from_b64
    if d.get("config") != config.model_dump():
        raise InputError(
            "detector state: it was saved with a different [detector] config "
            f"({d.get('config')!r}); resume with the same config"
        )
    try:
        k = d["n_pressure"]
        t_s = arrays(d["t_s"], (), "t_s").reshape(-1)
        b = len(t_s)
        state = DetectorState(
            n_seen=int(d["n_seen"]),
            buf_start=int(d["buf_start"]),
            t_s=t_s,
            acc_g=arrays(d["acc_g"], (3,), "acc_g"),
            temp_c=arrays(d["temp_c"], (), "temp_c").reshape(-1),
            pressure_kpa=(
                arrays(d["pressure_kpa"], (int(k),), "pressure_kpa")
                if k
                else np.zeros((b, 0))
            ),
            n_pressure=None if k is None else int(k),
            run_open=bool(d["run_open"]),
            piece_start=int(d["piece_start"]),
            last_end=int(d["last_end"]),
        )
    except KeyError as exc:
        raise InputError(f"detector state: missing key {exc.args[0]!r}") from None
    sizes = {len(state.t_s), len(state.acc_g), len(state.temp_c), len(state.pressure_kpa)}
    if len(sizes) != 1 or state.buf_start + len(state.t_s) != state.n_seen:
        raise InputError(
            "detector state: buffer lengths disagree "
            f"(t_s {len(state.t_s)}, acc_g {len(state.acc_g)}, temp_c {len(state.temp_c)}, "
            f"pressure_kpa {len(state.pressure_kpa)}, buf_start {state.buf_start}, "
            f"n_seen {state.n_seen})"
        )
    _check_indices(state, config)
    return state


def _check_indices(state: DetectorState, cfg: DetectorConfig) -> None:
    """InputError unless the state's indices are ones :func:`step` leaves: a corrupt state
    would have the kernels read and write outside their arrays (the numba ones unchecked)."""
    n, b0 = state.n_seen, state.buf_start
    problems = []
    if b0 < 0 or b0 > max(0, n - cfg.window_samples + 1):
        problems.append(f"buf_start {b0} outside 0..{max(0, n - cfg.window_samples + 1)} (the buffer holds "
                        "the last W - 1 samples at least)")
    if not -1 <= state.last_end < max(n, 0):
        problems.append(f"last_end {state.last_end} outside -1..n_seen - 1 ({n - 1})")
    if state.run_open and not b0 <= state.piece_start <= n + cfg.trim_samples:
        problems.append(f"the open piece starts at {state.piece_start}, outside the buffer's {b0}.."
                        f"{n + cfg.trim_samples}")
    if state.n_pressure is None and n:
        problems.append(f"{n} samples seen without a number of pressure channels")
    if state.n_pressure is not None and state.n_pressure < 0:
        problems.append(f"n_pressure {state.n_pressure} < 0")
    if problems:
        raise InputError(f"detector state: corrupt ({'; '.join(problems)})")


# ---------------------------------------------------------------------------- kernels
#: How a stage runs: True, with the numba kernels when they are available (``SELFCAL_NUMBA``
#: read then); False, with the numpy code; or a tuple from
#: :func:`selfcal.detect_numba.kernels_now` (or None), read once by :func:`step` for all
#: the stages of a chunk.
Accelerate = bool | tuple | None


def _accel(accelerate: Accelerate, i: int):
    """Kernel ``i`` of :func:`selfcal.detect_numba.kernels_now` for ``accelerate``, or None."""
    if isinstance(accelerate, tuple):
        return accelerate[i]
    return _kernel(i) if accelerate else None  # any true value: the kernels if the environment has them


# Inside the kernels the samples are held by channel: ``x`` of shape ``(c, n)``, one
# contiguous row per channel (ax, ay, az in g, then the pressure channels in kPa), so
# that every sum runs along contiguous memory.


def _exact_window_stats(x: np.ndarray, w: int, idx: np.ndarray, accelerate: Accelerate = True) -> tuple[np.ndarray, np.ndarray]:
    """Two-pass mean and sample sd of the ``w``-sample windows that start at ``idx``.

    Parameters
    ----------
    x : ndarray, shape (c, n)
        Samples by channel (any unit), all finite.
    w : int
        Window length, samples (>= 2, <= n).
    idx : ndarray of int, shape (k,)
        First sample of each window (``0 <= idx <= n - w``).
    accelerate : bool or tuple
        Use the numba kernel (:mod:`selfcal.detect_numba`: numpy's sums in numpy's order)
        when it is available; False forces the numpy code (see :data:`Accelerate`).

    Returns
    -------
    mean, sd : ndarray, shape (k, c)
        Same unit as ``x``; sd with ddof=1.

    Notes
    -----
    This is the definition of a window's statistics. Each window of each channel is
    copied to contiguous memory and reduced along it, so the result depends on its own
    ``w`` values only (not on ``n``, ``k`` or where the stream was cut).
    """
    c = x.shape[0]
    k = idx.shape[0]
    mean = np.empty((k, c))
    sd = np.empty((k, c))
    if c == 0 or k == 0:
        return mean, sd
    kernel = _accel(accelerate, 1)
    if kernel is not None:
        return kernel(np.asarray(x, dtype=np.float64), w, np.asarray(idx, dtype=np.int64))
    block = max(1, _BLOCK_VALUES // (w * c))
    offsets = np.arange(w)
    for lo in range(0, k, block):
        hi = min(k, lo + block)
        win = np.take(x, idx[lo:hi, None] + offsets, axis=1)  # (c, b, w), C-contiguous copy
        mu = win.mean(axis=-1)
        dev = win - mu[..., None]
        mean[lo:hi] = mu.T
        sd[lo:hi] = np.sqrt((dev * dev).sum(axis=-1) / (w - 1)).T
    return mean, sd


def _sd_limits(p2: list[float], first: list[float], w: int, length: int, thresholds: tuple):
    """Per channel, the sums of squared deviations a block's rolling sums can decide
    (see :func:`_sd_within`): ``(in_hi, out_hi, in_lo, out_lo)``, each ``(c, 1)``, or
    None if a bound overflows (then every window is decided the slow way).

    ``p2``: each channel's sum of squares about the block's first sample ``first``;
    ``thresholds``: per channel, the upper threshold as a sum of squares over ``1 + r``
    and over ``1 - r``, and the lower one over ``1 - r`` and ``1 + r`` (``-inf``: no
    lower bound), ``r`` the reference's relative rounding.

    The error bound of a window's sum of squared deviations, with ``u`` the unit
    roundoff, ``e1 = 2 (L + 1) u sqrt(L p2) + u sqrt(w p2)`` (a window sum of y, L the
    block's samples), ``e2 = (2 (L + 2) + 1) u p2`` (of y^2), is
    ``e2 + (2 sqrt(w p2) e1 + e1^2) / w + 6 u p2 + 4 u^2 w |first| sqrt(p2)``, which is
    ``c1 p2 + c2 |first| sqrt(p2)``. The reference's own mean is off by at most
    ``e3 = c3 (|first| + sqrt(p2))`` (``c3 = (log2 w + 32) u``: numpy's pairwise sum and
    the division, ``|first| + sqrt(p2)`` bounding every ``|x|`` of the block), which adds
    ``w e3^2`` to its sum of squared deviations; a value far from zero with almost no
    spread (a stuck channel at 1e155, an sd bound near 1e-17) is decided by that term, and
    past the float range it overflows (then the slow way). The margin is twice the sum.
    """
    u = _UNIT_ROUNDOFF
    k1 = 2 * (length + 1) * u * math.sqrt(length) + u * math.sqrt(w)
    c1 = (2 * (length + 2) + 1) * u + (2 * math.sqrt(w) * k1 + k1 * k1) / w + 6 * u
    c2 = 4 * u * u * w
    c3 = (math.log2(w) + 32) * u
    in_hi, out_hi, in_lo, out_lo = [], [], [], []
    for p, f, (hi_in, hi_out, lo_in, lo_out) in zip(p2, first, thresholds):
        if p >= 0:
            e3 = c3 * (abs(f) + math.sqrt(p))
            margin = 2 * (c1 * p + c2 * abs(f) * math.sqrt(p) + w * e3 * e3) + 1e-300
        else:
            margin = math.nan
        if not math.isfinite(margin):
            return None
        in_hi.append(hi_in - margin)
        out_hi.append(hi_out + margin)
        in_lo.append(lo_in + margin)
        out_lo.append(lo_out - margin)
    return (np.array(in_hi)[:, None], np.array(out_hi)[:, None], np.array(in_lo)[:, None],
            np.array(out_lo)[:, None])


@functools.lru_cache(maxsize=64)
def _sd_thresholds(lo_sd: tuple[float, ...], hi_sd: tuple[float, ...], w: int) -> tuple[tuple, np.ndarray]:
    """The sliding sd test's thresholds for ``w``-sample windows and per-channel sd bounds
    ``lo_sd`` / ``hi_sd`` (same unit as the samples; ``lo <= 0``: no lower bound): per
    channel the upper bound as a sum of squared deviations over ``1 + r`` and ``1 - r``,
    the lower over ``1 - r`` and ``1 + r`` (``-inf``: none), ``r`` the two-pass reference's
    relative rounding; as a tuple of 4-tuples and as a read-only ``(c, 4)`` array. Kept
    per bounds and length (a device's detector asks for the same ones at every chunk)."""
    r = (4 * math.log2(w) + 16) * _UNIT_ROUNDOFF  # relative: two-pass reference, sqrt, thresholds
    thresholds = []
    for hsd, lsd in zip(hi_sd, lo_sd):
        hs = hsd * hsd * (w - 1)
        ls = lsd * lsd * (w - 1) if lsd > 0 else -math.inf
        thresholds.append((hs / (1 + r), hs / (1 - r), ls / (1 - r), ls / (1 + r)))
    array = np.array(thresholds, dtype=np.float64).reshape(len(thresholds), 4)
    array.setflags(write=False)
    return tuple(thresholds), array


@functools.lru_cache(maxsize=64)
def _sd_bounds(sd_min_g: float, sd_max_g: float, pressure_sd_max_kpa: float, k: int,
               w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-channel sd bounds ``(lo (3 + k,), hi (3 + k,))`` of the three axes (g) and ``k``
    pressure channels (kPa, no lower bound), and their :func:`_sd_thresholds` array for
    ``w``-sample windows ``(3 + k, 4)``; all read-only, kept per settings."""
    lo_t = (sd_min_g,) * 3 + (0.0,) * k
    hi_t = (sd_max_g,) * 3 + (pressure_sd_max_kpa,) * k
    lo, hi = np.array(lo_t), np.array(hi_t)
    lo.setflags(write=False)
    hi.setflags(write=False)
    return lo, hi, _sd_thresholds(lo_t, hi_t, w)[1]


def _sd_within(x: np.ndarray, w: int, lo_sd: np.ndarray, hi_sd: np.ndarray, accelerate: Accelerate = True) -> np.ndarray:
    """Whether every channel's sample sd lies in ``[lo_sd, hi_sd]``, for every
    ``w``-sample sliding window, decided exactly as :func:`_exact_window_stats` decides.

    Parameters
    ----------
    x : ndarray, shape (c, n)
        Samples by channel (any unit), all finite.
    w : int
        Window length, samples (>= 2, <= n).
    lo_sd, hi_sd : ndarray, shape (c,)
        Bounds per channel, same unit as ``x`` (``lo_sd <= 0``: no lower bound).
    accelerate : bool or tuple
        Use the numba kernel (:mod:`selfcal.detect_numba`) when it is available: the
        same flags, in one pass; False forces the numpy code (see :data:`Accelerate`).

    Returns
    -------
    ndarray of bool, shape (n - w + 1,)

    Notes
    -----
    O(1) per sample. Window sums come from prefix sums that restart every
    ``_ROLL_BLOCK`` windows and are taken about the block's first sample (gravity
    does not cancel). Each block carries a rigorous bound on the rounding error of
    every window's sum of squares (a sequential sum of ``k`` terms is off by at most
    ``k u sum|terms|``, ``u`` the unit roundoff), and the two-pass reference's own
    rounding is a relative margin. A window within that margin of a bound, or with a
    non-finite sum, is recomputed by :func:`_exact_window_stats`. So the flags are the
    two-pass definition's, bit for bit, whatever the chunking: the rolling sums only
    decide the windows that are clearly in or clearly out.
    """
    c, n = x.shape
    m = n - w + 1
    ok = np.ones(max(m, 0), dtype=bool)
    if m <= 0 or c == 0:
        return ok
    u = _UNIT_ROUNDOFF
    inv_w = 1.0 / w
    thresholds, threshold_array = _sd_thresholds(tuple(lo_sd.tolist()), tuple(hi_sd.tolist()), w)
    kernel = _accel(accelerate, 0)
    if kernel is not None:  # the same verdicts, in one pass (selfcal.detect_numba)
        codes = kernel(np.asarray(x, dtype=np.float64), w, threshold_array, _ROLL_BLOCK, u)
        ok = codes == IN
        unsure = np.flatnonzero(codes == UNSURE)
        if unsure.size:
            _, sd = _exact_window_stats(x, w, unsure, accelerate)
            ok[unsure] = ((sd <= hi_sd) & (sd >= lo_sd)).all(axis=1)
        return ok
    for lo in range(0, m, _ROLL_BLOCK):
        hi = min(m, lo + _ROLL_BLOCK)
        seg = x[:, lo : hi + w - 1]
        length = seg.shape[1]
        q = np.empty((2 * c, length + 1))
        q[:, 0] = 0.0
        y = np.subtract(seg, seg[:, :1], out=q[:c, 1:])
        np.multiply(y, y, out=q[c:, 1:])
        np.cumsum(q, axis=1, out=q)  # prefix sums of y (rows :c) and y^2 (rows c:)
        d = q[:, w:] - q[:, :-w]
        s1 = d[:c]
        ss = d[c:]
        s1 *= s1
        s1 *= inv_w
        ss -= s1  # sum of squared deviations of each window, (c, hi - lo)
        # Rounding bound for this block, per channel: every prefix of y^2 is <= p2. In
        # plain floats (a handful of channels: numpy's per-call cost would dominate).
        limits = _sd_limits(q[c:, -1].tolist(), seg[:, 0].tolist(), w, length, thresholds)
        if limits is None:  # overflow: decide every window the slow way
            ok[lo:hi] = False
            maybe = np.ones(hi - lo, dtype=bool)
        else:
            in_hi, out_hi, in_lo, out_lo = limits
            with np.errstate(invalid="ignore"):
                sure_in = ((ss < in_hi) & (ss > in_lo)).all(axis=0)
                ok[lo:hi] = sure_in
                if sure_in.all():
                    continue
                # a channel whose rolling sum overflowed (inf, NaN) cannot rule a window out
                possible = (ss <= out_hi) & (ss >= out_lo) | ~np.isfinite(ss)
                maybe = possible.all(axis=0) & ~sure_in
        unsure = np.flatnonzero(maybe)
        if unsure.size:
            _, sd = _exact_window_stats(x, w, unsure + lo, accelerate)
            ok[lo + unsure] = ((sd <= hi_sd) & (sd >= lo_sd)).all(axis=1)  # sd >= 0 >= lo_sd: no bound
    return ok


def _window_flags(t: np.ndarray, x: np.ndarray, cfg: DetectorConfig, to_cal: ToCal | None,
                  accelerate: Accelerate = True) -> np.ndarray:
    """Pass/fail of every ``W``-sample sliding window of a stretch of samples.

    Parameters
    ----------
    t : ndarray, shape (n,), s
    x : ndarray, shape (3 + k, n)
        By channel: ax, ay, az (g), then ``k`` pressure channels (kPa).
    cfg : DetectorConfig
    to_cal : callable or None
        ``(m, 3) g -> (m, 3) g``; selects the calibrated norm test.

    Returns
    -------
    ndarray, shape (n - W + 1,), bool
        Window ``j`` (samples ``j .. j+W-1``) passes every condition.
    """
    w = cfg.window_samples
    n = t.shape[0]
    m = n - w + 1
    if m <= 0:
        return np.zeros(0, dtype=bool)
    k = x.shape[0] - 3
    lo_sd, hi_sd, thresholds = _sd_bounds(cfg.sd_min_g, cfg.sd_max_g, cfg.pressure_sd_max_kpa, k, w)
    kernel = _accel(accelerate, 2)
    if kernel is not None and t.dtype == np.float64 and x.dtype == np.float64:
        # every test but the calibrated norm in one call (selfcal.detect_numba); a few
        # windows (small chunks) are each reduced exactly, as the numpy code does below
        clip = math.nan if cfg.clip_abs_g is None else cfg.clip_abs_g
        norm_tol = math.nan if to_cal is not None else cfg.norm_tol_raw_g
        codes, n_unsure = kernel(t, x, w, clip, norm_tol, cfg.gap_limit_s, thresholds, _ROLL_BLOCK,
                                 _UNIT_ROUNDOFF, m <= _SMALL_WINDOWS)
        ok = codes == IN
        if n_unsure == 0 and to_cal is None:
            return ok
        with np.errstate(over="ignore", invalid="ignore"):
            finite = np.isfinite(x).all(axis=0)
            x0 = x if finite.all() else np.where(finite, x, 0.0)
            if n_unsure:
                unsure = np.flatnonzero(codes == UNSURE)
                _, sd = _exact_window_stats(x0, w, unsure, accelerate)
                ok[unsure] = ((sd <= hi_sd) & (sd >= lo_sd)).all(axis=1)
            return _calibrated_norm(ok, x0, w, cfg, to_cal, accelerate)
    with np.errstate(over="ignore", invalid="ignore"):  # inf/NaN samples fail below
        finite = np.isfinite(x).all(axis=0)
        bad = ~finite
        if cfg.clip_abs_g is not None:
            bad |= (np.abs(x[:3]) >= cfg.clip_abs_g).any(axis=0)
        if to_cal is None:
            bad |= np.abs(np.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]) - 1.0) >= cfg.norm_tol_raw_g
        dt = np.diff(t)
        gap = np.zeros(n, dtype=bool)
        gap[1:] = ~(dt > 0) | (dt > cfg.gap_limit_s)  # NaN steps break too
        if not (bad.any() or gap.any()):  # the usual still or clean stretch
            ok = np.ones(m, dtype=bool)
        else:  # integer counts per window: exact whatever the chunking
            cbad = np.zeros(n + 1, dtype=np.int64)
            cgap = np.zeros(n + 1, dtype=np.int64)
            np.cumsum(bad, out=cbad[1:])
            np.cumsum(gap, out=cgap[1:])
            ok = (cbad[w:] - cbad[:m] == 0) & (cgap[w:] - cgap[1 : m + 1] == 0)

        x0 = x if finite.all() else np.where(finite, x, 0.0)
        if m <= _SMALL_WINDOWS:  # few new windows (small chunks): reduce each one directly
            cand = np.flatnonzero(ok)
            _, sd = _exact_window_stats(x0, w, cand, accelerate)
            ok[cand] = ((sd <= hi_sd) & (sd >= lo_sd)).all(axis=1)
        elif ok.any():
            ok &= _sd_within(x0, w, lo_sd, hi_sd, accelerate)
        return _calibrated_norm(ok, x0, w, cfg, to_cal, accelerate)


def _calibrated_norm(ok: np.ndarray, x0: np.ndarray, w: int, cfg: DetectorConfig, to_cal: ToCal | None,
                     accelerate: Accelerate = True) -> np.ndarray:
    """``ok`` (m,) with the windows whose calibrated mean fails the norm test set False
    (``to_cal`` None: unchanged); ``x0`` (3 + k, n) the samples, every channel of a sample
    with a non-finite value 0.0 (g, kPa)."""
    if to_cal is not None:
        idx = np.flatnonzero(ok)
        if idx.size:
            mean, _ = _exact_window_stats(x0[:3], w, idx, accelerate)
            cal = np.asarray(to_cal(mean), dtype=float)
            if cal.shape != (idx.size, 3):
                raise InputError(
                    f"to_cal returned shape {cal.shape} for input shape ({idx.size}, 3); "
                    "it must map (m, 3) g to (m, 3) g"
                )
            dev = np.abs(np.sqrt((cal * cal).sum(axis=1)) - 1.0)
            ok[idx[~(dev <= cfg.norm_tol_cal_g)]] = False
    return ok


def _piece_ranges(
    piece_start: int, limit_end: int, final: bool, cfg: DetectorConfig
) -> tuple[list[int], int]:
    """Cut ``[piece_start, limit_end]`` (global sample indices) into pieces.

    Full pieces (``max_window_samples``) are cut while they end at or before
    ``limit_end``; with ``final`` the remainder is a piece too.

    Returns
    -------
    starts : list of int, length k
        First sample of each piece (the pieces are consecutive: each ends where the
        next starts, the last at ``next_start - 1``); a chunk closes a handful at most
        (one per ``max_window_s``), so plain ints.
    next_start : int
        First sample of the next piece.
    """
    size = cfg.max_window_samples
    if limit_end < piece_start:
        return [], piece_start
    if final:
        return list(range(piece_start, limit_end + 1, size)), limit_end + 1
    n_full = (limit_end - piece_start + 1) // size
    return list(range(piece_start, piece_start + size * n_full, size)), piece_start + size * n_full


def _pieces_table(t: np.ndarray, x: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                  cfg: DetectorConfig, accelerate: Accelerate = True) -> StillWindows:
    """Still windows of the pieces ``[lo, hi)`` that last ``min_duration_s``.

    Parameters
    ----------
    t : ndarray, shape (b,), s
    x : ndarray, shape (4 + k, b)
        Buffered samples by channel: ax, ay, az (g), ``k`` pressure channels (kPa),
        temperature (°C, NaN where absent).
    lo, hi : ndarray of int, shape (q,)
        Local index range of each piece (``hi`` excluded), in time order.
    cfg : DetectorConfig

    Returns
    -------
    StillWindows

    Notes
    -----
    A window's statistics are those of its own samples (:func:`_exact_window_stats`,
    pieces of one length together).
    """
    kernel = _accel(accelerate, 3)
    if kernel is not None and lo.size:  # the same table in one call (selfcal.detect_numba)
        _, mean, sd, n, t_start, t_end, temp_mean, psd = kernel(
            np.asarray(t, dtype=np.float64), np.asarray(x, dtype=np.float64), np.asarray(lo, dtype=np.int64),
            np.asarray(hi, dtype=np.int64), cfg.duration_floor_s)
        return StillWindows(mean_g=mean, sd_g=sd, n=n, t_start_s=t_start, t_end_s=t_end, temp_c=temp_mean,
                            pressure_sd_kpa=psd)
    keep = hi - lo >= 2
    keep[keep] = t[hi[keep] - 1] - t[lo[keep]] >= cfg.duration_floor_s
    lo, hi = lo[keep], hi[keep]
    q = lo.size
    if q == 0:
        return StillWindows()
    kp = x.shape[0] - 4
    mean = np.empty((q, 3))
    sd = np.empty((q, 3))
    temp_mean = np.full(q, np.nan)
    psd = np.full(q, np.nan)
    lengths = hi - lo
    one_length = lengths.min() == lengths.max()  # the usual case: no np.unique
    for length in ([int(lengths[0])] if one_length else np.unique(lengths).tolist()):
        rows = np.arange(q) if one_length else np.flatnonzero(lengths == length)
        block = max(1, _BLOCK_VALUES // (length * x.shape[0]))
        for b0 in range(0, rows.size, block):
            r = rows[b0 : b0 + block]
            # every channel in one call (acc, pressure, temperature): each window of each
            # channel is reduced on its own, so a temperature mean is the mean of its values
            with np.errstate(invalid="ignore", over="ignore"):
                ch_mean, ch_sd = _exact_window_stats(x, length, lo[r], accelerate)
            mean[r], sd[r] = ch_mean[:, :3], ch_sd[:, :3]
            t_mean = ch_mean[:, -1]
            whole = np.isfinite(t_mean)  # every value finite (a NaN or inf would show)
            temp_mean[r[whole]] = t_mean[whole]
            if not whole.all():  # gaps in temp_c (or a sum past the float range)
                rr = r[~whole]
                tt = x[-1][lo[rr, None] + np.arange(length)]  # (b, length)
                fin = np.isfinite(tt)
                every = fin.all(axis=1)
                if every.any():
                    temp_mean[rr[every]] = tt[every].mean(axis=1)
                for j in np.flatnonzero(~every & fin.any(axis=1)).tolist():
                    temp_mean[rr[j]] = float(np.ascontiguousarray(tt[j][fin[j]]).mean())
            if kp:
                psd[r] = ch_sd[:, 3 : 3 + kp].max(axis=1)
    return StillWindows(
        mean_g=mean,
        sd_g=sd,
        n=(hi - lo).astype(np.int64),
        t_start_s=t[lo].astype(float),
        t_end_s=t[hi - 1].astype(float),
        temp_c=temp_mean,
        pressure_sd_kpa=psd,
    )


def _emit(t: np.ndarray, x: np.ndarray, g0: int, starts: list[list[int]], ends: list[int],
          cfg: DetectorConfig, accelerate: Accelerate = True) -> StillWindows:
    """Table of the pieces cut by :func:`_piece_ranges` (global indices; ``g0`` is the
    buffer's first; ``ends[i]`` the last sample of the last piece of ``starts[i]``)."""
    lo: list[int] = []
    hi: list[int] = []
    for s, e in zip(starts, ends):
        if s:
            lo += s
            hi += s[1:]
            hi.append(e + 1)
    if not lo:
        return StillWindows()
    return _pieces_table(t, x, np.array(lo, dtype=np.int64) - g0, np.array(hi, dtype=np.int64) - g0, cfg,
                         accelerate)


def _by_channel(acc_g: np.ndarray, pressure_kpa: np.ndarray, temp_c: np.ndarray,
                state: DetectorState | None = None) -> np.ndarray:
    """``(4 + k, b + n)`` by channel: acc (g), pressure (kPa), temperature (°C); the
    state's buffered samples first when given."""
    k = pressure_kpa.shape[1]
    b = 0 if state is None else state.t_s.shape[0]
    n = acc_g.shape[0]
    x = np.empty((4 + k, b + n))
    if b and state.by_channel is not None:
        x[:, :b] = state.by_channel
    elif b:
        x[:3, :b] = state.acc_g.T
        if k:
            x[3 : 3 + k, :b] = state.pressure_kpa.T
        x[-1, :b] = state.temp_c
    x[:3, b:] = acc_g.T
    if k:
        x[3 : 3 + k, b:] = pressure_kpa.T
    x[-1, b:] = temp_c
    return x


def step(
    state: DetectorState,
    t_s: np.ndarray,
    acc_g: np.ndarray,
    temp_c: np.ndarray,
    pressure_kpa: np.ndarray,
    cfg: DetectorConfig,
    to_cal: ToCal | None = None,
) -> tuple[DetectorState, StillWindows]:
    """Pure kernel: consume one validated chunk, return the new state and the windows
    that closed in it.

    Parameters
    ----------
    state : DetectorState
        Carried state (not modified).
    t_s : ndarray, shape (n,), s
    acc_g : ndarray, shape (n, 3), g
    temp_c : ndarray, shape (n,), °C (NaN where absent)
    pressure_kpa : ndarray, shape (n, k), kPa (``k = 0`` without pressure; ``k`` must
        match ``state.n_pressure``)
    cfg : DetectorConfig
    to_cal : callable or None
        Current calibration ``(m, 3) g -> (m, 3) g`` for the tight norm test.

    Returns
    -------
    state : DetectorState
    windows : StillWindows
    """
    if t_s.shape[0] == 0:
        return state, StillWindows()
    held = state.pressure_kpa.shape[1] if state.t_s.shape[0] else state.n_pressure
    if held is not None and pressure_kpa.shape[1] != held:  # (the numba kernel would read past them)
        raise InputError(f"detector step: {pressure_kpa.shape[1]} pressure channels in the chunk, the state "
                         f"holds {held}")
    if t_s.shape[0] > _STEP_SAMPLES:  # long chunks in cache-sized steps (same windows)
        parts = []
        for lo in range(0, t_s.shape[0], _STEP_SAMPLES):
            sl = slice(lo, lo + _STEP_SAMPLES)
            state, part = step(state, t_s[sl], acc_g[sl], temp_c[sl], pressure_kpa[sl], cfg, to_cal)
            parts.append(part)
        return state, StillWindows.concat(parts)
    kernels = kernels_now()  # SELFCAL_NUMBA read once for every stage of the chunk
    if to_cal is None and kernels is not None and kernels[5] is not None:
        return _step_in_one_call(kernels[5], state, t_s, acc_g, temp_c, pressure_kpa, cfg)
    w = cfg.window_samples
    trim = cfg.trim_samples
    g0 = state.buf_start
    kp = pressure_kpa.shape[1]
    t = np.concatenate((state.t_s, t_s))
    x = _by_channel(acc_g, pressure_kpa, temp_c, state)  # (4 + kp, b + n)
    n_total = g0 + t.shape[0]

    # New test windows: j0 .. n_total - W (global), all starting inside the buffer.
    j0 = max(state.n_seen - w + 1, 0)
    l0 = j0 - g0
    flags = _window_flags(t[l0:], x[: 3 + kp, l0:], cfg, to_cal, kernels)

    run_open = state.run_open
    piece_start = state.piece_start
    last_end = state.last_end
    cut_starts: list[list[int]] = []
    cut_ends: list[int] = []
    if flags.size:
        if flags.all():  # the common cases (still or moving throughout) without diffs
            starts, ends = ([] if run_open else [j0]), []
        elif not flags.any():
            starts, ends = [], ([j0 - 1] if run_open else [])
        else:
            edges = _accel(kernels, 4)
            if edges is not None:  # the same edges in one call (selfcal.detect_numba)
                first, last = edges(flags, bool(run_open))
                starts = (first + j0).tolist()
                ends = (last + j0).tolist()
            else:
                d = np.diff(np.concatenate(([run_open], flags)).astype(np.int8))
                starts = (np.flatnonzero(d == 1) + j0).tolist()
                ends = (np.flatnonzero(d == -1) + j0 - 1).tolist()  # last passing window
        # Runs: (first passing window or None if it opened before, last or None if open).
        firsts: list[int | None] = ([None] if run_open else []) + starts
        runs = [(a, ends[i] if i < len(ends) else None) for i, a in enumerate(firsts)]
        last_window = n_total - w
        for a, b in runs:  # loop over runs, not samples
            if a is not None:
                piece_start = max(a + trim, last_end + 1)
                run_open = True
            if b is not None:
                seg_end = b + w - 1 - trim
                s, piece_start = _piece_ranges(piece_start, seg_end, True, cfg)
                cut_starts.append(s)
                cut_ends.append(piece_start - 1)
                last_end = max(last_end, seg_end)
                run_open = False
            else:
                known_end = last_window + w - 1 - trim
                s, piece_start = _piece_ranges(piece_start, known_end, False, cfg)
                cut_starts.append(s)
                cut_ends.append(piece_start - 1)

    keep = n_total - w + 1
    if run_open:
        keep = min(keep, piece_start)
    keep = min(max(keep, g0), n_total)
    k = keep - g0
    # the kept samples in one copy, by channel; the state's fields are views of it, and the
    # next chunk copies it back in one block (values unchanged)
    new_state = _carried(n_total, keep, t[k:].copy(), x[:, k:].copy(), run_open, piece_start, last_end)
    return new_state, _emit(t, x, g0, cut_starts, cut_ends, cfg, kernels)


def _carried(n_seen: int, buf_start: int, t_s: np.ndarray, buf: np.ndarray, run_open: bool, piece_start: int,
             last_end: int) -> DetectorState:
    """The state after a chunk, its sample fields views of ``buf`` (4 + k, b) by channel
    (g, kPa, °C) at times ``t_s`` (b,) s."""
    return DetectorState(
        n_seen=n_seen,
        buf_start=buf_start,
        t_s=t_s,
        acc_g=buf[:3].T,
        temp_c=buf[-1],
        pressure_kpa=buf[3:-1].T,
        n_pressure=buf.shape[0] - 4,
        run_open=run_open,
        piece_start=piece_start,
        last_end=last_end,
        by_channel=buf,
    )


def _plain(a: np.ndarray) -> np.ndarray:
    """``a`` (float64) as a C-contiguous, writable array (a copy only when it is not one:
    a column of a table, a read-only buffer), so that the kernel has one signature to
    compile."""
    flags = a.flags
    return a if flags.c_contiguous and flags.writeable else np.array(a, dtype=np.float64, order="C")


def _step_in_one_call(kernel, state: DetectorState, t_s: np.ndarray, acc_g: np.ndarray, temp_c: np.ndarray,
                      pressure_kpa: np.ndarray, cfg: DetectorConfig) -> tuple[DetectorState, StillWindows]:
    """:func:`step` without a calibrated norm test by the numba kernel ``kernel``
    (:func:`selfcal._detect_jit.step_chunk`): the same state and windows, in one call."""
    kp = pressure_kpa.shape[1]
    b = state.t_s.shape[0]
    if state.by_channel is not None:
        xb = state.by_channel
    elif b:
        xb = _by_channel(state.acc_g, state.pressure_kpa, state.temp_c)
    else:
        xb = np.empty((4 + kp, 0))
    lo_sd, hi_sd, thresholds = _sd_bounds(cfg.sd_min_g, cfg.sd_max_g, cfg.pressure_sd_max_kpa, kp,
                                          cfg.window_samples)
    (t_keep, buf, n_seen, buf_start, run_open, piece_start, last_end,
     mean, sd, n, t_start, t_end, temp, psd) = kernel(
        _plain(state.t_s), xb, _plain(t_s), _plain(acc_g), _plain(temp_c), _plain(pressure_kpa),
        state.buf_start, state.n_seen, bool(state.run_open),
        state.piece_start, state.last_end, cfg.window_samples, cfg.trim_samples, cfg.max_window_samples,
        math.nan if cfg.clip_abs_g is None else cfg.clip_abs_g, cfg.norm_tol_raw_g, cfg.gap_limit_s, thresholds,
        lo_sd, hi_sd, _ROLL_BLOCK, _UNIT_ROUNDOFF, _SMALL_WINDOWS, cfg.duration_floor_s)
    new_state = _carried(n_seen, buf_start, t_keep, buf, run_open, piece_start, last_end)
    if not n.shape[0]:
        return new_state, StillWindows()
    return new_state, StillWindows(mean_g=mean, sd_g=sd, n=n, t_start_s=t_start, t_end_s=t_end, temp_c=temp,
                                   pressure_sd_kpa=psd)


def flush_state(state: DetectorState, cfg: DetectorConfig) -> tuple[DetectorState, StillWindows]:
    """Pure kernel: end of stream. Close an open run; return a fresh state and the
    windows it closed."""
    windows = StillWindows()
    if state.run_open and state.n_seen >= cfg.window_samples:
        x = _by_channel(state.acc_g, state.pressure_kpa, state.temp_c)
        seg_end = state.n_seen - 1 - cfg.trim_samples
        s, nxt = _piece_ranges(state.piece_start, seg_end, True, cfg)
        windows = _emit(state.t_s, x, state.buf_start, [s], [nxt - 1], cfg)
    return DetectorState(), windows


# ------------------------------------------------------------------------------ class
class StaticDetector:
    """Streaming still-window detector (thin shell over :func:`step`).

    Parameters
    ----------
    config : DetectorConfig, dict or None
        The ``[detector]`` settings (a dict is validated; None: defaults).

    Attributes
    ----------
    state_ : DetectorState
        The carried state after the last :meth:`feed`.

    Examples
    --------
    >>> import numpy as np
    >>> det = StaticDetector(DetectorConfig(rate_hz=20.0))
    >>> rng = np.random.default_rng(0)
    >>> t = np.arange(200) / 20.0
    >>> acc = np.array([0.0, 0.0, 1.0]) + 0.003 * rng.standard_normal((200, 3))
    >>> w = StillWindows.concat([det.feed(t[:77], acc[:77]), det.feed(t[77:], acc[77:]),
    ...                          det.flush()])
    >>> len(w), int(w.n[0])
    (1, 192)
    """

    def __init__(self, config: DetectorConfig | dict | None = None):
        self.config = config

    @property
    def _cfg(self) -> DetectorConfig:
        """The validated config (``self.config`` itself is never changed)."""
        cfg = self.config
        if isinstance(cfg, DetectorConfig):
            return cfg
        cached = self.__dict__.get("_validated")
        if cached is not None and cached[0] is cfg:
            return cached[1]
        if cfg is None or isinstance(cfg, dict):
            valid = DetectorConfig.from_section(cfg)
            self.__dict__["_validated"] = (cfg, valid)
            return valid
        raise InputError(
            f"config: expected DetectorConfig, dict or None, got {type(cfg).__name__}"
        )

    @property
    def state_(self) -> DetectorState:
        st = self.__dict__.get("_state")
        if st is None:
            st = self.__dict__["_state"] = DetectorState()
        return st

    def feed(
        self,
        t_s: np.ndarray,
        acc_g: np.ndarray,
        temp_c: np.ndarray | None = None,
        pressure_kpa: np.ndarray | None = None,
        to_cal: ToCal | None = None,
    ) -> StillWindows:
        """Consume one chunk; return the still windows that closed in it.

        Parameters
        ----------
        t_s : array_like, shape (n,), s
            Sample times (increasing; a step ``<= 0`` or ``> max_gap_s`` breaks windows).
        acc_g : array_like, shape (n, 3), g
            Raw acceleration.
        temp_c : array_like, shape (n,), °C, optional
            Temperature (NaN where not read).
        pressure_kpa : array_like, shape (n, k), kPa, optional
            Pressure channels; ``k`` must stay the same for the whole stream.
        to_cal : callable, optional
            Current calibration, ``(m, 3) g -> (m, 3) g``: replaces the loose raw norm
            test by the tight calibrated one. Keep it fixed for chunk invariance.

        Returns
        -------
        StillWindows
        """
        cfg = self._cfg
        t, acc, temp, pres = self._validate(t_s, acc_g, temp_c, pressure_kpa)
        if to_cal is not None and not callable(to_cal):
            raise InputError(f"to_cal: expected a callable or None, got {type(to_cal).__name__}")
        state, windows = step(self.state_, t, acc, temp, pres, cfg, to_cal)
        self.__dict__["_state"] = state
        return windows

    def flush(self) -> StillWindows:
        """End of stream: close an open run and reset (the next feed starts a new stream).

        Returns
        -------
        StillWindows
        """
        state, windows = flush_state(self.state_, self._cfg)
        self.__dict__["_state"] = state
        return windows

    def state_dict(self) -> dict[str, Any]:
        """JSON-serialisable state (``json.dumps(..., allow_nan=False)`` works)."""
        return state_to_dict(self.state_, self._cfg)

    @classmethod
    def from_state(
        cls, config: DetectorConfig | dict | None, state: dict[str, Any]
    ) -> "StaticDetector":
        """Resume a detector saved with :meth:`state_dict` (same config required)."""
        det = cls(config)
        det.__dict__["_state"] = state_from_dict(state, det._cfg)
        return det

    def _validate(self, t_s, acc_g, temp_c, pressure_kpa):
        try:
            t = np.asarray(t_s, dtype=float)
            acc = np.asarray(acc_g, dtype=float)
        except (TypeError, ValueError) as exc:
            raise InputError(f"t_s/acc_g: not numeric arrays: {exc}") from None
        if t.ndim != 1:
            raise InputError(f"t_s: expected shape (n,), got {t.shape}")
        n = t.shape[0]
        if acc.shape != (n, 3):
            raise InputError(f"acc_g: expected shape ({n}, 3) to match t_s, got {acc.shape}")
        if temp_c is None:
            temp = np.full(n, np.nan)
        else:
            temp = np.asarray(temp_c, dtype=float)
            if temp.shape != (n,):
                raise InputError(f"temp_c: expected shape ({n},) to match t_s, got {temp.shape}")
        expected_k = self.state_.n_pressure
        if pressure_kpa is None:
            pres = np.zeros((n, 0))
        else:
            pres = np.asarray(pressure_kpa, dtype=float)
            if pres.ndim != 2 or pres.shape[0] != n or pres.shape[1] < 1:
                raise InputError(
                    f"pressure_kpa: expected shape ({n}, k) with k >= 1 to match t_s, "
                    f"got {pres.shape}"
                )
        if n and expected_k is not None and pres.shape[1] != expected_k:
            raise InputError(
                f"pressure_kpa: this stream has {expected_k} pressure channel(s), the chunk "
                f"has {pres.shape[1]} (pass the same channels in every chunk, or flush first)"
            )
        return t, acc, temp, pres
