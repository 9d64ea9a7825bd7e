"""Pose buffer: a bounded, diverse set of still poses, and what they determine.

Policy (documented in the README):

* **Diversity** — the distance between two poses is
  ``gamma = sqrt((angle / merge_angle_deg)^2 + (dT / merge_temp_c)^2)`` (the angle
  between their gravity directions; the temperature term only when both have one, so
  that the same orientation at another temperature is kept: it is what reveals a
  temperature effect). A new pose with ``gamma < 1`` to a stored one *replaces* it:
  the newest observation of a direction wins, which tracks a drifting sensor. If the
  stored pose is recent (``pool_within_s``) and not yet absorbed into the published
  model, the two are *pooled* instead (n-weighted mean, pooled sd), so a long still
  split into several windows counts as one pose with all its samples. A repeat of a
  pose already absorbed less than ``refresh_s`` ago replaces it but is marked absorbed:
  its information is already in the model, and what repeats share (systematic error)
  does not average down. After ``refresh_s`` a repeat counts again, so slow drifts
  are still tracked.
* **Bound** — when the buffer holds ``max_poses``, the most redundant pose goes: of the
  closest pair (smallest gamma), the older one. Isolated poses (the rare shoe-on-its-
  side) are never the ones evicted while redundant ones remain: coverage is preserved.
* **Held-out** — every pose gets a serial id; ids that are multiples of
  ``guard.heldout_every`` are held out of fitting and used by the guard. Once a
  publication has been validated on them they are *validated* and become training
  poses for the next refit, so no pose's information is lost.
* **Absorbed** — a pose whose information is already in the published model's
  posterior is marked absorbed, so that a sequential update does not count it twice.
* **Split** — the insole paper's axis-aligned poses (``O_cor``) and the rest
  (``O_train``) are available as masks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from selfcal.fit import PoseData, axis_aligned_mask


class PoseConfig(BaseModel):
    """The ``[poses]`` section."""

    model_config = ConfigDict(extra="forbid")

    max_poses: int = Field(240, ge=8, description="buffer size bound")
    merge_angle_deg: float = Field(3.0, gt=0, description="poses closer than this (and merge_temp_c) are one pose, deg")
    merge_temp_c: float = Field(2.0, gt=0, description="temperature scale of the diversity distance, degC")
    refresh_s: float = Field(
        86400.0, ge=0,
        description="a repeat of an absorbed pose within this time carries no new information (systematic errors do not average down), s",
    )
    pool_within_s: float = Field(
        600.0, ge=0, description="a repeat of a pose not yet absorbed and this recent is pooled with it (n-weighted), s"
    )
    axis_tol_g: float = Field(0.12, gt=0, description="axis-aligned (O_cor) tolerance, g")
    cube_g: float = Field(0.3, gt=0, description="GGIR-style coverage: both sides of +-cube_g on every axis")

    @classmethod
    def from_section(cls, section: dict[str, Any] | None) -> "PoseConfig":
        """Validate the ``[poses]`` TOML section."""
        return cls(**(section or {}))


_FIELDS = ("mean", "sd", "count", "t_s", "temp_c", "pose_id", "absorbed", "validated", "absorbed_at")


@dataclass
class PoseBuffer:
    """Bounded, diverse store of still poses (means in g).

    Arrays (length m = number of stored poses): ``mean (m,3) g``, ``sd (m,3) g``,
    ``count (m,)``, ``t_s (m,) s`` (window centre), ``temp_c (m,) degC`` (NaN if
    unknown), ``pose_id (m,) int``, ``absorbed (m,) bool``.
    """

    config: PoseConfig
    mean: np.ndarray
    sd: np.ndarray
    count: np.ndarray
    t_s: np.ndarray
    temp_c: np.ndarray
    pose_id: np.ndarray
    absorbed: np.ndarray
    validated: np.ndarray
    absorbed_at: np.ndarray
    next_id: int = 1
    n_seen: int = 0
    n_replaced: int = 0
    n_evicted: int = 0

    @classmethod
    def empty(cls, config: PoseConfig | None = None) -> "PoseBuffer":
        """A buffer with no pose."""
        return cls(
            config or PoseConfig(),
            np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0),
            np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool), np.zeros(0),
        )

    def __len__(self) -> int:
        return self.mean.shape[0]

    # ------------------------------------------------------------------ distance
    def _units(self) -> np.ndarray:
        """Unit directions of the stored poses (m, 3), cached between calls."""
        u = self.__dict__.get("_unit_cache")
        if u is None or u.shape[0] != len(self):
            u = self.mean / np.linalg.norm(self.mean, axis=1, keepdims=True)
            self.__dict__["_unit_cache"] = u
        return u

    def _gamma(self, mean: np.ndarray, temp_c: float) -> np.ndarray:
        """Diversity distance of one pose (3,) to every stored pose, (m,)."""
        if len(self) == 0:
            return np.zeros(0)
        u = mean / np.sqrt(mean @ mean)
        ang = np.degrees(np.arccos(np.clip(self._units() @ u, -1.0, 1.0)))
        g2 = (ang / self.config.merge_angle_deg) ** 2
        if np.isfinite(temp_c):
            dt = (self.temp_c - temp_c) / self.config.merge_temp_c
            g2 += np.where(np.isfinite(dt), dt * dt, 0.0)
        return g2  # squared distance: compared with 1

    def _pairwise_gamma(self) -> np.ndarray:
        stored = self._units()
        ang = np.degrees(np.arccos(np.clip(stored @ stored.T, -1.0, 1.0)))
        dt = np.abs(self.temp_c[:, None] - self.temp_c[None, :])
        g2 = (ang / self.config.merge_angle_deg) ** 2 + np.where(
            np.isfinite(dt), (dt / self.config.merge_temp_c) ** 2, 0.0
        )
        g = np.sqrt(g2)
        np.fill_diagonal(g, np.inf)
        return g

    # ------------------------------------------------------------------ updates
    def add(self, mean_g, sd_g, count, t_s, temp_c=None) -> dict[str, int]:
        """Add still windows (one loop step per window, O(m) numpy work each).

        Parameters
        ----------
        mean_g, sd_g : ndarray, shape (k, 3), g
        count : ndarray, shape (k,)
        t_s : ndarray, shape (k,), s
        temp_c : ndarray, shape (k,), degC, or None

        Returns
        -------
        dict with ``added``, ``replaced``, ``evicted`` counts and ``new_info``: the
        windows that brought information not yet in the published model.
        """
        mean_g = np.atleast_2d(np.asarray(mean_g, dtype=float))
        k = mean_g.shape[0]
        sd_g = np.broadcast_to(np.asarray(sd_g, dtype=float), (k, 3)) if sd_g is not None else np.full((k, 3), np.nan)
        count = np.broadcast_to(np.asarray(count, dtype=float), (k,)).tolist()
        t_s = np.broadcast_to(np.asarray(t_s, dtype=float), (k,)).tolist()
        temp = (np.full(k, np.nan) if temp_c is None else np.broadcast_to(np.asarray(temp_c, dtype=float), (k,))).tolist()
        valid = np.all(np.isfinite(mean_g), axis=1) & (np.einsum("ij,ij->i", mean_g, mean_g) > 0)
        stats = {"added": 0, "replaced": 0, "evicted": 0, "new_info": 0}
        for i in range(k):
            if not valid[i]:
                continue
            self.n_seen += 1
            row = (mean_g[i], sd_g[i], count[i], t_s[i], temp[i], self.next_id, False, False, np.nan)
            self.next_id += 1
            gamma2 = self._gamma(mean_g[i], temp[i])
            j = int(np.argmin(gamma2)) if gamma2.size else -1
            if j >= 0 and gamma2[j] < 1.0:
                if not self.absorbed[j] and abs(t_s[i] - self.t_s[j]) <= self.config.pool_within_s:
                    self._pool(j, mean_g[i], sd_g[i], count[i], t_s[i], temp[i])
                    stats["replaced"] += 1
                    stats["new_info"] += 1
                    continue
                absorbed_at = self.absorbed_at[j]
                repeat_of_absorbed = self.absorbed[j] and abs(t_s[i] - absorbed_at) <= self.config.refresh_s
                for name, value in zip(_FIELDS, row):
                    getattr(self, name)[j] = value
                if repeat_of_absorbed:
                    # same orientation, recently absorbed: keep the newest reading (for the
                    # guard and the detector), but do not count its information again
                    self.absorbed[j] = True
                    self.absorbed_at[j] = absorbed_at
                else:
                    stats["new_info"] += 1
                self._units()[j] = mean_g[i] / np.sqrt(mean_g[i] @ mean_g[i])
                self.n_replaced += 1
                stats["replaced"] += 1
                continue
            for name, value in zip(_FIELDS, row):
                arr = getattr(self, name)
                setattr(self, name, np.concatenate([arr, np.asarray([value], dtype=arr.dtype).reshape((1,) + arr.shape[1:])]))
            stats["added"] += 1
            stats["new_info"] += 1
            self.__dict__.pop("_unit_cache", None)
            if len(self) > self.config.max_poses:
                self._evict_one()
                stats["evicted"] += 1
        return stats

    def _pool(self, j: int, mean, sd, count, t_s, temp) -> None:
        """Pool a repeat of pose ``j`` into it (n-weighted; sd includes the spread of the means)."""
        n1, n2 = self.count[j], count
        n = n1 + n2
        m = (n1 * self.mean[j] + n2 * mean) / n
        var = (n1 * (self.sd[j] ** 2 + (self.mean[j] - m) ** 2) + n2 * (sd**2 + (mean - m) ** 2)) / n
        self.mean[j] = m
        self._units()[j] = m / np.sqrt(m @ m)
        self.sd[j] = np.sqrt(var)
        self.count[j] = n
        self.t_s[j] = (n1 * self.t_s[j] + n2 * t_s) / n
        if np.isfinite(temp) and np.isfinite(self.temp_c[j]):
            self.temp_c[j] = (n1 * self.temp_c[j] + n2 * temp) / n
        self.n_replaced += 1

    def _evict_one(self) -> None:
        g = self._pairwise_gamma()
        i, j = np.unravel_index(np.argmin(g), g.shape)
        drop = i if self.t_s[i] < self.t_s[j] else j
        keep = np.ones(len(self), dtype=bool)
        keep[drop] = False
        for name in _FIELDS:
            setattr(self, name, getattr(self, name)[keep])
        self.__dict__.pop("_unit_cache", None)
        self.n_evicted += 1

    def mark_absorbed(self, pose_ids: np.ndarray, t_s: float = np.nan) -> None:
        """Mark poses as absorbed into the published model's posterior (at time ``t_s``)."""
        new = np.isin(self.pose_id, pose_ids) & ~self.absorbed
        self.absorbed |= new
        self.absorbed_at[new] = t_s

    def mark_validated(self, pose_ids: np.ndarray) -> None:
        """Mark held-out poses as used once by the guard: from now on they are training poses."""
        self.validated |= np.isin(self.pose_id, pose_ids)

    # ------------------------------------------------------------------ views
    def pose_data(self, mask: np.ndarray | None = None) -> PoseData:
        """The stored poses (optionally a subset) as :class:`selfcal.fit.PoseData` in g."""
        mask = np.ones(len(self), dtype=bool) if mask is None else mask
        sd = self.sd[mask]
        temp = self.temp_c[mask]
        return PoseData(
            self.mean[mask],
            None if np.any(~np.isfinite(sd)) else sd,
            self.count[mask],
            self.t_s[mask],
            temp if np.all(np.isfinite(temp)) and temp.size else None,
        )

    def heldout(self, every: int) -> np.ndarray:
        """Held-out mask (m,) bool: pose ids that are multiples of ``every``."""
        return (self.pose_id % every) == 0

    def axis_aligned(self) -> np.ndarray:
        """The insole paper's O_cor mask (m,) bool; ``~mask`` is O_train."""
        if len(self) == 0:
            return np.zeros(0, dtype=bool)
        return axis_aligned_mask(self.mean, self.config.axis_tol_g)

    def cube_coverage(self) -> dict[str, bool]:
        """GGIR's rule: poses beyond both -cube_g and +cube_g on each axis."""
        c = self.config.cube_g
        out = {}
        for i, ax in enumerate("xyz"):
            v = self.mean[:, i] if len(self) else np.zeros(0)
            out[f"{ax}_neg"] = bool(np.any(v < -c))
            out[f"{ax}_pos"] = bool(np.any(v > c))
        return out

    def summary(self) -> dict:
        """Counts, time span and temperature range of the stored poses."""
        temp = self.temp_c[np.isfinite(self.temp_c)] if len(self) else np.zeros(0)
        return {
            "n_poses": len(self),
            "n_seen": self.n_seen,
            "n_replaced": self.n_replaced,
            "n_evicted": self.n_evicted,
            "n_axis_aligned": int(self.axis_aligned().sum()),
            "t_span_s": [float(self.t_s.min()), float(self.t_s.max())] if len(self) else None,
            "temp_range_c": [float(temp.min()), float(temp.max())] if temp.size else None,
            "cube_coverage": self.cube_coverage(),
        }

    # ------------------------------------------------------------------ state
    def to_json(self) -> dict:
        """JSON-serialisable state (exact: floats are written with repr precision)."""
        return {
            "config": self.config.model_dump(),
            "mean": self.mean.tolist(),
            "sd": [[None if not np.isfinite(x) else float(x) for x in row] for row in self.sd],
            "count": self.count.tolist(),
            "t_s": self.t_s.tolist(),
            "temp_c": [None if not np.isfinite(x) else float(x) for x in self.temp_c],
            "pose_id": self.pose_id.tolist(),
            "absorbed": self.absorbed.tolist(),
            "validated": self.validated.tolist(),
            "absorbed_at": [None if not np.isfinite(x) else float(x) for x in self.absorbed_at],
            "next_id": self.next_id,
            "n_seen": self.n_seen,
            "n_replaced": self.n_replaced,
            "n_evicted": self.n_evicted,
        }

    @classmethod
    def from_json(cls, d: dict) -> "PoseBuffer":
        """Inverse of :meth:`to_json`."""
        def arr(x, shape_tail=()):
            a = np.array([[np.nan if v is None else v for v in row] for row in x], dtype=float) if shape_tail else np.array(
                [np.nan if v is None else v for v in x], dtype=float)
            return a.reshape((-1,) + shape_tail)
        return cls(
            PoseConfig(**d["config"]),
            arr(d["mean"], (3,)), arr(d["sd"], (3,)), arr(d["count"]), arr(d["t_s"]), arr(d["temp_c"]),
            np.asarray(d["pose_id"], dtype=np.int64), np.asarray(d["absorbed"], dtype=bool),
            np.asarray(d["validated"], dtype=bool), arr(d["absorbed_at"]), int(d["next_id"]), int(d["n_seen"]), int(d["n_replaced"]), int(d["n_evicted"]),
        )
