"""Load benchmark of the selfcal service on loopback (127.0.0.1 only).

Starts a real ``selfcal serve`` (real OnlineCalibrator, SQLite WAL, synchronous=FULL)
and a *separate* load process. The load process simulates N insoles at 20 Hz, each
sending one batch every ``--batch-s`` seconds (open loop: sends are scheduled, not
paced by responses), over ``--connections`` keep-alive connections with a minimal
raw-asyncio HTTP/1.1 client (so the client costs little CPU), while an app client in its
own process issues ``GET /devices/{id}/calibration`` at ``--get-hz`` and records its
latency. The same GETs are also issued from inside the load loop, where they wait behind
the senders' work; both are printed.

For each device count it prints offered and sustained (acknowledged) samples/s, and
GET p50/p99; it stops after the first step that cannot sustain 90 % of the offered
load, or after the last step. Afterwards it reads /metrics to tell whether the refit
worker kept up (samples fed vs stored).

    python bench/service_load.py                       # JSON and binary batches
    python bench/service_load.py --devices 1000,2000 --format binary --step-s 6

Numbers depend on the machine (and on what else runs on it); they are not test gates.
"""

from __future__ import annotations

import argparse
import asyncio
import heapq
import json
import os
import random
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
KEY = "bench-key-0123456789"
RATE_HZ = 20.0


