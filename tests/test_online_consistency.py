"""The online calibrator's promises, checked against the truth on synthetic wear.

* A ``calibrated`` version's true whole-sphere error is within 2.5 x its
  ``predicted_sphere_rms_mg`` + 0.05 mg, and its parameter errors within a few sds.
* One bad "still" pose among the first six (norm off by 8-15 %) changes neither the
  time to the first ``calibrated`` by more than 20 % nor the final error by more than
  10 %: it cannot lock the device in.

bench/consistency.py scores the same promises on the simulator's week-long wear.
"""

import numpy as np
import pytest

from posegen import poses_from_truth, random_truth, sphere_rms_mg, spread_directions, tilted
from selfcal.calibrator import OnlineCalibrator
from selfcal.models import ErrorModel

A9 = ErrorModel("affine9")


def insole_wear(rng, n=900, step_s=240.0):
    """Directions of an insole's still poses in time order: mostly flat, some sides, a few upside down."""
    kind = rng.choice(4, size=n, p=[0.72, 0.12, 0.04, 0.12])
    base = np.array([[0, 0, 1.0], [0, 1.0, 0], [0, 0, -1.0], [1.0, 0, 0]])
    d = tilted(rng, base[kind], 10.0)
    sides = kind == 1
    d[sides] *= rng.choice([-1.0, 1.0], size=(sides.sum(), 1)) * np.array([1, 1, 1])
    other = kind == 3
    d[other] = spread_directions(rng, int(other.sum()))
    return d, step_s * np.arange(n)


def run(seed, bad_index=None, factor=1.0):
    rng = np.random.default_rng(seed)
    truth = random_truth(rng)
    d, t = insole_wear(rng)
    poses = poses_from_truth(rng, A9, truth, d, sample_sd_g=3e-3, count=200, t_s=t)
    mean = poses.mean.copy()
    if bad_index is not None:  # a "still" pose whose norm is off: scale its true specific force
        matrix, offset = A9.linear(truth)
        mean[bad_index] = factor * d[bad_index] @ np.linalg.inv(matrix).T + offset
    cal = OnlineCalibrator()
    events = []
    for i in range(0, len(t), 7):  # the gateway's batches
        sl = slice(i, i + 7)
        events += cal.feed_poses(mean[sl], poses.sd[sl], poses.count[sl], t[sl])
    events += cal.flush()
    versions = [e["calibration"] for e in events if e["published"]]
    return truth, versions


def first_calibrated_h(versions):
    for v in versions:
        if v["status"] == "calibrated":
            return v["t_s"] / 3600.0
    return None


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_calibrated_versions_keep_their_promise(seed):
    truth, versions = run(seed)
    cal = [v for v in versions if v["status"] == "calibrated"]
    assert cal, "the synthetic wear reaches 'calibrated'"
    for v in cal:
        theta = A9.from_dict(v["params"])
        true_mg = sphere_rms_mg(A9, theta, truth)
        assert true_mg <= 2.5 * v["predicted_sphere_rms_mg"] + 0.05, (v["version"], true_mg, v["predicted_sphere_rms_mg"])
        assert v["predicted_sphere_rms_mg"] <= 2.0
        z = (theta - truth) / np.array([v["std"][n] for n in A9.param_names])
        assert np.max(np.abs(z)) < 5.0, (v["version"], z)


@pytest.mark.parametrize("seed,bad_index,factor", [(4, 0, 1.10), (5, 3, 0.88), (6, 5, 1.15), (7, 2, 1.08)])
def test_one_bad_early_pose_neither_delays_nor_spoils(seed, bad_index, factor):
    truth, clean = run(seed)
    _, spoiled = run(seed, bad_index, factor)
    t_clean, t_bad = first_calibrated_h(clean), first_calibrated_h(spoiled)
    assert t_clean is not None and t_bad is not None
    assert abs(t_bad - t_clean) <= 0.2 * t_clean, (t_clean, t_bad)
    e_clean = sphere_rms_mg(A9, A9.from_dict(clean[-1]["params"]), truth)
    e_bad = sphere_rms_mg(A9, A9.from_dict(spoiled[-1]["params"]), truth)
    assert e_bad <= 1.1 * e_clean + 0.02, (e_clean, e_bad)  # 10 %, and 20 µg for rounding
