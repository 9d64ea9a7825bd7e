// selfcal dashboard, fleet page: every device with its served calibration, backlog and
// last refusal; counts per status (which also filter), a text filter, sortable columns.
// The table refreshes every REFRESH_MS without reloading the page (paused while the tab
// is hidden); rows are kept and updated in place, so focus and scroll stay put.
"use strict";

(function () {
  const REFRESH_MS = 5000;
  const PAGE_SIZE = 1000; // the /fleet maximum: 1000 devices in one request
  const STATUSES = ["calibrated", "provisional", "uncalibrated"];
  const STATUS_RANK = { calibrated: 0, provisional: 1, uncalibrated: 2 };

  const state = {
    devices: [],
    sortKey: "device_id",
    sortDir: 1,
    statusFilter: null,
    text: "",
    admin: false,
    loadedAt: null,
    rows: new Map(), // device_id -> <tr>
    timer: null,
    loading: false,
  };

  const tbody = document.querySelector("#fleet-table tbody");

  async function loadAll() {
    const devices = [];
    let after = null;
    for (;;) {
      const query = "/fleet?limit=" + PAGE_SIZE + (after ? "&after=" + encodeURIComponent(after) : "");
      const page = await selfcal.api(query);
      devices.push(...page.devices);
      if (!page.next_after) break;
      after = page.next_after;
    }
    return devices;
  }

  function refusalText(d) {
    const r = d.last_refusal;
    if (!r) return "";
    return (r.reason || "refused") + (r.kind === "batch" ? " (batch)" : "");
  }

  function sortValue(d, key) {
    switch (key) {
      case "status": return STATUS_RANK[d.status];
      case "last_seen": return d.last_seen ? Date.parse(d.last_seen) : null;
      case "last_refusal": return refusalText(d) || null;
      default: return d[key];
    }
  }

  function compare(a, b) {
    const va = sortValue(a, state.sortKey);
    const vb = sortValue(b, state.sortKey);
    if (va === vb) return a.device_id < b.device_id ? -1 : 1;
    if (va === null || va === undefined) return 1; // missing values last, whatever the direction
    if (vb === null || vb === undefined) return -1;
    return (va < vb ? -1 : 1) * state.sortDir;
  }

  function visible(d) {
    if (state.statusFilter && d.status !== state.statusFilter) return false;
    if (!state.text) return true;
    const t = state.text.toLowerCase();
    return d.device_id.toLowerCase().includes(t) || refusalText(d).toLowerCase().includes(t);
  }

  function cell(label, text, cls, title) {
    return selfcal.el("td", { "data-label": label, class: cls, title: title, text: text });
  }

  function rowFor(d) {
    let tr = state.rows.get(d.device_id);
    if (!tr) {
      tr = selfcal.el("tr", { dataset: { deviceId: d.device_id } });
      state.rows.set(d.device_id, tr);
    }
    const href = "/ui/devices/" + encodeURIComponent(d.device_id);
    const link = selfcal.el("a", { href: href, text: d.device_id, class: "device-link" });
    const status = selfcal.el("span", { class: "badge " + d.status, text: d.status });
    const version = d.version === null ? "–" : String(d.version) + (d.source && d.source !== "refit" ? " (" + d.source + ")" : "");
    const refusal = d.last_refusal;
    const cells = [
      selfcal.el("th", { scope: "row", "data-label": "Device" }, [link]),
      selfcal.el("td", { "data-label": "Status", class: "status" }, [status]),
      cell("Version", version, "version"),
      cell("Last seen", selfcal.fmtAgo(d.last_seen), "last-seen", d.last_seen || "no batch yet"),
      cell("Predicted sphere error (mg)", selfcal.fmtNumber(d.predicted_sphere_rms_mg, 2), "num predicted"),
      cell("Poses", d.n_poses === null ? "–" : String(d.n_poses), "num poses"),
      cell("Backlog (batches)", String(d.backlog_batches), "num backlog"),
      cell("Last refusal", refusalText(d) || "–", "refusal", refusal ? refusal.message : undefined),
    ];
    if (state.admin) {
      const actions = selfcal.el("td", { "data-label": "Actions", class: "actions" });
      if (d.version !== null && d.version >= 2) {
        const button = selfcal.el("button", {
          type: "button", class: "danger small rollback", text: "Roll back",
          "aria-label": "Roll back " + d.device_id + " to version " + (d.version - 1),
        });
        button.addEventListener("click", () => rollback(d));
        actions.append(button);
      }
      cells.push(actions);
    }
    // keep the focused control if this row holds it (a refresh must not steal focus)
    const focused = tr.contains(document.activeElement) ? document.activeElement.className : null;
    tr.replaceChildren(...cells);
    if (focused) {
      const again = tr.querySelector("." + focused.split(" ").filter(Boolean).join("."));
      if (again) again.focus();
    }
    tr.dataset.status = d.status;
    return tr;
  }

  function renderCounts() {
    const box = document.getElementById("status-counts");
    const counts = { all: state.devices.length };
    for (const s of STATUSES) counts[s] = 0;
    for (const d of state.devices) counts[d.status] += 1;
    const buttons = [["all", "All"], ...STATUSES.map((s) => [s, s[0].toUpperCase() + s.slice(1)])].map(([key, label]) => {
      const pressed = (state.statusFilter || "all") === key;
      const b = selfcal.el("button", {
        type: "button", class: "count " + key, "aria-pressed": pressed ? "true" : "false",
        dataset: { status: key },
      }, [selfcal.el("span", { class: "label", text: label + " " }), selfcal.el("span", { class: "n", text: String(counts[key]) })]);
      b.addEventListener("click", () => {
        state.statusFilter = key === "all" ? null : key;
        render();
        const again = box.querySelector('[data-status="' + key + '"]');
        if (again) again.focus();
      });
      return b;
    });
    box.replaceChildren(...buttons);
  }

  function renderHeaders() {
    for (const th of document.querySelectorAll("#fleet-table thead th[data-key]")) {
      const on = th.dataset.key === state.sortKey;
      if (on) th.setAttribute("aria-sort", state.sortDir > 0 ? "ascending" : "descending");
      else th.removeAttribute("aria-sort");
    }
    for (const th of document.querySelectorAll("#fleet-table .admin-only")) th.hidden = !state.admin;
  }

  function render() {
    const shown = state.devices.filter(visible).sort(compare);
    const rows = shown.map(rowFor);
    const current = Array.from(tbody.children);
    const same = current.length === rows.length && rows.every((r, i) => current[i] === r);
    if (!same) tbody.replaceChildren(...rows); // only when the order or the set changed
    const known = new Set(state.devices.map((d) => d.device_id));
    for (const id of state.rows.keys()) if (!known.has(id)) state.rows.delete(id);
    renderCounts();
    renderHeaders();
    const when = state.loadedAt ? state.loadedAt.toLocaleTimeString(undefined, { hour12: false }) : "–";
    document.getElementById("table-summary").textContent =
      "Showing " + shown.length + " of " + state.devices.length + " devices · updated " + when +
      " · refreshes every " + REFRESH_MS / 1000 + " s";
    const table = document.getElementById("fleet-table");
    if (!table.dataset.loaded) performance.mark("selfcal:table-filled"); // read by bench/ui_weight.py
    table.dataset.loaded = "true";
  }

  async function refresh() {
    if (state.loading) return;
    state.loading = true;
    try {
      state.devices = await loadAll();
      state.loadedAt = new Date();
      render();
    } catch (e) {
      if (e.status !== 401) {
        document.getElementById("table-summary").textContent = "Refresh failed: " + e.message + " (retrying)";
      }
    } finally {
      state.loading = false;
    }
  }

  function schedule() {
    clearTimeout(state.timer);
    state.timer = setTimeout(async () => {
      if (!document.hidden) await refresh();
      schedule();
    }, REFRESH_MS);
  }

  async function rollback(d) {
    const to = d.version - 1;
    const ok = await selfcal.confirmAction(
      "Roll back " + d.device_id + "?",
      "Version " + to + " will be served again, recorded as version " + (d.version + 1) +
        " (source rollback). The device's calibrator takes it as its model.",
      "Roll back to version " + to);
    if (!ok) return;
    const status = document.getElementById("action-status");
    try {
      const out = await selfcal.api("/devices/" + encodeURIComponent(d.device_id) + "/calibration/rollback",
        { method: "POST", json: { to_version: to } });
      status.className = "ok";
      status.textContent = d.device_id + ": now serving version " + out.version + " (rollback of version " + to + ").";
    } catch (e) {
      status.className = "error";
      status.textContent = d.device_id + ": rollback refused (" + e.status + "): " + e.message;
    }
    await refresh();
  }

  function init(scopes) {
    state.admin = scopes.includes("admin");
    for (const th of document.querySelectorAll("#fleet-table thead th[data-key]")) {
      th.querySelector("button").addEventListener("click", () => {
        const key = th.dataset.key;
        state.sortDir = state.sortKey === key ? -state.sortDir : 1;
        state.sortKey = key;
        render();
      });
    }
    const input = document.getElementById("filter-text");
    input.addEventListener("input", () => {
      state.text = input.value.trim();
      render();
    });
    document.addEventListener("visibilitychange", () => {
      if (!document.hidden) refresh();
    });
    refresh().then(schedule);
  }

  selfcal.start(init);
})();
