"""The simulation: a planned wear period + one device, streamed as samples or as poses.

:class:`Simulation` ties together the wearer schedule (:mod:`~selfcal.sim.wearer`), the
foot motion (:mod:`~selfcal.sim.motion`), temperature, pressure and the sensor
(:mod:`~selfcal.sim.sensor`). All randomness derives from one ``numpy.random.Generator``
at construction: independent child streams for the device, the plan, the motion, the
sensor noise, the radio and the poses, so switching an effect on never changes any
other draw, and :meth:`Simulation.iter_samples` / :meth:`Simulation.poses` can be called
again and give identical output.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from selfcal.sim import draw_numba
from selfcal.sim.config import SimConfig
from selfcal.sim.draw_numba import standard_normal
from selfcal.sim.motion import gait_force, gravity_foot, lowpass_noise, move_force
from selfcal.sim.pressure import pressure_by_channel
from selfcal.sim.sensor import SensorTruth, draw_sensor_truth, read_out, sensor_mean
from selfcal.sim.temperature import temperature_at
from selfcal.sim.wearer import (
    ACTIVITY_NAMES, GAIT, MOVE, OFF, STAIRS, STILL, Schedule, make_schedule,
)

TRUTH_FORMAT = "selfcal-sim-truth v1"
TRUTH_CONVENTION = (
    "raw = offset + inv(matrix) @ a_true (+ effects + noise), a_true in g in the foot frame; "
    "a_cal = matrix @ (raw - offset); params = QR factor R of matrix (positive diagonal)"
)

_STREAMS = ("sensor", "schedule", "motion", "noise", "radio", "pressure", "temperature", "poses")


@dataclass
class SampleChunk:
    """A block of the 20 Hz stream (rows lost on the radio already removed).

    Attributes
    ----------
    t_s : ndarray, shape (n,), s
    acc_g : ndarray, shape (n, 3), g (raw unit)
        What the insole reports.
    temp_c : ndarray, shape (n,), degC
        Reported temperature.
    pressure_kpa : ndarray, shape (n, 4), kPa
        Heel, midfoot, 1st metatarsal, toe.
    a_true_g : ndarray, shape (n, 3), g
        True specific force, foot frame.
    temp_true_c : ndarray, shape (n,), degC
        True sensor temperature (drives the effects).
    activity : ndarray of int8, shape (n,)
        Codes of :data:`selfcal.sim.wearer.ACTIVITY_NAMES`.
    still : ndarray of bool, shape (n,)
        True still moment (a STILL segment).
    index : ndarray of int64, shape (n,)
        Sample index before packet loss (``t_s = index / rate_hz``).

    The truth (``a_true_g``, ``temp_true_c``, ``activity``, ``still``, ``index``) is None
    in a chunk streamed without it (:meth:`Simulation.iter_samples` ``truth=False``).
    """

    t_s: np.ndarray
    acc_g: np.ndarray
    temp_c: np.ndarray
    pressure_kpa: np.ndarray
    a_true_g: np.ndarray | None
    temp_true_c: np.ndarray | None
    activity: np.ndarray | None
    still: np.ndarray | None
    index: np.ndarray | None

    def __len__(self) -> int:
        return len(self.t_s)

    def split(self, t_s: float) -> tuple["SampleChunk", "SampleChunk"]:
        """The rows before ``t_s`` (s) and the rows from it on (``t_s`` ascending)."""
        k = int(np.searchsorted(self.t_s, t_s, side="left"))
        names = SampleChunk.__dataclass_fields__
        cols = {n: getattr(self, n) for n in names}
        return (SampleChunk(**{n: None if v is None else v[:k] for n, v in cols.items()}),
                SampleChunk(**{n: None if v is None else v[k:] for n, v in cols.items()}))

    @staticmethod
    def concatenate(chunks: list["SampleChunk"]) -> "SampleChunk":
        """Join chunks in order (a column None in any of them is None)."""
        names = SampleChunk.__dataclass_fields__
        cols = {k: [getattr(c, k) for c in chunks] for k in names}
        return SampleChunk(**{k: None if any(v is None for v in vs) else np.concatenate(vs) for k, vs in cols.items()})


@dataclass
class PoseTable:
    """Still windows (one row each), as a still detector would report them.

    Attributes
    ----------
    t_s : ndarray, shape (m,), s
        Window start.
    duration_s : ndarray, shape (m,), s
    n : ndarray of int64, shape (m,)
        Samples received in the window (after packet loss).
    mean_g, sd_g : ndarray, shape (m, 3), g (raw unit)
        Mean and per-axis sd of the reported acceleration.
    temp_c : ndarray, shape (m,), degC
        Mean reported temperature.
    pressure_kpa : ndarray, shape (m, 4), kPa, or None
        Mean pressure per channel (None when :meth:`Simulation.poses` was asked without).
    a_true_g : ndarray, shape (m, 3), g
        True mean specific force (foot frame).
    temp_true_c : ndarray, shape (m,), degC
    activity : ndarray of int8, shape (m,)
    noise_var_g2 : ndarray, shape (m, 3), g^2
        True variance of the noise of each window mean, per axis (white sensor noise and
        quantisation averaged over ``n``, plus the low-pass sway): what an efficient
        estimator's weights would be (the Cramér-Rao bound of ``bench/consistency.py``).
    """

    t_s: np.ndarray
    duration_s: np.ndarray
    n: np.ndarray
    mean_g: np.ndarray
    sd_g: np.ndarray
    temp_c: np.ndarray
    pressure_kpa: np.ndarray | None
    a_true_g: np.ndarray
    temp_true_c: np.ndarray
    activity: np.ndarray
    noise_var_g2: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)


@dataclass
class SimTruth:
    """Everything a metric needs to compare against: device, wearer, seed, config."""

    sensor: SensorTruth
    config: SimConfig
    days: float
    rate_hz: float
    seed: int | None = None
    wearer: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (the ``*.truth.json`` content)."""
        d: dict[str, Any] = {"format": TRUTH_FORMAT, "convention": TRUTH_CONVENTION, "unit": "g"}
        d.update(self.sensor.to_dict())
        d.update({
            "seed": self.seed, "days": self.days, "rate_hz": self.rate_hz,
            "wearer": self.wearer, "config": self.config.model_dump(mode="json"),
        })
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SimTruth":
        """Inverse of :meth:`to_dict`."""
        return cls(
            sensor=SensorTruth.from_dict(d), config=SimConfig.from_section(d["config"]),
            days=float(d["days"]), rate_hz=float(d["rate_hz"]), seed=d.get("seed"),
            wearer=d.get("wearer", {}),
        )

    def write_json(self, path: str | Path) -> None:
        """Write the truth file."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def read_json(cls, path: str | Path) -> "SimTruth":
        """Read a truth file written by :meth:`write_json`."""
        return cls.from_dict(json.loads(Path(path).read_text()))


#: Standard normals a 20-Hz sample draws at least: 3 of sensor noise, 4 of pressure
#: noise and 1 of reported temperature (sway and gait draw more on their samples).
NORMALS_PER_SAMPLE = 8


class Simulation:
    """One device worn by one simulated person for ``days``.

    Parameters
    ----------
    config : SimConfig
    rng : numpy.random.Generator
        The only source of randomness (one draw of 4 words at construction seeds every
        child stream).
    days : float, optional
        Default ``config.days``.
    rate_hz : float, optional
        Default ``config.ble.rate_hz``.
    seed : int, optional
        Recorded in the truth (the seed ``rng`` was made from, if known).

    Attributes
    ----------
    truth : SimTruth
    schedule : Schedule

    Examples
    --------
    >>> sim = Simulation(SimConfig(), np.random.default_rng(1), days=0.05)
    >>> n = sum(len(c) for c in sim.iter_samples())
    """

    def __init__(self, config: SimConfig, rng: np.random.Generator, days: float | None = None,
                 rate_hz: float | None = None, seed: int | None = None):
        self.config = config
        self.days = float(days if days is not None else config.days)
        self.rate_hz = float(rate_hz or config.ble.rate_hz)
        root = np.random.SeedSequence(rng.integers(0, 2**63 - 1, size=4).tolist())
        self._seeds = dict(zip(_STREAMS, root.spawn(len(_STREAMS))))
        sensor = draw_sensor_truth(config, self._rng("sensor"))
        self.schedule = make_schedule(config, self._rng("schedule"), self.days, self.rate_hz)
        self.truth = SimTruth(sensor=sensor, config=config, days=self.days, rate_hz=self.rate_hz,
                              seed=seed, wearer=wearer_summary(self.schedule))

    def _rng(self, name: str) -> np.random.Generator:
        return np.random.default_rng(self._seeds[name])

    # ------------------------------------------------------------------ samples
    def chunk_bounds(self, chunk_s: float | None = None) -> list[tuple[int, int]]:
        """Segment ranges ``[a, b)`` of each streamed chunk (whole segments)."""
        s = self.schedule
        chunk_n = max(1, int(round((chunk_s or self.config.chunk_s) * self.rate_hz)))
        grp = s.start // chunk_n
        cuts = np.flatnonzero(np.diff(grp)) + 1
        edges = np.r_[0, cuts, len(s)]
        return list(zip(edges[:-1].tolist(), edges[1:].tolist()))

    def iter_samples(self, chunk_s: float | None = None, progress: bool = False,
                     truth: bool = True) -> Iterator[SampleChunk]:
        """Stream the whole wear period as :class:`SampleChunk` blocks.

        Parameters
        ----------
        chunk_s : float, optional
            Target chunk length (s); a chunk holds whole segments, so it can be longer.
            Default ``config.chunk_s`` (1 h).
        progress : bool
            Show a tqdm bar on stderr.
        truth : bool
            False leaves the truth columns out (None): what a device would send, the same
            values, without taking the received rows of five more columns.

        Yields
        ------
        SampleChunk
        """
        rngs = {k: self._rng(k) for k in ("motion", "noise", "radio", "pressure", "temperature")}
        bounds = self.chunk_bounds(chunk_s)
        # a long stream loads the normal draws' kernel (the same numbers): 8 and more a sample
        draw_numba.kernels(draws=NORMALS_PER_SAMPLE * float(self.schedule.n.sum()))
        it = bounds
        if progress:
            from tqdm import tqdm

            it = tqdm(bounds, unit="chunk", desc="simulate", leave=False)
        carry = {"next_packet": 0}
        for a, b in it:
            yield self._chunk(a, b, rngs, carry, truth)

    def _chunk(self, a: int, b: int, rngs: dict, carry: dict, truth: bool = True) -> SampleChunk:
        s, cfg, rate = self.schedule, self.config, self.rate_hz
        counts = s.n[a:b]
        i0 = int(s.start[a])
        total = int(counts.sum())
        loc = s.start[a:b] - i0
        # true specific force by axis (3, n): gravity everywhere, then sway, moves, gait
        # (each axis a contiguous row: on (n, 3) rows a broadcast or a row selection runs
        # an inner loop of 3 a row; the same draws and values bit for bit)
        f_axes = np.repeat(gravity_foot(s.pitch0[a:b], s.roll0[a:b]).T, counts, axis=1)
        motion = s.motion[a:b]
        phase = np.full(total, np.nan)
        sway = np.repeat(np.where(motion == STILL, s.sd_g[a:b], 0.0), counts)
        swaying = np.flatnonzero(sway > 0)  # rows by integer index: the same values, faster than a mask
        if len(swaying):
            noise = lowpass_noise(rngs["motion"], len(swaying), rate, cfg.posture.sway_corner_hz)
            sway_sw = sway[swaying]
            for c in range(3):
                f_axes[c, swaying] += noise[:, c] * sway_sw
        mv = np.flatnonzero(motion == MOVE)
        if len(mv):
            j = a + mv
            pos = _positions(loc[mv], counts[mv])
            f_axes[:, pos] = move_force(s.pitch0[j], s.roll0[j], s.pitch1[j], s.roll1[j], s.sd_g[j], counts[mv],
                                        rngs["motion"], rate).T
        for k in np.flatnonzero(motion == GAIT).tolist():
            j = a + k
            n = int(counts[k])
            fg, ph = gait_force(n, rate, float(s.cycle_s[j]), float(s.stride_m[j]), float(s.slope_rad[j]),
                                float(s.climb[j]), float(s.pitch0[j]), bool(s.activity[j] == STAIRS),
                                cfg.gait, rngs["motion"])
            f_axes[:, loc[k]:loc[k] + n] = fg.T
            phase[loc[k]:loc[k] + n] = ph
        f = f_axes.T  # (n, 3), a view
        index = np.arange(i0, i0 + total, dtype=np.int64)
        t_s = index / rate
        per_sample = lambda x: np.repeat(x[a:b], counts, axis=0)  # noqa: E731 - x[seg], as a faster copy
        tau = (index - per_sample(s.start)) / rate
        temp_true, _ = temperature_at(tau, per_sample(s.temp0_c), per_sample(s.heat0_c), per_sample(s.temp_target_c),
                                      per_sample(s.heat_target_c), per_sample(s.tau_t_s), per_sample(s.tau_h_s),
                                      per_sample(s.on_foot))
        raw = read_out(self.truth.sensor, sensor_mean(self.truth.sensor, f, temp_true, t_s), rngs["noise"])
        temp_rep = _report_temperature(temp_true, cfg, rngs["temperature"])
        moving = np.repeat(motion == MOVE, counts)
        press = pressure_by_channel(np.repeat(s.load[a:b].T, counts, axis=1), phase, moving, s.stand_kpa,
                                    cfg.pressure, rngs["pressure"], rate).T
        keep = _radio_keep(index, cfg.ble.samples_per_packet, cfg.ble.packet_loss_rate, rngs["radio"], carry)
        # the rows x[keep], C-contiguous: np.compress on a C array (0.19 against 0.65 ms an
        # hour of 3 axes), a boolean index on f and press, views by axis of (k, n) arrays
        # (0.65 against 1.7-2.2 ms: compress walks their rows with a stride of n)
        def rows(x: np.ndarray) -> np.ndarray:
            return np.compress(keep, x, axis=0) if x.flags.c_contiguous else np.ascontiguousarray(x[keep])

        if not truth:
            return SampleChunk(t_s=t_s[keep], acc_g=rows(raw), temp_c=temp_rep[keep], pressure_kpa=rows(press),
                               a_true_g=None, temp_true_c=None, activity=None, still=None, index=None)
        return SampleChunk(
            t_s=t_s[keep], acc_g=rows(raw), temp_c=temp_rep[keep], pressure_kpa=rows(press),
            a_true_g=rows(f), temp_true_c=temp_true[keep], activity=np.repeat(s.activity[a:b], counts)[keep],
            still=np.repeat(motion == STILL, counts)[keep], index=index[keep],
        )

    def samples(self) -> SampleChunk:
        """The whole stream in memory (for short simulations)."""
        return SampleChunk.concatenate(list(self.iter_samples()))

    # -------------------------------------------------------------------- poses
    def poses(self, pressure: bool = True) -> PoseTable:
        """Still windows directly, without per-sample data.

        Every still period of the schedule (the same as the sample stream's) is cut
        into windows of ``pose_window_s``; windows shorter than ``pose_min_s`` are
        dropped (after trimming ``pose_trim_s`` off both ends of each period, like the
        detector). Each window's mean is the noise-free sensor output at the window's mean
        temperature and mid time, plus the noise of a mean of ``n`` samples (white
        sensor noise and the low-pass sway); its sd is the per-sample sd with a
        chi-square sampling spread.

        ``pressure=False`` leaves the pressure channels out (``pressure_kpa`` is None): a
        replay feeds none of them, and a year's are 13 M draws and 0.1 GB. They are the
        last draws of the windows' own generator, so every other column is the same.

        Returns
        -------
        PoseTable
        """
        s, cfg, rate = self.schedule, self.config, self.rate_hz
        rng = self._rng("poses")
        st_start, st_n, st_seg = s.still_periods()
        trim = int(round(cfg.pose_trim_s * rate))
        st_start, st_n = st_start + trim, st_n - 2 * trim
        ok = st_n > 0
        st_start, st_n, st_seg = st_start[ok], st_n[ok], st_seg[ok]
        w_n = max(1, int(round(cfg.pose_window_s * rate)))
        n_win = -(-st_n // w_n)
        period = np.repeat(np.arange(len(st_n)), n_win)
        k = np.arange(len(period)) - np.repeat(np.r_[0, np.cumsum(n_win)[:-1]], n_win)
        w0 = st_start[period] + k * w_n
        w1 = np.minimum(w0 + w_n, st_start[period] + st_n[period])
        ok = (w1 - w0) >= cfg.pose_min_s * rate
        w0, w1, period = w0[ok], w1[ok], period[ok]
        seg0 = st_seg[period]
        m = len(w0)
        temp_true = self._window_temperature(w0, w1)
        t_start = w0 / rate
        dur = (w1 - w0) / rate
        t_mid = t_start + 0.5 * dur
        # a period's windows share its orientation: gravity once a period (elementwise, the
        # same values), gathered to its windows (a year: 3.2 M windows, ~0.1 M periods)
        a_true = gravity_foot(s.pitch0[st_seg], s.roll0[st_seg])[period]
        truth = self.truth.sensor
        # samples received
        spp = cfg.ble.samples_per_packet
        n_pk = np.maximum((w1 - w0) // spp, 1)
        n_recv = rng.binomial(n_pk, 1.0 - cfg.ble.packet_loss_rate) * spp
        n_recv = np.minimum(np.maximum(n_recv, 1), w1 - w0)
        dof = np.maximum(n_recv - 1, 1)
        # the draws, whole and in this order (the stream's numbers); the arithmetic on them
        # is done in place, by blocks of windows (:attr:`POSE_BLOCK`). 8 normals a window
        # (mean, temperature, pressure): a year's 3.2 M windows load the draws' kernels
        draw_numba.kernels(draws=8.0 * m)
        mean_g = standard_normal(rng, (m, 3))
        sd_g = rng.chisquare(np.broadcast_to(dof[:, None].astype(float), (m, 3)))
        temp_rep = standard_normal(rng, m)
        press = standard_normal(rng, (m, 4)) if pressure else None
        sway = s.sd_g[seg0]
        alpha = np.exp(-2 * np.pi * cfg.posture.sway_corner_hz / rate)
        corr = (1 + alpha) / (1 - alpha)
        noise_var = truth.noise_sd_g**2 + truth.lsb_g**2 / 12.0
        tc, pc = cfg.temperature, cfg.pressure
        var_mean = np.empty((m, 3))
        for lo in range(0, m, self.POSE_BLOCK):
            b = slice(lo, lo + self.POSE_BLOCK)
            mean_clean = sensor_mean(truth, a_true[b], temp_true[b], t_mid[b])
            sw2 = sway[b] ** 2
            root_n = np.sqrt(n_recv[b])
            sway_var = sw2 * corr
            for c in range(3):  # by column: an (n, 3) broadcast runs an inner loop of 3 a row
                np.divide(noise_var[c] + sway_var, n_recv[b], out=var_mean[b, c])
            mean_g[b] *= np.sqrt(var_mean[b])
            mean_g[b] += mean_clean
            sd_true = np.sqrt(noise_var[None, :] + sw2[:, None])
            chi = sd_g[b]
            chi /= dof[b, None]
            np.sqrt(chi, out=chi)
            chi *= sd_true
            temp_rep[b] *= tc.noise_sd_c / root_n
            temp_rep[b] += temp_true[b]
            if press is not None:
                p = press[b]
                p *= (pc.noise_kpa / root_n)[:, None]
                p += s.load[seg0[b]] * s.stand_kpa + pc.offset_kpa
                np.maximum(p, 0.0, out=p)
        return PoseTable(
            t_s=t_start, duration_s=dur, n=n_recv.astype(np.int64), mean_g=mean_g, sd_g=sd_g,
            temp_c=temp_rep, pressure_kpa=press, a_true_g=a_true, temp_true_c=temp_true,
            activity=s.activity[seg0], noise_var_g2=var_mean,
        )

    #: Windows whose means, sds, temperatures and pressures are computed at a time
    #: (:meth:`poses`): every value is a window's own, so the blocks give one pass's
    #: values bit for bit, and their temporaries stay ~1 MB, reused from block to block.
    POSE_BLOCK = 1 << 15

    #: Windows whose mean temperature is computed at a time (:meth:`_window_temperature`):
    #: its (k, 9) temporaries stay a few MB, which the allocator reuses from block to block.
    #: Memory first touched costs more here than the arithmetic on it (a year of windows
    #: at once made temporaries of ~230 MB each, most of the poses' time in page faults).
    TEMPERATURE_BLOCK = 1 << 15

    def _window_temperature(self, w0: np.ndarray, w1: np.ndarray) -> np.ndarray:
        """Mean true temperature (degC, (m,)) of the windows of samples ``[w0, w1)``: the
        9-point average over each window, computed in blocks of windows (every value is
        a row's own, so the blocks give the values of one pass bit for bit)."""
        s, rate = self.schedule, self.rate_hz
        frac = np.linspace(0.0, 1.0, 9)
        out = np.empty(len(w0))
        for lo in range(0, len(w0), self.TEMPERATURE_BLOCK):
            b0, b1 = w0[lo: lo + self.TEMPERATURE_BLOCK], w1[lo: lo + self.TEMPERATURE_BLOCK]
            pts = b0[:, None] + frac[None, :] * (b1 - b0 - 1)[:, None]
            # nearly every window lies in one segment: its constants are gathered once and
            # broadcast over the 9 points (the same values, elementwise the same arithmetic)
            ends = np.searchsorted(s.start, pts[:, [0, -1]], side="right") - 1
            one = ends[:, 0] == ends[:, 1]
            temp_pts = np.empty(pts.shape)
            for rows, segp in ((one, ends[one, :1]),
                               (~one, np.searchsorted(s.start, pts[~one], side="right") - 1)):
                tau = (pts[rows] - s.start[segp]) / rate
                temp_pts[rows], _ = temperature_at(tau, s.temp0_c[segp], s.heat0_c[segp], s.temp_target_c[segp],
                                                   s.heat_target_c[segp], s.tau_t_s[segp], s.tau_h_s[segp],
                                                   s.on_foot[segp])
            out[lo: lo + len(b0)] = temp_pts.mean(axis=1)
        return out


def _positions(local_start: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenated ``arange(local_start[i], local_start[i] + counts[i])``."""
    total = int(counts.sum())
    first = np.r_[0, np.cumsum(counts)[:-1]]
    return np.repeat(local_start - first, counts) + np.arange(total)


def _report_temperature(temp_true_c: np.ndarray, cfg: SimConfig, rng: np.random.Generator) -> np.ndarray:
    tc = cfg.temperature
    t = temp_true_c
    if tc.noise_sd_c > 0:
        t = t + tc.noise_sd_c * standard_normal(rng, len(t))
    if tc.lsb_c > 0:
        t = np.round(t / tc.lsb_c) * tc.lsb_c
    return t


def _radio_keep(index: np.ndarray, spp: int, loss: float, rng: np.random.Generator, carry: dict) -> np.ndarray:
    """Bernoulli loss per BLE packet of ``spp`` samples; a packet split across chunks
    keeps the decision drawn when its first sample was generated."""
    if loss <= 0 or len(index) == 0:
        return np.ones(len(index), bool)
    pkt = index // spp
    p0, p1 = int(pkt[0]), int(pkt[-1])
    lost = np.empty(p1 - p0 + 1, bool)
    first_new = carry["next_packet"] - p0  # packets < next_packet were drawn before
    n_old = max(0, min(first_new, len(lost)))
    if n_old:
        lost[:n_old] = carry.get("last_lost", False)
    lost[n_old:] = rng.random(len(lost) - n_old) < loss
    carry["next_packet"] = p1 + 1
    carry["last_lost"] = bool(lost[-1])
    return ~lost[pkt - p0]


def wearer_summary(s: Schedule) -> dict[str, Any]:
    """Activity fractions, still-period statistics and per-day draws of a schedule."""
    _, st_n, st_seg = s.still_periods()
    dur = st_n / s.rate_hz
    on = s.activity[st_seg] != OFF
    worn_s = float(s.n[s.on_foot].sum() / s.rate_hz)
    long_on = dur[on & (dur >= 2.0)]
    return {
        "activity_fraction": s.activity_fractions(),
        "worn_h": worn_s / 3600.0,
        "still_periods_on_foot_ge2s_per_worn_h": float(len(long_on) / max(worn_s / 3600.0, 1e-9)),
        "still_duration_on_foot_s_p50": float(np.median(long_on)) if len(long_on) else None,
        "still_fraction_of_worn_time": float(dur[on].sum() / max(worn_s, 1e-9)),
        "ambient_c": s.days[:, 0].round(2).tolist(),
        "foot_c": s.days[:, 1].round(2).tolist(),
        "walk_heat_c": s.days[:, 2].round(2).tolist(),
        "stand_kpa": s.stand_kpa.round(2).tolist(),
        "activity_codes": {str(k): v for k, v in ACTIVITY_NAMES.items()},
    }


def simulate_samples(config: SimConfig, rng: np.random.Generator, days: float | None = None,
                     seed: int | None = None) -> tuple[SampleChunk, SimTruth]:
    """Simulate a (short) stream in memory; return the data and the truth.

    Parameters
    ----------
    config : SimConfig
    rng : numpy.random.Generator
    days : float, optional
    seed : int, optional
        Recorded in the truth only.

    Returns
    -------
    SampleChunk, SimTruth
    """
    sim = Simulation(config, rng, days, seed=seed)
    return sim.samples(), sim.truth


def iter_samples(config: SimConfig, rng: np.random.Generator, days: float | None = None,
                 chunk_s: float | None = None, seed: int | None = None) -> tuple[Iterator[SampleChunk], SimTruth]:
    """Stream ``days`` of samples chunk by chunk; return the iterator and the truth.

    Returns
    -------
    iterator of SampleChunk, SimTruth
    """
    sim = Simulation(config, rng, days, seed=seed)
    return sim.iter_samples(chunk_s), sim.truth


def simulate_poses(config: SimConfig, rng: np.random.Generator, days: float | None = None,
                   seed: int | None = None) -> tuple[PoseTable, SimTruth]:
    """Pose-level simulation (still windows only); same wearer as the samples of the
    same generator state.

    Returns
    -------
    PoseTable, SimTruth
    """
    sim = Simulation(config, rng, days, seed=seed)
    return sim.poses(), sim.truth
