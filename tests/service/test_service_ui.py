"""The fleet dashboard (``/ui``) end to end, on the backend of this pass (SQLite or PostgreSQL).

A real ``selfcal serve`` (real calibrator, access log on) is fed with ``selfcal demo``'s
simulated insoles (``service_fleet``: the demo wearer, seeds 0-3, 2 h each), a device
turned through orientations on a bench (status calibrated), an insole switched on for
6 minutes (uncalibrated) and a device seeded from a jig only. Headless Chromium
(Playwright, Debian's ``/usr/bin/chromium``) then drives the pages.

The API part (new endpoints, scopes, assets) needs no browser; the browser part skips
when Playwright or Chromium is missing, except in CI on a machine that could install
Chromium (``service_browser.browser_required``), where it fails. The sqlite pass takes
screenshots of both pages; with ``SELFCAL_UPDATE_SCREENSHOTS=1`` they replace the README's
(``docs/img/ui_fleet.png``, ``docs/img/ui_device.png``), else they go to a temporary
folder (a test run leaves the working tree as it found it).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from pathlib import Path

import httpx
import pytest

from service_browser import CHROMIUM_ARGS, CONTRAST_JS, browser_required, browser_unavailable, chromium_executable
from service_fleet import JIG_CALIBRATION, post_stream, simulated_stream, tumbled_stream
from service_helpers import KEYS, REPO, ServerProcess, auth, backend

pytestmark = pytest.mark.service

WEARERS = [f"insole-{seed:02d}" for seed in range(4)]
BENCH = "bench-07"
SHORT = "insole-short"
JIG = "jig-01"
ALL_DEVICES = sorted([*WEARERS, BENCH, SHORT, JIG])
SCREENSHOTS = (REPO / "docs" / "img" if os.environ.get("SELFCAL_UPDATE_SCREENSHOTS") == "1"
               else Path(tempfile.gettempdir()) / "selfcal-ui-screenshots")
WIDE = {"width": 1280, "height": 800}
PHONE = {"width": 390, "height": 844}


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """A server holding the small fleet above, every batch processed."""
    tmp = tmp_path_factory.mktemp("ui")
    srv = ServerProcess(tmp / "selfcal.db", tmp, calibrator=None, env={"SELFCAL_ACCESS_LOG": "true"},
                        args=["--log-level", "info"])
    srv.start()
    try:
        last = {}
        with srv.client("ingest", timeout_s=30) as c:
            for seed, device in enumerate(WEARERS):
                last[device] = post_stream(c, device, simulated_stream(seed, 2.0))
            last[BENCH] = post_stream(c, BENCH, tumbled_stream(7))
            last[SHORT] = post_stream(c, SHORT, simulated_stream(11, 0.1))
        with srv.client("admin") as c:
            assert c.put(f"/devices/{JIG}/calibration", json=JIG_CALIBRATION).status_code == 200
        for device, seq in last.items():
            srv.wait_processed(device, seq, timeout_s=120)
        yield srv
    finally:
        srv.stop()


def _get(srv, path, scope="read"):
    with srv.client(scope) as c:
        r = c.get(path)
    assert r.status_code == 200, r.text
    return r.json()


# ----------------------------------------------------------------- the API the pages read
def test_fleet_endpoint_agrees_with_the_device_endpoints(fleet):
    rows = _get(fleet, "/fleet")["devices"]
    assert [d["device_id"] for d in rows] == ALL_DEVICES
    listed = {d["device_id"]: d for d in _get(fleet, "/devices?limit=1000")["devices"]}
    statuses = set()
    for row in rows:
        cal = _get(fleet, f"/devices/{row['device_id']}/calibration")
        assert row["status"] == listed[row["device_id"]]["status"] == cal["status"]
        assert row["version"] == cal["version"] and row["source"] == cal["source"]
        assert row["predicted_sphere_rms_mg"] == cal["predicted_sphere_rms_mg"]
        assert row["n_poses"] == cal["n_poses"] and row["backlog_batches"] == 0
        assert row["batches_stored"] == cal["batches_stored"]
        statuses.add(row["status"])
    assert statuses == {"calibrated", "provisional", "uncalibrated"}
    by_id = {d["device_id"]: d for d in rows}
    assert by_id[JIG]["last_seen"] is None and by_id[JIG]["source"] == "factory"  # seeded, never sent a batch
    assert by_id[WEARERS[0]]["last_seen"] is not None
    assert by_id[WEARERS[0]]["last_refusal"]["kind"] == "refit" and by_id[WEARERS[0]]["last_refusal"]["reason"]
    # paging and a single device
    first = _get(fleet, "/fleet?limit=3")
    assert [d["device_id"] for d in first["devices"]] == ALL_DEVICES[:3] and first["next_after"] == ALL_DEVICES[2]
    rest = _get(fleet, f"/fleet?limit=1000&after={first['next_after']}")
    assert [d["device_id"] for d in rest["devices"]] == ALL_DEVICES[3:] and rest["next_after"] is None
    one = _get(fleet, f"/fleet?device_id={BENCH}")["devices"]
    assert len(one) == 1 and one[0] == by_id[BENCH]


def test_refusals_log_every_refit_that_published_nothing(fleet):
    device = WEARERS[1]
    refusals = _get(fleet, f"/devices/{device}/refusals")["refusals"]
    assert refusals, "the demo wearer's calibrator holds back most refits"
    assert all(r["kind"] == "refit" and r["reason"] and r["at"] and r["t_s"] is not None for r in refusals)
    times = [r["at_unix_s"] for r in refusals]
    assert times == sorted(times)
    assert {r["reason"] for r in refusals} <= {"no_significant_change", "worse_than_current",
                                               "insufficient_coverage", "no_still_poses", "implausible",
                                               "not_converged"}
    last = _get(fleet, f"/fleet?device_id={device}")["devices"][0]["last_refusal"]
    assert last == refusals[-1]
    assert len(_get(fleet, f"/devices/{device}/refusals?limit=2")["refusals"]) == min(2, len(refusals))
    assert _get(fleet, f"/devices/{JIG}/refusals")["refusals"] == []


def test_poses_give_unit_directions_temperatures_residuals_and_undetermined_directions(fleet):
    device = WEARERS[0]
    cal = _get(fleet, f"/devices/{device}/calibration")
    poses = _get(fleet, f"/devices/{device}/poses")
    assert poses["available"] and poses["version"] == cal["version"] and poses["residual_basis"] == "served"
    n = poses["n_poses"]
    assert n >= cal["n_poses"] > 0  # the store may have grown since the served refit
    assert len(poses["direction"]) == len(poses["temp_c"]) == len(poses["residual_mg"]) == len(poses["windows"]) == n
    assert all(abs(math.hypot(*d) - 1.0) < 1e-3 for d in poses["direction"])
    assert all(15.0 < t < 40.0 for t in poses["temp_c"])  # the simulated insole warms in the shoe
    assert 0 < poses["residual_rms_mg"] < 5.0
    sphere = poses["sphere"]
    assert len(sphere["direction"]) == len(sphere["sd_mg"]) == len(sphere["undetermined"]) == 300
    assert all((sd > poses["undetermined_above_sd_mg"]) == u for sd, u in zip(sphere["sd_mg"], sphere["undetermined"]))
    assert 0 < sum(sphere["undetermined"]) < 300  # a flat-worn insole leaves part of the sphere open
    bench = _get(fleet, f"/devices/{BENCH}/poses")  # turned through every orientation: little left open
    assert sum(bench["sphere"]["undetermined"]) < sum(sphere["undetermined"])
    jig = _get(fleet, f"/devices/{JIG}/poses")  # seeded, never fed: no pose, all open
    assert jig["n_poses"] == 0 and all(jig["sphere"]["undetermined"])


def test_new_endpoints_need_the_read_scope_and_whoami_names_the_scopes(fleet):
    for path in ("/fleet", f"/devices/{BENCH}/refusals", f"/devices/{BENCH}/poses"):
        assert httpx.get(fleet.url + path).status_code == 401
        assert httpx.get(fleet.url + path, headers=auth("ingest")).status_code == 403
    for path in ("/devices/nope-1/refusals", "/devices/nope-1/poses"):
        assert httpx.get(fleet.url + path, headers=auth("read")).status_code == 404
    assert httpx.get(fleet.url + "/fleet?device_id=bad%20id", headers=auth("read")).status_code == 422
    assert httpx.get(fleet.url + "/whoami").status_code == 401
    assert httpx.get(fleet.url + "/whoami", headers={"Authorization": "Bearer not-a-key-123"}).status_code == 401
    assert _get(fleet, "/whoami", "read") == {"scopes": ["read"]}
    assert _get(fleet, "/whoami", "admin") == {"scopes": ["admin"]}
    assert _get(fleet, "/whoami", "all") == {"scopes": ["admin", "ingest", "read"]}


def test_dashboard_assets_ship_in_the_package_with_a_strict_policy(fleet):
    page = httpx.get(fleet.url + "/ui")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    csp = page.headers["content-security-policy"]
    assert "script-src 'self'" in csp and "frame-ancestors 'none'" in csp
    assert page.headers["referrer-policy"] == "no-referrer"
    assert "http://" not in page.text and "https://" not in page.text  # no CDN
    assert httpx.get(fleet.url + f"/ui/devices/{BENCH}").status_code == 200
    lib = httpx.get(fleet.url + "/ui/static/vendor/uplot/uPlot.iife.min.js", headers={"Accept-Encoding": "gzip"})
    assert lib.status_code == 200 and lib.headers["content-encoding"] == "gzip" and "uPlot" in lib.text
    again = httpx.get(fleet.url + "/ui/static/vendor/uplot/uPlot.iife.min.js", headers={"If-None-Match": lib.headers["etag"]})
    assert again.status_code == 304
    assert "MIT" in httpx.get(fleet.url + "/ui/static/vendor/uplot/LICENSE").text
    assert httpx.get(fleet.url + "/ui/static/nothing.js").status_code == 404
    assert httpx.get(fleet.url + "/ui/static/../main.py").status_code == 404
    assert "/ui" not in json.dumps(httpx.get(fleet.url + "/openapi.json").json()["paths"])


# ----------------------------------------------------------------- the pages, in Chromium
@pytest.fixture(scope="module")
def browser():
    why = browser_unavailable()
    if why:
        if browser_required():
            pytest.fail(f"CI as root with apt-get: the dashboard tests must run, but {why}")
        pytest.skip(why)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        chromium = pw.chromium.launch(executable_path=chromium_executable(), args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


def _page(browser, viewport=WIDE):
    context = browser.new_context(viewport=viewport, accept_downloads=True)
    page = context.new_page()
    page.set_default_timeout(15_000)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.errors = errors  # type: ignore[attr-defined]
    return page


def _open_fleet(page, url, scope="all"):
    page.goto(f"{url}/ui#key={KEYS[scope]}")
    page.wait_for_selector("#fleet-table[data-loaded=true]")


def _rows(page) -> dict[str, dict[str, str]]:
    return page.evaluate("""() => Object.fromEntries(Array.from(document.querySelectorAll('#fleet-table tbody tr'))
        .map(tr => [tr.dataset.deviceId, {status: tr.querySelector('.badge').textContent,
                                           version: tr.querySelector('.version').textContent}]))""")


def test_fleet_page_lists_every_device_with_the_status_the_api_reports(fleet, browser):
    page = _page(browser)
    _open_fleet(page, fleet.url)
    # the key handed over in the fragment is stored for the tab and gone from the address bar
    assert page.url == f"{fleet.url}/ui" and KEYS["all"] not in page.url
    assert page.evaluate("sessionStorage.getItem('selfcal.apiKey')") == KEYS["all"]
    assert page.evaluate("location.hash") == ""
    api = {d["device_id"]: d for d in _get(fleet, "/fleet")["devices"]}
    rows = _rows(page)
    assert sorted(rows) == ALL_DEVICES
    assert {k: r["status"] for k, r in rows.items()} == {k: d["status"] for k, d in api.items()}
    counts = page.evaluate("""() => Object.fromEntries(Array.from(document.querySelectorAll('#status-counts button'))
        .map(b => [b.dataset.status, Number(b.querySelector('.n').textContent)]))""")
    assert counts == {"all": 7, "calibrated": 1, "provisional": 5, "uncalibrated": 1}
    # filter by status (a count button) and by text
    page.click('#status-counts button[data-status="calibrated"]')
    assert list(_rows(page)) == [BENCH]
    page.click('#status-counts button[data-status="all"]')
    page.fill("#filter-text", "short")
    assert list(_rows(page)) == [SHORT]
    page.fill("#filter-text", "")
    # sort by predicted sphere error, descending on a second click (devices without one last)
    page.click('th[data-key="predicted_sphere_rms_mg"] button')
    page.click('th[data-key="predicted_sphere_rms_mg"] button')
    assert page.get_attribute('th[data-key="predicted_sphere_rms_mg"]', "aria-sort") == "descending"
    order = list(_rows(page))
    known = sorted((d for d in api.values() if d["predicted_sphere_rms_mg"] is not None),
                   key=lambda d: -d["predicted_sphere_rms_mg"])
    assert order[: len(known)] == [d["device_id"] for d in known] and order[-1] == SHORT
    if backend() == "sqlite":
        page.click('th[data-key="device_id"] button')
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SCREENSHOTS / "ui_fleet.png"))
    # it refreshes without reloading: a new device appears, the page is the same document
    page.evaluate("window.__sameDocument = true")
    with fleet.client("ingest") as c:
        post_stream(c, "insole-new", simulated_stream(12, 0.05))
    page.wait_for_selector('#fleet-table tr[data-device-id="insole-new"]', timeout=20_000)
    assert page.evaluate("window.__sameDocument") is True
    assert page.errors == []
    page.go_back()  # the entry with the key in its fragment was replaced, not kept in the history
    assert page.url == "about:blank"


def test_device_page_history_chart_has_one_point_per_version(fleet, browser):
    device = WEARERS[0]
    page = _page(browser)
    _open_fleet(page, fleet.url)
    page.click(f'#fleet-table tr[data-device-id="{device}"] a.device-link')
    page.wait_for_selector("main[data-loaded=true]")
    assert page.url == f"{fleet.url}/ui/devices/{device}"
    history = _get(fleet, f"/devices/{device}/calibration/history")
    n_versions = len(history["versions"])
    assert n_versions >= 2
    assert page.evaluate("window.selfcalCharts.history.data[0].length") == n_versions
    assert page.get_attribute("#chart-history", "data-points") == str(n_versions)
    # every parameter: its own chart with value and +-2 sd, one point per version
    params = list(history["versions"][-1]["calibration"]["params"])
    for name in params:
        data = page.evaluate(f"window.selfcalCharts['param-{name}'].data")
        assert len(data) == 4 and all(len(s) == n_versions for s in data)
        assert all(hi >= v >= lo for v, hi, lo in zip(data[1], data[2], data[3]) if None not in (v, hi, lo))
    refusals = _get(fleet, f"/devices/{device}/refusals")["refusals"]
    assert page.get_attribute("#chart-refusals", "data-points") == str(len(refusals))
    # refusals share the history's time axis
    same_axis = page.evaluate("""() => { const h = window.selfcalCharts.history.scales.x,
        r = window.selfcalCharts.refusals.scales.x; return [h.min === r.min, h.max === r.max]; }""")
    assert same_axis == [True, True]
    poses = _get(fleet, f"/devices/{device}/poses")
    shown = int(page.get_attribute("#chart-upper", "data-points")) + int(page.get_attribute("#chart-lower", "data-points"))
    assert shown == poses["n_poses"]
    assert page.get_attribute("#chart-residuals", "data-points") == str(poses["n_poses"])
    assert "undetermined" in page.inner_text("#coverage-legend")
    # the calibration JSON and its download
    cal = _get(fleet, f"/devices/{device}/calibration")
    assert json.loads(page.inner_text("#calibration-json")) == cal
    with page.expect_download() as download:
        page.click("#download-json")
    assert download.value.suggested_filename == f"calibration-{device}-v{cal['version']}.json"
    assert json.loads(Path(download.value.path()).read_text()) == cal
    if backend() == "sqlite":
        page.screenshot(path=str(SCREENSHOTS / "ui_device.png"), full_page=True)
    # a window turned to phone width: the charts are redrawn to fit, with the same points
    page.set_viewport_size(PHONE)
    page.wait_for_function(f"() => window.selfcalCharts.history.width <= {PHONE['width']}")
    assert page.evaluate("window.selfcalCharts.history.data[0].length") == n_versions
    assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
    assert page.errors == []


def test_admin_rollback_from_the_table_after_confirmation(fleet, browser):
    device = WEARERS[1]
    before = _get(fleet, f"/devices/{device}/calibration")
    page = _page(browser)
    _open_fleet(page, fleet.url, "all")
    button = f'#fleet-table tr[data-device-id="{device}"] button.rollback'
    page.click(button)
    assert page.is_visible("#confirm") and page.evaluate("document.activeElement.id") == "confirm-cancel"
    page.keyboard.press("Escape")  # cancelled: nothing happens
    assert not page.is_visible("#confirm")
    assert _get(fleet, f"/devices/{device}/calibration")["version"] == before["version"]
    page.click(button)
    page.click("#confirm-ok")
    new_version = before["version"] + 1
    page.wait_for_function(
        f"""() => document.querySelector('#fleet-table tr[data-device-id="{device}"] .version')
            .textContent === '{new_version} (rollback)'""")
    after = _get(fleet, f"/devices/{device}/calibration")
    assert after["version"] == new_version and after["source"] == "rollback"
    assert after["params"] == _get(fleet, f"/devices/{device}/calibration/history")["versions"][before["version"] - 2][
        "calibration"]["params"]
    assert "now serving version" in page.inner_text("#action-status")
    assert page.errors == []


def test_admin_seed_from_a_jig_calibration_goes_through_the_api_validation(fleet, browser):
    device = WEARERS[2]
    page = _page(browser)
    _open_fleet(page, fleet.url, "all")
    page.goto(f"{fleet.url}/ui/devices/{device}")
    page.wait_for_selector("main[data-loaded=true]")
    before = _get(fleet, f"/devices/{device}/calibration")
    singular = dict(JIG_CALIBRATION, matrix=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    page.fill("#seed-json", json.dumps(singular))
    page.click("#seed-button")
    page.click("#confirm-ok")
    page.wait_for_selector("#admin-status.error")
    assert "422" in page.inner_text("#admin-status") and "matrix" in page.inner_text("#admin-status")
    assert _get(fleet, f"/devices/{device}/calibration")["version"] == before["version"]  # nothing written
    page.fill("#seed-json", json.dumps(JIG_CALIBRATION))
    page.click("#seed-button")
    page.click("#confirm-ok")
    page.wait_for_selector("#admin-status.ok")
    after = _get(fleet, f"/devices/{device}/calibration")
    assert after["version"] == before["version"] + 1 and after["source"] == "factory"
    assert after["params"]["sx"] == pytest.approx(JIG_CALIBRATION["matrix"][0][0])
    page.wait_for_function(f"() => window.selfcalCharts.history.data[0].length === {after['version']}")
    assert page.errors == []


def test_read_key_sees_no_admin_action_and_the_server_refuses_it_when_forced(fleet, browser):
    device = WEARERS[3]
    before = _get(fleet, f"/devices/{device}/calibration")
    page = _page(browser)
    page.goto(f"{fleet.url}/ui")  # no key yet: the page asks for one
    page.wait_for_selector("#key-panel:not([hidden])")
    page.fill("#key-input", "wrong-key-000")
    page.click("#key-form button[type=submit]")
    page.wait_for_selector("#key-error:has-text('does not know')")
    page.fill("#key-input", KEYS["admin"])  # admin without read: the dashboard cannot show anything
    page.click("#key-form button[type=submit]")
    page.wait_for_selector("#key-error:has-text('no read scope')")
    page.fill("#key-input", KEYS["read"])
    page.click("#key-form button[type=submit]")
    page.wait_for_selector("#fleet-table[data-loaded=true]")
    assert page.locator("button.rollback").count() == 0
    assert not page.is_visible("#fleet-table th.admin-only")
    page.goto(f"{fleet.url}/ui/devices/{device}")
    page.wait_for_selector("main[data-loaded=true]")
    assert not page.is_visible("#admin") and not page.is_visible("#rollback-button")
    # forced from the page with its own key: the server refuses both actions
    statuses = page.evaluate("""async (device) => {
        const headers = {Authorization: 'Bearer ' + sessionStorage.getItem('selfcal.apiKey'),
                         'Content-Type': 'application/json'};
        const base = '/devices/' + device + '/calibration';
        const a = await fetch(base + '/rollback', {method: 'POST', headers, body: '{}'});
        const b = await fetch(base, {method: 'PUT', headers, body: JSON.stringify(
            {matrix: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], offset: [0, 0, 0]})});
        return [a.status, (await a.json()).error, b.status];
    }""", device)
    assert statuses == [403, "forbidden", 403]
    with fleet.client("read") as c:
        assert c.post(f"/devices/{device}/calibration/rollback", json={}).status_code == 403
    assert _get(fleet, f"/devices/{device}/calibration")["version"] == before["version"]
    assert page.errors == []


def test_keyboard_contrast_and_phone_width(fleet, browser):
    page = _page(browser)
    _open_fleet(page, fleet.url, "all")
    # keyboard only: Tab to the first device link (every stop shows a focus ring), Enter opens it
    page.evaluate("document.activeElement.blur()")
    for _ in range(40):
        page.keyboard.press("Tab")
        focus = page.evaluate("""() => { const e = document.activeElement, s = getComputedStyle(e);
            return {cls: e.className, tag: e.tagName, outline: s.outlineStyle, width: parseFloat(s.outlineWidth)}; }""")
        assert focus["outline"] != "none" and focus["width"] >= 2, focus
        if "device-link" in focus["cls"]:
            break
    else:
        pytest.fail("no device link reached with Tab")
    first = ALL_DEVICES[0]
    page.keyboard.press("Enter")
    page.wait_for_selector("main[data-loaded=true]")
    assert page.url.endswith(f"/ui/devices/{first}")
    page.go_back()
    page.wait_for_selector("#fleet-table[data-loaded=true]")
    page.focus('th[data-key="backlog_batches"] button')
    page.keyboard.press("Enter")
    assert page.get_attribute('th[data-key="backlog_batches"]', "aria-sort") == "ascending"
    # WCAG AA text contrast and no horizontal scrolling, wide and phone-width, both pages
    for viewport in (WIDE, PHONE):
        p = _page(browser, viewport)
        for path in ("/ui", f"/ui/devices/{WEARERS[0]}"):
            p.goto(f"{fleet.url}{path}#key={KEYS['all']}")
            p.wait_for_selector("#fleet-table[data-loaded=true], main[data-loaded=true]")
            report = p.evaluate(CONTRAST_JS)
            assert report["checked"] > 50 and report["failures"] == [], (viewport, path, report["failures"][:5])
            assert p.evaluate("document.documentElement.scrollWidth") <= viewport["width"], (viewport, path)
        assert p.errors == []


def test_keys_never_reach_the_access_log(fleet, browser):
    page = _page(browser)
    _open_fleet(page, fleet.url, "read")
    page.goto(f"{fleet.url}/ui/devices/{BENCH}")
    page.wait_for_selector("main[data-loaded=true]")
    time.sleep(0.3)  # the access log line is written after the response
    log = fleet.log.read_text()
    assert '"GET /ui HTTP/1.1" 200' in log and "/fleet" in log  # the access log is on
    for key in KEYS.values():
        assert key not in log
