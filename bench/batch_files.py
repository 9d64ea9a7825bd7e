"""Many files at once: wall time of ``selfcal calibrate FILE... --jobs N --summary`` on N copies of a day.

Writes one 24-h 100-Hz synthetic wrist recording (``bench/long_recordings.py``'s
generator, known truth), links it ``--copies`` times, then times, in one run:

* ``selfcal calibrate COPIES... --jobs 1 --summary``;
* ``selfcal calibrate COPIES... --jobs 2 --summary``;
* actipy's GGIR calibration of the same file, when actipy is installed (opt-in extra
  ``compare``: Academic Use Licence, needs Java); otherwise the row says so.

The copies are hard links to one file, so after the first read the operating system
may serve it from its page cache; a real set of different files would be read from
disk (about 2 s per file for the streaming read alone, see ``long_recordings.py``).

    python bench/batch_files.py                 # 100 copies of 24 h
    python bench/batch_files.py --copies 10 --hours 2
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
from long_recordings import write_recording  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=100)
    ap.add_argument("--hours", type=float, default=24.0)
    ap.add_argument("--dir", default=None, help="where to write (default: a temporary folder)")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        src = Path(tmp) / "day.csv"
        n = write_recording(src, args.hours)
        files = []
        for i in range(args.copies):
            f = Path(tmp) / f"wrist_{i:03d}.csv"
            os.link(src, f)
            files.append(str(f))
        print(f"{args.copies} copies of {args.hours:g} h ({n:,} rows, {src.stat().st_size / 1e6:.0f} MB each)",
              file=sys.stderr, flush=True)
        for jobs in (1, 2):
            out = Path(tmp) / f"out{jobs}"
            out.mkdir()
            t0 = time.perf_counter()
            p = subprocess.run([sys.executable, "-m", "selfcal.cli", "calibrate", *files, "--model",
                                "affine9+temperature_bias", "--jobs", str(jobs), "--summary", str(out / "s.csv")],
                               capture_output=True, text=True)
            wall = time.perf_counter() - t0
            summary = list(csv.DictReader((out / "s.csv").open()))
            ok = sum(r["status"] in ("calibrated", "provisional") for r in summary)
            rows.append((f"selfcal --jobs {jobs}", wall, f"{ok}/{len(summary)} calibrated (exit {p.returncode})"))
            print(f"--jobs {jobs}: {wall:.0f} s", file=sys.stderr, flush=True)
        if importlib.util.find_spec("actipy") is not None:
            t0 = time.perf_counter()
            code = ("import sys, actipy, pandas as pd; d = pd.read_csv(sys.argv[1], comment='#'); "
                    "d.index = pd.to_datetime(d.pop('t_s'), unit='s'); d.columns = ['x', 'y', 'z', 'temperature']; "
                    "actipy.processing.calibrate_gravity(d)")
            for f in files:
                subprocess.run([sys.executable, "-c", code, f], check=True, capture_output=True)
            rows.append(("actipy calibrate_gravity (one process per file)", time.perf_counter() - t0, ""))
        else:
            rows.append(("actipy", float("nan"), "not installed (opt-in extra 'compare'; Academic Use Licence, Java)"))
    print(f"| method | wall s for {args.copies} x {args.hours:g} h | per file s | note |")
    print("|---|---:|---:|---|")
    for name, wall, note in rows:
        print(f"| {name} | {wall:.0f} | {wall / args.copies:.1f} | {note} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
