"""A fake calibrator with the OnlineCalibrator interface (docs/internals.md), for plumbing tests.

It detects nothing. It counts samples and keeps an exact, order-independent checksum of
the sample times (sum of round(t_s * 1000)), so a test can tell that every acknowledged
sample was fed exactly once. It publishes a fixed model after ``publish_after_samples``
samples (``provisional``) and again after twice as many (``calibrated``).
Config: the ``[fake]`` section of the config dict (``publish_after_samples``).

(Named ``service_fakes`` rather than ``fakes``: ``tests/`` has no ``__init__.py``, so
test helper modules are top-level modules and must not collide across test folders.)
"""

from __future__ import annotations

import json

import numpy as np

FIXED_MATRIX = [[1.01, 0.002, -0.001], [0.0, 0.99, 0.003], [0.0, 0.0, 1.02]]
FIXED_OFFSET = [0.01, -0.02, 0.015]
PARAMS = ["bx", "by", "bz", "sx", "sy", "sz", "nxy", "nxz", "nyz"]


class FakeCalibrator:
    def __init__(self, config: dict | None = None, model: str = "affine9"):
        fake = (config or {}).get("fake", {})
        self.model = model
        self.publish_after = int(fake.get("publish_after_samples", 200))
        self.n_samples = 0
        self.t_ms_sum = 0
        self.last_t_s: float | None = None
        self.status = "uncalibrated"
        self.last_refit: dict | None = None
        self._calibration: dict | None = None

    def feed_samples(self, t_s, acc_g, temp_c=None, pressure_kpa=None) -> list[dict]:
        t_s = np.asarray(t_s, dtype=float)
        acc_g = np.asarray(acc_g, dtype=float)
        if acc_g.shape != (t_s.shape[0], 3):
            raise ValueError(f"acc_g: shape {acc_g.shape}, expected ({t_s.shape[0]}, 3)")
        if self.last_t_s is not None and t_s[0] < self.last_t_s:
            raise ValueError(f"t_s: {t_s[0]} < last fed {self.last_t_s}")
        if temp_c is not None and np.shape(temp_c) != t_s.shape:
            raise ValueError("temp_c: wrong shape")
        before = self.n_samples
        self.n_samples += int(t_s.shape[0])
        self.t_ms_sum += int(np.round(t_s * 1000.0).astype(np.int64).sum())
        self.last_t_s = float(t_s[-1])
        events = []
        for threshold, status in ((self.publish_after, "provisional"), (2 * self.publish_after, "calibrated")):
            if before < threshold <= self.n_samples:
                self.status = status
                self._calibration = self._model(status)
                events.append(
                    {"t_s": self.last_t_s, "published": True, "reason": None, "message": f"fake {status}",
                     "calibration": self._calibration}
                )
        self.last_refit = {
            "published": bool(events),
            "reason": None if events else "no_still_poses",
            "message": "fake calibrator",
            "t_s": self.last_t_s,
            "n_samples": self.n_samples,
            "t_ms_sum": self.t_ms_sum,
        }
        return events

    def _model(self, status: str) -> dict:
        std = {p: 1e-4 for p in PARAMS}
        std["nxz"] = None  # pretend one parameter is undetermined
        return {
            "model": self.model,
            "status": status,
            "params": {p: 0.0 for p in PARAMS},
            "std": std,
            "matrix": FIXED_MATRIX,
            "offset": FIXED_OFFSET,
            "n_poses": 6 if status == "provisional" else 12,
            "residual_rms_mg": 1.5,
        }

    def calibration(self) -> dict | None:
        return self._calibration

    def to_json(self) -> str:
        return json.dumps(
            {
                "model": self.model,
                "publish_after": self.publish_after,
                "n_samples": self.n_samples,
                "t_ms_sum": self.t_ms_sum,
                "last_t_s": self.last_t_s,
                "status": self.status,
                "last_refit": self.last_refit,
                "calibration": self._calibration,
            }
        )

    @classmethod
    def from_json(cls, s: str) -> "FakeCalibrator":
        d = json.loads(s)
        self = cls(model=d["model"])
        self.publish_after = d["publish_after"]
        self.n_samples = d["n_samples"]
        self.t_ms_sum = d["t_ms_sum"]
        self.last_t_s = d["last_t_s"]
        self.status = d["status"]
        self.last_refit = d["last_refit"]
        self._calibration = d["calibration"]
        return self


class SeedCrashCalibrator(FakeCalibrator):
    """A fake whose ``seed_calibration`` raises: an admin PUT then hits an unexpected error (a 500)."""

    def seed_calibration(self, params, std=None, t_s: float = 0.0) -> None:
        raise RuntimeError("injected failure in seed_calibration")
