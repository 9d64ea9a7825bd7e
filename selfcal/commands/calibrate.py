"""``selfcal calibrate REC [--model NAME] [--json] [--out CAL.json]``."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from selfcal.config import load_config
from selfcal.errors import CalibrationError, InputError
from selfcal.io import read_recording
from selfcal.models import ErrorModel


def add_arguments(parser) -> None:
    parser.add_argument("recording", metavar="REC", help="recording CSV (kind=samples or kind=poses)")
    parser.add_argument("--model", default="affine9", help="error model (scale6, affine9, affine9+effect...)")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument("--out", metavar="CAL.json", help="write the calibration JSON here")
    parser.add_argument("--history", metavar="FILE.jsonl",
                        help="write every published version here, one calibration JSON a line, in time order")
    parser.add_argument("--progress", action="store_true", help="progress bar on stderr")


def check_writable(path: str) -> None:
    """Raise InputError unless ``path`` can be written (its directory must exist)."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{path}: is a directory, not a file")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"{path}: directory {str(parent)!r} does not exist")
    if not os.access(parent, os.W_OK):
        raise InputError(f"{path}: directory {str(parent)!r} is not writable")


def write_history(path: str, result) -> int:
    """Write every published version of a run as JSON lines (recording unit); returns the count."""
    from selfcal.pipeline import version_in_unit

    n = 0
    tmp = Path(path).with_name(Path(path).name + ".tmp")
    with tmp.open("w", encoding="utf-8") as fh:
        for ev in result.events:
            if not ev.get("published") or ev.get("calibration") is None:
                continue
            c = version_in_unit(ev["calibration"], result.calibrator.model, result.normalizer, result.unit)
            fh.write(json.dumps(c, separators=(",", ":")) + "\n")
            n += 1
    os.replace(tmp, path)
    return n


def run(args) -> int:
    from selfcal.pipeline import calibrate_recording

    ErrorModel(args.model)  # validate the name before reading anything
    cfg = load_config(args.config)
    for target in (args.out, args.history):  # fail before the work, not after it
        if target:
            check_writable(target)
    rec = read_recording(args.recording)
    result = calibrate_recording(rec, args.model, cfg, progress=args.progress or sys.stderr.isatty())
    if args.history:
        write_history(args.history, result)
    out = {
        "recording": args.recording,
        "status": result.status,
        "n_windows": result.n_windows,
        "last_refit": result.last_refit,
        "notes": result.notes,
    }
    if result.calibration is None:
        reason = result.last_refit["reason"] if result.last_refit else "no_still_poses"
        message = result.last_refit["message"] if result.last_refit else "no still window was found"
        if args.json:
            print(json.dumps(dict(out, calibration=None, reason=reason, message=message)))
        raise CalibrationError(reason, f"{args.recording}: no calibration published: {message}")
    cal = result.calibration
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            json.dump(cal, fh, indent=2)
    if args.json:
        print(json.dumps(dict(cal, **out)))
        return 0
    print(f"{args.recording}: {result.status}, model {cal['model']}, {cal['n_poses']} poses "
          f"from {result.n_windows} still windows, residual RMS {cal['residual_rms_mg']:.3f} mg")
    for note in result.notes:
        print(f"  note: {note}")
    print(f"  {'param':>6} {'value':>14} {'std':>11}  determined")
    for name, value in cal["params"].items():
        print(f"  {name:>6} {value:14.6g} {cal['std'][name]:11.3g}  {'yes' if name in cal['determined'] else 'no'}")
    print(f"  a_cal_g = matrix @ (raw - offset), offset in {cal['unit']}")
    if args.out:
        print(f"  written to {args.out}")
    return 0
