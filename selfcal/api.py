"""The small public Python API: ``read``, ``calibrate``, ``Calibration``, ``load_calibration``, ``diagnose``.

In the style of the field's libraries (imucal's calibration object; tpcp's
"parameters in ``__init__``, one action method, results in ``*_``" for the online
calibrator):

    import selfcal
    rec = selfcal.read("data/imutk-xsens-multipose/samples.csv")
    cal = selfcal.calibrate(rec, model="affine9")
    acc_g = cal.apply(rec.acc)                      # (n, 3) in g
    cal.save("cal.json"); same = selfcal.load_calibration("cal.json")

A :class:`Calibration` is an immutable value: the contract JSON of the design
(``format: selfcal-calibration``), with its parameters in the recording's unit. Files
written by any release carry ``format_version``; this release reads version 1.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from selfcal.errors import CalibrationError, InputError
from selfcal.models import ErrorModel

#: Calibration file format versions this release reads.
READABLE_FORMAT_VERSIONS = (1,)


@dataclass(frozen=True)
class Calibration:
    """A published calibration: ``a_g = matrix @ (raw - offset)`` plus the model's effects.

    Attributes
    ----------
    model : str — error model (``"affine9"``, ``"affine9+temperature_bias"``...)
    unit : str — unit of the raw readings it applies to (``g``, ``mps2``, ``counts``)
    params, std : dict name -> float — parameters and their standard deviations (raw unit)
    status : str — ``provisional`` or ``calibrated`` (a promise: see README)
    predicted_sphere_rms_mg : float or None — whole-sphere calibrated-norm RMS error the
        covariance predicts, mg, with what the effects the model lacks could add
        (``data["unmodelled"]``: their names and share, mg, as what the poses leave open and
        what they say the effects are; ``data["predicted_sphere_rms_mg_model"]``: the model's own)
    temp_ref_c, t_ref_s : float — reference temperature (degC) and time origin (s) of effects
    data : dict — the whole contract JSON (every other field, unchanged)
    """

    model: str
    unit: str
    params: dict[str, float]
    std: dict[str, float]
    status: str
    predicted_sphere_rms_mg: float | None
    temp_ref_c: float = 25.0
    t_ref_s: float = 0.0
    data: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    # ------------------------------------------------------------------ views
    def _model(self) -> ErrorModel:
        return ErrorModel(self.model, self.temp_ref_c, self.t_ref_s)

    @property
    def theta(self) -> np.ndarray:
        """Parameter vector (p,) in the model's order (raw unit)."""
        return self._model().from_dict(self.params)

    @property
    def matrix(self) -> np.ndarray:
        """Linear part (3, 3), g per raw unit."""
        return self._model().linear(self.theta)[0]

    @property
    def offset(self) -> np.ndarray:
        """Offset (3,), raw unit."""
        return self._model().linear(self.theta)[1]

    def apply(self, acc, temp_c=None, t_s=None) -> np.ndarray:
        """Calibrated specific force (n, 3) in g from raw readings ``acc`` (n, 3) in ``unit``.

        ``temp_c`` (n,) degC and ``t_s`` (n,) s are needed by temperature and drift effects.
        """
        acc = np.asarray(acc, dtype=float)
        if acc.ndim != 2 or acc.shape[1] != 3:
            raise InputError(f"apply: acc must have shape (n, 3), got {acc.shape}")
        return self._model().apply(self.theta, acc, temp_c, t_s)

    # ------------------------------------------------------------------ files
    def to_json(self) -> str:
        """The contract JSON text."""
        return json.dumps(self.to_dict(), indent=2)

    def to_dict(self) -> dict[str, Any]:
        """The contract JSON as a dict (the fields above over ``data``)."""
        out = dict(self.data)
        out.update(format="selfcal-calibration", format_version=out.get("format_version", 1), model=self.model,
                   unit=self.unit, params=dict(self.params), std=dict(self.std), status=self.status,
                   predicted_sphere_rms_mg=self.predicted_sphere_rms_mg, temp_ref_c=self.temp_ref_c,
                   t_ref_s=self.t_ref_s, matrix=self.matrix.tolist(), offset=self.offset.tolist())
        return out

    @classmethod
    def from_json(cls, text: str | dict, source: str = "calibration") -> "Calibration":
        """Parse contract JSON (text or dict); errors name ``source`` and the field."""
        try:
            d = json.loads(text) if isinstance(text, (str, bytes)) else dict(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"{source}:{exc.lineno}:{exc.colno}: invalid JSON: {exc.msg}") from None
        if d.get("format", "selfcal-calibration") != "selfcal-calibration":
            raise InputError(f"{source}: not a selfcal calibration (format {d.get('format')!r})")
        version = d.get("format_version", 1)
        if version not in READABLE_FORMAT_VERSIONS:
            raise InputError(f"{source}: calibration format_version {version!r}; this release reads "
                             f"{list(READABLE_FORMAT_VERSIONS)}")
        for key in ("model", "unit", "params"):
            if key not in d:
                raise InputError(f"{source}: field {key!r} is missing")
        try:
            model = ErrorModel(d["model"], float(d.get("temp_ref_c", 25.0)), float(d.get("t_ref_s", 0.0)))
            params = {str(k): float(v) for k, v in d["params"].items()}
            model.from_dict(params)
            std = {str(k): float(v) for k, v in (d.get("std") or {}).items() if v is not None}
        except (TypeError, ValueError, AttributeError) as exc:
            raise InputError(f"{source}: {exc}") from None
        pred = d.get("predicted_sphere_rms_mg")
        return cls(model.name, str(d["unit"]), params, std, str(d.get("status", "provisional")),
                   None if pred is None else float(pred), model.temp_ref_c, model.t_ref_s, d)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the contract JSON to ``path`` (atomic replace); returns the path."""
        p = Path(path)
        if not p.parent.is_dir():
            raise InputError(f"{path}: directory {str(p.parent)!r} does not exist")
        tmp = p.with_name(p.name + ".tmp")
        tmp.write_text(self.to_json() + "\n", encoding="utf-8")
        os.replace(tmp, p)
        return p


def load_calibration(path: str | os.PathLike) -> Calibration:
    """Read a calibration JSON file written by ``Calibration.save`` or ``selfcal calibrate --out``."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: calibration file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    return Calibration.from_json(text, source=os.fspath(path))


def read(path: str | os.PathLike):
    """Read a recording (selfcal CSV contract) into a :class:`selfcal.io.Recording`."""
    from selfcal.io import read_recording

    return read_recording(path)


def calibrate(recording, model: str = "affine9", config: dict | str | os.PathLike | None = None,
              progress: bool = False, fixed_model: bool = False) -> Calibration:
    """Calibrate a recording (a ``Recording`` or a path) with the online calibrator.

    Parameters
    ----------
    recording : Recording or path — samples or poses, in g, m/s² or raw counts
    model : str — error model to start from; online model selection may add an effect the
        poses support (or drop one it added): ``Calibration.model`` says which it ended on
    config : dict (loaded) or path of a TOML file overriding the defaults, or None
    progress : bool — progress bar on stderr
    fixed_model : bool — keep ``model`` as it is (no online model selection)

    Returns
    -------
    Calibration — in the recording's unit

    Raises
    ------
    CalibrationError — nothing could be published (``.reason`` says why)
    InputError — a bad file or argument
    """
    from selfcal.config import load_config
    from selfcal.pipeline import calibrate_path, calibrate_recording

    ErrorModel(model)
    cfg = dict(config) if isinstance(config, dict) else load_config(config)
    if fixed_model:
        cfg["selection"] = dict(cfg.get("selection") or {}, enabled=False)
    if isinstance(recording, (str, os.PathLike)):  # a file is streamed in blocks (bounded memory)
        run = calibrate_path(recording, model, cfg, progress=progress)
        source = os.fspath(recording)
    else:
        run = calibrate_recording(recording, model, cfg, progress=progress)
        source = str(recording.path)
    if run.calibration is None:
        last = run.last_refit or {}
        raise CalibrationError(last.get("reason") or "no_still_poses", last.get("message") or "no still window found")
    return Calibration.from_json(run.calibration, source=source)


def diagnose(recording, config: dict | str | os.PathLike | None = None, base_model: str = "affine9") -> dict:
    """What the base model misses on a recording: the diagnosis report (dict, as ``selfcal diagnose --json``)."""
    from selfcal.config import load_config
    from selfcal.diagnosis import diagnose_recording

    cfg = config if isinstance(config, dict) else load_config(config)
    report, _ = diagnose_recording(recording, cfg, base_model)  # a path is streamed
    report.pop("_arrays", None)
    return report
