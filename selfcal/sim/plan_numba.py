"""Optional numba kernels of the simulator's planner (:mod:`selfcal.sim._plan_jit`): the same plan, faster.

The wearer's semi-Markov chain (:meth:`selfcal.sim.wearer._Builder.worn`) and the
segments' temperature recurrence (:func:`selfcal.sim.temperature.segment_start_states`)
are scalar Python loops, most of a poses-level replay's simulator. Their kernels do the
same operations in the same order and take the same draws from the same generator, so a
schedule is the same bit for bit, and so is every result drawn from it. At first use
they are compiled (or loaded from numba's cache) and run against the Python code on a
few simulated days; if anything differs, or numba fails, the Python code plans, with
one warning.

numba is optional (``pip install 'selfcal[fast]'``); ``SELFCAL_NUMBA=0`` switches these
kernels off as it does the detector's (:mod:`selfcal.detect_numba`).
"""

from __future__ import annotations

import functools
import threading
import warnings
from types import SimpleNamespace


#: A plan shorter than this (days) is made in Python unless the kernels are loaded
#: already: their first load in a process (0.3-0.7 s from numba's cache, longer to
#: compile) costs about what the Python planner takes for ~10 days (30-50 ms a day).
LOAD_FOR_DAYS = 10.0


def kernels(days: float | None = None) -> SimpleNamespace | None:
    """``worn`` and ``start_states`` (:mod:`selfcal.sim._plan_jit`), or None (numba missing,
    switched off by ``SELFCAL_NUMBA``, or not the Python planner's results here).

    ``days``: the length of the plan about to be made; shorter than :data:`LOAD_FOR_DAYS`,
    it gets the kernels only if they are loaded already (None: load them regardless).
    """
    from selfcal.detect_numba import enabled

    if not enabled():
        return None
    if days is not None and days < LOAD_FOR_DAYS and _checked.cache_info().currsize == 0:
        return None
    return _checked()


_lock = threading.Lock()


@functools.lru_cache(maxsize=1)
def _checked() -> SimpleNamespace | None:
    with _lock:
        try:
            found = _load()
        except ImportError:
            return None
        except Exception as exc:  # noqa: BLE001 - an accelerator must never stop the simulator
            warnings.warn(f"selfcal: the simulator planner's numba kernels are not used ({exc!r}); "
                          "planning in Python", RuntimeWarning, stacklevel=2)
            return None
        if found is None:
            return None
        try:
            ok = _same_plan(found)
        except Exception as exc:  # noqa: BLE001 - an accelerator must never stop the simulator
            warnings.warn(f"selfcal: the simulator planner's numba kernels are not used ({exc!r}); "
                          "planning in Python", RuntimeWarning, stacklevel=2)
            return None
        if not ok:
            warnings.warn("selfcal: the simulator planner's numba kernels differ from its Python code "
                          "on this machine; planning in Python", RuntimeWarning, stacklevel=2)
            return None
        return found


def _load() -> SimpleNamespace | None:
    """The kernels (numba compiles them at their first call), or None when numba's JIT is
    switched off (``NUMBA_DISABLE_JIT``: they would run as plain Python, slower than the
    Python planner); ImportError without numba."""
    import numba

    if numba.config.DISABLE_JIT:
        return None
    from selfcal.sim import _plan_jit

    return SimpleNamespace(worn=_plan_jit.worn, start_states=_plan_jit.start_states)


def _same_plan(k: SimpleNamespace) -> bool:
    """Whether the kernels plan what the Python code does, row for row and bit for bit
    (the generator left in the same state), over 2 days of two wearers of the default
    configuration, with still rows between the days (a kernel's block then continues)."""
    import numpy as np

    from selfcal.sim import temperature
    from selfcal.sim.config import SimConfig
    from selfcal.sim.wearer import OFF, _Builder

    cfg = SimConfig()
    for seed in (0, 1):
        python, compiled = (_Builder(cfg, np.random.default_rng(seed)) for _ in range(2))
        for day in range(2):
            for b in (python, compiled):
                b.still(600.0 if day == 0 else 0.0, OFF, b.orient, 0.001, (0.0, 0.0, 0.0, 0.0))
            python.worn_python(14 * 3600.0)
            compiled.worn_compiled(k.worn, 14 * 3600.0)
        table = python.table()
        if not (np.array_equal(table, compiled.table(), equal_nan=True) and python.t == compiled.t
                and python.orient == compiled.orient and python.load == compiled.load
                and python.next_still == compiled.next_still
                and python.rng.bit_generator.state == compiled.rng.bit_generator.state):
            return False
        rng = np.random.default_rng(seed)
        m = len(table)
        args = (rng.uniform(10, 5000, m), rng.uniform(15, 35, m), np.where(rng.random(m) < 0.3, 4.0, 0.0),
                rng.uniform(300, 3000, m), np.full(m, 120.0), rng.random(m) < 0.6, 21.5)
        if not all(np.array_equal(x, y) for x, y in zip(temperature.start_states_python(*args),
                                                        temperature.segment_start_states(*args, kernel=k))):
            return False
    return True
