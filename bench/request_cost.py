"""CPU cost of one request in an API process: server CPU milliseconds per ingest and per GET.

A GET's latency under load is set by what the API process's event loop does for every
request in front of it, so this is the figure to drive down. For each configuration a
real ``selfcal serve`` is started (PostgreSQL: ``--no-refit``, so no refit runs in the
process measured; SQLite: the refits run in-process, so its POST figure includes them
unless ``--sqlite`` is skipped), then one keep-alive client sends ``--n`` binary batches
of 400 samples (20 s at 20 Hz) for ``--devices`` devices, one at a time, then ``--n``
GETs. The server's CPU time (user + system, from ``/proc``) is read before and after
each phase. Sequential requests on an idle machine: no queueing, just the work.

    python bench/request_cost.py                 # h11 and httptools, PostgreSQL and SQLite
    python bench/request_cost.py --n 2000 --parsers httptools --backends postgresql

Linux only (``/proc``). The figures depend on the machine; they are not test gates.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "bench"))
sys.path.insert(0, str(REPO / "tests"))

from service_load import KEY, Conn, encode, free_port, insole_stream, stop_server, wait_up  # noqa: E402


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of ``pid`` and its children still alive (Linux /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    pids = [pid]
    try:
        pids += [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        pass
    for p in pids:
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / tick
    return total


def run(backend: str, db: str, parser: str, args) -> dict[str, float]:
    import asyncio

    port = free_port()
    env = dict(os.environ, SELFCAL_API_KEYS=f"{KEY}=ingest+read", SELFCAL_HTTP_PARSER=parser)
    cmd = [sys.executable, "-m", "selfcal.cli", "serve", "--db", db, "--port", str(port), "--log-level", "warning"]
    if backend == "postgresql":
        cmd += ["--no-refit"]
    server = subprocess.Popen(cmd, env=env, cwd=str(REPO), stderr=subprocess.DEVNULL)
    try:
        wait_up(port)
        rng = np.random.default_rng(args.seed)
        stream = insole_stream(rng, 400 * 64)
        bodies = []
        for i in range(args.n):
            dev, seq = i % args.devices, i // args.devices
            c = (400 * seq) % (len(stream) - 400)
            body, ctype = encode("binary", seq, seq * 20.0 + np.arange(400) / 20.0, stream[c:c + 400])
            bodies.append((f"/devices/cost-{dev:05d}/samples", body, ctype))

        async def send_posts(conn: Conn) -> None:
            for path, body, ctype in bodies:
                status, _ = await conn.request("POST", path, body, ctype)
                assert status == 200, status

        async def send_gets(conn: Conn) -> None:
            for i in range(args.n):
                status, _ = await conn.request("GET", f"/devices/cost-{i % args.devices:05d}/calibration")
                assert status in (200, 404), status

        async def main() -> dict[str, float]:
            conn = Conn("127.0.0.1", port)
            await conn.request("GET", "/healthz")
            out = {}
            for name, fn in (("post", send_posts), ("get", send_gets)):
                c0, t0 = cpu_s(server.pid), time.perf_counter()
                await fn(conn)
                wall = time.perf_counter() - t0
                out[f"{name}_cpu_ms"] = 1e3 * (cpu_s(server.pid) - c0) / args.n
                out[f"{name}_wall_ms"] = 1e3 * wall / args.n
            return out

        return asyncio.run(main())
    finally:
        stop_server(server)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1500, help="requests per phase")
    ap.add_argument("--devices", type=int, default=500)
    ap.add_argument("--parsers", default="h11,httptools")
    ap.add_argument("--backends", default="postgresql,sqlite")
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args()
    print(f"selfcal request cost: {args.n} binary ingests of 400 samples over {args.devices} devices, then "
          f"{args.n} GETs, one keep-alive connection, sequential; server CPU (user + system) per request\n")
    print("| backend | parser | ingest CPU ms | ingest wall ms | GET CPU ms | GET wall ms |")
    print("|---|---|---:|---:|---:|---:|")
    pg_ctx = None
    try:
        for backend in args.backends.split(","):
            for parser in args.parsers.split(","):
                if backend == "postgresql":
                    if pg_ctx is None:
                        from pg_cluster import PgCluster, unavailable

                        why = unavailable()
                        if why:
                            print(f"PostgreSQL unavailable: {why}", file=sys.stderr)
                            break
                        pg_ctx = PgCluster()
                        pg_ctx.start()
                    db = pg_ctx.create_database(f"cost_{parser}")
                    r = run(backend, db, parser, args)
                else:
                    with tempfile.TemporaryDirectory(prefix="selfcal-cost-") as tmp:
                        r = run(backend, f"{tmp}/cost.db", parser, args)
                note = " (refits in-process)" if backend == "sqlite" else ""
                print(f"| {backend}{note} | {parser} | {r['post_cpu_ms']:.2f} | {r['post_wall_ms']:.2f} | "
                      f"{r['get_cpu_ms']:.2f} | {r['get_wall_ms']:.2f} |", flush=True)
    finally:
        if pg_ctx is not None:
            pg_ctx.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
