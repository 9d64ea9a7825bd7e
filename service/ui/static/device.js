// selfcal dashboard, device page: the served calibration, the history of versions (each
// parameter with its +-2 sd band, the predicted sphere error) with the refusals on the
// same time axis, the pose coverage on an equal-area projection of the sphere coloured by
// temperature with the undetermined directions marked, the residual histogram, the
// calibration JSON (download), and for an admin key: rollback and a jig seed.
// Charts: uPlot (vendored, MIT). Every chart has a text alternative (tables, labels).
"use strict";

(function () {
  const deviceId = decodeURIComponent(window.location.pathname.split("/").pop());
  const base = "/devices/" + encodeURIComponent(deviceId);
  const SYNC_KEY = "selfcal-time";
  const charts = {}; // name -> uPlot, also on window.selfcalCharts (tests read the plotted points)
  window.selfcalCharts = charts;
  let current = null;

  // Parameter display units (the service works in g): [factor, offset subtracted, unit]
  const PARAM_UNITS = {
    b: [1e3, 0, "mg"], s: [1e3, 1, "‰ (s − 1)"], n: [1e3, 0, "mrad"], psi: [1e3, 0, "mrad"],
    theta: [1e3, 0, "mrad"], phi: [1e3, 0, "mrad"], tb: [1e3, 0, "mg/°C"], ts: [1e6, 0, "ppm/°C"],
    db: [1e3, 0, "mg/day"], q: [1e3, 0, "‰/g"],
  };
  // Colours with >= 3:1 contrast against white (WCAG non-text contrast), colour-blind safe order
  const COLOURS = { line: "#0b57d0", band: "rgba(11, 87, 208, 0.16)", accent: "#b3261e", grid: "#d9d9d9" };
  // Temperature bins: a sequential palette (cividis-like), every colour >= 3:1 on white
  const TEMP_COLOURS = ["#00429d", "#3a6aa8", "#6b7f3a", "#a06a00", "#b3261e"];
  const NO_TEMP_COLOUR = "#5f6368";
  const REFUSAL_COLOURS = ["#6b4aa8", "#b3261e", "#0b6e4f", "#8a5300", "#00579c", "#5f6368", "#a0306e"];

  function unitOf(name) {
    const family = name.match(/^(tb|ts|db|psi|theta|phi|b|s|n|q)/);
    return PARAM_UNITS[family ? family[1] : ""] || [1, 0, ""];
  }

  function el(tag, attrs, children) {
    return selfcal.el(tag, attrs, children);
  }

  function chartWidth(node) {
    return Math.max(240, Math.floor(node.getBoundingClientRect().width || node.parentElement.clientWidth || 600));
  }

  function pad2(n) {
    return String(n).padStart(2, "0");
  }

  /** Time ticks on one line, local time: HH:MM:SS(.s) for short spans, MM-DD HH:MM for long ones. */
  function timeTicks(u, splits) {
    const span = (u.scales.x.max - u.scales.x.min) || 1;
    return splits.map((s) => {
      const d = new Date(s * 1000);
      const hms = pad2(d.getHours()) + ":" + pad2(d.getMinutes());
      if (span > 2 * 86400) return pad2(d.getMonth() + 1) + "-" + pad2(d.getDate()) + " " + hms;
      if (span > 600) return hms;
      const sec = span < 20 ? (d.getSeconds() + (s % 1)).toFixed(1).padStart(4, "0") : pad2(d.getSeconds());
      return hms + ":" + sec;
    });
  }

  function timeAxis(extra) {
    return axisStyle(Object.assign({ values: timeTicks, size: 34, space: 90 }, extra || {}));
  }

  function axisStyle(extra) {
    return Object.assign({ stroke: "#1a1a1a", grid: { stroke: COLOURS.grid, width: 1 }, ticks: { stroke: COLOURS.grid } }, extra || {});
  }

  function mount(name, node, opts, data) {
    if (charts[name]) charts[name].destroy();
    node.replaceChildren();
    const chart = new uPlot(opts, data, node);
    charts[name] = chart;
    node.dataset.points = String(name === "history" ? data[0].length : node.dataset.points || "");
    return chart;
  }

  // ------------------------------------------------------------ summary
  function renderSummary(cal, fleetRow) {
    const items = [
      ["Status", cal.status], ["Version", cal.version === null ? "none yet" : cal.version + (cal.source ? " (" + cal.source + ")" : "")],
      ["Predicted sphere error", cal.predicted_sphere_rms_mg === null ? "–" : selfcal.fmtNumber(cal.predicted_sphere_rms_mg, 2) + " mg"],
      ["Fit residual RMS", cal.residual_rms_mg === null ? "–" : selfcal.fmtNumber(cal.residual_rms_mg, 2) + " mg"],
      ["Poses", cal.n_poses === null ? "–" : String(cal.n_poses)],
      ["Undetermined parameters", (cal.undetermined || []).join(", ") || "none"],
      ["Samples fed", cal.samples_processed.toLocaleString()],
      ["Batches stored", cal.batches_stored.toLocaleString()],
      ["Backlog", fleetRow ? fleetRow.backlog_batches + " batches" : "–"],
      ["Rejected batches", String(cal.rejected_batches)],
      ["Last refit", cal.last_refit ? (cal.last_refit.published ? "published" : "refused: " + (cal.last_refit.reason || "?")) : "–"],
      ["Published", cal.updated_at ? selfcal.fmtTime(cal.updated_at) : "–"],
    ];
    const dl = document.getElementById("summary");
    dl.replaceChildren(...items.map(([k, v]) => el("div", {}, [el("dt", { text: k }), el("dd", { text: v })])));
  }

  // ------------------------------------------------------------ history
  function seconds(iso) {
    return Date.parse(iso) / 1000;
  }

  function timeRange(versions, refusals) {
    const xs = versions.map((v) => seconds(v.created_at)).concat(refusals.map((r) => r.at_unix_s));
    if (!xs.length) return null;
    let lo = Math.min(...xs);
    let hi = Math.max(...xs);
    const pad = Math.max(1, (hi - lo) * 0.04);
    return [lo - pad, hi + pad];
  }

  function renderHistory(versions, refusals) {
    const node = document.getElementById("chart-history");
    const xs = versions.map((v) => seconds(v.created_at));
    const ys = versions.map((v) => (v.calibration.predicted_sphere_rms_mg ?? null));
    const range = timeRange(versions, refusals);
    const known = ys.filter((y) => y !== null);
    node.setAttribute("aria-label", versions.length
      ? "Predicted sphere error of " + versions.length + " versions, from " + selfcal.fmtNumber(known[0], 2) +
        " mg to " + selfcal.fmtNumber(known[known.length - 1], 2) + " mg"
      : "No version yet");
    node.dataset.points = String(xs.length);
    if (!versions.length) {
      node.replaceChildren(el("p", { class: "muted", text: "No version published yet." }));
      return;
    }
    mount("history", node, {
      width: chartWidth(node), height: 220,
      cursor: { sync: { key: SYNC_KEY }, points: { size: 9 } },
      scales: { x: { time: true, range: () => range }, y: { range: (u, lo, hi) => [0, Math.max(1, hi * 1.15)] } },
      axes: [timeAxis(), axisStyle({ label: "mg", size: 56 })],
      series: [
        { label: "time" },
        { label: "predicted sphere error (mg)", stroke: COLOURS.line, width: 2, points: { show: true, size: 8, fill: COLOURS.line },
          value: (u, v) => selfcal.fmtNumber(v, 2) + " mg" },
      ],
    }, [xs, ys]);
  }

  function renderRefusals(versions, refusals) {
    const node = document.getElementById("chart-refusals");
    const reasons = Array.from(new Set(refusals.map((r) => (r.kind === "batch" ? "batch: " : "") + (r.reason || "?")))).sort();
    node.setAttribute("aria-label", refusals.length
      ? refusals.length + " refusals: " + reasons.map((r) => r + " " + refusals.filter((x) => ((x.kind === "batch" ? "batch: " : "") + (x.reason || "?")) === r).length).join(", ")
      : "No refusal recorded");
    node.dataset.points = String(refusals.length);
    if (!refusals.length) {
      node.replaceChildren(el("p", { class: "muted", text: "No refusal recorded." }));
      return;
    }
    const range = timeRange(versions, refusals);
    // one series per reason (aligned data: the union of times, null where another reason)
    const times = Array.from(new Set(refusals.map((r) => r.at_unix_s))).sort((a, b) => a - b);
    const index = new Map(times.map((t, i) => [t, i]));
    const data = [times];
    reasons.forEach((reason, k) => {
      const ys = new Array(times.length).fill(null);
      for (const r of refusals) {
        if (((r.kind === "batch" ? "batch: " : "") + (r.reason || "?")) === reason) ys[index.get(r.at_unix_s)] = k;
      }
      data.push(ys);
    });
    mount("refusals", node, {
      width: chartWidth(node), height: 60 + 26 * reasons.length,
      cursor: { sync: { key: SYNC_KEY }, points: { size: 9 } },
      legend: { show: false },
      scales: { x: { time: true, range: () => range }, y: { range: [-0.7, reasons.length - 0.3] } },
      axes: [timeAxis(), axisStyle({
        size: 190, splits: () => reasons.map((_, i) => i), values: () => reasons, grid: { show: false },
      })],
      series: [{ label: "time" }].concat(reasons.map((reason, k) => ({
        label: reason, stroke: REFUSAL_COLOURS[k % REFUSAL_COLOURS.length], width: 0, paths: () => null,
        points: { show: true, size: 8, fill: REFUSAL_COLOURS[k % REFUSAL_COLOURS.length] },
      }))),
    }, data);
  }

  function renderParams(versions) {
    const box = document.getElementById("param-charts");
    box.replaceChildren();
    const names = [];
    for (const v of versions) for (const name of Object.keys(v.calibration.params || {})) if (!names.includes(name)) names.push(name);
    if (!names.length) {
      box.append(el("p", { class: "muted", text: "No parameters yet." }));
      return;
    }
    const xs = versions.map((v) => seconds(v.created_at));
    const range = timeRange(versions, []);
    for (const name of names) {
      const [factor, offset, unit] = unitOf(name);
      const val = versions.map((v) => {
        const p = (v.calibration.params || {})[name];
        return p === null || p === undefined ? null : (p - offset) * factor;
      });
      const sd = versions.map((v) => {
        const s = (v.calibration.std || {})[name];
        return s === null || s === undefined ? null : s * factor;
      });
      const hi = val.map((y, i) => (y === null || sd[i] === null ? null : y + 2 * sd[i]));
      const lo = val.map((y, i) => (y === null || sd[i] === null ? null : y - 2 * sd[i]));
      const figure = el("figure", { class: "chart-figure small" });
      const node = el("div", { class: "chart", role: "img", id: "chart-param-" + name });
      const last = val[val.length - 1];
      const lastSd = sd[sd.length - 1];
      node.setAttribute("aria-label", name + ": " + selfcal.fmtNumber(last, 3) + (lastSd === null ? "" : " ± " + selfcal.fmtNumber(2 * lastSd, 3)) + " " + unit + " in the last version");
      figure.append(node, el("figcaption", { text: name + " (" + unit + ")" }));
      box.append(figure);
      mount("param-" + name, node, {
        width: chartWidth(node), height: 150,
        cursor: { sync: { key: SYNC_KEY } },
        legend: { show: false },
        scales: { x: { time: true, range: () => range } },
        axes: [timeAxis(), axisStyle({ size: 64 })],
        bands: [{ series: [2, 3], fill: COLOURS.band }],
        series: [
          { label: "time" },
          { label: name, stroke: COLOURS.line, width: 2, points: { show: true, size: 6, fill: COLOURS.line } },
          { label: name + " + 2 sd", stroke: "rgba(11, 87, 208, 0.45)", width: 1, dash: [4, 3], points: { show: false } },
          { label: name + " − 2 sd", stroke: "rgba(11, 87, 208, 0.45)", width: 1, dash: [4, 3], points: { show: false } },
        ],
      }, [xs, val, hi, lo]);
    }
  }

  function renderVersionTable(versions) {
    const tbody = document.querySelector("#versions-table tbody");
    tbody.replaceChildren(...versions.slice().reverse().map((v) => el("tr", {}, [
      el("th", { scope: "row", "data-label": "Version", text: String(v.version) }),
      el("td", { "data-label": "Published", text: selfcal.fmtTime(v.created_at) }),
      el("td", { "data-label": "Status", text: v.status }),
      el("td", { "data-label": "Source", text: v.source }),
      el("td", { "data-label": "Predicted sphere error (mg)", class: "num", text: selfcal.fmtNumber(v.calibration.predicted_sphere_rms_mg ?? null, 2) }),
      el("td", { "data-label": "Poses", class: "num", text: v.calibration.n_poses ?? "–" }),
    ])));
  }

  function renderRefusalTable(refusals) {
    const tbody = document.querySelector("#refusals-table tbody");
    tbody.replaceChildren(...refusals.slice().reverse().slice(0, 200).map((r) => el("tr", {}, [
      el("td", { "data-label": "Recorded", text: selfcal.fmtTime(r.at) }),
      el("td", { "data-label": "Kind", text: r.kind + (r.seq !== null ? " (seq " + r.seq + ")" : "") }),
      el("td", { "data-label": "Reason", text: r.reason || "–" }),
      el("td", { "data-label": "Message", text: r.message }),
    ])));
  }

  // ------------------------------------------------------------ coverage
  /** Lambert azimuthal equal-area projection of a unit vector onto its hemisphere's disc (radius sqrt 2). */
  function project(d) {
    const up = d[2] >= 0;
    const k = Math.sqrt(2 / (1 + Math.abs(d[2])));
    return { up: up, x: d[0] * k, y: d[1] * k };
  }

  function scatterPaths(colour, shape) {
    return (u, seriesIdx) => {
      uPlot.orient(u, seriesIdx, (series, dataX, dataY, scaleX, scaleY, valToPosX, valToPosY, xOff, yOff, xDim, yDim) => {
        const d = u.data[seriesIdx];
        const ctx = u.ctx;
        const r = 3.5 * devicePixelRatio;
        ctx.save();
        ctx.fillStyle = colour;
        ctx.strokeStyle = colour;
        ctx.lineWidth = 1.6 * devicePixelRatio;
        const path = new Path2D();
        for (let i = 0; i < d[0].length; i++) {
          const cx = valToPosX(d[0][i], scaleX, xDim, xOff);
          const cy = valToPosY(d[1][i], scaleY, yDim, yOff);
          if (shape === "cross") {
            path.moveTo(cx - r, cy - r); path.lineTo(cx + r, cy + r);
            path.moveTo(cx - r, cy + r); path.lineTo(cx + r, cy - r);
          } else {
            path.moveTo(cx + r, cy);
            path.arc(cx, cy, r, 0, 2 * Math.PI);
          }
        }
        if (shape === "cross") ctx.stroke(path);
        else ctx.fill(path);
        ctx.restore();
      });
      return null;
    };
  }

  function drawDisc(u) {
    const ctx = u.ctx;
    const cx = u.valToPos(0, "x", true);
    const cy = u.valToPos(0, "y", true);
    const r = Math.abs(u.valToPos(Math.SQRT2, "x", true) - cx);
    ctx.save();
    ctx.strokeStyle = "#767676";
    ctx.lineWidth = devicePixelRatio;
    ctx.beginPath();
    ctx.arc(cx, cy, r, 0, 2 * Math.PI);
    ctx.stroke();
    ctx.restore();
  }

  function temperatureBins(temps) {
    const known = temps.filter((t) => t !== null);
    if (!known.length) return null;
    const lo = Math.min(...known);
    const hi = Math.max(...known);
    const n = TEMP_COLOURS.length;
    const width = Math.max((hi - lo) / n, 1e-9);
    const edges = Array.from({ length: n + 1 }, (_, i) => lo + i * width);
    return { lo: lo, hi: hi, edges: edges, binOf: (t) => Math.min(n - 1, Math.floor((t - lo) / width)) };
  }

  function renderCoverage(poses) {
    const note = document.getElementById("coverage-note");
    const legend = document.getElementById("coverage-legend");
    if (!poses.available) {
      note.textContent = "No pose coverage: " + poses.note;
      for (const id of ["chart-upper", "chart-lower"]) {
        document.getElementById(id).replaceChildren(el("p", { class: "muted", text: "No poses." }));
        document.getElementById(id).setAttribute("aria-label", "No poses");
      }
      legend.replaceChildren();
      return;
    }
    const bins = temperatureBins(poses.temp_c);
    const groups = TEMP_COLOURS.map(() => ({ up: [[], []], down: [[], []], n: 0 }));
    const noTemp = { up: [[], []], down: [[], []], n: 0 };
    poses.direction.forEach((d, i) => {
      const t = poses.temp_c[i];
      const g = t === null || !bins ? noTemp : groups[bins.binOf(t)];
      const p = project(d);
      const side = p.up ? g.up : g.down;
      side[0].push(p.x);
      side[1].push(p.y);
      g.n += 1;
    });
    const und = { up: [[], []], down: [[], []] };
    let nUnd = 0;
    poses.sphere.direction.forEach((d, i) => {
      if (!poses.sphere.undetermined[i]) return;
      const p = project(d);
      const side = p.up ? und.up : und.down;
      side[0].push(p.x);
      side[1].push(p.y);
      nUnd += 1;
    });
    const labels = groups.map((g, k) => bins ? bins.edges[k].toFixed(1) + "–" + bins.edges[k + 1].toFixed(1) + " °C" : "");
    for (const [id, sideName, title] of [["chart-upper", "up", "upper"], ["chart-lower", "down", "lower"]]) {
      const node = document.getElementById(id);
      const series = [null];
      const data = [null];
      groups.forEach((g, k) => {
        if (!g.n) return;
        series.push({ label: labels[k], stroke: TEMP_COLOURS[k], fill: TEMP_COLOURS[k], paths: scatterPaths(TEMP_COLOURS[k], "dot"),
          facets: [{ scale: "x", auto: false }, { scale: "y", auto: false }], points: { show: false } });
        data.push(g[sideName]);
      });
      if (noTemp.n) {
        series.push({ label: "no temperature", stroke: NO_TEMP_COLOUR, paths: scatterPaths(NO_TEMP_COLOUR, "dot"),
          facets: [{ scale: "x", auto: false }, { scale: "y", auto: false }], points: { show: false } });
        data.push(noTemp[sideName]);
      }
      series.push({ label: "undetermined direction", stroke: "#1a1a1a", paths: scatterPaths("#1a1a1a", "cross"),
        facets: [{ scale: "x", auto: false }, { scale: "y", auto: false }], points: { show: false } });
      data.push(und[sideName]);
      const nHere = groups.reduce((s, g) => s + g[sideName][0].length, 0) + noTemp[sideName][0].length;
      node.setAttribute("aria-label", nHere + " stored poses and " + und[sideName][0].length +
        " undetermined directions on the " + title + " hemisphere");
      node.dataset.points = String(nHere);
      const size = Math.min(360, chartWidth(node));
      mount(id, node, {
        mode: 2, width: size, height: size,
        legend: { show: false }, cursor: { show: false },
        scales: { x: { time: false, range: [-1.5, 1.5] }, y: { range: [-1.5, 1.5] } },
        axes: [axisStyle({ show: false }), axisStyle({ show: false })],
        hooks: { drawClear: [drawDisc] },
        series: series,
      }, data);
    }
    const items = groups.map((g, k) => (g.n ? el("li", {}, [el("span", { class: "swatch", "data-colour": k, "aria-hidden": "true" }),
      el("span", { text: labels[k] + ": " + g.n + " poses" })]) : null)).filter(Boolean);
    if (noTemp.n) items.push(el("li", {}, [el("span", { class: "swatch none", "aria-hidden": "true" }), el("span", { text: "no temperature: " + noTemp.n + " poses" })]));
    items.push(el("li", {}, [el("span", { class: "cross", "aria-hidden": "true", text: "×" }),
      el("span", { text: "undetermined: " + nUnd + " of " + poses.sphere.direction.length +
        " directions (predicted norm error sd > " + poses.undetermined_above_sd_mg + " mg)" })]));
    legend.replaceChildren(...items);
    note.textContent = poses.n_poses + " stored poses (gravity direction in the sensor frame, Lambert equal-area " +
      "projection of each hemisphere), coloured by temperature; × marks the directions where the predicted " +
      "calibrated-norm error sd exceeds " + poses.undetermined_above_sd_mg + " mg.";
  }

  function renderResiduals(poses) {
    const node = document.getElementById("chart-residuals");
    const caption = document.getElementById("residual-caption");
    const values = (poses.residual_mg || []).filter((v) => v !== null);
    node.dataset.points = String(values.length);
    if (!values.length) {
      node.replaceChildren(el("p", { class: "muted", text: "No residuals (no stored poses)." }));
      node.setAttribute("aria-label", "No residuals");
      return;
    }
    const lo = Math.min(...values);
    const hi = Math.max(...values);
    const nBins = Math.max(5, Math.min(40, Math.ceil(Math.sqrt(values.length) * 1.5)));
    const width = Math.max((hi - lo) / nBins, 1e-6);
    const counts = new Array(nBins).fill(0);
    for (const v of values) counts[Math.min(nBins - 1, Math.floor((v - lo) / width))] += 1;
    const centres = counts.map((_, i) => lo + (i + 0.5) * width);
    const basis = poses.residual_basis === "served" ? "the served version " + poses.version : "no calibration (nominal model)";
    caption.textContent = "Norm residual |a_cal| − 1 g (mg) of the " + values.length + " stored poses under " + basis +
      "; RMS " + selfcal.fmtNumber(poses.residual_rms_mg, 2) + " mg.";
    node.setAttribute("aria-label", "Histogram of " + values.length + " residuals from " + lo.toFixed(2) + " to " + hi.toFixed(2) + " mg");
    mount("residuals", node, {
      width: chartWidth(node), height: 200,
      legend: { show: false },
      scales: { x: { time: false, range: [lo - width, hi + width] }, y: { range: (u, a, b) => [0, Math.max(1, b * 1.1)] } },
      axes: [axisStyle({ label: "residual (mg)", values: (u, ticks) => ticks.map((t) => t.toFixed(1)) }), axisStyle({ label: "poses", size: 50 })],
      series: [{ label: "mg" }, { label: "poses", stroke: COLOURS.line, fill: "rgba(11, 87, 208, 0.35)", width: 1,
        paths: uPlot.paths.bars({ size: [0.92, 100] }), points: { show: false } }],
    }, [centres, counts]);
  }

  // ------------------------------------------------------------ calibration JSON
  function renderJson(cal) {
    const text = JSON.stringify(cal, null, 2);
    document.getElementById("calibration-json").textContent = text;
    const button = document.getElementById("download-json");
    button.onclick = () => {
      const blob = new Blob([text + "\n"], { type: "application/json" });
      const url = URL.createObjectURL(blob);
      const a = el("a", { href: url, download: "calibration-" + deviceId + "-v" + (cal.version ?? 0) + ".json" });
      document.body.append(a);
      a.click();
      a.remove();
      setTimeout(() => URL.revokeObjectURL(url), 1000);
    };
  }

  // ------------------------------------------------------------ admin
  function renderAdmin(history) {
    const select = document.getElementById("rollback-to");
    const versions = history.versions.filter((v) => v.version !== history.current_version).reverse();
    select.replaceChildren(...versions.map((v) => el("option", {
      value: String(v.version), text: "version " + v.version + " · " + v.status + " · " + v.source + " · " +
        selfcal.fmtNumber(v.calibration.predicted_sphere_rms_mg ?? null, 2) + " mg",
    })));
    document.getElementById("rollback-button").disabled = versions.length === 0;
    const seed = document.getElementById("seed-json");
    if (!seed.value) {
      seed.placeholder = '{"matrix": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], "offset": [0.0, 0.0, 0.0], "note": "jig, 6 faces"}';
    }
  }

  function adminStatus(text, ok) {
    const status = document.getElementById("admin-status");
    status.className = ok ? "ok" : "error";
    status.textContent = text;
  }

  function wireAdmin() {
    document.getElementById("rollback-form").addEventListener("submit", async (event) => {
      event.preventDefault();
      const to = Number(document.getElementById("rollback-to").value);
      if (!to) return;
      const ok = await selfcal.confirmAction("Roll back " + deviceId + "?",
        "Version " + to + " will be served again as a new version (source rollback); the calibrator takes it as its model.",
        "Roll back to version " + to);
      if (!ok) return;
      try {
        const out = await selfcal.api(base + "/calibration/rollback", { method: "POST", json: { to_version: to } });
        adminStatus("Now serving version " + out.version + " (rollback of version " + to + ").", true);
        await load();
      } catch (e) {
        adminStatus("Rollback refused (" + e.status + "): " + e.message, false);
      }
    });
    document.getElementById("seed-file").addEventListener("change", async (event) => {
      const file = event.target.files[0];
      if (file) document.getElementById("seed-json").value = await file.text();
    });
    document.getElementById("seed-form").addEventListener("submit", async (event) => {
      event.preventDefault();
      let body;
      try {
        body = JSON.parse(document.getElementById("seed-json").value);
      } catch (e) {
        adminStatus("The jig calibration is not valid JSON: " + e.message, false);
        return;
      }
      const ok = await selfcal.confirmAction("Seed " + deviceId + " from this jig calibration?",
        "It becomes the served version (source factory) and the prior of later refits, if the service accepts it.",
        "Seed");
      if (!ok) return;
      try {
        const out = await selfcal.api(base + "/calibration", { method: "PUT", json: body });
        adminStatus("Seeded: now serving version " + out.version + " (factory).", true);
        await load();
      } catch (e) {
        adminStatus("Seed refused (" + e.status + "): " + e.message, false);
      }
    });
  }

  // ------------------------------------------------------------ load
  function render(data) {
    renderSummary(data.cal, data.row);
    renderHistory(data.history.versions, data.refusals.refusals);
    renderRefusals(data.history.versions, data.refusals.refusals);
    renderParams(data.history.versions);
    renderVersionTable(data.history.versions);
    renderRefusalTable(data.refusals.refusals);
    renderCoverage(data.poses);
    renderResiduals(data.poses);
    renderJson(data.cal);
    renderAdmin(data.history);
  }

  async function load() {
    const error = document.getElementById("load-error");
    let cal, history, refusals, poses, fleet;
    try {
      [cal, history, refusals, poses, fleet] = await Promise.all([
        selfcal.api(base + "/calibration"),
        selfcal.api(base + "/calibration/history"),
        selfcal.api(base + "/refusals"),
        selfcal.api(base + "/poses"),
        selfcal.api("/fleet?device_id=" + encodeURIComponent(deviceId)),
      ]);
    } catch (e) {
      error.textContent = e.status === 404 ? "No device " + deviceId + " on this service." : "Cannot load " + deviceId + ": " + e.message;
      return;
    }
    error.textContent = "";
    const row = (fleet.devices || []).find((d) => d.device_id === deviceId) || null;
    current = { cal, history, refusals, poses, row };
    render(current);
    const main = document.getElementById("main");
    if (!main.dataset.loaded) performance.mark("selfcal:device-rendered"); // read by bench/ui_weight.py
    main.dataset.loaded = "true";
  }

  document.getElementById("crumb-device").textContent = deviceId;
  document.getElementById("device-title").textContent = deviceId;
  document.title = deviceId + " · selfcal";
  let resizeTimer = null;
  window.addEventListener("resize", () => {
    clearTimeout(resizeTimer);
    resizeTimer = setTimeout(() => { if (current) render(current); }, 250); // redraw at the new width, no refetch
  });
  selfcal.start((scopes) => {
    if (scopes.includes("admin")) wireAdmin();
    load();
  });
})();
