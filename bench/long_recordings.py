"""Long recordings: wall time and peak memory of ``selfcal calibrate`` on days of 100 Hz data.

Writes synthetic wrist recordings (5 columns: ``t_s, ax_g, ay_g, az_g, temp_c`` at
100 Hz) of the given lengths, from a known sensor (affine9 + temperature offset), then
measures, each in its own process (peak RSS from ``getrusage`` of that process alone):

* ``selfcal calibrate FILE --model affine9+temperature_bias`` (streamed in blocks);
* a one-thread streaming read of the same file with ``pyarrow.csv.open_csv`` (the
  baseline: what reading alone costs);
* when it is installed, scikit-digital-health's ``CalibrateAccelerometer`` (MIT; van
  Hees with temperature) on the same data, read whole with pyarrow as its users do;

and prints wall time, peak RSS, rows/s, the ratio to the streaming read, and the
calibration's whole-sphere error against the known truth.

    python bench/long_recordings.py                  # 1 h and 24 h
    python bench/long_recordings.py --hours 1,24,168 # and 7 days (a 2.7 GB file)
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = 100.0

TRUTH = {"bx": 0.031, "by": -0.042, "bz": 0.018, "sx": 1.021, "sy": 0.984, "sz": 1.012,
         "nxy": 0.004, "nxz": -0.006, "nyz": 0.003, "tbx": 4e-4, "tby": -3e-4, "tbz": 6e-4}


def write_recording(path: Path, hours: float, seed: int = 0) -> int:
    """A synthetic wrist recording: still bouts in random orientations, motion between; rows written."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    sys.path.insert(0, str(ROOT))
    from selfcal.models import ErrorModel

    model = ErrorModel("affine9+temperature_bias")
    theta = model.from_dict(TRUTH)
    matrix, offset = model.linear(theta)
    minv = np.linalg.inv(matrix)
    tb = np.array([TRUTH["tbx"], TRUTH["tby"], TRUTH["tbz"]])
    rng = np.random.default_rng(seed)
    n_total = int(hours * 3600 * RATE_HZ)
    with path.open("w") as fh:
        fh.write("# selfcal-recording v1\n# kind=samples\n# sensor=synthetic wrist (bench/long_recordings.py)\n"
                 "t_s,ax_g,ay_g,az_g,temp_c\n")
    written = 0
    with path.open("ab") as fh:
        while written < n_total:
            n = min(360_000, n_total - written)  # one hour per chunk
            a = np.empty((n, 3))
            i = 0
            while i < n:  # alternate still bouts (10-300 s) and motion (2-60 s)
                k = min(n - i, int(rng.uniform(10, 300) * RATE_HZ))
                d = rng.normal(size=3)
                a[i:i + k] = d / np.linalg.norm(d)
                i += k
                m = min(n - i, int(rng.uniform(2, 60) * RATE_HZ))
                d = rng.normal(size=3)
                a[i:i + m] = d / np.linalg.norm(d) + rng.normal(0, 0.3, (m, 3))
                i += m
            t = (written + np.arange(n)) / RATE_HZ
            temp = 26.0 + 5.0 * np.sin(2 * np.pi * t / 86400.0) + 1.5 * np.sin(2 * np.pi * t / 5400.0)
            raw = a @ minv.T + offset + np.outer(temp - 25.0, tb) + rng.normal(0, 0.003, (n, 3))
            table = pa.table({"t_s": np.round(t, 2), "ax_g": np.round(raw[:, 0], 5), "ay_g": np.round(raw[:, 1], 5),
                              "az_g": np.round(raw[:, 2], 5), "temp_c": np.round(temp, 2)})
            pacsv.write_csv(table, fh, write_options=pacsv.WriteOptions(include_header=False))
            written += n
    return written


def measured(argv: list[str]) -> tuple[float, float, str]:
    """(wall s, peak RSS MB, stdout) of a command, measured in a wrapper process of its own."""
    wrapper = ("import resource, subprocess, sys, time, json; t0 = time.perf_counter(); "
               "p = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
               "w = time.perf_counter() - t0; r = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss; "
               "print(json.dumps({'wall': w, 'rss_kb': r, 'rc': p.returncode, 'out': p.stdout[-20000:], "
               "'err': p.stderr[-2000:]}))")
    p = subprocess.run([sys.executable, "-c", wrapper, *argv], capture_output=True, text=True, check=True)
    d = json.loads(p.stdout)
    if d["rc"] != 0:
        raise RuntimeError(f"{argv} exited {d['rc']}: {d['err']}")
    return d["wall"], d["rss_kb"] / 1024.0, d["out"]


PYARROW_READ = """
import sys, pyarrow.csv as c
r = c.open_csv(sys.argv[1], read_options=c.ReadOptions(skip_rows=3, use_threads=False, block_size=1 << 22))
n = 0
for b in r:
    n += b.num_rows
print(n)
"""


SKDH_RUN = """
import json, sys, numpy as np, pyarrow.csv as c
from skdh.preprocessing import CalibrateAccelerometer
hours = float(sys.argv[2])
tab = c.read_csv(sys.argv[1], read_options=c.ReadOptions(skip_rows=3))  # skdh works on whole arrays
t = tab.column("t_s").to_numpy() + 1.7e9
acc = np.column_stack([tab.column(k).to_numpy() for k in ("ax_g", "ay_g", "az_g")])
temp = tab.column("temp_c").to_numpy()
del tab
r = CalibrateAccelerometer(min_hours=min(72.0, 0.5 * hours)).predict(time=t, accel=acc, fs=100.0, temperature=temp)
m = np.ravel(r["temperature scale"])
j = int(np.argmax(np.abs(m)))  # the calibration's mean temperature, from one applied sample
tc = float(temp[0] - (r["accel"][0, j] - (acc[0, j] + r["offset"][j]) * r["scale"][j]) / m[j]) if m[j] else 25.0
print(json.dumps({"offset": np.ravel(r["offset"]).tolist(), "scale": np.ravel(r["scale"]).tolist(),
                  "temp_scale": m.tolist(), "temp_mean": tc}))
"""


