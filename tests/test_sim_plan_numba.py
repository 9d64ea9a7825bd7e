"""The simulator planner's optional numba kernels (selfcal.sim.plan_numba) plan what its
Python code does, bit for bit: every row the planner builds (before the rows are cut to
sample indices), the builder's state, every column of the schedule and the generator's
state after it, for several wearers, lengths and configurations; a kernel that fails or
differs is not used, and the Python code plans the same schedule."""

from __future__ import annotations

import dataclasses
import importlib.util

import numpy as np
import pytest

from selfcal.sim import plan_numba, temperature, wearer
from selfcal.sim.config import SimConfig

needs_numba = pytest.mark.skipif(importlib.util.find_spec("numba") is None,
                                 reason="numba is not installed (pip install 'selfcal[fast]')")

CONFIGS = dict(plan_numba.CHECK_SECTIONS, **{
    # short quiet periods and long moves, walks only long, tilt-free standing
    "restless": {"activity": {"walk_long_fraction": 1.0},
                 "posture": {"stand_quiet": {"median_s": 0.5, "gsd": 1.0, "min_s": 0.5, "max_s": 0.5},
                             "stand_shift": {"median_s": 3.0, "gsd": 2.0, "min_s": 0.4, "max_s": 20},
                             "sit_heel_pitch_deg": [20.0, 20.0]}},
})


@pytest.fixture
def compiled():
    """The kernels as compiled, not through their first-use check (which would hide a
    kernel that differs by planning in Python)."""
    k = plan_numba._load()
    if k is None:
        pytest.skip("numba's JIT is disabled (NUMBA_DISABLE_JIT): the kernels would run as Python")
    return k


def plan(monkeypatch, kernels, cfg: SimConfig, seed: int, days: float):
    """The schedule, the planner's rows and final state (captured at ``_finish``) and the
    generator's state after the plan, with ``kernels`` (None: the Python planner)."""
    monkeypatch.setattr(plan_numba, "kernels", lambda days=None: kernels)
    seen = {}
    finish = wearer._finish

    def capture(b, *args):
        seen.update(table=b.table(), t=b.t, orient=b.orient, load=b.load, next_still=b.next_still)
        return finish(b, *args)

    monkeypatch.setattr(wearer, "_finish", capture)
    rng = np.random.default_rng(seed)
    schedule = wearer.make_schedule(cfg, rng, days)
    monkeypatch.undo()
    return schedule, seen, rng.bit_generator.state


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return (a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
            and np.array_equal(np.signbit(a), np.signbit(b)))


@needs_numba
@pytest.mark.parametrize("name", sorted(CONFIGS))
@pytest.mark.parametrize("seed, days", [(1, 0.2), (2, 1.0), (3, 4.5)])
def test_the_kernels_plan_the_python_schedule_bit_for_bit(monkeypatch, compiled, name, seed, days):
    cfg = SimConfig.from_section(CONFIGS[name])
    fast, fast_rows, fast_state = plan(monkeypatch, compiled, cfg, seed, days)
    slow, slow_rows, slow_state = plan(monkeypatch, None, cfg, seed, days)
    assert len(slow_rows["table"]) > 0
    assert same_bits(fast_rows.pop("table"), slow_rows.pop("table"))  # the raw durations, not only the indices
    assert fast_rows == slow_rows
    for f in dataclasses.fields(slow):
        a, b = getattr(fast, f.name), getattr(slow, f.name)
        assert same_bits(a, b) if isinstance(b, np.ndarray) else a == b, f.name
    assert fast_state == slow_state  # the draws after the plan (the simulation's) are the same


@needs_numba
def test_a_kernel_that_outgrows_the_room_reserved_for_it_plans_the_same_rows(monkeypatch, compiled):
    """The kernel writes into the builder's buffer, and makes a bigger one itself when the
    room reserved ahead runs out: with no room to spare at all (a buffer of one row,
    reserved to the exact size asked), the plan is the Python planner's, bit for bit."""
    def exact(self, k):
        if self._n + k > self._cols.shape[1]:
            bigger = np.empty((len(wearer._COLUMNS), self._n + k))
            bigger[:, :self._n] = self._cols[:, :self._n]
            self._cols = bigger

    grown = []

    def worn(*args):
        out = compiled.worn(*args)
        grown.append(out[0] is not args[-2])
        return out

    cfg = SimConfig.from_section(CONFIGS["restless"])
    slow, slow_rows, slow_state = plan(monkeypatch, None, cfg, 5, 2.0)
    monkeypatch.setattr(wearer._Builder, "_INITIAL_ROWS", 1)
    monkeypatch.setattr(wearer._Builder, "reserve", exact)
    fast, fast_rows, fast_state = plan(monkeypatch, type(compiled)(worn=worn, start_states=compiled.start_states),
                                       cfg, 5, 2.0)
    assert any(grown) and same_bits(fast_rows.pop("table"), slow_rows.pop("table")) and fast_rows == slow_rows
    for f in dataclasses.fields(slow):
        a, b = getattr(fast, f.name), getattr(slow, f.name)
        assert same_bits(a, b) if isinstance(b, np.ndarray) else a == b, f.name
    assert fast_state == slow_state


