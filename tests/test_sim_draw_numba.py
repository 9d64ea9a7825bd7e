"""The simulator's optional numba draws (selfcal.sim.draw_numba) are numpy's: the same
normals and low-pass noise from the same generator, the generator left in the same
state, every shape; a stream and a pose table drawn with them are the same bit for bit
as without them; a kernel one ulp or one draw off is refused at its check."""

from __future__ import annotations

import dataclasses
import importlib.util
from types import SimpleNamespace

import numpy as np
import pytest

from selfcal.sim import SimConfig, Simulation, draw_numba
from selfcal.sim.motion import lowpass_noise

needs_numba = pytest.mark.skipif(importlib.util.find_spec("numba") is None,
                                 reason="numba is not installed (pip install 'selfcal[fast]')")


@pytest.fixture
def kernels():
    """The kernels as compiled, not through their first-use check."""
    import numba

    if numba.config.DISABLE_JIT:
        pytest.skip("numba's JIT is disabled (NUMBA_DISABLE_JIT)")
    return draw_numba._load()


@needs_numba
@pytest.mark.parametrize("seed", [3, 2027])
def test_the_kernel_draws_numpys_numbers_and_leaves_numpys_state(kernels, seed):
    ours, theirs = np.random.default_rng(seed), np.random.default_rng(seed)
    for shape in (2_000, (5_000, 4), (1_500, 3), 999, (0, 4), (250_000,)):
        got = draw_numba.standard_normal(ours, shape, accelerate=kernels)
        want = theirs.standard_normal(shape)
        assert got.shape == want.shape and got.dtype == np.float64
        assert np.array_equal(got, want), shape
        assert ours.bit_generator.state == theirs.bit_generator.state, shape
        # the stream goes on the same by numpy's own draws too
        assert np.array_equal(ours.random(3), theirs.random(3))
    for n, dim, corner_hz in ((72_000, 4, 0.3), (3_000, 3, 1.5), (1, 3, 2.0), (2_000, 3, 1e7)):
        got = lowpass_noise(ours, n, 20.0, corner_hz, dim, accelerate=kernels)
        want = lowpass_noise(theirs, n, 20.0, corner_hz, dim, accelerate=False)
        assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want)), (n, dim)
        assert ours.bit_generator.state == theirs.bit_generator.state


def test_numpy_draws_where_the_kernel_is_not_given(monkeypatch):
    """No kernels, a few draws, or a bit generator other than PCG64: numpy's own call."""
    calls = []

    def fill(rng, out):  # pragma: no cover - it must not be called
        calls.append(out.shape)

    counting = SimpleNamespace(fill_standard_normal=fill, lowpass=fill)
    cases = [(np.random.default_rng(1), (10, 4), None),  # below _FEW, even when loaded
                        (np.random.Generator(np.random.MT19937(1)), (5_000, 3), counting),
                        (np.random.default_rng(1), (5_000, 3), False)]
    monkeypatch.setenv("SELFCAL_NUMBA", "1")
    monkeypatch.setattr(draw_numba.DRAWS, "_found", [counting])  # "loaded"
    for rng, shape, accelerate in cases:
        twin = np.random.Generator(type(rng.bit_generator)(1))
        got = draw_numba.standard_normal(rng, shape, accelerate=accelerate)
        assert np.array_equal(got, twin.standard_normal(shape))
    assert calls == []
    monkeypatch.setattr(draw_numba.DRAWS, "_found", [])