def skdh_sphere_error_mg(res: dict) -> float:
    """Whole-sphere error (mg) at 25 degC of skdh's ``a = (y + d) s + (T - Tc) m``, against TRUTH."""
    from selfcal.fit import sphere_directions
    from selfcal.models import ErrorModel

    truth = ErrorModel("affine9+temperature_bias")
    m, b = truth.linear(truth.from_dict(TRUTH))
    raw = sphere_directions(2000) @ np.linalg.inv(m).T + b
    a = (raw + np.asarray(res["offset"])) * np.asarray(res["scale"]) + (25.0 - res["temp_mean"]) * np.asarray(res["temp_scale"])
    return float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - 1) ** 2)) * 1e3)


def sphere_error_mg(cal: dict) -> float:
    """Whole-sphere calibrated-norm RMS error (mg) of a calibration at 25 degC, against TRUTH."""
    from selfcal.fit import sphere_directions
    from selfcal.models import ErrorModel

    model = ErrorModel(cal["model"])
    truth = ErrorModel("affine9+temperature_bias")
    th_t = truth.from_dict(TRUTH)
    m, b = truth.linear(th_t)
    dirs = sphere_directions(2000)
    raw = dirs @ np.linalg.inv(m).T + b
    a = model.apply(model.from_dict(cal["params"]), raw, np.full(len(raw), 25.0), np.zeros(len(raw)))
    return float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - 1) ** 2)) * 1e3)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", default="1,24", help="lengths in hours, comma-separated (168 = 7 days)")
    ap.add_argument("--dir", default=None, help="where to write the files (default: a temporary folder)")
    args = ap.parse_args(argv)
    hours = [float(h) for h in args.hours.split(",")]
    selfcal = [sys.executable, "-m", "selfcal.cli", "calibrate"]
    rows = []
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        for h in hours:
            path = Path(tmp) / f"wrist_{h:g}h.csv"
            t0 = time.perf_counter()
            n = write_recording(path, h)
            print(f"[{h:g} h] wrote {n:,} rows, {path.stat().st_size / 1e6:.0f} MB in {time.perf_counter() - t0:.0f} s",
                  file=sys.stderr, flush=True)
            w_read, rss_read, _ = measured([sys.executable, "-c", PYARROW_READ, str(path)])
            w_cal, rss_cal, out = measured([*selfcal, str(path), "--model", "affine9+temperature_bias", "--json"])
            cal = json.loads(out)
            skdh = None
            if importlib.util.find_spec("skdh") is not None and h >= 24:  # skdh needs >= 12 h
                w_sk, rss_sk, out_sk = measured([sys.executable, "-c", SKDH_RUN, str(path), str(h)])
                skdh = {"s": w_sk, "rss_mb": rss_sk, "sphere_error_mg": skdh_sphere_error_mg(json.loads(out_sk))}
            rows.append({"skdh": skdh, "hours": h, "rows": n, "file_mb": path.stat().st_size / 1e6,
                         "read_s": w_read, "read_rss_mb": rss_read, "selfcal_s": w_cal, "selfcal_rss_mb": rss_cal,
                         "rows_per_s": n / w_cal, "ratio_to_read": w_cal / w_read, "status": cal["status"],
                         "sphere_error_mg": sphere_error_mg(cal), "predicted_mg": cal["predicted_sphere_rms_mg"]})
            path.unlink()
    print("| length | rows | file MB | pyarrow read s (RSS MB) | selfcal s | selfcal peak RSS MB | rows/s | × read | "
          "status | sphere error mg (predicted) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|---|")
    for r in rows:
        print(f"| {r['hours']:g} h | {r['rows']:,} | {r['file_mb']:.0f} | {r['read_s']:.1f} ({r['read_rss_mb']:.0f}) | "
              f"{r['selfcal_s']:.1f} | {r['selfcal_rss_mb']:.0f} | {r['rows_per_s'] / 1e3:.0f} k | "
              f"{r['ratio_to_read']:.1f} | {r['status']} | {r['sphere_error_mg']:.3f} ({r['predicted_mg']:.3f}) |")
    if any(r["skdh"] for r in rows):
        print("\nscikit-digital-health (CalibrateAccelerometer with temperature, on arrays read whole with pyarrow), "
              "same files, each in its own process:\n")
        print("| length | skdh s | skdh peak RSS MB | skdh sphere error mg | selfcal s | selfcal peak RSS MB | selfcal sphere error mg |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for r in rows:
            if r["skdh"]:
                k = r["skdh"]
                print(f"| {r['hours']:g} h | {k['s']:.1f} | {k['rss_mb']:.0f} | {k['sphere_error_mg']:.3f} | "
                      f"{r['selfcal_s']:.1f} | {r['selfcal_rss_mb']:.0f} | {r['sphere_error_mg']:.3f} |")
    else:
        print("\nscikit-digital-health is not installed (pip install scikit-digital-health): no skdh row.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
