"""``selfcal diagnose REC [--json] [--report DIR]``."""

from __future__ import annotations

import json
import sys

from selfcal.config import load_config


def add_arguments(parser) -> None:
    parser.add_argument("recording", metavar="REC", help="recording CSV (kind=samples or kind=poses)")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument("--report", metavar="DIR", help="write a Markdown report with plots into DIR")
    parser.add_argument("--base-model", default="affine9", help="base model without effects (default affine9; the effects are what diagnose tests)")


def run(args) -> int:
    from selfcal.diagnosis import diagnose_recording

    cfg = load_config(args.config)
    if args.report:  # the report folder is created (with its parents) before the work starts
        from pathlib import Path

        from selfcal.errors import InputError

        try:
            Path(args.report).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"--report {args.report}: cannot create the folder ({exc.strerror or exc})") from exc
    # a path: samples are streamed through the detector in blocks (only still poses in memory)
    report, _ = diagnose_recording(args.recording, cfg, args.base_model, keep_arrays=bool(args.report),
                                   progress=sys.stderr.isatty())
    if args.report and report.get("kind") != "soaks_only":  # (its soaks are in the JSON and the text)
        from selfcal.report import write_report

        path = write_report(report, args.report)
        report["report"] = str(path)
    report.pop("_arrays", None)
    if args.json:
        print(json.dumps(report))
        return 0
    if report.get("kind") == "soaks_only":
        print(f"{args.recording}: {report['why']}")
        for sk in report["soaks"]["soaks"]:
            print(f"  soak {sk['t_start_s']:.0f}-{sk['t_end_s']:.0f} s, {sk['dtemp_c']:.1f} degC, "
                  f"{sk['n_windows']} windows: {sk['effect']}  "
                  + ", ".join(f"{n} {sk['coef'][n]:+.3f} ± {sk['std'][n]:.3f}" for n in sk["determined"]))
        print(f"  cause: {report['cause']}  ({report['soaks']['answer']})")
        if args.report:
            print("  report: none (a report needs the base model: 12 poses or more)")
        return 0
    g = report["gain"]
    print(f"{args.recording}: {report['n_poses']} poses; base {report['base_model']['model']} "
          f"RMS {report['base_model']['residual_rms_mg']:.3f} mg "
          f"(simulated: {report['discrepancy']['rms_mg']['simulated_mean']:.3f} mg)")
    for e in report["effects"]:
        print(f"  {e['name']:<19} {'SELECTED' if e['selected'] else ('supported' if e.get('supported') else '-'):<10} {e['evidence']}")
    print(f"  cause: {report['cause']}" + (f" (ambiguous: {report['ambiguous']})" if report.get("ambiguous") else ""))
    print(f"  soaks: {report['soaks']['answer']}")
    mg = lambda x: "-" if x is None else f"{x:.3f}"  # noqa: E731 - (None: no pose held out)
    print(f"  held-out RMS {mg(g['heldout_rms_mg_before'])} -> {mg(g['heldout_rms_mg_after'])} mg ({g['split']})")
    if args.report:
        print(f"  report: {report['report']}")
    return 0
