"""Optional numba kernel of the error models' residuals and Jacobian: the same values, faster.

:meth:`selfcal.models.ErrorModel.residual_jac` is the innermost call of every fit (each
Levenberg-Marquardt evaluation, the curvature probes, the held-out checks): about thirty
numpy operations over (n, 3) arrays. For ``scale6`` and ``affine9`` with any effects, the
kernel (:mod:`selfcal._model_jit`) computes them row by row in one pass, the same
expressions in the same order, so its residuals and Jacobian are numpy's bit for bit, and
every fit, published version and replay is the same with or without it. A second kernel
(:func:`whitening_kernel`) does a whole Levenberg-Marquardt evaluation of a fit whose noise
follows the scales (:meth:`selfcal.fit.NoiseModel.whitened`: the residuals, the Jacobian
and both divided by sigma, ~15 array operations) in one call, checked the same way. At its first load
in a process it is compiled (or loaded from numba's cache) and compared with the numpy
code on every model of :data:`CHECK_MODELS`; if anything differs, or numba fails, the
numpy code runs, with one warning.

Loading costs a few tenths of a second from numba's cache (seconds to compile into an
empty one), about what the numpy code spends on ~20 000 rows: a call with fewer rows than
:data:`LOAD_FOR_ROWS` uses the kernel only once something loaded it (:func:`load`: the
replays, the service's refit workers).

numba is optional (``pip install 'selfcal[fast]'``); ``SELFCAL_NUMBA=0`` switches these
kernels off as it does the detector's (:mod:`selfcal.detect_numba`).
"""

from __future__ import annotations

import numpy as np

from selfcal.numba_check import CheckedKernel, same_bits

#: A call with fewer rows uses the kernel only if it is loaded already.
LOAD_FOR_ROWS = 2000

#: The models of the first-use check: each base without effects, every effect alone, and
#: combinations of several (the kernel's branches are per effect).
CHECK_MODELS = (
    "scale6", "affine9",
    "affine9+temperature_bias", "affine9+temperature_scale", "affine9+time_drift_bias",
    "affine9+scale_nonlinearity", "affine9+temperature_cross", "affine9+bias_step",
    "scale6+temperature_bias+temperature_scale+time_drift_bias+scale_nonlinearity+bias_step",
    "affine9+temperature_bias+temperature_scale+time_drift_bias+scale_nonlinearity+temperature_cross+bias_step",
    "affine9+temperature_bias+temperature_cross",
)


def _load_residual_jac():
    from selfcal import _model_jit

    return _model_jit.residual_jac


def _load_whitening():
    from selfcal import _model_jit

    return _model_jit.whitened_residual_jac


def kernel(n_rows: int = 0):
    """The kernel ``residual_jac`` of :mod:`selfcal._model_jit`, or None: numba missing,
    switched off by ``SELFCAL_NUMBA``, not numpy's results here, or not loaded yet and
    ``n_rows`` below :data:`LOAD_FOR_ROWS`."""
    return RESIDUAL_JAC.available(load=n_rows >= LOAD_FOR_ROWS)


def whitening_kernel(n_rows: int = 0):
    """The kernel ``whitened_residual_jac`` of :mod:`selfcal._model_jit` (the residuals and
    Jacobian whitened by a :class:`selfcal.fit.NoiseModel`, one call per Levenberg-Marquardt
    evaluation), or None: as :func:`kernel`, or not the numpy code's values here."""
    if kernel(n_rows) is None:
        return None
    return WHITENING.get()


def load() -> bool:
    """Load and check the kernels now (a process about to run many fits); whether the
    residual kernel is used."""
    used = kernel(LOAD_FOR_ROWS) is not None
    whitening_kernel(LOAD_FOR_ROWS)
    return used


def loaded() -> bool:
    """Whether the kernel was loaded and checked (or found unusable) in this process."""
    return RESIDUAL_JAC.loaded()


def reset() -> None:
    """Forget the loaded kernels (tests)."""
    RESIDUAL_JAC.reset()
    WHITENING.reset()


def _same_as_numpy(kern) -> bool:
    """Whether ``kern`` gives the numpy code's residuals and Jacobian bit for bit (the signs
    of zeros included) on every model of :data:`CHECK_MODELS`, at random parameters and
    readings (rows with zeros, a row of -0.0) and with a layout the fits pass (a column
    slice)."""
    for model, n, raw, theta, temp, t_s in _check_cases(2024, 37):
        big = np.empty((n, 5))
        big[:, 1:4] = raw
        for rows in (raw, big[:, 1:4]):
            want = model.residual_jac(theta, rows, temp, t_s, accelerate=False)
            got = model.residual_jac(theta, rows, temp, t_s, accelerate=kern)
            if not (same_bits(got[0], want[0]) and same_bits(got[1], want[1])):
                return False
    return True


def _check_cases(seed: int, n: int):
    """``(model, n, raw (n, 3), theta, temp_c (n,), t_s (n,))``, 3 per model of
    :data:`CHECK_MODELS`: readings near the axes and between them, a row of zeros and one
    of -0.0, parameters near nominal, temperatures and times across the effects' ranges."""
    from selfcal.models import ErrorModel

    rng = np.random.default_rng(seed)
    for name in CHECK_MODELS:
        model = ErrorModel(name, temp_ref_c=25.0, t_ref_s=1e5, t_step_s=3e5)
        for trial in range(3):
            raw = rng.normal(0.0, 0.6, (n, 3)) + rng.choice([-1.0, 1.0], (n, 3)) * (rng.random((n, 3)) < 0.4)
            raw[3] = 0.0
            raw[4] = -0.0
            theta = model.nominal() + rng.normal(0.0, 0.05, model.n_params)
            yield model, n, raw, theta, rng.uniform(-10.0, 45.0, n), rng.uniform(0.0, 6e5, n)


def _same_whitening_as_numpy(kern) -> bool:
    """Whether ``kern`` gives :meth:`selfcal.fit.NoiseModel.whitened`'s numpy values bit
    for bit (residuals, Jacobian and both whitened) on every model of :data:`CHECK_MODELS`,
    with noise weights as a robust fit scales them (one near zero: a rejected pose)."""
    from selfcal.fit import NoiseModel

    rng = np.random.default_rng(2025)
    for model, n, raw, theta, temp, t_s in _check_cases(2025, 41):
        weights = rng.uniform(0.1, 1.0, n)
        weights[5] = 1e-12
        noise = NoiseModel(rng.uniform(0.0, 4e-6, (n, 3)), float(rng.choice([0.0, 1e-6])), None).scaled(weights)
        with np.errstate(all="ignore"):
            want = noise.whitened(model, theta, raw, temp, t_s, accelerate=False)
            got = noise.whitened(model, theta, raw, temp, t_s, accelerate=kern)
        if not all(same_bits(g, w) for g, w in zip(got, want)):
            return False
    return True


#: The two kernels, each loaded and checked once per process.
RESIDUAL_JAC = CheckedKernel("the error models' numba kernel", _load_residual_jac, _same_as_numpy)
WHITENING = CheckedKernel("the error models' whitening kernel", _load_whitening, _same_whitening_as_numpy)