# ------------------------------------------------------------------ data
def insole_stream(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) raw g: still poses (mostly flat, some tilted) of 3-8 s with motion between."""
    out = []
    matrix = np.diag(1.0 + rng.uniform(-0.03, 0.03, 3))
    offset = rng.uniform(-0.05, 0.05, 3)
    while sum(len(p) for p in out) < n:
        d = rng.normal(size=3) if rng.random() < 0.4 else np.array([0, 0, 1.0]) + rng.normal(0, 0.08, 3)
        d /= np.linalg.norm(d)
        out.append(np.tile(d, (int(rng.uniform(3, 8) * RATE_HZ), 1)))
        out.append(d + rng.normal(0, 0.4, (int(1.5 * RATE_HZ), 3)))
    a = np.vstack(out)[:n]
    return offset + a @ np.linalg.inv(matrix).T + rng.normal(0, 2e-3, a.shape)


def wear_stream(seed: int, days: float, skip_days: float = 0.0) -> np.ndarray:
    """(n, 3) raw g: an insole worn ``days`` days by one simulated wearer (selfcal.sim, seed
    ``seed``), from ``skip_days`` after midnight of day 0: nights on the floor, sitting,
    standing and walking, as the calibrator meets them in a fleet."""
    from selfcal.config import load_config, section
    from selfcal.sim.config import SimConfig
    from selfcal.sim.simulator import Simulation

    cfg = load_config()
    sim = Simulation(SimConfig.from_section(section(cfg, "sim")), np.random.default_rng(seed), days=skip_days + days)
    # streamed an hour at a time: only the days sent are held (a week skipped is not a week in memory)
    kept = [c.acc_g[c.t_s >= skip_days * 86400.0] for c in sim.iter_samples(chunk_s=3600)]
    return np.ascontiguousarray(np.concatenate(kept))


def encode(fmt: str, seq: int, t: np.ndarray, acc: np.ndarray) -> tuple[bytes, str]:
    if fmt == "binary":
        head = struct.pack("<4sqIHH", b"SCB1", seq, len(t), 0, 0)
        return head + np.ascontiguousarray(t, "<f8").tobytes() + np.ascontiguousarray(acc.T, "<f8").tobytes(), \
            "application/x-selfcal-batch"
    import orjson

    body = {"seq": seq, "t_s": t.tolist(), "ax_g": acc[:, 0].tolist(), "ay_g": acc[:, 1].tolist(),
            "az_g": acc[:, 2].tolist()}
    return orjson.dumps(body), "application/json"


# ------------------------------------------------------------------ raw HTTP client
class Conn:
    def __init__(self, host: str, port: int):
        self.host, self.port = host, port
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def request(self, method: str, path: str, body: bytes = b"", ctype: str = "application/json") -> tuple[int, bytes]:
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        head = (f"{method} {path} HTTP/1.1\r\nHost: {self.host}\r\nAuthorization: Bearer {KEY}\r\n"
                f"Content-Type: {ctype}\r\nContent-Length: {len(body)}\r\n\r\n").encode()
        self.writer.write(head + body)
        raw = await self.reader.readuntil(b"\r\n\r\n")
        lines = raw.decode("latin-1").split("\r\n")
        status = int(lines[0].split(" ")[1])
        length = 0
        for line in lines[1:]:
            if line.lower().startswith("content-length:"):
                length = int(line.split(":", 1)[1])
        data = await self.reader.readexactly(length) if length else b""
        return status, data


# ------------------------------------------------------------------ load process
async def load_main(args) -> None:
    try:
        import uvloop  # noqa: F401

        asyncio.set_event_loop_policy(uvloop.EventLoopPolicy())
    except ImportError:
        pass
    host, port = "127.0.0.1", args.port
    rng = np.random.default_rng(args.seed)
    n_batch = int(round(args.batch_s * RATE_HZ))
    stream = insole_stream(rng, 20000)  # drawn in every case, so the generator's next draws do not depend on --data
    if args.data == "wear":
        stream = wear_stream(args.wear_seed, args.wear_days, args.wear_skip_days)
    steps = [] if args.devices == "none" else [int(x) for x in args.devices.split(",")]
    max_dev = max(steps, default=1)
    seq = [0] * max_dev
    cursor = [int(c) for c in rng.integers(0, len(stream) - n_batch, max_dev)]
    # each device's clock (s): from --t0-s, spread over --t0-spread-s (its own generator, so
    # that the data drawn above stay the same with or without a spread)
    t_start = (args.t0_s + np.random.default_rng([args.seed, 7]).uniform(0.0, args.t0_spread_s, max_dev)).tolist()
    queue: asyncio.Queue = asyncio.Queue()
    state = {"acked": 0, "errors": 0, "active": 0}

    async def sender():
        conn = Conn(host, port)
        while True:
            dev = await queue.get()
            s = seq[dev]
            seq[dev] += 1
            t = t_start[dev] + s * args.batch_s + np.arange(n_batch) / RATE_HZ
            c = cursor[dev]
            cursor[dev] = (c + n_batch) % (len(stream) - n_batch)
            body, ctype = encode(args.format, s, t, stream[c : c + n_batch])
            try:
                status, _ = await conn.request("POST", f"/devices/bench-{dev:05d}/samples", body, ctype)
            except (OSError, asyncio.IncompleteReadError):
                status, conn = 0, Conn(host, port)
            if status == 200:
                state["acked"] += n_batch
            else:
                state["errors"] += 1

    async def scheduler(n_dev: int, stop: float):
        # device i sends at phase i/n_dev * batch_s, then every batch_s; a heap of due
        # times, so a tick costs what is due rather than a scan of every device
        start = time.monotonic()
        due = [(start + (i / n_dev) * args.batch_s, i) for i in range(n_dev)]
        heapq.heapify(due)
        while time.monotonic() < stop:
            now = time.monotonic()
            while due[0][0] <= now:
                when, i = heapq.heappop(due)
                queue.put_nowait(i)
                heapq.heappush(due, (when + args.batch_s, i))
            await asyncio.sleep(0.01)

    async def prober(lat: list, stop: float, n_dev: int):
        conn = Conn(host, port)
        r = random.Random(args.seed)
        while time.monotonic() < stop:
            dev = r.randrange(min(n_dev, max(1, sum(1 for s in seq[:n_dev] if s > 0))))
            t0 = time.perf_counter()
            status, _ = await conn.request("GET", f"/devices/bench-{dev:05d}/calibration")
            if status in (200, 404):
                lat.append(time.perf_counter() - t0)
            await asyncio.sleep(1.0 / args.get_hz)

    def summary(lat: list) -> dict:
        lat_ms = np.array(lat) * 1e3 if lat else np.array([np.nan])
        return {"get_p50_ms": round(float(np.percentile(lat_ms, 50)), 2),
                "get_p99_ms": round(float(np.percentile(lat_ms, 99)), 2),
                "get_max_ms": round(float(lat_ms.max()), 2), "get_n": len(lat)}

    async def probe_ids(ids: list[str], lat: list, stop: float):
        conn = Conn(host, port)
        r = random.Random(args.seed)
        while time.monotonic() < stop:
            t0 = time.perf_counter()
            status, _ = await conn.request("GET", f"/devices/{r.choice(ids)}/calibration")
            if status in (200, 404):
                lat.append(time.perf_counter() - t0)
            await asyncio.sleep(1.0 / args.get_hz)

    if args.inflight_devices > 0:  # phases 1 and 2 (--inflight-devices 0 skips them)
        # ---- phase 1: idle (two known devices, nothing else running)
        ids = [f"inflight-{d}" for d in range(args.inflight_devices)]
        nb = args.inflight_batch
        next_seq = {i: 0 for i in ids}
        c0 = Conn(host, port)
        for i in ids:
            body, ctype = encode(args.format, 0, np.arange(nb) / RATE_HZ, stream[:nb])
            await c0.request("POST", f"/devices/{i}/samples", body, ctype)
            next_seq[i] = 1
        await asyncio.sleep(1.0)
        lat: list[float] = []
        await probe_ids(ids, lat, time.monotonic() + args.step_s)
        print(json.dumps({"phase": "idle", "devices": 0, "in_flight": 0, "req_per_s": 0, "errors": 0,
                          **summary(lat)}), flush=True)

        # ---- phase 2: a few devices, each with K requests in flight (closed loop, paced)
        stats = {"acked": 0, "errors": 0, "sent": 0}

        async def inflight_sender(dev: str, k: int, stop: float):
            conn = Conn(host, port)
            period = args.inflight_devices * args.inflight / args.inflight_rate
            nxt = time.monotonic() + k * period / args.inflight
            while time.monotonic() < stop:
                s = next_seq[dev]
                next_seq[dev] += 1
                t = s * nb / RATE_HZ + np.arange(nb) / RATE_HZ
                c = (s * nb) % (len(stream) - nb)
                body, ctype = encode(args.format, s, t, stream[c: c + nb])
                try:
                    status, _ = await conn.request("POST", f"/devices/{dev}/samples", body, ctype)
                except (OSError, asyncio.IncompleteReadError):
                    status, conn = 0, Conn(host, port)
                stats["sent"] += 1
                stats["acked" if status == 200 else "errors"] += 1
                nxt += period
                await asyncio.sleep(max(0.0, nxt - time.monotonic()))

        stop = time.monotonic() + args.warmup_s + args.step_s
        tasks = [asyncio.create_task(inflight_sender(d, k, stop)) for d in ids for k in range(args.inflight)]
        await asyncio.sleep(args.warmup_s)
        lat = []
        a0, e0, t0 = stats["acked"], stats["errors"], time.monotonic()
        await probe_ids(ids, lat, stop)
        a1, e1, t1 = stats["acked"], stats["errors"], time.monotonic()
        await asyncio.gather(*tasks)
        print(json.dumps({"phase": "in-flight", "devices": args.inflight_devices, "in_flight": args.inflight,
                          "req_per_s": round((a1 - a0) / (t1 - t0), 1), "errors": e1 - e0, **summary(lat)}), flush=True)
    if args.devices == "none":
        return

    senders = [asyncio.create_task(sender()) for _ in range(args.connections)]
    for n_dev in steps:
        start = time.monotonic()
        stop = start + args.warmup_s + args.step_s
        sched = asyncio.create_task(scheduler(n_dev, stop))
        await asyncio.sleep(args.warmup_s)
        lat: list[float] = []
        probe = asyncio.create_task(prober(lat, stop, n_dev))
        # an app's reads come from its own process: the same GETs from a client that does
        # not share this loop (and its batch encoding) with the senders
        app = subprocess.Popen(
            [sys.executable, __file__, "--probe-only", "--port", str(port), "--get-hz", str(args.get_hz),
             "--probe-devices", str(n_dev), "--probe-start", repr(start), "--probe-stop", repr(stop),
             "--batch-s", str(args.batch_s), "--warmup-s", str(args.warmup_s), "--seed", str(args.seed + 1)],
            stdout=subprocess.PIPE, text=True)
        a0, e0, t0 = state["acked"], state["errors"], time.monotonic()
        await asyncio.sleep(args.step_s)
        a1, e1, t1 = state["acked"], state["errors"], time.monotonic()
        await sched
        await probe
        app_out, _ = await asyncio.to_thread(app.communicate)
        app_lat = json.loads(app_out.strip().splitlines()[-1])
        offered = n_dev * RATE_HZ
        sustained = (a1 - a0) / (t1 - t0)
        rec = {"phase": "fleet", "devices": n_dev, "in_flight": args.connections, "offered_sps": offered,
               "sustained_sps": round(sustained), "req_per_s": round(sustained / n_batch, 1),
               "backlog_batches": queue.qsize(), "errors": e1 - e0, **summary(lat),
               **{f"app_{k}": v for k, v in app_lat.items()}}
        print(json.dumps(rec), flush=True)
        while not queue.empty():  # drain backlog between steps (bounded: the queue only shrinks)
            queue.get_nowait()
        if sustained < 0.9 * offered:
            break
    for s in senders:
        s.cancel()


async def probe_main(args) -> None:
    """The app client: GETs at ``--get-hz`` on devices that have sent a batch, from its
    own process and event loop; prints one JSON line of latency percentiles (ms)."""
    conn = Conn("127.0.0.1", args.port)
    r = random.Random(args.seed)
    lat: list[float] = []
    await asyncio.sleep(max(0.0, args.probe_start + args.warmup_s - time.monotonic()))
    while time.monotonic() < args.probe_stop:
        # device i first sends at start + i / n * batch_s: pick among those that have
        sent = int(args.probe_devices * min(1.0, (time.monotonic() - args.probe_start) / args.batch_s))
        dev = r.randrange(max(1, sent))
        t0 = time.perf_counter()
        status, _ = await conn.request("GET", f"/devices/bench-{dev:05d}/calibration")
        if status in (200, 404):
            lat.append(time.perf_counter() - t0)
        await asyncio.sleep(1.0 / args.get_hz)
    lat_ms = np.array(lat) * 1e3 if lat else np.array([np.nan])
    print(json.dumps({"get_p50_ms": round(float(np.percentile(lat_ms, 50)), 2),
                      "get_p99_ms": round(float(np.percentile(lat_ms, 99)), 2),
                      "get_max_ms": round(float(lat_ms.max()), 2), "get_n": len(lat)}), flush=True)


# ------------------------------------------------------------------ driver
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_up(port: int, timeout_s: float = 90.0) -> None:
    """Wait until the server on ``port`` answers /healthz (RuntimeError after ``timeout_s``)."""
    import httpx

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"server on port {port} did not come up")


def stop_server(server: subprocess.Popen) -> None:
    """SIGTERM, then a kill after 30 s."""
    server.send_signal(signal.SIGTERM)
    try:
        server.wait(timeout=30)
    except subprocess.TimeoutExpired:
        server.kill()


def metric_values(port: int) -> dict[str, float]:
    import httpx

    text = httpx.get(f"http://127.0.0.1:{port}/metrics", headers={"Authorization": f"Bearer {KEY}"}, timeout=30).text
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, _, value = line.rpartition(" ")
            out[name] = float(value)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--devices", default="500,1000,2000,5000,10000", help="device counts, one step each")
    p.add_argument("--batch-s", type=float, default=5.0, help="seconds of samples per batch (100 at 20 Hz)")
    p.add_argument("--step-s", type=float, default=8.0, help="measured seconds per step")
    p.add_argument("--warmup-s", type=float, default=2.0)
    p.add_argument("--connections", type=int, default=32)
    p.add_argument("--get-hz", type=float, default=100.0)
    p.add_argument("--format", choices=["json", "binary", "both"], default="both")
    p.add_argument("--refit-threads", type=int, default=1, help="refit worker threads of the server")
    p.add_argument("--synchronous", choices=["FULL", "NORMAL"], default="FULL")
    p.add_argument("--inflight-devices", type=int, default=2, help="devices of the in-flight phase")
    p.add_argument("--inflight", type=int, default=4, help="requests in flight per device (in-flight phase)")
    p.add_argument("--inflight-rate", type=float, default=200.0, help="POST/s offered in the in-flight phase")
    p.add_argument("--inflight-batch", type=int, default=20, help="samples per batch in the in-flight phase")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--data", choices=["sphere", "wear"], default="sphere",
                   help="sphere: still poses in random directions (40 %%) with motion between, ~1 000 s shared by "
                        "every device (a new pose cell every few batches: refits every few minutes); wear: one "
                        "simulated insole wearer (selfcal.sim), each device at its own point of it")
    p.add_argument("--wear-seed", type=int, default=2, help="--data wear: the wearer's simulation seed")
    p.add_argument("--wear-days", type=float, default=1.0, help="--data wear: days of wear shared by the devices")
    p.add_argument("--wear-skip-days", type=float, default=0.0, help="--data wear: start this many days into the wear")
    p.add_argument("--t0-s", type=float, default=0.0, help="device clock (s) of every device's first sample")
    p.add_argument("--t0-spread-s", type=float, default=0.0,
                   help="spread each device's first sample uniformly over this many seconds after --t0-s")
    p.add_argument("--load-only", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--probe-only", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--probe-devices", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--probe-start", type=float, default=0.0, help=argparse.SUPPRESS)
    p.add_argument("--probe-stop", type=float, default=0.0, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.probe_only:
        asyncio.run(probe_main(args))
        return 0
    if args.load_only:
        asyncio.run(load_main(args))
        return 0

    formats = ["json", "binary"] if args.format == "both" else [args.format]
    print(f"selfcal service load: batches of {args.batch_s:g} s ({int(args.batch_s * RATE_HZ)} samples), "
          f"{args.connections} connections, GET probe {args.get_hz:g} Hz, {os.cpu_count()} CPUs, "
          f"synchronous={args.synchronous}")
    for fmt in formats:
        with tempfile.TemporaryDirectory(prefix="selfcal-bench-") as tmp:
            port = free_port()
            env = dict(os.environ, SELFCAL_API_KEYS=f"{KEY}=ingest+read", SELFCAL_SQLITE_SYNCHRONOUS=args.synchronous)
            server = subprocess.Popen(
                [sys.executable, "-m", "selfcal.cli", "serve", "--db", f"{tmp}/bench.db", "--port", str(port),
                 "--refit-threads", str(args.refit_threads), "--log-level", "warning"],
                env=env, cwd=str(REPO), stderr=subprocess.DEVNULL,
            )
            try:
                wait_up(port)
                print(f"\n[{fmt}] devices  offered/s  sustained/s  req/s  GET p50 ms  GET p99 ms  errors")
                load = subprocess.Popen(
                    [sys.executable, __file__, "--load-only", "--port", str(port), "--devices", args.devices,
                     "--batch-s", str(args.batch_s), "--step-s", str(args.step_s), "--warmup-s", str(args.warmup_s),
                     "--connections", str(args.connections), "--get-hz", str(args.get_hz), "--format", fmt,
                     "--seed", str(args.seed), "--inflight-devices", str(args.inflight_devices),
                     "--inflight", str(args.inflight), "--inflight-rate", str(args.inflight_rate),
                     "--inflight-batch", str(args.inflight_batch)],
                    stdout=subprocess.PIPE, text=True,
                )
                for line in load.stdout:
                    r = json.loads(line)
                    if r["phase"] != "fleet":
                        label = "idle (GET only)" if r["phase"] == "idle" else \
                            f"{r['devices']} devices x {r['in_flight']} in flight, {r['req_per_s']:g} POST/s"
                        print(f"[{fmt}] {label:<44} GET p50 {r['get_p50_ms']:6.2f} ms  p99 {r['get_p99_ms']:6.2f} ms  "
                              f"max {r['get_max_ms']:6.2f} ms  (n={r['get_n']}, errors {r['errors']})", flush=True)
                        continue
                    print(f"[{fmt}] {r['devices']:7d}  {r['offered_sps']:9.0f}  {r['sustained_sps']:11.0f}  "
                          f"{r['req_per_s']:5.0f}  {r['app_get_p50_ms']:10.2f}  {r['app_get_p99_ms']:10.2f}  "
                          f"{r['errors']:6d}   (GETs from inside the load loop: p50 {r['get_p50_ms']:.2f}, "
                          f"p99 {r['get_p99_ms']:.2f} ms)", flush=True)
                load.wait(timeout=600)
                m = metric_values(port)
                stored = m.get("selfcal_ingest_samples_total", 0)
                fed = m.get("selfcal_worker_samples_total", 0)
                refits = sum(v for k, v in m.items() if k.startswith("selfcal_refits_total"))
                print(f"[{fmt}] stored {stored:.0f} samples, fed to calibrators {fed:.0f} "
                      f"({100 * fed / max(stored, 1):.0f} %), refits {refits:.0f}, "
                      f"db commits {m.get('selfcal_db_commits_total', 0):.0f} for "
                      f"{m.get('selfcal_db_writes_total', 0):.0f} writes")
            finally:
                stop_server(server)
    return 0


if __name__ == "__main__":
    sys.exit(main())
