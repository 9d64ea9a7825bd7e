"""REFERENCE COPY, kept for tests and bench/detector_speed.py only: the still detector as
it was before the O(1) rolling statistics (selfcal/detect.py at commit 814a27f). Every
sliding window is copied and reduced in full (O(W) per sample). The fast detector must
return the same windows, bit for bit (tests/test_detect_reference.py).

Streaming static (still-pose) detector.

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

Chunk invariance: every statistic is computed from its own samples (a contiguous copy
of each window, reduced along its contiguous axis; counts by integer cumsums), never
from running float sums, so the numbers do not depend on where chunks were cut. The
carried state is the last ``W - 1`` samples plus the open piece (bounded by
``max_window_s``), and it is explicit: :func:`step` is the pure kernel
``step(state, chunk) -> (state, windows)``; :class:`StaticDetector` is a thin shell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

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
STATE_VERSION = 1

#: Calibration callable: ``(m, 3)`` raw acceleration in g -> ``(m, 3)`` calibrated g.
ToCal = Callable[[np.ndarray], np.ndarray]

# Largest number of float64 values materialised at once when copying sliding windows.
_BLOCK_VALUES = 1 << 20


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


def state_to_dict(state: DetectorState, config: DetectorConfig) -> dict[str, Any]:
    """JSON-serialisable form of a state (lists, floats, ints; NaN as null)."""
    return {
        "version": STATE_VERSION,
        "config": config.model_dump(),
        "n_seen": int(state.n_seen),
        "buf_start": int(state.buf_start),
        "t_s": _to_list(state.t_s),
        "acc_g": _to_list(state.acc_g),
        "temp_c": _to_list(state.temp_c),
        "pressure_kpa": _to_list(state.pressure_kpa),
        "n_pressure": state.n_pressure,
        "run_open": bool(state.run_open),
        "piece_start": int(state.piece_start),
        "last_end": int(state.last_end),
    }


def state_from_dict(d: dict[str, Any], config: DetectorConfig) -> DetectorState:
    """Inverse of :func:`state_to_dict`; checks version and config."""
    if not isinstance(d, dict):
        raise InputError(f"detector state: expected a dict, got {type(d).__name__}")
    if d.get("version") != STATE_VERSION:
        raise InputError(
            f"detector state: version {d.get('version')!r} is not supported "
            f"(expected {STATE_VERSION})"
        )
    if d.get("config") != config.model_dump():
        raise InputError(
            "detector state: it was saved with a different [detector] config "
            f"({d.get('config')!r}); resume with the same config"
        )
    try:
        k = d["n_pressure"]
        b = len(d["t_s"])
        state = DetectorState(
            n_seen=int(d["n_seen"]),
            buf_start=int(d["buf_start"]),
            t_s=_from_list(d["t_s"], (), "t_s").reshape(-1),
            acc_g=_from_list(d["acc_g"], (3,), "acc_g"),
            temp_c=_from_list(d["temp_c"], (), "temp_c").reshape(-1),
            pressure_kpa=(
                _from_list(d["pressure_kpa"], (int(k),), "pressure_kpa")
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
    return state


# ---------------------------------------------------------------------------- kernels
def _window_mean_sd(x: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-window mean and sample sd of every ``w``-sample sliding window.

    Parameters
    ----------
    x : ndarray, shape (n, c)
        Samples (any unit), all finite.
    w : int
        Window length, samples (>= 2, <= n).

    Returns
    -------
    mean, sd : ndarray, shape (n - w + 1, c)
        Same unit as ``x``; sd with ddof=1.

    Notes
    -----
    Each window is copied to contiguous memory and reduced along that axis, so its
    result depends on its own ``w`` values only (not on ``n`` or on where the stream
    was cut); a block loop bounds the memory.
    """
    n, c = x.shape
    m = n - w + 1
    mean = np.empty((m, c))
    sd = np.empty((m, c))
    if c == 0 or m <= 0:
        return mean, sd
    block = max(1, _BLOCK_VALUES // (w * c))
    for lo in range(0, m, block):
        hi = min(m, lo + block)
        win = np.ascontiguousarray(sliding_window_view(x[lo : hi + w - 1], w, axis=0))
        mu = win.mean(axis=-1)
        dev = win - mu[..., None]
        mean[lo:hi] = mu
        sd[lo:hi] = np.sqrt((dev * dev).sum(axis=-1) / (w - 1))
    return mean, sd


def _piece_stats(
    t: np.ndarray, acc: np.ndarray, temp: np.ndarray, pres: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Statistics of one still window.

    Parameters
    ----------
    t : ndarray, shape (n,), s
    acc : ndarray, shape (n, 3), g
    temp : ndarray, shape (n,), °C (NaN where absent)
    pres : ndarray, shape (n, k), kPa

    Returns
    -------
    mean : ndarray, shape (3,), g
    sd : ndarray, shape (3,), g (ddof=1)
    temp_mean : float, °C
        Mean of the finite readings (NaN if none).
    pressure_sd : float, kPa
        Largest per-channel sd (NaN if ``k = 0``).
    """
    a = np.ascontiguousarray(acc.T)  # (3, n): reduce along the contiguous axis
    n = a.shape[1]
    mu = a.mean(axis=1)
    dev = a - mu[:, None]
    sd = np.sqrt((dev * dev).sum(axis=1) / (n - 1))
    ok = np.isfinite(temp)
    temp_mean = float(np.ascontiguousarray(temp[ok]).mean()) if ok.any() else math.nan
    if pres.shape[1]:
        p = np.ascontiguousarray(pres.T)
        pdev = p - p.mean(axis=1)[:, None]
        psd = float(np.sqrt((pdev * pdev).sum(axis=1) / (n - 1)).max())
    else:
        psd = math.nan
    return mu, sd, temp_mean, psd


def _window_flags(
    t: np.ndarray,
    acc: np.ndarray,
    pres: np.ndarray,
    cfg: DetectorConfig,
    to_cal: ToCal | None,
) -> np.ndarray:
    """Pass/fail of every ``W``-sample sliding window of a stretch of samples.

    Parameters
    ----------
    t : ndarray, shape (n,), s
    acc : ndarray, shape (n, 3), g
    pres : ndarray, shape (n, k), kPa
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
    finite = np.isfinite(acc).all(axis=1) & np.isfinite(pres).all(axis=1)
    bad = ~finite
    with np.errstate(invalid="ignore"):
        if cfg.clip_abs_g is not None:
            bad |= (np.abs(acc) >= cfg.clip_abs_g).any(axis=1)
        if to_cal is None:
            bad |= np.abs(np.sqrt((acc * acc).sum(axis=1)) - 1.0) >= cfg.norm_tol_raw_g
        dt = np.diff(t)
        gap = np.zeros(n, dtype=bool)
        gap[1:] = ~(dt > 0) | (dt > cfg.max_gap_s + 1e-3 / cfg.rate_hz)  # NaN steps break too
    # Integer counts per window: exact whatever the chunking.
    cbad = np.concatenate(([0], np.cumsum(bad, dtype=np.int64)))
    cgap = np.concatenate(([0], np.cumsum(gap, dtype=np.int64)))
    ok = (cbad[w:] - cbad[:m] == 0) & (cgap[w:] - cgap[1 : m + 1] == 0)

    a0 = np.where(finite[:, None], acc, 0.0)
    mean, sd = _window_mean_sd(a0, w)
    ok &= (sd <= cfg.sd_max_g).all(axis=1) & (sd >= cfg.sd_min_g).all(axis=1)
    if pres.shape[1]:
        p0 = np.where(finite[:, None], pres, 0.0)
        _, psd = _window_mean_sd(p0, w)
        ok &= psd.max(axis=1) <= cfg.pressure_sd_max_kpa
    if to_cal is not None:
        idx = np.flatnonzero(ok)
        if idx.size:
            cal = np.asarray(to_cal(mean[idx]), dtype=float)
            if cal.shape != (idx.size, 3):
                raise InputError(
                    f"to_cal returned shape {cal.shape} for input shape ({idx.size}, 3); "
                    "it must map (m, 3) g to (m, 3) g"
                )
            with np.errstate(invalid="ignore"):
                dev = np.abs(np.sqrt((cal * cal).sum(axis=1)) - 1.0)
            ok[idx[~(dev <= cfg.norm_tol_cal_g)]] = False
    return ok


def _emit_pieces(
    buf: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    g0: int,
    piece_start: int,
    limit_end: int,
    final: bool,
    cfg: DetectorConfig,
    out: list[tuple],
) -> int:
    """Cut ``[piece_start, limit_end]`` into pieces; return the next piece start.

    Full pieces (``max_window_samples``) are emitted while they end at or before
    ``limit_end``; with ``final`` the remainder is emitted too. A piece is kept when it
    lasts at least ``min_duration_s``.
    """
    t, acc, temp, pres = buf
    size = cfg.max_window_samples
    ps = piece_start
    while True:
        if ps + size - 1 <= limit_end:
            pe = ps + size - 1
        elif final and ps <= limit_end:
            pe = limit_end
        else:
            break
        lo, hi = ps - g0, pe - g0 + 1
        if t[hi - 1] - t[lo] >= cfg.min_duration_s - 1e-3 / cfg.rate_hz and hi - lo >= 2:
            mu, sd, tc, psd = _piece_stats(t[lo:hi], acc[lo:hi], temp[lo:hi], pres[lo:hi])
            out.append((mu, sd, hi - lo, t[lo], t[hi - 1], tc, psd))
        ps = pe + 1
    return ps


def _table(rows: list[tuple]) -> StillWindows:
    if not rows:
        return StillWindows()
    return StillWindows(
        mean_g=np.array([r[0] for r in rows], dtype=float).reshape(-1, 3),
        sd_g=np.array([r[1] for r in rows], dtype=float).reshape(-1, 3),
        n=np.array([r[2] for r in rows], dtype=np.int64),
        t_start_s=np.array([r[3] for r in rows], dtype=float),
        t_end_s=np.array([r[4] for r in rows], dtype=float),
        temp_c=np.array([r[5] for r in rows], dtype=float),
        pressure_sd_kpa=np.array([r[6] for r in rows], dtype=float),
    )


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
    w = cfg.window_samples
    trim = cfg.trim_samples
    g0 = state.buf_start
    t = np.concatenate((state.t_s, t_s))
    acc = np.concatenate((state.acc_g, acc_g), axis=0)
    temp = np.concatenate((state.temp_c, temp_c))
    old_p = state.pressure_kpa
    if old_p.shape[0] == 0:
        old_p = np.zeros((0, pressure_kpa.shape[1]))
    pres = np.concatenate((old_p, pressure_kpa), axis=0)
    n_total = g0 + t.shape[0]

    # New test windows: j0 .. n_total - W (global), all starting inside the buffer.
    j0 = max(state.n_seen - w + 1, 0)
    l0 = j0 - g0
    flags = _window_flags(t[l0:], acc[l0:], pres[l0:], cfg, to_cal)

    run_open = state.run_open
    piece_start = state.piece_start
    last_end = state.last_end
    rows: list[tuple] = []
    buf = (t, acc, temp, pres)
    if flags.size:
        d = np.diff(np.concatenate(([run_open], flags)).astype(np.int8))
        starts = (np.flatnonzero(d == 1) + j0).tolist()
        ends = (np.flatnonzero(d == -1) + j0 - 1).tolist()  # last passing window
        runs: list[tuple[int | None, int | None]] = []
        if run_open:
            runs.append((None, ends.pop(0) if ends else None))
        for a in starts:
            runs.append((a, ends.pop(0) if ends else None))
        last_window = n_total - w
        for a, b in runs:  # loop over runs, not samples
            if a is not None:
                piece_start = max(a + trim, last_end + 1)
                run_open = True
            if b is not None:
                seg_end = b + w - 1 - trim
                piece_start = _emit_pieces(buf, g0, piece_start, seg_end, True, cfg, rows)
                last_end = max(last_end, seg_end)
                run_open = False
            else:
                known_end = last_window + w - 1 - trim
                piece_start = _emit_pieces(buf, g0, piece_start, known_end, False, cfg, rows)

    keep = n_total - w + 1
    if run_open:
        keep = min(keep, piece_start)
    keep = min(max(keep, g0), n_total)
    k = keep - g0
    new_state = DetectorState(
        n_seen=n_total,
        buf_start=keep,
        t_s=t[k:].copy(),
        acc_g=acc[k:].copy(),
        temp_c=temp[k:].copy(),
        pressure_kpa=pres[k:].copy(),
        n_pressure=pressure_kpa.shape[1],
        run_open=run_open,
        piece_start=piece_start,
        last_end=last_end,
    )
    return new_state, _table(rows)


def flush_state(state: DetectorState, cfg: DetectorConfig) -> tuple[DetectorState, StillWindows]:
    """Pure kernel: end of stream. Close an open run; return a fresh state and the
    windows it closed."""
    rows: list[tuple] = []
    if state.run_open and state.n_seen >= cfg.window_samples:
        buf = (state.t_s, state.acc_g, state.temp_c, state.pressure_kpa)
        seg_end = state.n_seen - 1 - cfg.trim_samples
        _emit_pieces(buf, state.buf_start, state.piece_start, seg_end, True, cfg, rows)
    return DetectorState(), _table(rows)


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
