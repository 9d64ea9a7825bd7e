"""Pose store: a compressed but complete history of still poses, as sufficient statistics.

The online calibrator refits *all* of a device's still poses at every refit (one MAP
problem, re-linearised each time), so nothing may be thrown away and memory must stay
bounded. The store keeps one **cell** per (gravity-direction cell x temperature band x
time block): the still windows that fall in it are summed into sufficient statistics,
and the cell is fitted as one pose.

* **Direction cell**: the unit direction rounded on a grid of step
  ``merge_angle_deg`` (in radians); **temperature band**: ``merge_temp_c`` wide (windows
  without a temperature share one band); **time block**: ``block_s`` long.
* **Representative pose** of a cell: its mean direction scaled to its mean raw norm.
  A raw vector's norm, not the mean vector, is averaged: averaging vectors of
  different directions would shorten the norm (a 3 deg spread costs up to 1.4 mg).
* **Noise of a cell** (what the fit weighs it by): the per-window noise is the
  detector's, projected on gravity: white sensor noise (per-axis sd up to
  ``white_sd_g``) averages as ``sd^2 / n``; scatter above it is slow motion (sway) with
  one independent value per ``motion_corr_s`` (measured on the simulator: windows of
  20-40 mg scatter have mean errors of 5 mg, 18x what ``sd / sqrt(n)`` says). That is combined with the cell's own scatter
  of window norms about a plane in direction (so the anisotropy of the raw sensor is not
  counted as noise), with ``prior_dof`` pseudo-windows of the former. That is divided
  by the number of windows, and a **systematic floor** is added once per cell
  (``fit.sigma_floor_g``, in the fit): repeats of one pose in one block share their
  systematic error and do not average it down. Older cells also get the process-noise
  variance for their age (the sensor may have drifted since).
* **Gate** (model-free): a window whose raw norm is far from the raw norm of its own
  cell (``gate_k`` x the cell's scatter, and at least ``gate_abs_g``) is not pooled; it
  goes into an *outlier twin* of the cell, kept and fitted (with the robust loss), so
  that one bad "still" window cannot bias a cell of good ones. No model is involved:
  the gate that admits poses never depends on the model they could refute.
* **Bound**: at most ``max_cells`` cells. Past it, the older half of the cells that can
  still be coarsened (not at the top level, not held at a bias step's barrier) is
  coarsened (pairs of blocks merged, exactly: the statistics are sums); if that is not
  enough, the oldest cells are dropped (counted in ``n_dropped``).
* **Folds**: every cell has a fold ``hash(key) % folds`` for the guard's rotating
  held-out split (a cell that is coarsened may change fold).
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from selfcal.fit import PoseData
from selfcal.groupsum import sum_by_group

# columns of the statistics table
_NW, _NS = 0, 1  # windows, samples
_SU = slice(2, 5)  # sum of unit directions
_SUU = slice(5, 11)  # sum of u u^T (xx, xy, xz, yy, yz, zz)
_SD = 11  # sum of d = |x| - 1
_SDU = slice(12, 15)  # sum of d u
_SDD = 15  # sum of d^2
_SVN = 16  # sum of the detector's window-mean noise variance along gravity, g^2
_ST = 17  # sum of window centre times, s
_STEMP = 18  # sum of temperatures (windows with one)
_NTEMP = 19  # windows with a temperature
N_STATS = 20
_UU_IDX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_UU_ROW = np.array([i for i, _ in _UU_IDX])
_UU_COL = np.array([j for _, j in _UU_IDX])
# the entry of _UU_IDX that each element of a symmetric 3x3 (row-major) holds
_UU_FULL = np.array([_UU_IDX.index((min(i, j), max(i, j))) for i in range(3) for j in range(3)])

_NO_TEMP_BAND = 1023
#: the first span of a cell's windows that the gate decides together when it redoes the
#: cell in order (:meth:`PoseStore._gate_in_order`; later spans follow the windows passed)
_GATE_SPAN = 32
#: Coarsening passes a bound makes at most before it drops cells (a pass raises the older half
#: of the cells that can be coarsened by one level; a cell has 15 levels to go at most).
_BOUND_MAX_PASSES = 64
#: A window with ``|mean|`` or a per-axis sd at or past this (g, normalised units) is no
#: still pose (gravity is 1 g; sensors saturate at tens of g): a corrupt packet.
_MAX_STILL_G = 1e3


class PoseConfig(BaseModel):
    """The ``[poses]`` section: cells of the pose store."""

    model_config = ConfigDict(extra="forbid")

    max_cells: int = Field(6000, ge=16, description="bound on stored cells (memory and refit time)")
    merge_angle_deg: float = Field(3.0, ge=0.5, le=20, description="direction-cell size, deg")
    merge_temp_c: float = Field(2.0, gt=0, description="temperature-band width, degC")
    block_s: float = Field(3600.0, gt=0, description="time-block length, s")
    white_sd_g: float = Field(
        0.004, gt=0, description="per-axis sample sd up to which a window's scatter is taken as white sensor noise, g")
    motion_corr_s: float = Field(
        0.6, gt=0, description="scatter above white_sd_g is slow motion: one independent value per this many s")
    window_floor_g: float = Field(
        3e-4, ge=0, description="independent error of every window mean (what the noise does not explain), g")
    prior_dof: float = Field(3.0, ge=0, description="weight (in windows) of the detector's noise against a cell's own scatter")
    gate_k: float = Field(8.0, gt=0, description="a window this many scatter sds off its cell's norm goes to the outlier twin")
    gate_abs_g: float = Field(0.01, gt=0, description="...and at least this far off, g")
    gate_min_windows: int = Field(3, ge=2, description="gate only cells with at least this many windows")
    folds: int = Field(5, ge=2, description="held-out folds of the guard (cell key hash modulo folds)")
    axis_tol_g: float = Field(0.12, gt=0, description="axis-aligned (O_cor) tolerance, g")
    cube_g: float = Field(0.3, gt=0, description="GGIR-style coverage: both sides of +-cube_g on every axis")

    @classmethod
    def from_section(cls, section: dict[str, Any] | None) -> "PoseConfig":
        """Validate the ``[poses]`` TOML section."""
        return cls(**(section or {}))


#: Windows given to one step of :meth:`PoseStore.add` at first (doubled after a step that
#: took all of its windows).
ADD_BLOCK_WINDOWS = 2048


def _as_shape(x, shape: tuple[int, ...]) -> np.ndarray:
    """``x`` as a float array of ``shape`` (a view, not a copy, where it already is one;
    a scalar or a row is repeated)."""
    a = np.asarray(x, dtype=float)
    return a if a.shape == shape else np.broadcast_to(a, shape)


def _group_edges(sorted_keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, last): (k,) bool, whether each of ``sorted_keys`` starts / ends its run of equal keys."""
    k = sorted_keys.shape[0]
    first = np.empty(k, dtype=bool)
    last = np.empty(k, dtype=bool)
    if k:
        np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=first[1:])
        last[:-1] = first[1:]
        first[0] = last[-1] = True
    return first, last


