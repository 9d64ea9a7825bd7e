"""Weight and time to first render of the fleet dashboard (``/ui``) at 1 000 devices.

Starts a real ``selfcal serve`` (real OnlineCalibrator, SQLite) on 127.0.0.1 and fills
it with ``--devices`` devices: all but one turned through 4-27 still orientations on a bench
(``tests/service/service_fleet.tumbled_stream``, one batch each, seeds 0..N-1: a mix of
calibrated, provisional and uncalibrated), and one insole streaming 2 h of the demo
wearer (the device page measured). Then headless Chromium (Playwright, Debian's
``/usr/bin/chromium``; ``scripts/chromium.sh``) opens the pages ``--runs`` times, each
in a fresh browser context (cold cache), and once more in the same context (warm:
revalidated assets answer 304).

Printed per page: bytes transferred (encoded body + headers) for the page itself
(HTML, JS, CSS) and for its API data (JSON), request counts, and the browser's own
timings from navigation start: first contentful paint, DOMContentLoaded, and the
page's mark when its content is on screen (``selfcal:table-filled`` once the 1 000 rows
are in the table; ``selfcal:device-rendered`` once every chart is drawn). Also the
size and time of ``GET /fleet`` for 1 000 devices, plain and gzipped (httpx, loopback).

    python bench/ui_weight.py                 # 1000 devices, 5 runs
    python bench/ui_weight.py --devices 200 --runs 3

Numbers depend on the machine (and on what else runs on it); they are not test gates.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests" / "service"))

from service_browser import CHROMIUM_ARGS, browser_unavailable, chromium_executable  # noqa: E402
from service_fleet import post_stream, simulated_stream, tumbled_stream  # noqa: E402
from service_helpers import KEYS, ServerProcess  # noqa: E402

PAGE_TYPES = {"document", "script", "stylesheet"}
SIM_DEVICE = "insole-sim-00"


def populate(srv: ServerProcess, n_devices: int) -> float:
    """Feed the fleet; returns the seconds until every batch was fed (backlog 0)."""
    t0 = time.perf_counter()
    with srv.client("ingest", timeout_s=60) as c:
        for i in range(n_devices - 1):  # and the simulated insole: n_devices in all
            post_stream(c, f"bench-{i:04d}", tumbled_stream(i, n_poses=4 + i % 24))
        post_stream(c, SIM_DEVICE, simulated_stream(0, 2.0))
    with srv.client("read") as c:
        while True:
            ready = c.get("/readyz").json()
            if ready["backlog_batches"] == 0:
                break
            time.sleep(0.5)
    return time.perf_counter() - t0


def measure(page, url: str, done_selector: str, mark: str) -> dict:
    """Open ``url`` and return bytes and timings (ms from navigation start)."""
    sizes: list[tuple[str, int]] = []

    def finished(request) -> None:
        s = request.sizes()
        sizes.append((request.resource_type, s["responseBodySize"] + s["responseHeadersSize"]))

    page.on("requestfinished", finished)
    page.goto(url)
    page.wait_for_selector(done_selector, timeout=60_000)
    # an arrow function: a bare expression would be eval'd, which the page's CSP forbids
    page.wait_for_function(f"() => performance.getEntriesByName('{mark}').length > 0")
    timing = page.evaluate(f"""() => {{
        const nav = performance.getEntriesByType('navigation')[0];
        const fcp = performance.getEntriesByName('first-contentful-paint')[0];
        return {{fcp: fcp ? fcp.startTime : null, dcl: nav.domContentLoadedEventEnd,
                 done: performance.getEntriesByName('{mark}')[0].startTime}};
    }}""")
    page.remove_listener("requestfinished", finished)
    page_bytes = sum(n for kind, n in sizes if kind in PAGE_TYPES)
    data_bytes = sum(n for kind, n in sizes if kind in ("fetch", "xhr"))
    return {"page_bytes": page_bytes, "data_bytes": data_bytes, "requests": len(sizes), **timing}


def summary(rows: list[dict], key: str) -> str:
    """Median (min-max) of ``key`` over the runs, in ms."""
    values = [r[key] for r in rows if r[key] is not None]
    if not values:
        return "-"
    return f"{statistics.median(values):8.0f} ({min(values):.0f}-{max(values):.0f})"


def main() -> int:
    """Fill the fleet, measure both pages, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", type=int, default=1000)
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    why = browser_unavailable()
    if why:
        print(f"ui_weight: {why}", file=sys.stderr)
        return 1
    from playwright.sync_api import sync_playwright

    import httpx

    with tempfile.TemporaryDirectory(prefix="selfcal-ui-bench-") as tmp:
        srv = ServerProcess(Path(tmp) / "bench.db", Path(tmp), calibrator=None)
        srv.start()
        try:
            fill_s = populate(srv, args.devices)
            with srv.client("read") as c:
                fleet = c.get("/fleet", headers={"Accept-Encoding": "identity"})
                rows = fleet.json()["devices"]
                timings: dict[str, list[float]] = {"identity": [], "gzip": []}
                sizes: dict[str, int] = {}
                for _ in range(10):
                    for encoding in timings:
                        t0 = time.perf_counter()
                        with c.stream("GET", "/fleet", headers={"Accept-Encoding": encoding}) as r:
                            sizes[encoding] = len(b"".join(r.iter_raw()))
                        timings[encoding].append(1e3 * (time.perf_counter() - t0))
            counts = {s: sum(d["status"] == s for d in rows) for s in ("calibrated", "provisional", "uncalibrated")}
            print(f"fleet: {len(rows)} devices ({counts}), filled in {fill_s:.1f} s")
            for encoding, ms in timings.items():
                print(f"GET /fleet ({encoding}): {sizes[encoding] / 1024:.0f} KiB on the wire, "
                      f"{statistics.median(ms):.0f} ms median of 10 (loopback, request to last byte)")
            key = KEYS["all"]
            results: dict[str, list[dict]] = {"fleet cold": [], "fleet warm": [], "device cold": [], "device warm": []}
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=chromium_executable(), args=CHROMIUM_ARGS)
                for _ in range(args.runs):
                    for name, path, selector, mark in (
                        ("fleet", "/ui", "#fleet-table[data-loaded=true]", "selfcal:table-filled"),
                        ("device", f"/ui/devices/{SIM_DEVICE}", "main[data-loaded=true]", "selfcal:device-rendered"),
                    ):
                        context = browser.new_context(viewport={"width": 1280, "height": 800})
                        page = context.new_page()
                        results[f"{name} cold"].append(measure(page, f"{srv.url}{path}#key={key}", selector, mark))
                        if name == "fleet":
                            assert page.locator("#fleet-table tbody tr").count() == len(rows)
                        results[f"{name} warm"].append(measure(page, f"{srv.url}{path}", selector, mark))
                        context.close()
                browser.close()
        finally:
            srv.stop()

    print(f"\n{args.runs} runs each, 1280x800; median (min-max). Bytes: encoded body + headers; "
          f"times: ms from navigation start")
    print(f"{'':12s} {'page KiB':>9s} {'data KiB':>9s} {'requests':>8s} {'first paint ms':>22s} "
          f"{'DOMContentLoaded ms':>22s} {'content on screen ms':>22s}")
    for name, rows_ in results.items():
        kib_page = statistics.median(r["page_bytes"] for r in rows_) / 1024
        kib_data = statistics.median(r["data_bytes"] for r in rows_) / 1024
        reqs = statistics.median(r["requests"] for r in rows_)
        print(f"{name:12s} {kib_page:9.1f} {kib_data:9.1f} {reqs:8.0f} {summary(rows_, 'fcp'):>22s} "
              f"{summary(rows_, 'dcl'):>22s} {summary(rows_, 'done'):>22s}")
    print(f"\ncontent on screen: fleet = the {len(rows)}-row table filled (performance mark selfcal:table-filled); "
          "device = every chart drawn (selfcal:device-rendered)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