@needs_numba
def test_the_kernels_pass_their_first_use_check_where_numba_is(monkeypatch, compiled, recwarn):
    monkeypatch.setenv("SELFCAL_NUMBA", "1")
    plan_numba.reset()
    try:
        assert plan_numba.kernels() is not None
        assert not [w for w in recwarn if "planner" in str(w.message)]
        monkeypatch.setenv("SELFCAL_NUMBA", "0")
        assert plan_numba.kernels() is None
    finally:
        plan_numba.reset()


@needs_numba
def test_a_short_plan_does_not_load_the_kernels_but_uses_them_once_loaded(monkeypatch, compiled):
    """Below LOAD_FOR_DAYS the first load is not paid for one plan; once loaded they are
    used; the temperature recurrence alone never loads them."""
    monkeypatch.setenv("SELFCAL_NUMBA", "1")
    plan_numba.reset()
    try:
        assert plan_numba.kernels(plan_numba.LOAD_FOR_DAYS / 2) is None
        temperature.segment_start_states(np.ones(3), np.ones(3), np.zeros(3), np.full(3, 100.0),
                                         np.full(3, 50.0), np.ones(3, bool), 20.0)
        assert not plan_numba.loaded()
        assert plan_numba.kernels(plan_numba.LOAD_FOR_DAYS) is not None
        assert plan_numba.kernels(0.1) is not None
    finally:
        plan_numba.reset()


@needs_numba
def test_the_temperature_recurrence_kernel_gives_the_python_states(compiled):
    rng = np.random.default_rng(4)
    m = 5000
    args = (rng.uniform(1, 8000, m), rng.uniform(10, 36, m), np.where(rng.random(m) < 0.3, 3.0, 0.0),
            rng.uniform(200, 4000, m), rng.uniform(60, 600, m), rng.random(m) < 0.5, 19.0)
    args[1][:5] = [0.0, -0.0, np.inf, np.nan, -1e300]
    for a, b in zip(temperature.segment_start_states(*args, kernel=compiled),
                    temperature.start_states_python(*args)):
        assert same_bits(a, b)


@needs_numba
def test_kernels_that_fail_or_differ_leave_the_python_planner_with_one_warning(monkeypatch, compiled):
    """No numba, a compiler error, a kernel one ulp off, one that draws once more, one
    that cuts still periods at another length: the Python code plans, the same schedule."""
    import types

    from selfcal.sim import _plan_jit

    cfg = SimConfig()
    monkeypatch.setenv("SELFCAL_NUMBA", "0")
    rng = np.random.default_rng(9)
    want, want_state = wearer.make_schedule(cfg, rng, 12.0), rng.bit_generator.state
    monkeypatch.setenv("SELFCAL_NUMBA", "1")

    def no_numba():
        raise ImportError("No module named 'numba'")

    def fails_to_compile():
        raise RuntimeError("Failed in nopython mode pipeline (step: nopython frontend)")

    def one_ulp_off(rng, total, *rest):
        rows, t, nxt = compiled.worn(rng, total, *rest)
        rows[len(rows) // 2, 0] = np.nextafter(rows[len(rows) // 2, 0], np.inf)
        return rows, t, nxt

    def one_draw_more(rng, total, *rest):
        out = compiled.worn(rng, total, *rest)
        rng.random()
        return out

    def pieces_of_an_hour(rng, total, par, *rest):
        par = par.copy()
        par[_plan_jit.P_MAX_STILL_PIECE_S] = 3600.0  # only the sitting wearer's stills reach it
        return compiled.worn(rng, total, par, *rest)

    def kernels(worn):
        return lambda: types.SimpleNamespace(worn=worn, start_states=compiled.start_states)

    assert plan_numba._same_plan(kernels(compiled.worn)())
    try:
        for load, warns in ((no_numba, False), (fails_to_compile, True), (kernels(one_ulp_off), True),
                            (kernels(one_draw_more), True), (kernels(pieces_of_an_hour), True)):
            monkeypatch.setattr(plan_numba, "_load", load)
            plan_numba.reset()
            if warns:
                with pytest.warns(RuntimeWarning, match="planning in Python"):
                    assert plan_numba.kernels() is None
            else:
                assert plan_numba.kernels() is None
            rng = np.random.default_rng(9)
            got = wearer.make_schedule(cfg, rng, 12.0)
            assert rng.bit_generator.state == want_state
            for f in dataclasses.fields(want):
                a, b = getattr(got, f.name), getattr(want, f.name)
                assert same_bits(a, b) if isinstance(b, np.ndarray) else a == b, f.name
    finally:
        monkeypatch.undo()
        plan_numba.reset()
