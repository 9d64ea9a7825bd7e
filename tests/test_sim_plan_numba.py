"""The simulator planner's optional numba kernels (selfcal.sim.plan_numba) plan what its
Python code does, bit for bit: every column of a schedule and the generator's state
after it, for several wearers, lengths and configurations; a kernel that fails or
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

CONFIGS = {
    "default": {},
    # every state can follow every other, long walks common, the rarer sitting postures common
    "busy": {"activity": {"from_sit": {"stand": 0.5, "walk": 0.3, "stairs": 0.2},
                          "from_stairs": {"walk": 0.4, "stand": 0.3, "sit": 0.1, "stairs": 0.2},
                          "walk_long_fraction": 0.5},
             "posture": {"sit_flat_p": 0.1, "sit_heel_p": 0.3, "sit_toes_p": 0.3, "sit_crossed_p": 0.3,
                         "stand_tilt_sd_deg": 0.0, "sit_sway_sd_mg": 0.0}},
    # short bouts: many postures an hour, and still pieces split at the 30-min bound
    "sitting": {"activity": {"from_stand": {"sit": 1.0}, "sit": {"median_s": 7200, "gsd": 1.5, "min_s": 60,
                                                                 "max_s": 10800}},
                "posture": {"sit_quiet": {"median_s": 2400, "gsd": 2.0, "min_s": 1, "max_s": 7200}}},
}


def schedule(monkeypatch, on: bool, cfg: SimConfig, seed: int, days: float):
    """The schedule and the generator's state after it, by the kernels as compiled (not
    through their first-use check, which would hide a kernel that differs) or in Python."""
    monkeypatch.setattr(plan_numba, "kernels", (lambda days=None: plan_numba._load()) if on else lambda days=None: None)
    rng = np.random.default_rng(seed)
    return wearer.make_schedule(cfg, rng, days), rng.bit_generator.state


@needs_numba
@pytest.mark.parametrize("name", sorted(CONFIGS))
@pytest.mark.parametrize("seed, days", [(1, 0.2), (2, 1.0), (3, 4.5)])
def test_the_kernels_plan_the_python_schedule_bit_for_bit(monkeypatch, name, seed, days):
    cfg = SimConfig.from_section(CONFIGS[name])
    fast, fast_state = schedule(monkeypatch, True, cfg, seed, days)
    slow, slow_state = schedule(monkeypatch, False, cfg, seed, days)
    assert len(fast) > 0 and len(fast) == len(slow)
    for f in dataclasses.fields(slow):
        a, b = getattr(fast, f.name), getattr(slow, f.name)
        if isinstance(b, np.ndarray):
            assert a.dtype == b.dtype, f.name
            assert np.array_equal(a, b, equal_nan=True), f.name
            assert np.array_equal(np.signbit(a), np.signbit(b)), f.name
        else:
            assert a == b, f.name
    assert fast_state == slow_state  # the draws after the plan (the simulation's) are the same


@needs_numba
def test_the_kernels_pass_their_first_use_check_where_numba_is(monkeypatch, recwarn):
    monkeypatch.setenv("SELFCAL_NUMBA", "1")
    plan_numba._checked.cache_clear()
    assert plan_numba.kernels() is not None
    assert not [w for w in recwarn if "planner" in str(w.message)]
    monkeypatch.setenv("SELFCAL_NUMBA", "0")
    assert plan_numba.kernels() is None


@needs_numba
def test_a_short_plan_does_not_load_the_kernels_but_uses_them_once_loaded(monkeypatch):
    """Below LOAD_FOR_DAYS the first load is not paid for one plan; once loaded they are used."""
    monkeypatch.setenv("SELFCAL_NUMBA", "1")
    plan_numba._checked.cache_clear()
    try:
        assert plan_numba.kernels(plan_numba.LOAD_FOR_DAYS / 2) is None
        assert plan_numba._checked.cache_info().currsize == 0
        assert plan_numba.kernels(plan_numba.LOAD_FOR_DAYS) is not None
        assert plan_numba.kernels(0.1) is not None
    finally:
        plan_numba._checked.cache_clear()


@needs_numba
def test_the_temperature_recurrence_kernel_gives_the_python_states():
    rng = np.random.default_rng(4)
    m = 5000
    args = (rng.uniform(1, 8000, m), rng.uniform(10, 36, m), np.where(rng.random(m) < 0.3, 3.0, 0.0),
            rng.uniform(200, 4000, m), rng.uniform(60, 600, m), rng.random(m) < 0.5, 19.0)
    for a, b in zip(temperature.segment_start_states(*args, kernel=plan_numba._load()),
                    temperature.start_states_python(*args)):
        assert np.array_equal(a, b)


@needs_numba
def test_kernels_that_fail_or_differ_leave_the_python_planner_with_one_warning(monkeypatch):
    """No numba, a compiler error, a kernel one ulp off: the Python code plans, the same
    schedule; the first-use check sees a kernel that differs in one row or one draw."""
    import types

    cfg = SimConfig()
    monkeypatch.setenv("SELFCAL_NUMBA", "0")
    rng = np.random.default_rng(9)
    want, want_state = wearer.make_schedule(cfg, rng, 1.5), rng.bit_generator.state
    monkeypatch.setenv("SELFCAL_NUMBA", "1")

    def no_numba():
        raise ImportError("No module named 'numba'")

    def fails_to_compile():
        raise RuntimeError("Failed in nopython mode pipeline (step: nopython frontend)")

    def python_worn(rng, total, *rest):  # the Python planner, behind the kernel's signature
        return _python_as_kernel(rng, total, *rest)

    def one_ulp_off(rng, total, *rest):
        rows, t, nxt = python_worn(rng, total, *rest)
        rows[len(rows) // 2, 0] = np.nextafter(rows[len(rows) // 2, 0], np.inf)
        return rows, t, nxt

    def one_draw_more(rng, total, *rest):
        out = python_worn(rng, total, *rest)
        rng.random()
        return out

    def kernels(worn):
        return lambda: types.SimpleNamespace(
            worn=worn, start_states=lambda eh, et, ratio, base, ht, on, t0: _states_from_terms(eh, et, ratio, base,
                                                                                             ht, on, t0))

    assert plan_numba._same_plan(kernels(python_worn)())  # the check passes the Python code itself
    try:
        for load, warns in ((no_numba, False), (fails_to_compile, True), (kernels(one_ulp_off), True),
                            (kernels(one_draw_more), True)):
            monkeypatch.setattr(plan_numba, "_load", load)
            plan_numba._checked.cache_clear()
            if warns:
                with pytest.warns(RuntimeWarning, match="planning in Python"):
                    assert plan_numba.kernels() is None
            else:
                assert plan_numba.kernels() is None
            rng = np.random.default_rng(9)
            got = wearer.make_schedule(cfg, rng, 1.5)
            assert rng.bit_generator.state == want_state
            for f in dataclasses.fields(want):
                a, b = getattr(got, f.name), getattr(want, f.name)
                assert np.array_equal(a, b, equal_nan=True) if isinstance(b, np.ndarray) else a == b, f.name
    finally:
        monkeypatch.undo()
        plan_numba._checked.cache_clear()


def _python_as_kernel(rng, total, par, sit_cdf, next_code, next_cdf, next_len, t, orient, load, last, next_still):
    """``_Builder.worn_python`` with the kernel's inputs and outputs (its state from them)."""
    b = wearer._Builder(SimConfig(), np.random.default_rng(0))  # (its own draw of the shoe's pitch)
    b.rng = rng
    b.t, b.orient, b.load, b.next_still = t, (float(orient[0]), float(orient[1])), tuple(load), int(next_still)
    if last[0] >= 0:
        b.rows.append((0.0, 0, int(last[0]), last[1], last[2], last[1], last[2]) + (0.0,) * 9 + (last[3],))
    n0 = len(b.rows)
    b._kernel_inputs = None
    b.shoe_pitch = par[37]
    b.worn_python(total)
    orient[:] = b.orient
    load[:] = b.load
    return np.array(b.rows[n0:], dtype=float).reshape(-1, len(wearer._COLUMNS)), b.t, b.next_still


def _states_from_terms(eh, et, ratio, base, ht, on, t0):
    """``start_states``' recurrence in Python, from the kernel's inputs."""
    m = len(eh)
    temp0, heat0 = np.empty(m), np.empty(m)
    t, h = t0, 0.0
    for i in range(m):
        temp0[i], heat0[i] = t, h
        b = (h - ht[i]) * ratio[i] if on[i] else 0.0
        c = t - base[i] - b
        t = base[i] + b * eh[i] + c * et[i]
        h = ht[i] + (h - ht[i]) * eh[i]
    return temp0, heat0
