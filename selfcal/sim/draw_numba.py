"""Optional numba kernels of the simulator's random draws: the same numbers, faster.

A 20-Hz stream draws 8 standard normals a sample and more (the sensor's white noise, the
pressure channels' noise and sway, the reported temperature, the foot's sway), ~14 M a
device-day: a third of the samples-level simulator's time. numpy's
``Generator.standard_normal`` takes ~10 ns a number here; numba's implementation of the
same method (numpy's ziggurat, on the same bit generator and its state) takes ~3 ns, and
gives the same numbers from the same state, and leaves the generator in the same state.

The kernels (:mod:`selfcal.sim._draw_jit`) are those draws, and the low-pass noise of the
foot's sway and the pressure channels (:func:`selfcal.sim.motion.lowpass_noise`: the draws
and ``scipy.signal.lfilter``'s recurrence in one pass, 1.5 against 2.3 ms for an hour of 4
channels). They do the numpy code's operations in the same order (no fastmath, and no
function numpy computes with its own SIMD code: exp and log differ in the last bit here),
so a stream drawn with them is the same bit for bit, and so are the draws after it. (The
arithmetic of the read-out, the reported temperature and the pressure noise was tried as
kernels too: 0.0-0.25 ms an hour of samples better than numpy's passes, not worth a kernel.)

They are used once loaded (:func:`load`; a stream of at least :data:`LOAD_FOR_DRAWS`
normals loads them). The first load compares each with the numpy code on several
generators, shapes and values (:func:`_same_as_numpy`) and refuses them, with a warning,
if one number or the generator's state differs. Only PCG64 generators (what
``np.random.default_rng`` makes, and every stream of :class:`selfcal.sim.Simulation`) are
given to them. numba is optional (``pip install 'selfcal[fast]'``); ``SELFCAL_NUMBA=0``
turns them off.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from selfcal.numba_check import CheckedKernel, same_bits

#: Normals a simulation is about to draw from which it loads the kernels (:func:`kernels`):
#: their first load in a process (~0.1-0.5 s from numba's cache once numba is imported)
#: costs what numpy's draws lose over ~2 x 10^7 normals, about a day and a half of a 20-Hz stream.
LOAD_FOR_DRAWS = 20_000_000

#: Draws below this many go to numpy (the kernel's call costs ~10 us, ~1 000 numpy draws).
_FEW = 1_000


def _load() -> SimpleNamespace:
    from selfcal.sim import _draw_jit

    return SimpleNamespace(**{name: getattr(_draw_jit, name) for name in KERNELS})


#: The kernels of :mod:`selfcal.sim._draw_jit`.
KERNELS = ("fill_standard_normal", "lowpass")


def kernels(draws: float | None = None) -> SimpleNamespace | None:
    """The kernels if they are loaded and usable here, else None. ``draws``: the normals
    about to be drawn; at least :data:`LOAD_FOR_DRAWS` loads them (None never loads them)."""
    return DRAWS.available(load=draws is not None and draws >= LOAD_FOR_DRAWS)


def for_draws(rng: np.random.Generator, size: int, accelerate=None) -> SimpleNamespace | None:
    """The kernels to draw ``size`` numbers from ``rng`` with, or None for numpy's code.

    ``accelerate``: None takes them if they are loaded (:func:`kernels`), for ``size`` of at
    least :data:`_FEW` (a kernel call costs ~10 us); False never; or the kernels to use
    (the check's way of giving them). A bit generator other than PCG64 always gets None."""
    if accelerate is False or type(rng.bit_generator) is not np.random.PCG64:
        return None
    if accelerate is None:
        return kernels() if size >= _FEW else None
    return accelerate


def load() -> bool:
    """Load and check the kernels now; whether they are used."""
    return DRAWS.available(load=True) is not None


def standard_normal(rng: np.random.Generator, shape, accelerate=None) -> np.ndarray:
    """``rng.standard_normal(shape)``: float64 standard normals of ``shape`` (int or tuple),
    the same numbers and the same generator state after, by the kernel when it is loaded
    (``accelerate``: see :func:`for_draws`)."""
    out_shape = (shape,) if np.ndim(shape) == 0 else tuple(shape)
    found = for_draws(rng, int(np.prod(out_shape, dtype=np.int64)), accelerate)
    if found is None:
        return rng.standard_normal(out_shape)
    out = np.empty(out_shape)
    found.fill_standard_normal(rng, out)
    return out


def _same_as_numpy(k: SimpleNamespace) -> bool:
    """Whether the kernels give the numpy code's values bit for bit and leave the generator
    in its state: the normals from three generators (one spawned as the simulator's streams
    are), 1 to 300 000 of them (the ziggurat's rare tail steps among them), numpy's own
    draws between the kernel's; the low-pass noise of 3 and 4 columns, short and long,
    filtered and not."""
    from selfcal.sim.motion import lowpass_noise

    def same_twice(draw) -> bool:
        """``draw(rng, accelerate)`` by numpy and by the kernels from twin generators."""
        for seed in (0, 2026, np.random.SeedSequence(7).spawn(3)[2]):
            theirs, ours = np.random.default_rng(seed), np.random.default_rng(seed)
            with np.errstate(all="ignore"):
                want, got = draw(theirs, False), draw(ours, k)
            if not (same_bits(got, want) and same_bits(ours.random(3), theirs.random(3))):
                return False
            if ours.bit_generator.state != theirs.bit_generator.state:
                return False
        return True

    for shape in ((1,), (7,), (4, 3), (100_000, 4), (33, 1), (0, 4), (300_000,)):
        if not same_twice(lambda rng, acc: standard_normal(rng, shape, acc)):
            return False
    for n, dim, corner_hz in ((1, 4, 0.3), (5, 3, 2.0), (20_000, 4, 0.3), (20_000, 3, 1.5), (50, 3, 1e6)):
        if not same_twice(lambda rng, acc: lowpass_noise(rng, n, 20.0, corner_hz, dim, accelerate=acc)):
            return False
    return True


#: The kernels, loaded and checked once per process.
DRAWS = CheckedKernel("the simulator's numba draws", _load, _same_as_numpy)
