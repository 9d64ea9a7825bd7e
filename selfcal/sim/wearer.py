"""The wearer's day: a schedule of segments (what the foot / shoe does, when).

A :class:`Schedule` is a columnar table of segments, each one of three motion types:

* ``STILL`` — a fixed orientation with small sway (quiet standing, a sitting posture,
  the shoe on the floor). These are the still moments the calibrator lives on.
* ``MOVE`` — a short band-limited movement between two orientations (weight shift,
  fidget, sit-to-stand, the shoe handled when put on / taken off).
* ``GAIT`` — a walking or stairs bout (see :mod:`selfcal.sim.motion`).

Time origin: ``t = 0`` is midnight of day 0, the shoe off the foot. Clock times of the
config (``wear_start_h`` ...) are hours after midnight of each day.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from selfcal.sim import plan_numba
from selfcal.sim.config import LogNormalDuration, SimConfig
from selfcal.sim.temperature import segment_start_states

SECONDS_PER_DAY = 86400.0

# activity codes (per segment and per sample)
OFF, SIT, STAND, WALK, STAIRS, HANDLING = 0, 1, 2, 3, 4, 5
ACTIVITY_NAMES = {OFF: "off_foot", SIT: "sit", STAND: "stand", WALK: "walk", STAIRS: "stairs", HANDLING: "handling"}
# motion codes
STILL, MOVE, GAIT = 0, 1, 2

#: Longest still segment; longer ones are split (same still_id) so that the ambient
#: temperature and the streamed chunks stay fine-grained.
MAX_STILL_PIECE_S = 1800.0

_COLUMNS = (
    "dur_s", "activity", "motion", "pitch0", "roll0", "pitch1", "roll1", "sd_g",
    "cycle_s", "stride_m", "slope_rad", "climb", "l1", "l2", "l3", "l4", "still_id",
)


def _draw(d: LogNormalDuration, rng: np.random.Generator, size: int | None = None) -> np.ndarray | float:
    x = d.median_s * np.exp(np.log(d.gsd) * rng.standard_normal(size))
    if size is None:  # one draw: min/max is np.clip's value without its per-call cost
        return float(min(max(x, d.min_s), d.max_s))
    return np.clip(x, d.min_s, d.max_s)


def _cdf(probs) -> np.ndarray:
    """Cumulative distribution of (unnormalised) probabilities, as Generator.choice builds it."""
    p = np.asarray(probs, float)
    cdf = (p / p.sum()).cumsum()
    cdf /= cdf[-1]
    return cdf


def _nonneg(v: float) -> float:
    """``np.maximum(v, 0.0)`` of one float: NaN kept, -0.0 made 0.0 (as numpy's does)."""
    return v if (v > 0.0 or v != v) else 0.0


def _pick(cdf: np.ndarray, rng: np.random.Generator) -> int:
    """``rng.choice(len(cdf), p=...)`` for a precomputed :func:`_cdf`: the same draw from
    the same stream (one uniform, searched in the cdf), without choice's checks per call."""
    return int(cdf.searchsorted(rng.random(), side="right"))


@dataclass
class Schedule:
    """Columnar segment table of a simulated wear period.

    Attributes
    ----------
    rate_hz : float
        Sample rate the integer columns refer to.
    start : ndarray of int64, shape (m,)
        First sample index of each segment (``t_s = index / rate_hz``).
    n : ndarray of int64, shape (m,)
        Samples per segment (>= 1).
    activity, motion : ndarray of int8, shape (m,)
        Codes (``OFF, SIT, ...`` and ``STILL, MOVE, GAIT``).
    pitch0, roll0, pitch1, roll1 : ndarray, shape (m,), rad
        Orientation at the start and end (equal for STILL). Pitch > 0: toes up;
        roll > 0: left side (+y) up; roll = pi: upside down.
    sd_g : ndarray, shape (m,), g
        Sway sd (STILL) or movement acceleration sd (MOVE).
    cycle_s, stride_m, slope_rad, climb : ndarray, shape (m,)
        GAIT bout: mean gait cycle (s), stride length (m), terrain slope (rad),
        climb (+1 stairs up, -1 down, 0 level).
    load : ndarray, shape (m, 4)
        Pressure load per channel relative to the wearer's standing load.
    still_id : ndarray of int64, shape (m,)
        Id of the still period (pieces of a long period share it), -1 if not STILL.
    temp0_c, heat0_c, temp_target_c, heat_target_c, tau_t_s, tau_h_s : ndarray, shape (m,)
        Temperature model constants and start states (see :mod:`selfcal.sim.temperature`).
    on_foot : ndarray of bool, shape (m,)
    days : ndarray of float, shape (n_days, 3)
        Per-day draws: ambient mean (degC), in-shoe plateau (degC), walking heat (degC).
    stand_kpa : ndarray, shape (4,), kPa
        This wearer's standing load per channel.
    """

    rate_hz: float
    start: np.ndarray
    n: np.ndarray
    activity: np.ndarray
    motion: np.ndarray
    pitch0: np.ndarray
    roll0: np.ndarray
    pitch1: np.ndarray
    roll1: np.ndarray
    sd_g: np.ndarray
    cycle_s: np.ndarray
    stride_m: np.ndarray
    slope_rad: np.ndarray
    climb: np.ndarray
    load: np.ndarray
    still_id: np.ndarray
    temp0_c: np.ndarray
    heat0_c: np.ndarray
    temp_target_c: np.ndarray
    heat_target_c: np.ndarray
    tau_t_s: np.ndarray
    tau_h_s: np.ndarray
    on_foot: np.ndarray
    days: np.ndarray
    stand_kpa: np.ndarray

    @property
    def n_samples(self) -> int:
        """Total samples before packet loss."""
        return int(self.start[-1] + self.n[-1]) if len(self.n) else 0

    def __len__(self) -> int:
        return len(self.n)

    def activity_fractions(self) -> dict[str, float]:
        """Share of time per activity (before packet loss)."""
        tot = self.n.sum()
        return {name: float(self.n[self.activity == code].sum() / tot) for code, name in ACTIVITY_NAMES.items()}

    def still_periods(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Merged still periods: (start sample, n samples, first segment index), each (k,)."""
        idx = np.flatnonzero(self.motion == STILL)
        sid = self.still_id[idx]
        first = np.r_[True, sid[1:] != sid[:-1]]
        groups = np.cumsum(first) - 1
        starts = self.start[idx][first]
        ns = np.bincount(groups, weights=self.n[idx]).astype(np.int64)
        return starts, ns, idx[first]


class _Builder:
    """Accumulates segment rows (in seconds) while the day is planned."""

    _INITIAL_ROWS = 4096  # the buffer's room at the start (a day of the default wearer)

    def __init__(self, cfg: SimConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        self.rows: list[tuple] = []  # the latest rows (planned in Python), after those in the buffer
        # earlier rows by column, (len(_COLUMNS), capacity) float64, the first ``_n`` filled.
        # numpy allocates it (its large arrays get transparent huge pages; the kernel's own
        # allocations got 4 KiB pages: 60 000 page faults for a year's plan) and the schedule
        # reads its columns as they are, without a copy. Room not yet filled is never touched.
        self._cols = np.empty((len(_COLUMNS), self._INITIAL_ROWS))
        self._n = 0
        self._rows_per_s = 0.0  # the most rows a second of a worn period has taken so far
        self.kernels = None  # the planner's numba kernels (plan_numba.kernels), or None: Python
        self._kernel_inputs: tuple | None = None  # their constants, built at first use
        self.t = 0.0
        self.orient = (0.0, 0.0)
        self.load = (0.0, 0.0, 0.0, 0.0)
        self.next_still = 0
        p = cfg.posture
        self.shoe_pitch = np.deg2rad(p.shoe_pitch_deg + p.shoe_pitch_sd_deg * rng.standard_normal())
        # choice tables, built once (the planner draws hundreds of thousands of postures)
        self._off_cdf = _cdf([p.off_flat_p, p.off_side_p, p.off_upside_down_p])
        self._sit_cdf = _cdf([p.sit_flat_p, p.sit_heel_p, p.sit_toes_p, p.sit_crossed_p])
        a = cfg.activity
        self._next_state = {name: (list(row), _cdf([row[k] for k in row])) for name, row in
                            (("sit", a.from_sit), ("stand", a.from_stand), ("walk", a.from_walk),
                             ("stairs", a.from_stairs))}

    # -- primitives -------------------------------------------------------------
    def last_row(self):
        """The latest row (a tuple, or a column of the buffer), or None."""
        if self.rows:
            return self.rows[-1]
        return self._cols[:, self._n - 1] if self._n else None

    def reserve(self, k: int) -> None:
        """Room in the buffer for ``k`` more rows (a copy into a bigger one, twice as large
        at least, when it lacks it)."""
        if self._n + k > self._cols.shape[1]:
            bigger = np.empty((len(_COLUMNS), max(2 * self._cols.shape[1], self._n + k)))
            bigger[:, :self._n] = self._cols[:, :self._n]
            self._cols = bigger

    def reserve_until(self, t_end_s: float) -> None:
        """Room for the rows up to ``t_end_s`` (s) at the rate planned so far and a quarter
        more (never touched unless filled), at most :data:`_RESERVE_MAX_ROWS`: a long plan
        is not copied through a dozen doublings."""
        if self.t <= 0 or t_end_s <= self.t:
            return
        planned = self._n + len(self.rows)
        self.reserve(min(int(1.25 * planned / self.t * (t_end_s - self.t)) + 4096, _RESERVE_MAX_ROWS))

    def _flush(self) -> None:
        """The rows planned in Python, into the buffer."""
        if self.rows:
            rows = np.array(self.rows, dtype=float)
            self.rows = []
            self._append(rows)

    def _append(self, rows: np.ndarray) -> None:
        k = len(rows)
        self.reserve(k)
        self._cols[:, self._n:self._n + k] = rows.T
        self._n += k

    def add_block(self, rows: np.ndarray) -> None:
        """Append rows planned elsewhere, (k, len(_COLUMNS)) float64, after the rows so far."""
        self._flush()
        self._append(rows)

    def table(self) -> np.ndarray:
        """Every row so far, (m, len(_COLUMNS)) float64."""
        return np.ascontiguousarray(self.columns().T)

    def columns(self) -> np.ndarray:
        """:meth:`table` by column: (len(_COLUMNS), m) float64, each column a contiguous
        row (the same values; a year's table is ~1.7 M rows, and selecting its columns
        from rows read every one strided). A view of the builder's buffer, not a copy."""
        self._flush()
        return self._cols[:, :self._n]

    def still(self, dur: float, act: int, orient: tuple[float, float], sd_g: float, load) -> None:
        last = self.last_row()
        if last is not None and last[2] == STILL and (last[3], last[4]) == tuple(orient):
            sid = last[-1]  # continues the previous still period
        else:
            sid = self.next_still
            self.next_still += 1
        left = dur
        while left > 0:
            piece = min(left, MAX_STILL_PIECE_S)
            self.rows.append((piece, act, STILL, *orient, *orient, sd_g, 0, 0, 0, 0, *load, sid))
            left -= piece
        self.t += dur
        self.orient = orient
        self.load = tuple(load)

    def move(self, dur: float, act: int, to: tuple[float, float], sd_g: float, load=None) -> None:
        load = self.load if load is None else load
        self.rows.append((dur, act, MOVE, *self.orient, *to, sd_g, 0, 0, 0, 0, *load, -1))
        self.t += dur
        self.orient = to

    def gait(self, dur: float, act: int, climb: float) -> None:
        g = self.cfg.gait
        rng = self.rng
        if act == STAIRS:
            cycle = g.stairs_cycle_s * (1 + 0.05 * rng.standard_normal())
            stride = g.stairs_stride_length_m
            slope = 0.0
        else:
            cycle = g.cycle_s + g.cycle_sd_s * rng.standard_normal()
            stride = g.stride_length_m + g.stride_length_sd_m * rng.standard_normal()
            slope = np.deg2rad(g.slope_sd_deg * rng.standard_normal())
        cycle = float(np.clip(cycle, 0.7, 2.2))
        stride = float(max(stride, 0.3))
        flat = (self.shoe_pitch + slope, 0.0)
        self.rows.append((dur, act, GAIT, *flat, *flat, 0.0, cycle, stride, slope, climb, np.nan, 0, 0, 0, -1))
        self.t += dur
        self.orient = flat
        self.load = (1.0, 1.0, 1.0, 1.0)

    # -- postures -----------------------------------------------------------------
    def off_orientation(self) -> tuple[float, float]:
        p, rng = self.cfg.posture, self.rng
        k = _pick(self._off_cdf, rng)
        tilt = np.deg2rad(p.off_tilt_sd_deg) * rng.standard_normal(2)
        if k == 0:
            return (self.shoe_pitch + tilt[0], tilt[1])
        if k == 1:
            return (tilt[0], np.sign(rng.uniform(-1, 1)) * np.pi / 2 + tilt[1])
        return (-self.shoe_pitch + tilt[0], np.pi + tilt[1])

    # The postures are drawn hundreds of thousands of times: plain float arithmetic, in
    # the order (and so with the results, bit for bit) of the numpy expressions it replaced.
    def stand_posture(self) -> tuple[tuple[float, float], tuple]:
        p, rng = self.cfg.posture, self.rng
        t0, t1 = rng.standard_normal(2).tolist()
        c = math.radians(p.stand_tilt_sd_deg)
        w = 0.15 * rng.standard_normal()
        share = rng.uniform(0.8, 1.2)
        load = (share * (1 + w), share * 1.0, share * (1 - w), share * (1 - w))
        return (float(self.shoe_pitch) + c * t0, c * t1), load

    def sit_posture(self) -> tuple[tuple[float, float], float, tuple]:
        p, rng = self.cfg.posture, self.rng
        k = _pick(self._sit_cdf, rng)
        f = self.cfg.pressure.sit_factor
        sway = p.sit_sway_sd_mg * 1e-3
        if k == 0:
            t0, t1 = rng.standard_normal(2).tolist()
            c = math.radians(p.sit_flat_tilt_sd_deg)
            orient = (float(self.shoe_pitch) + c * t0, c * t1)
            z = 1 + 0.2 * rng.standard_normal()
            load = ((f * 1.2) * z, (f * 1.0) * z, (f * 0.9) * z, (f * 0.6) * z)
        elif k == 1:
            orient = (math.radians(rng.uniform(*p.sit_heel_pitch_deg)), math.radians(5 * rng.standard_normal()))
            load = (f * 2.0, f * 0.2, f * 0.0, f * 0.0)
        elif k == 2:
            orient = (math.radians(rng.uniform(*p.sit_toes_pitch_deg)), math.radians(5 * rng.standard_normal()))
            load = (f * 0.0, f * 0.2, f * 1.8, f * 1.5)
        else:
            roll = math.radians(rng.uniform(*p.sit_crossed_roll_deg)) * (-1, 1)[int(rng.integers(0, 2))]
            orient = (math.radians(rng.uniform(-40, 0)), roll)
            load = (0.0, 0.0, 0.0, 0.0)
            sway = p.sit_crossed_sway_sd_mg * 1e-3
        return orient, sway, tuple(_nonneg(v) for v in load)

    # -- activities ---------------------------------------------------------------
    def _alternating(self, total: float, quiet: LogNormalDuration, move: LogNormalDuration):
        k = int(total / (quiet.median_s + move.median_s)) * 2 + 8
        q = _draw(quiet, self.rng, k)
        m = _draw(move, self.rng, k)
        out = []
        used = 0.0
        for qi, mi in zip(q.tolist(), m.tolist()):
            if used >= total:
                break
            mi = min(mi, total - used)
            out.append(("move", mi))
            used += mi
            if used >= total:
                break
            qi = min(qi, total - used)
            out.append(("quiet", qi))
            used += qi
        return out

    def stand(self, total: float) -> None:
        p = self.cfg.posture
        for kind, d in self._alternating(total, p.stand_quiet, p.stand_shift):
            if kind == "move":
                orient, load = self.stand_posture()
                self.move(d, STAND, orient, p.stand_shift_sd_g, load=self.load)
                self._pending = (orient, load)
            else:
                orient, load = self._pending
                self.still(d, STAND, orient, p.stand_sway_sd_mg * 1e-3, load)

    def sit(self, total: float) -> None:
        p = self.cfg.posture
        for kind, d in self._alternating(total, p.sit_quiet, p.sit_fidget):
            if kind == "move":
                orient, sway, load = self.sit_posture()
                self.move(d, SIT, orient, p.sit_fidget_sd_g)
                self._pending = (orient, sway, load)
            else:
                orient, sway, load = self._pending
                self.still(d, SIT, orient, sway, load)

    def off(self, total: float) -> None:
        p = self.cfg.posture
        d = min(float(_draw(p.handling, self.rng)), total / 2)
        orient = self.off_orientation()
        self.move(d, HANDLING, orient, p.handling_sd_g, load=(0.0, 0.0, 0.0, 0.0))
        self.still(total - d, OFF, orient, p.off_sway_sd_mg * 1e-3, (0.0, 0.0, 0.0, 0.0))

    def don(self) -> None:
        p = self.cfg.posture
        d = float(_draw(p.handling, self.rng))
        orient, load = self.stand_posture()
        self.move(d, HANDLING, orient, p.handling_sd_g, load=(0.0, 0.0, 0.0, 0.0))

    def worn(self, total: float) -> None:
        """Semi-Markov chain of sit / stand / walk / stairs for ``total`` seconds (the
        numba kernel when it is there and on, the same rows and draws; else Python)."""
        kernels = self.kernels
        if kernels is None:
            self.worn_python(total)
        else:
            self.worn_compiled(kernels.worn, total)

    def kernel_inputs(self) -> tuple:
        """The planner's constants as the kernel takes them (built once per builder)."""
        if self._kernel_inputs is None:
            from selfcal.sim import _plan_jit as J

            a, p, g = self.cfg.activity, self.cfg.posture, self.cfg.gait
            par = np.zeros(J.N_PAR)
            for slot, d in ((J.P_SIT, a.sit), (J.P_STAND, a.stand), (J.P_WALK_SHORT, a.walk_short),
                            (J.P_WALK_LONG, a.walk_long), (J.P_STAIRS, a.stairs), (J.P_STAND_QUIET, p.stand_quiet),
                            (J.P_STAND_SHIFT, p.stand_shift), (J.P_SIT_QUIET, p.sit_quiet),
                            (J.P_SIT_FIDGET, p.sit_fidget)):
                par[slot:slot + 4] = (d.median_s, np.log(d.gsd), d.min_s, d.max_s)
            par[J.P_WALK_LONG_FRACTION] = a.walk_long_fraction
            par[J.P_SHOE_PITCH] = self.shoe_pitch
            par[J.P_STAND_TILT_RAD] = math.radians(p.stand_tilt_sd_deg)
            par[J.P_STAND_SHIFT_SD_G] = p.stand_shift_sd_g
            par[J.P_STAND_SWAY_G] = p.stand_sway_sd_mg * 1e-3
            par[J.P_SIT_FACTOR] = self.cfg.pressure.sit_factor
            par[J.P_SIT_SWAY_G] = p.sit_sway_sd_mg * 1e-3
            par[J.P_SIT_FLAT_TILT_RAD] = math.radians(p.sit_flat_tilt_sd_deg)
            par[J.P_SIT_HEEL_PITCH_DEG:J.P_SIT_HEEL_PITCH_DEG + 2] = p.sit_heel_pitch_deg
            par[J.P_SIT_TOES_PITCH_DEG:J.P_SIT_TOES_PITCH_DEG + 2] = p.sit_toes_pitch_deg
            par[J.P_SIT_CROSSED_ROLL_DEG:J.P_SIT_CROSSED_ROLL_DEG + 2] = p.sit_crossed_roll_deg
            par[J.P_SIT_CROSSED_SWAY_G] = p.sit_crossed_sway_sd_mg * 1e-3
            par[J.P_SIT_FIDGET_SD_G] = p.sit_fidget_sd_g
            par[[J.P_STAIRS_CYCLE_S, J.P_STAIRS_STRIDE_M, J.P_CYCLE_S, J.P_CYCLE_SD_S]] = (
                g.stairs_cycle_s, g.stairs_stride_length_m, g.cycle_s, g.cycle_sd_s)
            par[[J.P_STRIDE_M, J.P_STRIDE_SD_M, J.P_SLOPE_SD_DEG]] = (
                g.stride_length_m, g.stride_length_sd_m, g.slope_sd_deg)
            par[J.P_MAX_STILL_PIECE_S] = MAX_STILL_PIECE_S
            states = ("sit", "stand", "walk", "stairs")  # the kernel's state codes 0..3
            next_code = np.zeros((4, 4), dtype=np.int64)
            next_cdf = np.ones((4, 4))
            next_len = np.zeros(4, dtype=np.int64)
            for i, name in enumerate(states):
                names, cdf = self._next_state[name]
                next_code[i, :len(names)] = [states.index(x) for x in names]
                next_cdf[i, :len(cdf)] = cdf
                next_len[i] = len(cdf)
            self._kernel_inputs = (par, self._sit_cdf, next_code, next_cdf, next_len)
        return self._kernel_inputs

    def worn_compiled(self, kernel, total: float) -> None:
        """:meth:`worn` by the numba kernel (:mod:`selfcal.sim._plan_jit`), its rows written
        into the buffer (room reserved for what the busiest worn second so far took, and
        the kernel grows the buffer itself beyond that)."""
        orient = np.array(self.orient, dtype=float)
        load = np.array(self.load, dtype=float)
        self._flush()
        n0 = self._n
        self.reserve(int(1.5 * self._rows_per_s * total) + 256)
        cols, n, t, next_still = kernel(self.rng, float(total), *self.kernel_inputs(), float(self.t), orient,
                                        load, int(self.next_still), self._cols, n0)
        self._cols, self._n = cols, int(n)
        if total > 0:
            self._rows_per_s = max(self._rows_per_s, (self._n - n0) / total)
        self.t, self.next_still = t, int(next_still)
        self.orient, self.load = (float(orient[0]), float(orient[1])), tuple(load.tolist())

    def worn_python(self, total: float) -> None:
        """:meth:`worn` in Python (the reference the kernel is checked against)."""
        a = self.cfg.activity
        rng = self.rng
        end = self.t + total
        state = "stand"
        climb = 1.0
        while self.t < end - 1e-9:
            left = end - self.t
            if state == "sit":
                self.sit(min(float(_draw(a.sit, rng)), left))
            elif state == "stand":
                self.stand(min(float(_draw(a.stand, rng)), left))
            elif state == "walk":
                dist = a.walk_long if rng.uniform() < a.walk_long_fraction else a.walk_short
                self.gait(min(float(_draw(dist, rng)), left), WALK, 0.0)
            else:
                climb = -climb if rng.uniform() < 0.8 else climb  # mostly up then down
                self.gait(min(float(_draw(a.stairs, rng)), left), STAIRS, climb)
            names, cdf = self._next_state[state]
            state = names[_pick(cdf, rng)]


#: The most rows a plan reserves room for after its first day (~1.1 GB of address space,
#: ~3 years of the default wearer); a longer plan grows its buffer by doubling beyond it.
_RESERVE_MAX_ROWS = 8_000_000


def make_schedule(config: SimConfig, rng: np.random.Generator, days: float, rate_hz: float | None = None) -> Schedule:
    """Plan ``days`` of wear: segments, orientations, loads and temperature constants.

    Parameters
    ----------
    config : SimConfig
    rng : numpy.random.Generator
        Drives every draw of the plan (and nothing else).
    days : float
        Length of the simulation (days, from midnight of day 0).
    rate_hz : float, optional
        Sample rate of the integer columns (default ``config.ble.rate_hz``).

    Returns
    -------
    Schedule
    """
    rate = float(rate_hz or config.ble.rate_hz)
    total_s = float(days) * SECONDS_PER_DAY
    b = _Builder(config, rng)
    b.kernels = plan_numba.kernels(days)
    dc, tc = config.day, config.temperature
    n_days = int(np.ceil(days)) + 1
    day_draws = np.column_stack([
        rng.uniform(*tc.ambient_c, n_days),
        rng.uniform(*tc.foot_c, n_days),
        rng.uniform(*tc.walk_heat_c, n_days),
    ])
    b.orient = b.off_orientation()
    d = 0
    while b.t < total_s:
        day0 = d * SECONDS_PER_DAY
        ws = day0 + 3600 * (dc.wear_start_h + dc.wear_start_sd_h * rng.standard_normal())
        we = day0 + 3600 * (dc.wear_end_h + dc.wear_end_sd_h * rng.standard_normal())
        ws = max(ws, b.t + 60.0)
        we = max(we, ws + 3600.0)
        # night / morning: the shoe stays where it was left (no new orientation)
        if b.t < ws:
            b.still(ws - b.t, OFF, b.orient, config.posture.off_sway_sd_mg * 1e-3, (0.0, 0.0, 0.0, 0.0))
        if b.t >= total_s:
            break
        n_breaks = rng.poisson(dc.breaks_per_day)
        br_start = np.sort(rng.uniform(ws + 1800, max(we - 1800, ws + 1801), n_breaks))
        br_dur = np.atleast_1d(_draw(dc.break_duration, rng, n_breaks))
        b.don()
        for s0, bd in zip(br_start.tolist(), br_dur.tolist()):
            if s0 <= b.t + 60 or s0 + bd >= we:
                continue
            b.worn(s0 - b.t)
            b.off(bd)
            b.don()
        if we > b.t:
            b.worn(we - b.t)
        next_ws = day0 + SECONDS_PER_DAY + 3600 * dc.wear_start_h
        b.off(max(next_ws - b.t, 600.0))
        d += 1
        if d == 1:
            b.reserve_until(total_s)  # at the first day's rate
    return _finish(b, config, rate, total_s, day_draws)


def _rows_kept(keep: np.ndarray) -> slice | np.ndarray:
    """An index of the rows ``keep`` (bool, (m,)): a slice when they are the first ones
    (the usual case: only rows past the end are dropped), so that selecting them is a
    view, not a copy; otherwise ``keep`` itself."""
    k = int(np.count_nonzero(keep))
    return slice(0, k) if keep[:k].all() else keep


def _finish(b: _Builder, config: SimConfig, rate: float, total_s: float, day_draws: np.ndarray) -> Schedule:
    table = b.columns()
    cols = dict(zip(_COLUMNS, table))
    t_start = np.r_[0.0, np.cumsum(cols["dur_s"])[:-1]]
    keep = t_start < total_s
    t_end = np.minimum(t_start + cols["dur_s"], total_s)
    i0 = np.rint(t_start * rate).astype(np.int64)
    i1 = np.rint(t_end * rate).astype(np.int64)
    keep &= i1 > i0
    take = _rows_kept(keep)
    start, n = i0[take], (i1 - i0)[take]
    if not isinstance(take, slice):
        # a few rows (segments shorter than half a sample) are dropped from the middle: each
        # column's kept values move to its front in place (one temporary a column, the same
        # size each time, reused), not into 17 new arrays of the whole plan
        k = len(start)
        for row in table:
            row[:k] = row[take]
        take = slice(0, k)
    sel = {name: v[take] for name, v in cols.items()}
    t0 = start / rate
    dur = n / rate
    act = sel["activity"].astype(np.int8)
    # temperature constants
    tc = config.temperature
    day_idx = np.minimum((t0 // SECONDS_PER_DAY).astype(int), len(day_draws) - 1)
    clock_h = (t0 % SECONDS_PER_DAY) / 3600.0
    ambient = day_draws[day_idx, 0] + tc.ambient_daily_swing_c * np.cos(2 * np.pi * (clock_h - 15.0) / 24.0)
    on_foot = np.isin(act, (SIT, STAND, WALK, STAIRS))
    walking = np.isin(act, (WALK, STAIRS))
    target = np.where(on_foot, day_draws[day_idx, 1], ambient)
    heat_t = np.where(walking, day_draws[day_idx, 2], 0.0)
    tau_t = np.where(on_foot, tc.tau_on_s, tc.tau_off_s)
    tau_h = np.full(len(n), tc.tau_walk_s)
    tau_h = np.where(np.isclose(tau_h, tau_t), tau_h * 1.001, tau_h)
    temp0, heat0 = segment_start_states(dur, target, heat_t, tau_t, tau_h, on_foot, float(ambient[0]),
                                        kernel=b.kernels)
    pc = config.pressure
    stand_kpa = np.asarray(pc.stand_kpa) * np.exp(pc.wearer_sd * b.rng.standard_normal(4))
    return Schedule(
        rate_hz=rate, start=start, n=n, activity=act, motion=sel["motion"].astype(np.int8),
        pitch0=sel["pitch0"], roll0=sel["roll0"], pitch1=sel["pitch1"], roll1=sel["roll1"],
        sd_g=sel["sd_g"], cycle_s=sel["cycle_s"], stride_m=sel["stride_m"], slope_rad=sel["slope_rad"],
        climb=sel["climb"], load=np.column_stack([sel["l1"], sel["l2"], sel["l3"], sel["l4"]]),
        still_id=sel["still_id"].astype(np.int64), temp0_c=temp0, heat0_c=heat0, temp_target_c=target,
        heat_target_c=heat_t, tau_t_s=tau_t, tau_h_s=tau_h, on_foot=on_foot, days=day_draws,
        stand_kpa=stand_kpa,
    )
