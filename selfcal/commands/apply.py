"""``selfcal apply REC --calibration CAL.json --out REC2``."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from selfcal.errors import InputError
from selfcal.io import read_recording, write_recording
from selfcal.models import ErrorModel


class CalibrationFile(BaseModel):
    """The fields of a calibration JSON that ``apply`` needs (others are kept, ignored)."""

    model_config = ConfigDict(extra="allow")

    model: str
    unit: str
    params: dict[str, float]
    temp_ref_c: float = 25.0
    t_ref_s: float = 0.0


def add_arguments(parser) -> None:
    parser.add_argument("recording", metavar="REC")
    parser.add_argument("--calibration", required=True, metavar="CAL.json")
    parser.add_argument("--out", required=True, metavar="REC2", help="output recording (specific force in g)")


def load_calibration(path: str) -> CalibrationFile:
    """Read and validate a calibration JSON; errors name the file and the field."""
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise InputError(f"{path}: calibration file not found") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}:{exc.lineno}:{exc.colno}: invalid JSON: {exc.msg}") from None
    try:
        return CalibrationFile(**data)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise InputError(f"{path}: field {'.'.join(map(str, first['loc']))}: {first['msg']}") from None


def run(args) -> int:
    from selfcal.commands.calibrate import check_writable

    check_writable(args.out)
    cal = load_calibration(args.calibration)
    model = ErrorModel(cal.model, cal.temp_ref_c, cal.t_ref_s)
    theta = model.from_dict(cal.params)
    rec = read_recording(args.recording)
    if rec.unit != cal.unit:
        raise InputError(
            f"{args.recording}: recording is in {rec.unit!r} but {args.calibration} was fitted on {cal.unit!r} data; "
            "calibrate this recording (or one in the same unit) first"
        )
    a_g = model.apply(theta, rec.acc, rec.temp_c, rec.t_s)
    sd = None
    if rec.sd is not None:
        matrix, _ = model.linear(theta)
        sd = rec.sd * np.linalg.norm(matrix, axis=1)  # first-order per-axis scaling
    out = replace(rec, unit="g", acc=a_g, sd=sd, path=args.out,
                  meta=dict(rec.meta, calibrated_with=args.calibration.replace("\n", " ")))
    write_recording(args.out, out)
    norm = np.linalg.norm(a_g, axis=1)
    print(f"{args.out}: {len(rec)} rows calibrated with {cal.model}; median |a| = {np.median(norm):.5f} g")
    return 0
