"""Optional numba kernels of the simulator's planner (:mod:`selfcal.sim._plan_jit`): the same plan, faster.

The wearer's semi-Markov chain (:meth:`selfcal.sim.wearer._Builder.worn`) and the
segments' temperature recurrence (:func:`selfcal.sim.temperature.segment_start_states`)
are scalar Python loops, most of a poses-level replay's simulator. Their kernels do the
same operations in the same order and take the same draws from the same generator, so a
schedule is the same bit for bit, and so is every result drawn from it. At first use
they are compiled (or loaded from numba's cache) and run against the Python code on a
few simulated days of three wearers; if anything differs, or numba fails, the Python
code plans, with one warning.

numba is optional (``pip install 'selfcal[fast]'``); ``SELFCAL_NUMBA=0`` switches these
kernels off as it does the detector's (:mod:`selfcal.detect_numba`).
"""

from __future__ import annotations

from types import SimpleNamespace

from selfcal.numba_check import CheckedKernel, same_bits

#: A plan shorter than this (days) is made in Python unless the kernels are loaded
#: already: their first load in a process (0.3-0.7 s from numba's cache, longer to
#: compile) costs about what the Python planner takes for ~10 days (30-65 ms a day).
LOAD_FOR_DAYS = 10.0

#: The wearers of the first-use check (``[sim]`` sections): the default one; one whose
#: chain can go from any state to any other, with every sitting posture common; and one
#: that sits for hours (still periods cut into pieces).
CHECK_SECTIONS = {
    "default": {},
    "busy": {"activity": {"from_sit": {"stand": 0.5, "walk": 0.3, "stairs": 0.2},
                          "from_stairs": {"walk": 0.4, "stand": 0.3, "sit": 0.1, "stairs": 0.2},
                          "walk_long_fraction": 0.5},
             "posture": {"sit_flat_p": 0.1, "sit_heel_p": 0.3, "sit_toes_p": 0.3, "sit_crossed_p": 0.3,
                         "stand_tilt_sd_deg": 0.0, "sit_sway_sd_mg": 0.0}},
    "sitting": {"activity": {"from_stand": {"sit": 1.0},
                             "sit": {"median_s": 7200, "gsd": 1.5, "min_s": 60, "max_s": 10800}},
                "posture": {"sit_quiet": {"median_s": 2400, "gsd": 2.0, "min_s": 1, "max_s": 7200}}},
}


def kernels(days: float | None = None) -> SimpleNamespace | None:
    """``worn`` and ``start_states`` (:mod:`selfcal.sim._plan_jit`), or None (numba missing,
    switched off by ``SELFCAL_NUMBA``, or not the Python planner's results here).

    ``days``: the length of the plan about to be made; shorter than :data:`LOAD_FOR_DAYS`,
    it gets the kernels only if they are loaded already (None: load them regardless).
    """
    return PLANNER.available(load=days is None or days >= LOAD_FOR_DAYS)


def loaded() -> bool:
    """Whether the kernels were loaded and checked (or found unusable) in this process."""
    return PLANNER.loaded()


def reset() -> None:
    """Forget the loaded kernels (tests)."""
    PLANNER.reset()


def _load() -> SimpleNamespace | None:
    """The kernels (numba compiles them at their first call), or None when numba's JIT is
    switched off (``NUMBA_DISABLE_JIT``: they would run as plain Python, slower than the
    Python planner); ImportError without numba."""
    import numba

    if numba.config.DISABLE_JIT:
        return None
    from selfcal.sim import _plan_jit, wearer

    if _plan_jit.N_COLUMNS != len(wearer._COLUMNS):
        raise RuntimeError(f"the kernel writes {_plan_jit.N_COLUMNS} columns, the schedule has "
                           f"{len(wearer._COLUMNS)}")
    return SimpleNamespace(worn=_plan_jit.worn, start_states=_plan_jit.start_states)


def _same_plan(k: SimpleNamespace) -> bool:
    """Whether the kernels plan what the Python code does, row for row and bit for bit (the
    signs of zeros, and the generator left in the same state), for the wearers of
    :data:`CHECK_SECTIONS` over two days each, with still rows between the days."""
    import numpy as np

    from selfcal.sim import temperature
    from selfcal.sim.config import SimConfig
    from selfcal.sim.wearer import OFF, _Builder

    for seed, section in enumerate(CHECK_SECTIONS.values()):
        cfg = SimConfig.from_section(section)
        python, compiled = (_Builder(cfg, np.random.default_rng(seed)) for _ in range(2))
        for day in range(2):
            for b in (python, compiled):
                b.still(600.0 if day == 0 else 0.0, OFF, b.orient, 0.001, (0.0, 0.0, 0.0, 0.0))
            python.worn_python(14 * 3600.0)
            compiled.worn_compiled(k.worn, 14 * 3600.0)
        table = python.table()
        if not (same_bits(table, compiled.table()) and python.t == compiled.t
                and python.orient == compiled.orient and python.load == compiled.load
                and python.next_still == compiled.next_still
                and python.rng.bit_generator.state == compiled.rng.bit_generator.state):
            return False
        rng = np.random.default_rng(seed)
        m = len(table)
        args = (rng.uniform(10, 5000, m), rng.uniform(15, 35, m), np.where(rng.random(m) < 0.3, 4.0, 0.0),
                rng.uniform(300, 3000, m), np.full(m, 120.0), rng.random(m) < 0.6, 21.5)
        if not all(same_bits(x, y) for x, y in zip(temperature.start_states_python(*args),
                                                    temperature.segment_start_states(*args, kernel=k))):
            return False
    return True


#: The kernels, loaded and checked once per process (``_load`` is looked up at the load,
#: so that tests can give another).
PLANNER = CheckedKernel("the simulator planner's numba kernels", lambda: _load(), lambda k: _same_plan(k),
                        reference="the Python planner", fallback="planning in Python")
