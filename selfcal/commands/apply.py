"""``selfcal apply REC --calibration CAL.json --out REC2``."""

from __future__ import annotations

import json
import sys
from dataclasses import replace

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from selfcal.errors import InputError
from selfcal.io import iter_recording, write_recording_blocks
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
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text (byte {exc.start}): not a calibration file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the calibration file ({exc.strerror or exc})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: a calibration file is a JSON object, got a {type(data).__name__}")
    try:
        return CalibrationFile(**data)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise InputError(f"{path}: field {'.'.join(map(str, first['loc']))}: {first['msg']}") from None


def run(args) -> int:
    """Calibrate a recording block by block (bounded memory) and write it in g."""
    from selfcal.commands.calibrate import check_writable

    check_writable(args.out, [args.recording, args.calibration])
    cal = load_calibration(args.calibration)
    model = ErrorModel(cal.model, cal.temp_ref_c, cal.t_ref_s)
    theta = model.from_dict(cal.params)
    matrix, _ = model.linear(theta)
    # |a| of every row in a histogram (1e-6 g bins over 0.5-1.5 g): the median without
    # keeping the rows
    edges_g = (0.5, 1.5)
    bins = np.zeros(1_000_002, dtype=np.int64)  # under, 1e6 bins, over

    from selfcal.pipeline import ByteProgress

    bar = ByteProgress(args.recording, "apply", sys.stderr.isatty())

    def calibrated():
        for rec in iter_recording(args.recording, progress=bar):
            if rec.unit != cal.unit:
                raise InputError(
                    f"{args.recording}: recording is in {rec.unit!r} but {args.calibration} was fitted on "
                    f"{cal.unit!r} data; calibrate this recording (or one in the same unit) first"
                )
            a_g = model.apply(theta, rec.acc, rec.temp_c, rec.t_s)
            sd = None if rec.sd is None else rec.sd * np.linalg.norm(matrix, axis=1)  # first-order
            norm = np.linalg.norm(a_g, axis=1)
            idx = np.clip(np.floor((norm - edges_g[0]) * 1e6).astype(np.int64) + 1, 0, bins.size - 1)
            bins[:] += np.bincount(idx, minlength=bins.size)
            yield replace(rec, unit="g", acc=a_g, sd=sd, path=args.out,
                          meta=dict(rec.meta, calibrated_with=args.calibration.replace("\n", " ")))

    try:
        rows = write_recording_blocks(args.out, calibrated())
    finally:
        bar.close()
    k = int(np.searchsorted(np.cumsum(bins), (rows + 1) // 2))
    median = edges_g[0] + (k - 0.5) / 1e6 if 0 < k < bins.size - 1 else float("nan")
    print(f"{args.out}: {rows} rows calibrated with {cal.model}; median |a| = {median:.5f} g")
    return 0