def _running_sums(start_rows: np.ndarray, rows: np.ndarray, first: np.ndarray, accelerate=None) -> np.ndarray:
    """Each group's running sums before each of its rows, added in order from its start row.

    ``rows`` (k, m) come in groups of consecutive rows (``first``: (k,) bool, a group's first
    row); ``start_rows`` (k, m) holds each group's start on its first row (the others are
    not read). Row i of the result is ``((start + r_a) + r_a+1) + ... + r_i-1`` over the
    earlier rows of its group, in that order, plus 0.0: bit for bit what adding the rows one
    at a time gives (a difference of one cumsum across groups is not: it rounds). One
    sequential cumsum per group when the groups are few, else one vectorised step per
    position in a group (the loop runs min(groups, longest group) times).

    ``accelerate``: None uses the kernel of :mod:`selfcal.sums_numba` once it is loaded
    (the same additions in the same order, in one call), False the numpy code; or a kernel.
    """
    k = rows.shape[0]
    out = np.empty_like(rows)
    if k == 0:
        return out
    if accelerate is None:
        from selfcal.sums_numba import kernels

        found = kernels()
        accelerate = None if found is None else found.running_sums
    if accelerate is not None and accelerate is not False:
        accelerate(np.ascontiguousarray(start_rows, dtype=float), np.ascontiguousarray(rows, dtype=float),
                   np.ascontiguousarray(first, dtype=bool), out)
        return out
    # out: each group's start row on its first row, then its rows but the last, shifted by one
    out[1:] = rows[:-1]
    firsts = np.flatnonzero(first)
    out[firsts] = start_rows[firsts]
    ends = np.append(firsts[1:], k)
    longest = int((ends - firsts).max())
    if len(firsts) <= longest:  # (the usual service batch: one group, one cumsum)
        for a, b in zip(firsts.tolist(), ends.tolist()):
            if b - a > 1:
                np.cumsum(out[a:b], axis=0, out=out[a:b])
    else:
        group = np.cumsum(first) - 1
        pos = np.arange(k) - firsts[group]
        run = out[firsts]  # a copy: the start rows
        by_pos = np.argsort(pos, kind="stable")
        cuts = np.append(0, np.cumsum(np.bincount(pos)))
        for j in range(longest):
            r = by_pos[cuts[j]:cuts[j + 1]]  # the j-th row of each group that has one
            g = group[r]
            if j:
                run[g] += rows[r - 1]  # one row per group: run[g] = run[g] + the row before
            out[r] = run[g]
    out += 0.0  # as one window a call: a cell's stored sums never hold -0.0
    return out


def _enc(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype="<f8").tobytes()).decode("ascii")


def _dec(s: "str | np.ndarray", shape_tail: tuple[int, ...] = ()) -> np.ndarray:
    if isinstance(s, np.ndarray):  # already decoded (a checkpoint patch applied, selfcal.checkpoint)
        return np.asarray(s, dtype=float).reshape((-1,) + shape_tail)
    a = np.frombuffer(base64.b64decode(s), dtype="<f8").astype(float)
    return a.reshape((-1,) + shape_tail)


