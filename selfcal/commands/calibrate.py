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
    parser.add_argument("recording", metavar="REC", nargs="+",
                        help="recording(s): selfcal CSV (samples or poses), .cwa, .gt3x or .bin; several files: "
                             "one calibration JSON each in --out-dir, one summary row each")
    parser.add_argument("--model", default="affine9",
                        help="error model to start from (scale6, affine9, affine9+effect...); online model selection "
                             "may add an effect the poses support, or drop one it added")
    parser.add_argument("--fixed-model", action="store_true",
                        help="keep --model as it is (no online model selection: [selection] enabled = false)")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument("--out", metavar="CAL.json", help="write the calibration JSON here")
    parser.add_argument("--history", metavar="FILE.jsonl",
                        help="write every published version here, one calibration JSON a line, in time order")
    parser.add_argument("--progress", action="store_true", help="progress bar on stderr")
    parser.add_argument("--columns", metavar="NAMES",
                        help="a plain CSV without the selfcal header: its columns in order, e.g. t_s,ax_g,ay_g,az_g "
                             "(bare t,x,y,z take --unit)")
    parser.add_argument("--unit", choices=("g", "mps2", "counts"), help="unit of bare x,y,z in --columns")
    parser.add_argument("--jobs", type=int, default=1, metavar="N", help="several files: N processes (default 1)")
    parser.add_argument("--summary", metavar="SUMMARY.csv",
                        help="several files: summary table (CSV, plus a Markdown report and a plot beside it)")
    parser.add_argument("--out-dir", metavar="DIR",
                        help="several files: where the calibration JSONs go (default: the summary's folder, or .)")


def check_writable(path: str, inputs: "tuple[str, ...] | list[str]" = ()) -> None:
    """Raise InputError unless ``path`` can be written (its directory must exist) without
    overwriting one of ``inputs`` (the files the command reads)."""
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{path}: is a directory, not a file")
    for source in inputs:
        if p.exists() and Path(source).exists() and os.path.samefile(p, source):
            raise InputError(f"{path}: is also an input ({source}); writing it would destroy that input")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"{path}: directory {str(parent)!r} does not exist")
    if not os.access(parent, os.W_OK):
        raise InputError(f"{path}: directory {str(parent)!r} is not writable")


def write_history(path: str, result) -> int:
    """Write every published version of a run as JSON lines (recording unit); returns the count."""
    from selfcal.pipeline import published_versions

    n = 0
    tmp = Path(path).with_name(Path(path).name + ".tmp")
    with tmp.open("w", encoding="utf-8") as fh:
        for c in published_versions(result):
            fh.write(json.dumps(c, separators=(",", ":")) + "\n")
            n += 1
    os.replace(tmp, path)
    return n


def run_many(args) -> int:
    """Several files: each in its own process; the exit code is the number of files that failed."""
    from selfcal.batch import run_batch

    if args.out or args.history or args.json:
        raise InputError("--out, --history and --json take one recording; with several use --out-dir and --summary")
    if args.jobs < 1:
        raise InputError(f"--jobs: must be >= 1, got {args.jobs}")
    if args.summary:
        check_writable(args.summary, args.recording)
    names: dict[str, str] = {}
    for rec in args.recording:  # each file's calibration is named after it, in one folder
        other = names.setdefault(Path(rec).name, rec)
        if other != rec:
            raise InputError(f"{other} and {rec} have the same name: their calibrations would both be "
                             f"{Path(rec).name}.cal.json in the output folder (rename one, or run them apart)")
    out_dir = args.out_dir or (str(Path(args.summary).parent) if args.summary else ".")
    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise InputError(f"--out-dir {out_dir}: is a file, not a folder")
    load_config(args.config)  # a bad config is a usage error before any work
    from selfcal.io import plain_columns

    columns = plain_columns(args.columns, args.unit) if args.columns else None
    rows = run_batch(args.recording, args.model, args.config, out_dir, args.jobs, args.summary,
                     progress=args.progress or sys.stderr.isatty(), columns=columns, fixed_model=args.fixed_model)
    failed = [r for r in rows if r["status"] in ("error", "uncalibrated")]
    for r in rows:
        print(f"{r['file']}: {r['status']}" + (f" ({r['refusal_reason'] or r['error']})" if r in failed else
                                                f", predicted sphere {r['predicted_sphere_rms_mg']} mg"))
    if args.summary:
        print(f"summary: {args.summary} (+ {Path(args.summary).with_suffix('.md').name})")
    print(f"{len(rows) - len(failed)} of {len(rows)} files calibrated; {len(failed)} failed", file=sys.stderr)
    return min(len(failed), 100)


def run(args) -> int:
    from selfcal.pipeline import calibrate_recording

    ErrorModel(args.model)
    if len(args.recording) > 1 or args.summary or args.jobs != 1:
        return run_many(args)
    args.recording = args.recording[0]

    ErrorModel(args.model)  # validate the name before reading anything
    cfg = load_config(args.config)
    if args.fixed_model:
        cfg.setdefault("selection", {})["enabled"] = False
    for target in (args.out, args.history):  # fail before the work, not after it
        if target:
            check_writable(target, [args.recording])
    if args.out and args.history and Path(args.out).resolve() == Path(args.history).resolve():
        raise InputError(f"--out and --history are the same file ({args.out})")
    from selfcal.io import plain_columns
    from selfcal.pipeline import calibrate_path

    columns = plain_columns(args.columns, args.unit) if args.columns else None
    if args.unit and not args.columns:
        raise InputError("--unit applies to --columns (a plain CSV); a selfcal recording names its units")
    # streamed in blocks: only the still poses stay in memory, whatever the file's length
    result = calibrate_path(args.recording, args.model, cfg, progress=args.progress or sys.stderr.isatty(),
                            columns=columns)
    if args.history and result.calibration is not None:  # a run that published nothing keeps the file as it was
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
    if args.out:  # atomic: an existing file is replaced whole or not at all
        tmp = Path(args.out).with_name(Path(args.out).name + ".tmp")
        tmp.write_text(json.dumps(cal, indent=2), encoding="utf-8")
        os.replace(tmp, args.out)
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
