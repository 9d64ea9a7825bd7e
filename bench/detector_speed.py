"""Still-detector throughput: the fast detector next to the reference it replaced.

Streams (simulated wear, seed 1):

* 20 Hz insole: 3 axes (g), temperature, 4 pressure channels (kPa), 1 day;
* 100 Hz wrist-like: the simulator's motion at 100 Hz, 3 axes and temperature only
  (no pressure), 1 day.

Each is fed to ``selfcal.detect.StaticDetector`` (today's, O(1) rolling statistics),
with its numpy code (``SELFCAL_NUMBA=0``) and with its numba kernels when numba is
installed (``selfcal.detect_numba``), and to ``tests/reference_detect.py`` (the O(W)
implementation it replaced, kept as a reference) in chunks of 1, 400 and 50 000 samples
and as one whole chunk, in the same run. Prints M samples/s for each, the ratio of the
faster to the reference, whether the windows are identical (bit for bit, all three), and
the detector state's memory per device (largest over the stream, fed in 5-s batches as
the service does).

    python bench/detector_speed.py            # chunk size 1 on the first 20 000 samples
    python bench/detector_speed.py --quick    # shorter streams
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import reference_detect as reference  # noqa: E402
from selfcal import detect as fast  # noqa: E402
from selfcal import detect_numba  # noqa: E402
from selfcal.sim.config import SimConfig  # noqa: E402
from selfcal.sim.simulator import simulate_samples  # noqa: E402

FIELDS = ("mean_g", "sd_g", "n", "t_start_s", "t_end_s", "temp_c", "pressure_sd_kpa")


def stream(rate_hz: float, days: float, pressure: bool, seed: int = 1):
    """(t_s, acc_g, temp_c, pressure_kpa or None) of simulated wear."""
    cfg = SimConfig() if rate_hz == 20 else SimConfig(ble={"rate_hz": rate_hz})
    s, _ = simulate_samples(cfg, np.random.default_rng(seed), days=days)
    return s.t_s, s.acc_g, s.temp_c, (s.pressure_kpa if pressure else None)


def feed(module, rate_hz: float, data, chunk: int, limit: int | None = None):
    """Feed in chunks; return (seconds, samples, windows)."""
    t, a, tc, p = data
    n = len(t) if limit is None else min(limit, len(t))
    det = module.StaticDetector(module.DetectorConfig(rate_hz=rate_hz))
    out = []
    t0 = time.perf_counter()
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        out.append(det.feed(t[lo:hi], a[lo:hi], tc[lo:hi], None if p is None else p[lo:hi]))
    out.append(det.flush())
    return time.perf_counter() - t0, n, module.StillWindows.concat(out)


@contextlib.contextmanager
def numba_switched(on: bool):
    """The fast detector with (``on``) or without its numba kernels (``SELFCAL_NUMBA``)."""
    before = os.environ.get("SELFCAL_NUMBA")
    os.environ["SELFCAL_NUMBA"] = "1" if on else "0"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("SELFCAL_NUMBA", None)
        else:
            os.environ["SELFCAL_NUMBA"] = before


def identical(a, b) -> bool:
    return len(a) == len(b) and all(
        np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True) for f in FIELDS)


def state_bytes(rate_hz: float, data, batch_s: float = 5.0) -> tuple[int, int]:
    """Largest detector state over the stream: (numpy bytes, JSON bytes of state_dict)."""
    t, a, tc, p = data
    det = fast.StaticDetector(fast.DetectorConfig(rate_hz=rate_hz))
    chunk = int(batch_s * rate_hz)
    best, best_json, best_at = 0, 0, 0
    for lo in range(0, len(t), chunk):
        hi = lo + chunk
        det.feed(t[lo:hi], a[lo:hi], tc[lo:hi], None if p is None else p[lo:hi])
        st = det.state_
        nbytes = st.t_s.nbytes + st.acc_g.nbytes + st.temp_c.nbytes + st.pressure_kpa.nbytes
        if nbytes > best:
            best, best_at = nbytes, lo
            best_json = len(json.dumps(det.state_dict(), allow_nan=False))
    return best, best_json


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter streams (0.25 day, 1 h)")
    ap.add_argument("--one-limit", type=int, default=20_000,
                    help="samples fed one at a time (chunk size 1)")
    args = ap.parse_args(argv)
    cases = [("20 Hz insole (acc, temp, 4 pressure)", 20.0, 0.25 if args.quick else 1.0, True),
             ("100 Hz wrist-like (acc, temp)", 100.0, 1 / 24 if args.quick else 1.0, False)]
    have_numba = detect_numba._kernels() is not None  # compiled (or loaded from numba's cache) before timing
    print("numba: " + ("installed (the fast detector's kernels: selfcal.detect_numba)" if have_numba else
                       "not installed (pip install 'selfcal[fast]'); the numba column is empty"))
    print("| stream | chunk | samples | reference M/s | fast, numpy M/s | fast, numba M/s | ratio | windows | identical |")
    print("|---|---|---|---|---|---|---|---|---|")
    mem = []
    for name, rate, days, pressure in cases:
        data = stream(rate, days, pressure)
        for chunk in (1, 400, 50_000, len(data[0])):
            limit = args.one_limit if chunk == 1 else None
            label = "whole" if chunk == len(data[0]) else f"{chunk:,}"
            tr, n, wr = feed(reference, rate, data, chunk, limit)
            with numba_switched(False):
                tp, _, wp = feed(fast, rate, data, chunk, limit)
            same = identical(wp, wr)
            tn = None
            if have_numba:
                with numba_switched(True):
                    tn, _, wn = feed(fast, rate, data, chunk, limit)
                same = same and identical(wn, wr)
            best = min(tp, tn) if tn is not None else tp
            numba_col = f"{n / tn / 1e6:.2f}" if tn is not None else "—"
            print(f"| {name} | {label} | {n:,} | {n / tr / 1e6:.2f} | {n / tp / 1e6:.2f} | {numba_col} | "
                  f"{tr / best:.1f}x | {len(wp)} | {'yes' if same else 'NO'} |", flush=True)
        mem.append((name, *state_bytes(rate, data)))
    print()
    for name, nb, js in mem:
        print(f"detector state per device, {name}: largest {nb / 1024:.1f} KiB of arrays, "
              f"{js / 1024:.1f} KiB as JSON (state_dict)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
