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

from selfcal.sim.config import EFFECT_NAMES, SimConfig
from selfcal.sim.sensor import SensorTruth, canonical_params, canonical_qr, draw_sensor_truth, sensor_mean
from selfcal.sim.simulator import (
    PoseTable,
    SampleChunk,
    Simulation,
    SimTruth,
    iter_samples,
    simulate_poses,
    simulate_samples,
)
from selfcal.sim.wearer import ACTIVITY_NAMES, Schedule, make_schedule

__all__ = [
    "ACTIVITY_NAMES", "EFFECT_NAMES", "PoseTable", "SampleChunk", "Schedule", "SensorTruth", "SimConfig",
    "SimTruth", "Simulation", "canonical_params", "canonical_qr", "draw_sensor_truth", "iter_samples",
    "make_schedule", "sensor_mean", "simulate_poses", "simulate_samples",
]
