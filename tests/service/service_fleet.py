"""A small simulated fleet for the dashboard tests and bench: ``selfcal demo``'s wearers,
posted to a real server as binary batches.

Each insole streams what the demo's virtual insole streams (:class:`selfcal.demo.SimSource`
over :func:`selfcal.demo.make_simulation`: the demo wearer, from 5 min before the shoe
goes on), here straight over HTTP instead of through the BLE stack and the gateway, so
that a fleet with published versions and refusals exists in seconds. Seeds are fixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import httpx
import numpy as np

from selfcal.config import load_config
from selfcal.demo import SimSource, demo_sim_config, make_simulation
from selfcal_service.schemas import BINARY_MEDIA_TYPE, Batch

#: Samples per posted batch (the gateway's demo batch size, below the service's 2000).
BATCH_SAMPLES = 1900


@dataclass
class Stream:
    """One insole's samples: times (s), specific force (g), temperature (degC)."""

    t_s: np.ndarray
    acc_g: np.ndarray
    temp_c: np.ndarray


def simulated_stream(seed: int, hours: float) -> Stream:
    """``hours`` of the demo wearer ``seed`` as the demo's virtual insole streams them."""
    sim = make_simulation(demo_sim_config(load_config(None)), seed, hours)
    source = SimSource(sim, hours)
    source.started = True  # no BLE subscriber to wait for: stream from the first sample
    parts = []
    while (chunk := source()) is not None:
        parts.append(chunk)
    return Stream(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                  np.concatenate([p[3] for p in parts]))


def tumbled_stream(seed: int, n_poses: int = 30, rate_hz: float = 20.0) -> Stream:
    """A device turned through well-spread still orientations on a bench (4 s still, 1.5 s
    of motion between), with an affine error like a consumer part's (bias +-60 mg, scale
    +-3 %, axes +-0.6 deg) and 2 mg noise: enough for status ``calibrated`` in ~3 min."""
    rng = np.random.default_rng(seed)
    scale = 1.0 + rng.uniform(-0.03, 0.03, 3)
    nxy, nxz, nyz = np.deg2rad(rng.uniform(-0.6, 0.6, 3))
    matrix = np.diag(scale) @ np.array([[1.0, nxy, nxz], [0.0, 1.0, nyz], [0.0, 0.0, 1.0]])
    offset = rng.uniform(-0.06, 0.06, 3)
    d = rng.normal(size=(n_poses, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    parts = []
    for direction in d:
        parts.append(np.tile(direction, (int(4.0 * rate_hz), 1)))
        parts.append(direction + rng.normal(0, 0.4, (int(1.5 * rate_hz), 3)))
    a_true = np.vstack(parts)
    raw = offset + a_true @ np.linalg.inv(matrix).T + rng.normal(0, 2e-3, a_true.shape)
    t = np.arange(len(raw)) / rate_hz
    return Stream(t, raw, 24.0 + 0.002 * t)


def post_stream(client: httpx.Client, device_id: str, stream: Stream, first_seq: int = 0) -> int:
    """POST the stream as binary batches (SCB2, with CRC) from ``first_seq``; the last seq."""
    seq = first_seq - 1
    for seq, i in enumerate(range(0, len(stream.t_s), BATCH_SAMPLES), start=first_seq):
        sl = slice(i, i + BATCH_SAMPLES)
        batch = Batch(seq, stream.t_s[sl], stream.acc_g[sl], stream.temp_c[sl])
        r = client.post(f"/devices/{device_id}/samples", content=batch.to_bytes(crc=True),
                        headers={"Content-Type": BINARY_MEDIA_TYPE})
        assert r.status_code == 200, r.text
    return seq


#: A jig (factory) calibration as a bench would give it: a_cal_g = matrix @ (raw_g - offset_g).
JIG_CALIBRATION = {
    "matrix": [[1.012, 0.0, 0.0], [0.0, 0.991, 0.0], [0.0, 0.0, 1.004]],
    "offset": [0.012, -0.008, 0.021],
    "note": "jig, 6 faces (test fixture)",
}
