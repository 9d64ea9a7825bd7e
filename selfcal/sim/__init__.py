"""Insole wearer + sensor simulator (seeded, every part configured by ``[sim]``).

Two levels of output:

* a **sample stream** (:meth:`Simulation.iter_samples`): chunks of the 20 Hz stream of
  an insole (acceleration, temperature, 4 pressure channels), days long, with truth;
* **poses** (:meth:`Simulation.poses`): still windows directly (mean, sd, n, t, temp),
  for Monte-Carlo work that does not need the samples.

Both follow the same wearer schedule, drawn from one ``numpy.random.Generator``.
The equations are in ``docs/simulation.md``.

Examples
--------
>>> import numpy as np
>>> from selfcal.sim import SimConfig, Simulation
>>> sim = Simulation(SimConfig(), np.random.default_rng(7), days=0.1)
>>> poses = sim.poses()
>>> truth = sim.truth.to_dict()   # matrix, offset, params, effects, seed, config
"""

import importlib
from typing import Any

from selfcal.sim.config import EFFECT_NAMES, SimConfig  # light: pydantic only

#: where each public name lives; the heavy modules (scipy.signal, interpolation) load on
#: first use, so ``selfcal --version`` and commands that only need the effect names
#: do not pay ~0.4 s for them
_LAZY = {
    "SensorTruth": "sensor", "canonical_params": "sensor", "canonical_qr": "sensor",
    "draw_sensor_truth": "sensor", "sensor_mean": "sensor",
    "PoseTable": "simulator", "SampleChunk": "simulator", "Simulation": "simulator", "SimTruth": "simulator",
    "iter_samples": "simulator", "simulate_poses": "simulator", "simulate_samples": "simulator",
    "ACTIVITY_NAMES": "wearer", "Schedule": "wearer", "make_schedule": "wearer",
}


def __getattr__(name: str) -> Any:
    """Import a public name's module on first access (PEP 562)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'selfcal.sim' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"selfcal.sim.{module}"), name)
    globals()[name] = value
    return value

__all__ = [
    "ACTIVITY_NAMES", "EFFECT_NAMES", "PoseTable", "SampleChunk", "Schedule", "SensorTruth", "SimConfig",
    "SimTruth", "Simulation", "canonical_params", "canonical_qr", "draw_sensor_truth", "iter_samples",
    "make_schedule", "sensor_mean", "simulate_poses", "simulate_samples",
]
