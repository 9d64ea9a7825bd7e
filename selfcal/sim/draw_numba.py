"""An optional numba kernel of the simulator's normal draws: the same numbers, faster.

A 20-Hz stream draws 8 standard normals a sample and more (the sensor's white noise, the
pressure channels' noise and sway, the reported temperature, the foot's sway), ~14 M a
device-day: a third of the samples-level simulator's time. numpy's
``Generator.standard_normal`` takes ~10 ns a number here; numba's implementation of the
same method (numpy's ziggurat, on the same bit generator and its state) takes ~3 ns, and
gives the same numbers from the same state, and leaves the generator in the same state.
So a stream drawn with the kernel is the same bit for bit, and the draws after it are too.

:func:`standard_normal` is ``rng.standard_normal(shape)``, by the kernel when it is
loaded (:func:`load`; a stream of at least :data:`LOAD_FOR_DRAWS` normals loads it), else
by numpy. The first load compares the kernel with numpy on several generators, shapes and
interleavings (:func:`_same_as_numpy`) and refuses it, with a warning, if one number or the
generator's state differs. Only PCG64 generators (what ``np.random.default_rng`` makes,
and every stream of :class:`selfcal.sim.Simulation`) are given to it. numba is optional
(``pip install 'selfcal[fast]'``); ``SELFCAL_NUMBA=0`` turns it off.
"""

from __future__ import annotations

import numpy as np

from selfcal.numba_check import CheckedKernel, same_bits

#: Normals a simulation is about to draw from which it loads the kernel (:func:`kernel`):
#: its first load in a process (~0.1-0.5 s from numba's cache once numba is imported)
#: costs what numpy's draws lose over ~2 x 10^7 normals, about a day and a half of a 20-Hz stream.
LOAD_FOR_DRAWS = 20_000_000

#: Draws below this many go to numpy (the kernel's call costs ~10 us, ~1 000 numpy draws).
_FEW = 1_000


def _load():
    from selfcal.sim import _draw_jit

    return _draw_jit.fill_standard_normal


def kernel(draws: float | None = None):
    """The kernel if it is loaded and usable here, else None. ``draws``: the normals about
    to be drawn; at least :data:`LOAD_FOR_DRAWS` loads it (None never loads it)."""
    from selfcal.detect_numba import enabled

    if not enabled():
        return None
    if not NORMALS.loaded() and (draws is None or draws < LOAD_FOR_DRAWS):
        return None
    return NORMALS.get()


def load() -> bool:
    """Load and check the kernel now; whether it is used."""
    from selfcal.detect_numba import enabled

    return enabled() and NORMALS.get() is not None


def standard_normal(rng: np.random.Generator, shape, accelerate=None) -> np.ndarray:
    """``rng.standard_normal(shape)``: float64 standard normals of ``shape`` (int or tuple),
    the same numbers and the same generator state after, by the kernel when it is loaded.

    ``accelerate``: None takes the kernel if it is loaded (:func:`kernel`); False, numpy;
    or the kernel itself."""
    if accelerate is None:
        accelerate = kernel()
    out_shape = (shape,) if np.ndim(shape) == 0 else tuple(shape)
    size = int(np.prod(out_shape, dtype=np.int64))
    if (accelerate is None or accelerate is False or size < _FEW
            or type(rng.bit_generator) is not np.random.PCG64):
        return rng.standard_normal(out_shape)
    out = np.empty(out_shape)
    accelerate(rng, out)
    return out


def _same_as_numpy(fill) -> bool:
    """Whether the kernel draws numpy's numbers and leaves the generator in numpy's state:
    three generators (one spawned as the simulator's streams are), shapes of 1 to 300 000
    values (the ziggurat's rare tail steps among them), kernel and numpy draws interleaved."""
    shapes = [(1,), (7,), (4, 3), (100_000, 4), (33, 1), (0, 4), (300_000,)]
    for seed in (0, 2026, np.random.SeedSequence(7).spawn(3)[2]):
        ours, theirs = np.random.default_rng(seed), np.random.default_rng(seed)
        for i, shape in enumerate(shapes):
            want = theirs.standard_normal(shape)
            got = np.empty(shape)
            fill(ours, got)
            if not same_bits(got, want):
                return False
            if i % 2:  # numpy's own draws between the kernel's: the same stream on
                if not same_bits(ours.random(5), theirs.random(5)):
                    return False
        if ours.bit_generator.state != theirs.bit_generator.state:
            return False
    return True


#: The kernel, loaded and checked once per process.
NORMALS = CheckedKernel("the simulator's numba normal draws", _load, _same_as_numpy)