def _fold_of(keys: np.ndarray, folds: int) -> np.ndarray:
    """Deterministic fold of each cell key (a multiplicative hash)."""
    h = (keys.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(33)
    return (h % np.uint64(folds)).astype(np.int64)


def window_noise_var(u: np.ndarray, sd_g: np.ndarray, count: np.ndarray, rate_hz: float, cfg: PoseConfig) -> np.ndarray:
    """Variance (g^2) of each still window's mean along gravity, shape (k,).

    ``u`` (k, 3) unit gravity directions, ``sd_g`` (k, 3) per-axis sample sd (g),
    ``count`` (k,) samples. White sensor noise (per-axis sd up to ``cfg.white_sd_g``)
    averages as ``1/n``; scatter above it is slow motion, one independent value per
    ``cfg.motion_corr_s`` of the window's ``count / rate_hz`` s.
    """
    var_axis = np.asarray(sd_g, dtype=float) ** 2
    white = np.minimum(var_axis, cfg.white_sd_g**2)
    motion = var_axis - white
    count = np.asarray(count, dtype=float)
    duration = np.maximum(count / rate_hz, cfg.motion_corr_s)
    per_axis = white / count[:, None] + motion * (cfg.motion_corr_s / duration)[:, None]
    return np.einsum("ij,ij->i", u * u, per_axis)


@dataclass
class PoseStore:
    """Bounded store of still-pose cells (normalised units, ~g).

    Arrays (length m = number of cells): ``key (m,) int64`` (direction, band, block,
    level, outlier flag), ``stats (m, 20)`` sums (see the module docstring),
    ``t_first (m,) s`` and ``t_last (m,) s`` (first and last window time).
    """

    config: PoseConfig
    key: np.ndarray
    stats: np.ndarray
    t_first: np.ndarray
    t_last: np.ndarray
    n_seen: int = 0
    n_gated: int = 0
    n_merged: int = 0
    n_dropped: int = 0
    t_origin: float | None = None  # time of the first window: blocks are counted from it
    # times (s) no coarsening merges across: the bias steps found (a cell that mixes windows
    # from both sides of a step has a mean that is neither the old offset nor the new)
    barriers_s: list[float] = field(default_factory=list)
    # key -> row lookup: (the keys sorted, their rows), or None until next asked
    _index: tuple | None = field(default=None, repr=False, compare=False)
    # the per-cell derived values of one ``stats`` array (eigh of every cell's 3x3 scatter),
    # kept between refits: (the array itself, the result). Holding the array keeps its id
    # from being reused. Rows changed in place or appended since are in ``_dirty`` (arrays
    # of row indices): only those are computed again, each row's values depending on its
    # own statistics only.
    _derived_cache: tuple | None = field(default=None, repr=False, compare=False)
    _dirty: list = field(default_factory=list, repr=False, compare=False)
    _dirty_rows: int = field(default=0, repr=False, compare=False)  # their total length

    @classmethod
    def empty(cls, config: PoseConfig | None = None) -> "PoseStore":
        """A store with no cell."""
        return cls(config or PoseConfig(), np.zeros(0, np.int64), np.zeros((0, N_STATS)), np.zeros(0), np.zeros(0))

    def __len__(self) -> int:
        return int(self.key.shape[0])

    def _reindex(self) -> None:
        order = np.argsort(self.key, kind="stable")
        self._index = (self.key[order], order.astype(np.int64))

    def _index_stale(self) -> None:
        """The keys changed: the key -> row lookup is rebuilt when next asked (``_bound`` may
        merge several times before then)."""
        self._index = None

    # ------------------------------------------------------------------ keys
    def _keys(self, u: np.ndarray, temp: np.ndarray, t_s: np.ndarray, origin: float | None = None) -> np.ndarray:
        """Cell keys of windows (level 0); time blocks counted from ``origin`` (default the store's)."""
        step = np.radians(self.config.merge_angle_deg)
        g = np.rint(u / step).astype(np.int64) + 64  # 0..128 for step >= ~0.9 deg
        has_t = np.isfinite(temp)
        band = np.where(has_t, np.floor(np.where(has_t, temp, 0.0) / self.config.merge_temp_c), 0).astype(np.int64)
        band = np.where(has_t, np.minimum(np.maximum(band + 512, 0), _NO_TEMP_BAND - 1), _NO_TEMP_BAND)
        # blocks counted from the first window: a constant shift of the device clock changes nothing
        if origin is None:
            origin = self.t_origin if self.t_origin is not None else 0.0
        block = np.floor((t_s - origin) / self.config.block_s).astype(np.int64) + (1 << 20)
        key = ((block * 1024 + band) * 256 + g[:, 0]) * 256 + g[:, 1]
        return (key * 256 + g[:, 2]) * 32  # 5 low bits: level (4) and outlier flag (1)

    @staticmethod
    def _level(key: np.ndarray) -> np.ndarray:
        return (key >> 1) & 15

    # ------------------------------------------------------------------ cell views
    def _derived(self, rows: np.ndarray | slice | None = None):
        """(mean direction (k,3), mean d (k,), per-window noise variance (k,), scatter dof (k,)).

        Kept from the last call: the rows changed since (``_dirty``) are computed again,
        the others reused, so a refit after a few adds costs a few rows, not the store
        (the same values: each row's come from its own statistics, by the same operations)."""
        cache = self._derived_cache
        if cache is None or cache[0] is not self.stats:
            full = self._derived_from(self.stats)
        elif self._dirty:
            changed = np.unique(np.concatenate(self._dirty))
            part = self._derived_from(self.stats[changed])
            full = []
            for old, new in zip(cache[1], part):
                out = np.empty((len(self),) + old.shape[1:], dtype=old.dtype)
                out[: len(old)] = old  # appended rows are all in `changed`
                out[changed] = new
                full.append(out)
            full = tuple(full)
        else:
            full = cache[1]
        self._derived_cache = (self.stats, full)
        self._dirty, self._dirty_rows = [], 0
        return full if rows is None else tuple(x[rows] for x in full)

    def _changed(self, rows: np.ndarray, before: np.ndarray | None = None) -> None:
        """Rows of ``stats`` changed in place, or (``before``: the array ``stats`` replaced
        by a longer copy of it) appended: the kept derived values follow."""
        cache = self._derived_cache
        if cache is None or cache[0] is not (self.stats if before is None else before):
            self._derived_cache, self._dirty, self._dirty_rows = None, [], 0  # not this array's: computed afresh
            return
        self._derived_cache = (self.stats, cache[1])
        self._dirty.append(np.asarray(rows, dtype=np.int64))
        self._dirty_rows += self._dirty[-1].size
        if len(self._dirty) > 256 or self._dirty_rows > len(self):
            # many adds between refits: one array, or nothing kept (bounded by the store)
            changed = np.unique(np.concatenate(self._dirty))
            if 2 * changed.size > len(self):
                self._derived_cache, self._dirty, self._dirty_rows = None, [], 0
            else:
                self._dirty, self._dirty_rows = [changed], changed.size

    def _derived_from(self, s: np.ndarray, direction: bool = True):
        """:meth:`_derived` of a statistics table ``s`` (k, N_STATS); ``direction=False``
        leaves the mean direction out (None), for the gate, which does not use it."""
        nw = s[:, _NW]
        su = s[:, _SU]
        ubar = su / nw[:, None]
        dbar = s[:, _SD] / nw
        # the 6 distinct entries of each cell's direction scatter, then the symmetric 3x3
        uu = s[:, _SUU] / nw[:, None] - ubar[:, _UU_ROW] * ubar[:, _UU_COL]
        cuu = uu[:, _UU_FULL].reshape(-1, 3, 3)
        cdu = s[:, _SDU] / nw[:, None] - dbar[:, None] * ubar
        cdd = s[:, _SDD] / nw - dbar**2
        # regression of the norm on the direction (the raw sensor's anisotropy within a cell
        # is not noise): residual variance = cdd - cdu^T cuu^+ cdu
        evals, evecs = np.linalg.eigh(cuu)
        keep = evals > 1e-9  # direction spread above (3e-5 rad)^2
        proj = np.einsum("kij,ki->kj", evecs, cdu)
        explained = np.sum(np.where(keep, proj**2 / np.where(keep, evals, 1.0), 0.0), axis=1)
        ssr = np.maximum(cdd - explained, 0.0) * nw
        dof = np.maximum(nw - 1.0 - keep.sum(axis=1), 0.0)
        v_model = s[:, _SVN] / nw
        nu0 = self.config.prior_dof
        v_emp = np.where(dof > 0, ssr / np.maximum(dof, 1.0), 0.0)
        v_win = np.where(nu0 + dof > 0, (nu0 * v_model + dof * v_emp) / np.maximum(nu0 + dof, 1e-12), v_model)
        if direction:
            return su / np.linalg.norm(su, axis=1, keepdims=True), dbar, v_win, dof
        return None, dbar, v_win, dof

    # ------------------------------------------------------------------ updates
    def add(self, mean_g, sd_g, count, t_s, temp_c=None, rate_hz: float = 20.0,
            max_new_cells: int | None = None) -> dict[str, int]:
        """Add still windows (normalised units, ~g).

        Parameters
        ----------
        mean_g, sd_g : ndarray, shape (k, 3), g — window means and per-axis sample sds
            (sd may be None: ``default_sd_g`` of the fit is then used by the caller)
        count : ndarray, shape (k,) — samples per window
        t_s : ndarray, shape (k,), s — window centre times
        temp_c : ndarray, shape (k,), degC, or None
        rate_hz : float — sample rate, Hz (a window lasts ``count / rate_hz`` s)
        max_new_cells : int, optional — stop after the window that opens this many new
            cells (an outlier twin counts: it is a cell of its own); None adds them all

        Returns
        -------
        dict with ``added`` (windows stored), ``new_cells``, ``gated``, ``new_info``
        (new cells, the unit the scheduler counts), ``consumed`` (the leading windows
        of the input that were taken: all of them unless ``max_new_cells`` stopped it, or,
        with ``max_new_cells`` given, the store was bounded), ``t_max`` (s: the latest
        time of the windows stored, -inf if none; invalid windows are consumed, not stored)
        and ``bounded`` (whether the store was bounded).

        The store is bounded (``max_cells``) right after the window that takes it past
        the bound, as it would be if the windows came one at a time. So with the caller's
        scheduler stopping at ``max_new_cells``, no outcome depends on how a stream of
        windows is split into calls, and the store is the same bit for bit: a cell's
        windows are added to it in order and new cells appended in the order they came,
        and each window is gated against its cell's running sums added in that order too.
        """
        mean = np.atleast_2d(np.asarray(mean_g, dtype=float))
        k = mean.shape[0]
        count = _as_shape(count, (k,))
        t_s = _as_shape(t_s, (k,))
        temp = None if temp_c is None else _as_shape(temp_c, (k,))
        sd = None if sd_g is None else _as_shape(sd_g, (k, 3))
        out = {"added": 0, "new_cells": 0, "gated": 0, "new_info": 0, "consumed": 0, "t_max": -np.inf,
               "bounded": False}
        i = 0
        # the windows go to _add_part in blocks: a part stops at the window that bounds the
        # store (or opens the caller's last new cell), and each part's keys and validity are
        # computed for every window it is given, so handing each the whole rest of the batch
        # made a full store's adds quadratic (a 365-day replay gave parts ~12 000 windows to
        # take ~1 200). A block that was taken whole doubles the next one. How the windows are
        # split into calls changes nothing (see above), so neither do the blocks.
        block = ADD_BLOCK_WINDOWS
        while i < k or k == 0:
            left = None if max_new_cells is None else max(int(max_new_cells) - out["new_cells"], 1)
            j = min(k, i + block)
            part = self._add_part(mean[i:j], None if sd is None else sd[i:j], count[i:j], t_s[i:j],
                                  None if temp is None else temp[i:j], rate_hz, left)
            block = 2 * block if part["consumed"] == j - i else ADD_BLOCK_WINDOWS
            for name in ("added", "new_cells", "gated", "new_info"):
                out[name] += part[name]
            out["t_max"] = max(out["t_max"], part["t_max"])
            out["bounded"] = out["bounded"] or part["bounded"]
            i += part["consumed"]
            # a part that bounded the store stops a caller's quota too: the scheduler's
            # threshold follows the store's size, which the bound just cut (continuing to the
            # quota counted by the size before it made the refits depend on the calls' split)
            if k == 0 or (max_new_cells is not None and (out["new_cells"] >= max_new_cells or part["bounded"])):
                break
        out["consumed"] = i
        return out

    def _add_part(self, mean_g, sd_g, count, t_s, temp_c, rate_hz: float, max_new_cells: int | None) -> dict[str, int]:
        """:meth:`add` up to the window that opens ``max_new_cells`` new cells or takes the
        store past ``max_cells`` (then bounded), whichever comes first; ``consumed``: the
        leading windows of the input it took. The inputs are :meth:`add`'s, already float
        arrays of their shapes (read-only views: the selection by ``valid`` below copies)."""
        mean = mean_g
        k = mean.shape[0]
        temp = np.full(k, np.nan) if temp_c is None else temp_c
        # a missing (NaN) sd is the default; an infinite one stays, and fails the size check below
        sd = np.full((k, 3), 3e-3) if sd_g is None else np.where(np.isnan(sd_g), 3e-3, sd_g)
        with np.errstate(over="ignore", invalid="ignore"):
            norm = np.sqrt(np.einsum("ij,ij->i", mean, mean)) if k else np.zeros(0)
            # a window with |mean| or sd past _MAX_STILL_G is no still pose: stored, its huge
            # (or, past ~1e154 g, overflowing) sums would spoil its cell's for good
            representable = (norm < _MAX_STILL_G) & np.all(sd < _MAX_STILL_G, axis=1)
        valid = (np.all(np.isfinite(mean), axis=1) & (norm > 0) & np.isfinite(t_s) & (count >= 1)
                 & representable)
        out = {"added": 0, "new_cells": 0, "gated": 0, "new_info": 0, "consumed": k, "t_max": -np.inf,
               "bounded": False}
        if not valid.any():
            return out
        valid_idx = np.flatnonzero(valid)
        mean, sd, count, t_s, temp, norm = mean[valid], sd[valid], count[valid], t_s[valid], temp[valid], norm[valid]
        u = mean / norm[:, None]
        d = norm - 1.0
        if self.t_origin is None:
            self.t_origin = float(t_s[0])
        key = self._keys(u, temp, t_s)
        # the windows up to the one that opens the last new cell allowed (the caller's, or the
        # one past max_cells): the gate's decisions for them do not depend on later windows
        cap = self.config.max_cells + 1 - len(self)
        if max_new_cells is not None:
            cap = min(cap, int(max_new_cells))
        cap = max(cap, 1)
        # Only a prefix can be taken: every window that opens a new cell by its own key still
        # does after the gate (its cell is empty, so it is not gated), so the cut lies at or
        # before the cap-th of them. The gate and the statistics are computed for that prefix
        # only (the rest is this method's next call's): with a full store, recomputing them
        # for every remaining window at each cut made an add quadratic in its windows.
        fresh = np.zeros(0, dtype=np.int64)
        if len(key) > cap:  # (a batch no longer than cap is taken whole, or cut by the gate below)
            pkeys, pfirst = np.unique(key, return_index=True)
            fresh = np.sort(pfirst[self._rows_of(pkeys) < 0])
        if fresh.size >= cap and int(fresh[cap - 1]) + 1 < len(key):
            m = int(fresh[cap - 1]) + 1
            u, d, sd, count, t_s, temp, key = u[:m], d[:m], sd[:m], count[:m], t_s[:m], temp[:m], key[:m]
            valid_idx = valid_idx[:m]
            out["consumed"] = int(valid_idx[-1]) + 1
        vn = window_noise_var(u, sd, count, rate_hz, self.config) + self.config.window_floor_g**2
        row = self._rows(u, d, vn, count, t_s, temp)
        # model-free gate, with the semantics of adding the windows one by one
        gated = self._gate(key, row, d)
        if gated.any():
            key = key + gated.astype(np.int64)
        ukeys, first, inv = np.unique(key, return_index=True, return_inverse=True)
        target = self._rows_of(ukeys)
        if int(np.count_nonzero(target < 0)) >= cap:
            fresh = np.sort(first[target < 0])
            cut = int(fresh[cap - 1]) + 1
            if cut < len(key):
                key, row, t_s, gated = key[:cut], row[:cut], t_s[:cut], gated[:cut]
                out["consumed"] = int(valid_idx[cut - 1]) + 1
                ukeys, first, inv = np.unique(key, return_index=True, return_inverse=True)
                target = self._rows_of(ukeys)
        out["gated"] = int(gated.sum())
        self.n_gated += out["gated"]
        # accumulate per key, as one call per window would: each cell's windows added to it
        # in order, ((stored + w1) + w2) + ..., not stored + (w1 + w2), so that how the
        # windows were split into calls changes no bit of the sums (a service worker that
        # restores a device feeds the batches since its checkpoint in one call); sums: each
        # key's new total, its stored row included
        exist = target >= 0
        t = target[exist]
        if len(ukeys) == len(key):  # each key once (the usual batch): no accumulation
            sums = np.empty((len(ukeys), N_STATS))
            sums[inv] = row + 0.0  # as np.add.at into zeros makes it (-0.0 becomes 0.0)
            sums[exist] += self.stats[t]  # stored + window (an IEEE sum does not depend on the order of two terms)
            tmin = np.empty(len(ukeys))
            tmin[inv] = t_s
            tmax = tmin
        else:  # the stored rows first in each group: sum_by_group adds in input order
            sums = sum_by_group(np.concatenate([np.flatnonzero(exist), inv]), np.concatenate([self.stats[t], row]),
                                len(ukeys))
            tmin = np.full(len(ukeys), np.inf)
            tmax = np.full(len(ukeys), -np.inf)
            np.minimum.at(tmin, inv, t_s)
            np.maximum.at(tmax, inv, t_s)
        if t.size:
            self.stats[t] = sums[exist]
            self._changed(t)  # an in-place change: those rows' derived values are stale
            self.t_first[t] = np.minimum(self.t_first[t], tmin[exist])
            self.t_last[t] = np.maximum(self.t_last[t], tmax[exist])
        # new cells in the order their first windows came (as one call per window appends them)
        new = np.flatnonzero(~exist)
        new = new[np.argsort(first[new], kind="stable")]
        if new.size:
            self.key = np.concatenate([self.key, ukeys[new]])
            stored, self.stats = self.stats, np.vstack([self.stats, sums[new]])
            self._changed(np.arange(len(stored), len(self)), before=stored)
            self.t_first = np.concatenate([self.t_first, tmin[new]])
            self.t_last = np.concatenate([self.t_last, tmax[new]])
            self._index_stale()
        out["added"] = int(len(key))
        out["t_max"] = float(t_s.max()) if len(t_s) else -np.inf
        out["new_cells"] = int(new.size)
        if max_new_cells is not None and new.size >= max_new_cells:
            # stopped at the window that opened the last cell allowed: invalid windows after
            # it are the next call's, as one call per window would leave them (the caller's
            # clock must not run past the refit this stop is for)
            out["consumed"] = int(valid_idx[len(key) - 1]) + 1
        out["new_info"] = out["new_cells"]
        self.n_seen += int(len(key))
        if len(self) > self.config.max_cells:
            self._bound()
            out["bounded"] = True
        return out

    @staticmethod
    def _rows(u, d, vn, count, t_s, temp) -> np.ndarray:
        """Statistics of single windows (k, N_STATS)."""
        row = np.zeros((len(d), N_STATS))
        row[:, _NW] = 1.0
        row[:, _NS] = count
        row[:, _SU] = u
        for c, (i, j) in enumerate(_UU_IDX):
            row[:, _SUU.start + c] = u[:, i] * u[:, j]
        row[:, _SD] = d
        row[:, _SDU] = d[:, None] * u
        row[:, _SDD] = d * d
        row[:, _SVN] = vn
        row[:, _ST] = t_s
        has_t = np.isfinite(temp)
        row[:, _STEMP] = np.where(has_t, temp, 0.0)
        row[:, _NTEMP] = has_t
        return row

    def _rows_of(self, keys: np.ndarray) -> np.ndarray:
        """Stored row of each key (-1 if new), shape of ``keys`` (int64)."""
        if self._index is None:
            self._reindex()
        sorted_keys, rows = self._index
        if sorted_keys.size == 0:
            return np.full(np.shape(keys), -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(sorted_keys, keys), sorted_keys.size - 1)
        return np.where(sorted_keys[pos] == keys, rows[pos], -1)

    def _gate_one(self, running: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Gate decisions (k,) of windows with norms ``d`` against their cells' running statistics.

        The threshold is never below ``gate_abs_g``, so a window within it of its cell's
        mean norm passes whatever the cell's scatter: the scatter (an eigen-decomposition
        per cell, :meth:`_derived_from`) is computed for the others only, each from its
        own row as before (the same decisions, bit for bit)."""
        c = self.config
        enough = np.flatnonzero(running[:, _NW] >= c.gate_min_windows)
        out = np.zeros(len(d), dtype=bool)
        if enough.size:
            s = running[enough]
            dev = np.abs(d[enough] - s[:, _SD] / s[:, _NW])  # |d - dbar|, as _derived_from has dbar
            far = ~(dev <= c.gate_abs_g)  # NaN too: decided below as before
            if far.any():
                _, _, v_win, _ = self._derived_from(s[far], direction=False)
                out[enough[far]] = dev[far] > np.maximum(c.gate_k * np.sqrt(v_win), c.gate_abs_g)
        return out

    def _gate(self, key: np.ndarray, row: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Which windows go to their cell's outlier twin, exactly as if added one at a time.

        Each window is compared with its cell as it stands just before it (stored windows
        plus the earlier, not gated, windows of this batch): the running sums of each cell
        are added in order from its stored row, as one call per window adds them
        (:func:`_running_sums`), so the decisions do not depend on how the windows were
        split into calls, bit for bit; a group that a gate decision changes is redone in
        order (:meth:`_gate_in_order`).
        """
        k = len(key)
        if k == 1:  # one window (a service batch): its cell as stored, nothing before it
            idx = self._rows_of(key)
            pre = self.stats[idx] if idx[0] >= 0 else np.zeros((1, N_STATS))
            return self._gate_one(pre + 0.0, d)  # as the general path: + 0.0 (-0.0 becomes 0.0)
        order = np.argsort(key, kind="stable")
        ks, rs, ds = key[order], row[order], d[order]
        start, last = _group_edges(ks)
        idx = self._rows_of(ks)
        pre = np.zeros((k, N_STATS))
        if (idx >= 0).any():
            pre[idx >= 0] = self.stats[idx[idx >= 0]]
        gated_s = self._gate_one(_running_sums(pre, rs, start), ds)
        # a gated window with later windows in its group (none when nothing is gated)
        redo = np.unique(ks[gated_s & ~last]) if gated_s.any() else ()
        for kk in redo:
            pos = np.flatnonzero(ks == kk)
            gated_s[pos] = self._gate_in_order(pre[pos[0]], rs[pos], ds[pos])
        gated = np.zeros(k, dtype=bool)
        gated[order] = gated_s
        return gated

    def _gate_in_order(self, start: np.ndarray, rows: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Gate decisions (k,) of the windows ``rows`` (k, N_STATS) of one cell, in order,
        each against the cell as it stands just before it: ``start`` (N_STATS,) plus the
        earlier windows not gated.

        The same decisions and sums as adding them one at a time (``run += row``): the
        running sums over a span of windows are one ``cumsum`` of ``[run, rows...]``
        (sequential, so bit for bit those of the loop), gated in one call; at the first
        gated window the sums restart without it, over a span twice as long as the run of
        windows that passed before it (one window when none did: a run of gated windows
        costs what the loop did). A span doubles while none is gated, so a group costs
        about a call per gated window, not per window."""
        out = np.zeros(len(d), dtype=bool)
        run, i, span = start, 0, _GATE_SPAN
        while i < len(d):
            m = min(span, len(d) - i)
            # the cell before each window
            seq = run[None, :] if m == 1 else np.cumsum(np.vstack([run[None, :], rows[i: i + m - 1]]), axis=0)
            g = self._gate_one(seq, d[i: i + m])
            if g.any():
                j = int(np.argmax(g))
                out[i + j] = True
                run, i, span = seq[j], i + j + 1, 2 * j + 1  # the gated window is not pooled
            else:
                run, i, span = seq[-1] + rows[i + m - 1], i + m, 2 * span
        return out

    def _bound(self) -> None:
        """Coarsen the older half of the cells that can be coarsened (merge block pairs),
        then drop the oldest cells if needed.

        A cell cannot be coarsened when its doubled block would hold a barrier (a bias
        step) or it is at the top level. Such cells do not count in the half: held at a
        barrier, they would fill it, and each pass would merge the few recent cells left
        in it, freeing room for about one new cell, so that every new cell after a step
        paid a whole bound (a 45-day replay with a step took 92 s; 10 s now).

        Passes go on while a cell can be coarsened (a new cell needs up to 15 to reach the
        level of its group's oldest): after 8 passes, cells were dropped, the oldest first,
        which were the largest (the top level, thousands of windows) even when every group
        would have fitted in ``max_cells`` once merged."""
        for _ in range(_BOUND_MAX_PASSES):
            if len(self) <= self.config.max_cells:
                return
            can = self._level(self.key) < 15
            if self.barriers_s:
                can &= ~self._doubling_straddles(self.key)
            if not can.any():
                break
            old = can & (self.t_last <= np.median(self.t_last[can]))
            key = self.key.copy()
            lvl = self._level(key[old])
            flag = key[old] & 1
            rest = key[old] >> 5  # (block, band, direction)
            block = rest >> (10 + 24)
            low = rest & ((1 << 34) - 1)
            block = (block >> (lvl + 1)) << (lvl + 1)  # start of the doubled block
            key[old] = ((((block << 34) | low) << 5) | ((lvl + 1) << 1) | flag)
            self._merge_keys(key)
        if len(self) > self.config.max_cells:  # still too many: drop the oldest cells
            order = np.argsort(self.t_last, kind="stable")
            drop = order[: len(self) - self.config.max_cells]
            keep = np.ones(len(self), dtype=bool)
            keep[drop] = False
            self.n_dropped += int(drop.size)
            self.key, self.stats = self.key[keep], self.stats[keep]
            self.t_first, self.t_last = self.t_first[keep], self.t_last[keep]
            self._index_stale()

    def _doubling_straddles(self, key: np.ndarray) -> np.ndarray:
        """(m,) bool: the doubled block of each cell would hold a barrier strictly inside it."""
        lvl = self._level(key)
        block = (key >> 5) >> (10 + 24)
        start = (block >> (lvl + 1)) << (lvl + 1)
        origin = self.t_origin if self.t_origin is not None else 0.0
        t0 = origin + (start - (1 << 20)).astype(float) * self.config.block_s
        t1 = t0 + np.ldexp(self.config.block_s, lvl + 1)
        out = np.zeros(len(key), dtype=bool)
        for b in self.barriers_s:
            out |= (t0 < b) & (b < t1)
        return out

    def add_barrier(self, t_s: float) -> None:
        """From now on no coarsening merges windows from before ``t_s`` (s) with windows after it."""
        if t_s not in self.barriers_s:
            self.barriers_s = sorted(self.barriers_s + [float(t_s)])

    def straddles(self, t_s: float) -> np.ndarray:
        """(m,) bool: cells holding windows from both sides of ``t_s`` (s)."""
        return (self.t_first < t_s) & (self.t_last >= t_s)

    def _merge_keys(self, key: np.ndarray) -> None:
        ukeys, inv = np.unique(key, return_inverse=True)
        if len(ukeys) == len(key):
            self.key = key
            self._index_stale()
            return
        stats = sum_by_group(inv, self.stats, len(ukeys))
        tf = np.full(len(ukeys), np.inf)
        tl = np.full(len(ukeys), -np.inf)
        np.minimum.at(tf, inv, self.t_first)
        np.maximum.at(tl, inv, self.t_last)
        self.n_merged += len(key) - len(ukeys)
        self.key, self.stats, self.t_first, self.t_last = ukeys, stats, tf, tl
        self._index_stale()

    # ------------------------------------------------------------------ views
    def folds(self) -> np.ndarray:
        """Fold of every cell (m,) int (from its key)."""
        return _fold_of(self.key >> 5, self.config.folds)

    def clusters(self) -> np.ndarray:
        """Cluster label of every cell (m,) int: its direction cell and temperature band,
        whatever its time block (the fit's cluster-robust covariance groups by this)."""
        return (self.key >> 5) & ((1 << 34) - 1)

    def outlier_twin(self) -> np.ndarray:
        """Cells holding windows the gate kept apart (m,) bool."""
        return (self.key & 1).astype(bool)

    def window_counts(self) -> np.ndarray:
        """Windows per cell (m,)."""
        return self.stats[:, _NW].copy()

    def mean_temp(self) -> np.ndarray:
        """Mean temperature of each cell (m,) degC (NaN if its windows had none)."""
        nt = self.stats[:, _NTEMP]
        return np.where(nt > 0, self.stats[:, _STEMP] / np.maximum(nt, 1), np.nan)

    def pose_data(self, mask: np.ndarray | None = None, t_now_s: float | None = None,
                  age_var_g2_per_day: float = 0.0) -> PoseData:
        """The cells (optionally a subset) as poses to fit, :class:`selfcal.fit.PoseData`.

        Each cell is one pose: its representative vector (mean direction x mean raw
        norm, ~g), an effective per-axis sd whose projection on gravity is the
        variance of the cell mean (``count = 1``), the mean window time and the mean
        temperature. With ``t_now_s``, a cell of age ``A`` days gets
        ``age_var_g2_per_day * A`` more variance (the sensor may have drifted).
        The fit adds the systematic floor once per cell.
        """
        mask = np.ones(len(self), dtype=bool) if mask is None else np.asarray(mask)
        rows = np.flatnonzero(mask) if mask.dtype == bool else mask
        direction, dbar, v_win, _ = self._derived(rows)
        s = self.stats[rows]
        nw = s[:, _NW]
        mean = direction * (1.0 + dbar)[:, None]
        var = v_win / nw
        t_mean = s[:, _ST] / nw
        if t_now_s is not None and age_var_g2_per_day > 0:
            var = var + age_var_g2_per_day * np.maximum(t_now_s - t_mean, 0.0) / 86400.0
        sd = np.repeat(np.sqrt(var)[:, None], 3, axis=1)
        temp = self.mean_temp()[rows]
        return PoseData(mean, sd, np.ones(len(rows)), t_mean, temp if np.all(np.isfinite(temp)) and len(temp) else None)

    def axis_aligned(self) -> np.ndarray:
        """The insole paper's O_cor mask over cells (m,) bool."""
        from selfcal.fit import axis_aligned_mask

        if len(self) == 0:
            return np.zeros(0, dtype=bool)
        return axis_aligned_mask(self._derived()[0], self.config.axis_tol_g)

    def cube_coverage(self) -> dict[str, bool]:
        """GGIR's rule: cells beyond both -cube_g and +cube_g on each axis."""
        c = self.config.cube_g
        u = self._derived()[0] if len(self) else np.zeros((0, 3))
        return {f"{ax}_{sgn}": bool(np.any(u[:, i] < -c) if sgn == "neg" else np.any(u[:, i] > c))
                for i, ax in enumerate("xyz") for sgn in ("neg", "pos")}

    def summary(self) -> dict:
        """Counts, time span and temperature range of the stored cells."""
        temp = self.mean_temp()
        temp = temp[np.isfinite(temp)]
        return {
            "n_cells": len(self),
            "n_windows": int(self.stats[:, _NW].sum()) if len(self) else 0,
            "n_seen": self.n_seen,
            "n_gated": self.n_gated,
            "n_outlier_cells": int(self.outlier_twin().sum()),
            "n_merged": self.n_merged,
            "n_dropped": self.n_dropped,
            "n_axis_aligned": int(self.axis_aligned().sum()),
            "t_span_s": [float(self.t_first.min()), float(self.t_last.max())] if len(self) else None,
            "temp_range_c": [float(temp.min()), float(temp.max())] if temp.size else None,
            "cube_coverage": self.cube_coverage(),
        }

    # ------------------------------------------------------------------ state
    def to_json(self, rows: bool = True) -> dict:
        """JSON-serialisable state; arrays as base64 little-endian float64 (exact, compact).
        ``rows=False``: the per-cell fields (``key``, ``stats``, ``t_first``, ``t_last``) are
        None, in their places (a checkpoint patch fills them, ``selfcal.checkpoint``)."""
        return {
            "config": self.config.model_dump(),
            "key": self.key.tolist() if rows else None,
            "stats": _enc(self.stats) if rows else None,
            "t_first": _enc(self.t_first) if rows else None,
            "t_last": _enc(self.t_last) if rows else None,
            "n_seen": self.n_seen,
            "n_gated": self.n_gated,
            "n_merged": self.n_merged,
            "n_dropped": self.n_dropped,
            "t_origin": self.t_origin,
            "barriers_s": list(self.barriers_s),
        }

    @classmethod
    def from_json(cls, d: dict) -> "PoseStore":
        """Inverse of :meth:`to_json`; ValueError for a state whose per-cell fields disagree
        (a late IndexError at the next add otherwise)."""
        obj = cls(
            PoseConfig(**d["config"]),
            np.asarray(d["key"], dtype=np.int64).reshape(-1),
            _dec(d["stats"], (N_STATS,)),
            _dec(d["t_first"]),
            _dec(d["t_last"]),
            int(d["n_seen"]), int(d["n_gated"]), int(d["n_merged"]), int(d["n_dropped"]), d.get("t_origin"),
            [float(x) for x in d.get("barriers_s", [])],
        )
        sizes = {len(obj.key), len(obj.stats), len(obj.t_first), len(obj.t_last)}
        if len(sizes) != 1:
            raise ValueError(f"pose store: its cells' fields disagree in length (key {len(obj.key)}, stats "
                             f"{len(obj.stats)}, t_first {len(obj.t_first)}, t_last {len(obj.t_last)})")
        if len(np.unique(obj.key)) != len(obj.key) or not np.all(np.isfinite(obj.stats)):
            raise ValueError("pose store: duplicate cell keys or non-finite sums")
        obj._reindex()
        return obj
