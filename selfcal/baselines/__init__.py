"""Comparison methods ("baselines") for the selfcal benchmarks.

Each baseline is a function of still-pose data::

    result = BASELINES[name](mean, sd=None, n_samples=None, t_s=None, temp_c=None, **options)

``mean`` (n, 3) is the raw specific force in any unit (g, m/s^2, counts); ``sd`` (n, 3)
the per-axis sd in the same unit, ``n_samples`` (n,), ``t_s`` (n,) s, ``temp_c`` (n,) degC
are optional and used only by methods that need them. Methods that need known
orientations (:func:`requires_known_orientation`) also take ``gravity_dir`` (n, 3) or
auto-classify axis-aligned poses.

Every method calibrates to a **unit norm**: the returned :class:`BaselineResult` maps
the input unit to g with ``a_cal_g = matrix @ (raw - offset)`` (+ a temperature term
for GGIR-type methods). Methods that assume g-scale data pre-scale internally (an
affine sphere-fit normalisation, mapped back exactly; option ``prescale``), except
``seed_lm``, which is a faithful port and works in the unit its ``g`` argument names.

The baselines are self-contained: they do not use ``selfcal.models`` / ``selfcal.fit``.

============== ===================================================================
name           method
============== ===================================================================
seed_lm        seed LM loop of lm-accelerometer-calibration.txt, defects included
lm_fixed       same model, correct residual/Jacobian, gain-ratio LM
lm_random_init insole paper: plain LM from a random [0, 1] start (triangular model)
insole_lm_ls   insole paper: LS initial-value correction on O_cor + LM on O_train
ellipsoid6     axis-aligned ellipsoid, linear LS (ellipsoid-fit-calibration.txt)
quadric9       general quadric a1x^2+...+a9z = 1, Cholesky calibration
six_face       min/max of the six +-axis faces (known orientations)
twelve_position 12-parameter linear LS with known orientations
da_lm          Dragonfly Algorithm + LM (da-lm-calibration.txt)
ggir_autocal   van Hees 2014 / GGIR g.calibrate, with temperature offset
ggir_actipy    actipy's calibrate_gravity (registered only if actipy imports)
imu_tk_style   IMU-TK-like 9-parameter norm fit, one LM start (scipy MINPACK)
============== ===================================================================
"""

from __future__ import annotations

import importlib.util
from typing import Callable

from ._common import BaselineResult, prescale_poses
from .da_lm import da_lm
from .ellipsoid import ellipsoid6, quadric9
from .ggir import ggir_actipy, ggir_autocal, ggir_sphere_coverage, ggir_still_mask
from .known_orientation import classify_faces, six_face, twelve_position
from .lm import classify_axis_aligned, imu_tk_style, insole_lm_ls, lm_fixed, lm_random_init
from .seed_lm import seed_lm

__all__ = [
    "BASELINES",
    "BaselineResult",
    "requires_known_orientation",
    "seed_lm",
    "lm_fixed",
    "lm_random_init",
    "insole_lm_ls",
    "ellipsoid6",
    "quadric9",
    "six_face",
    "twelve_position",
    "da_lm",
    "ggir_autocal",
    "ggir_actipy",
    "imu_tk_style",
    "ggir_still_mask",
    "ggir_sphere_coverage",
    "classify_faces",
    "classify_axis_aligned",
    "prescale_poses",
]

#: name -> function. ``ggir_actipy`` is present only when ``actipy`` is importable.
BASELINES: dict[str, Callable[..., BaselineResult]] = {
    "seed_lm": seed_lm,
    "lm_fixed": lm_fixed,
    "lm_random_init": lm_random_init,
    "insole_lm_ls": insole_lm_ls,
    "ellipsoid6": ellipsoid6,
    "quadric9": quadric9,
    "six_face": six_face,
    "twelve_position": twelve_position,
    "da_lm": da_lm,
    "ggir_autocal": ggir_autocal,
    "imu_tk_style": imu_tk_style,
}
if importlib.util.find_spec("actipy") is not None:
    BASELINES["ggir_actipy"] = ggir_actipy

_KNOWN_ORIENTATION = frozenset({"six_face", "twelve_position"})


def requires_known_orientation(name: str) -> bool:
    """Whether baseline ``name`` needs the true orientation of the poses.

    Such methods accept ``gravity_dir`` (n, 3) or auto-classify axis-aligned poses, and
    raise ``ValueError`` if the poses do not allow it. (``insole_lm_ls`` classifies
    its ``O_cor`` poses from the readings alone and does not need them.)

    Parameters
    ----------
    name : str
        A key of :data:`BASELINES` (or ``"ggir_actipy"``).

    Returns
    -------
    bool

    Raises
    ------
    KeyError
        For an unknown name.
    """
    if name not in BASELINES and name != "ggir_actipy":
        raise KeyError(f"unknown baseline {name!r}; known: {sorted(BASELINES)}")
    return name in _KNOWN_ORIENTATION