@needs_numba
def test_the_check_refuses_a_kernel_one_ulp_or_one_draw_off(kernels, monkeypatch):
    monkeypatch.setenv("SELFCAL_NUMBA", "1")
    assert draw_numba._same_as_numpy(kernels)

    def ulp_off(rng, out):
        kernels.fill_standard_normal(rng, out)
        if out.size > 50:
            flat = out.reshape(-1)
            flat[50] = np.nextafter(flat[50], np.inf)

    def one_more_draw(rng, out):
        kernels.fill_standard_normal(rng, out)
        if out.size > 50:
            rng.standard_normal()  # the values are right, the generator's state is not

    def lowpass_ulp_off(rng, n, dim, alpha, gain):
        out = kernels.lowpass(rng, n, dim, alpha, gain)
        out[-1, -1] = np.nextafter(out[-1, -1], -np.inf)
        return out

    for wrong in (SimpleNamespace(fill_standard_normal=ulp_off, lowpass=kernels.lowpass),
                  SimpleNamespace(fill_standard_normal=one_more_draw, lowpass=kernels.lowpass),
                  SimpleNamespace(fill_standard_normal=kernels.fill_standard_normal, lowpass=lowpass_ulp_off)):
        assert not draw_numba._same_as_numpy(wrong), wrong
        monkeypatch.setattr(draw_numba.DRAWS, "_load", lambda w=wrong: w)
        monkeypatch.setattr(draw_numba.DRAWS, "_found", [])
        with pytest.warns(RuntimeWarning, match="numba draws gave other results than the numpy code"):
            assert not draw_numba.load()
        assert draw_numba.kernels(draws=1e12) is None
    monkeypatch.setattr(draw_numba.DRAWS, "_found", [])


def _stream(cfg: SimConfig, seed: int, days: float) -> list:
    sim = Simulation(cfg, np.random.default_rng(seed), days=days)
    return [c for c in sim.iter_samples(chunk_s=1800)] + [sim.poses()]


@needs_numba
@pytest.mark.parametrize("seed,effects", [(11, ()), (12, ("temperature_bias", "scale_nonlinearity"))])
def test_a_stream_and_its_poses_are_the_same_with_and_without_the_kernel(kernels, monkeypatch, seed, effects):
    cfg = SimConfig().with_effects(list(effects)) if effects else SimConfig()
    monkeypatch.setenv("SELFCAL_NUMBA", "1")
    used = []  # loaded (every call takes them), and counting what they draw

    def fill(rng, out):
        used.append(out.size)
        kernels.fill_standard_normal(rng, out)

    def lowpass(rng, n, dim, alpha, gain):
        used.append(n * dim)
        return kernels.lowpass(rng, n, dim, alpha, gain)

    monkeypatch.setattr(draw_numba.DRAWS, "_found", [SimpleNamespace(fill_standard_normal=fill, lowpass=lowpass)])
    with_kernel = _stream(cfg, seed, 0.3)
    assert sum(used) > 8 * 0.3 * 86400 * 20 * 0.5  # most of the stream's draws went through it
    monkeypatch.setenv("SELFCAL_NUMBA", "0")
    without = _stream(cfg, seed, 0.3)
    assert len(with_kernel) == len(without) > 5
    for a, b in zip(with_kernel, without):
        for f in dataclasses.fields(a):
            x, y = getattr(a, f.name), getattr(b, f.name)
            if isinstance(x, np.ndarray):
                assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), f.name
    monkeypatch.setattr(draw_numba.DRAWS, "_found", [])


def test_a_long_stream_loads_the_kernel_and_a_short_one_does_not(monkeypatch):
    monkeypatch.setenv("SELFCAL_NUMBA", "1")
    monkeypatch.setattr(draw_numba.DRAWS, "_found", [])
    monkeypatch.setattr(draw_numba.DRAWS, "_load", lambda: SimpleNamespace())
    monkeypatch.setattr(draw_numba.DRAWS, "_same", lambda k: True)
    assert draw_numba.kernels(draws=draw_numba.LOAD_FOR_DRAWS - 1) is None and not draw_numba.DRAWS.loaded()
    assert draw_numba.kernels(draws=draw_numba.LOAD_FOR_DRAWS) is not None
    monkeypatch.setenv("SELFCAL_NUMBA", "0")
    assert draw_numba.kernels() is None
    monkeypatch.setattr(draw_numba.DRAWS, "_found", [])
