// selfcal dashboard: what the fleet and device pages share. The API key (sessionStorage
// of this tab only), calls to the JSON API with "Authorization: Bearer KEY", the key
// form, the confirmation dialog and number/time formatting. No data is ever written into
// the page as HTML: every value goes through textContent.
"use strict";

const selfcal = (function () {
  const KEY_ITEM = "selfcal.apiKey";
  let memoryKey = null; // only when sessionStorage is blocked

  function getKey() {
    try {
      return window.sessionStorage.getItem(KEY_ITEM) || memoryKey;
    } catch (e) {
      return memoryKey;
    }
  }

  function setKey(key) {
    try {
      window.sessionStorage.setItem(KEY_ITEM, key);
    } catch (e) {
      memoryKey = key;
    }
  }

  function forgetKey() {
    memoryKey = null;
    try {
      window.sessionStorage.removeItem(KEY_ITEM);
    } catch (e) {
      /* nothing stored */
    }
  }

  class ApiError extends Error {
    constructor(status, body) {
      super((body && body.message) || "HTTP " + status);
      this.status = status;
      this.body = body;
    }
  }

  /** Call the JSON API; resolves to the parsed body, rejects with an ApiError. */
  async function api(path, options) {
    const opts = options || {};
    const key = getKey();
    const headers = { Accept: "application/json" };
    if (key) headers.Authorization = "Bearer " + key;
    let body;
    if (opts.json !== undefined) {
      headers["Content-Type"] = "application/json";
      body = JSON.stringify(opts.json);
    }
    const response = await fetch(path, {
      method: opts.method || "GET", headers: headers, body: body, cache: "no-store", credentials: "omit",
    });
    const text = await response.text();
    let parsed = null;
    try {
      parsed = text ? JSON.parse(text) : null;
    } catch (e) {
      parsed = { message: text };
    }
    if (!response.ok) {
      if (response.status === 401) document.dispatchEvent(new CustomEvent("selfcal:unauthorized"));
      throw new ApiError(response.status, parsed);
    }
    return parsed;
  }

  /** Create an element: el("td", {class: "num", text: "3"}, [children]). */
  function el(tag, attrs, children) {
    const node = document.createElement(tag);
    for (const [name, value] of Object.entries(attrs || {})) {
      if (value === undefined || value === null || value === false) continue;
      if (name === "text") node.textContent = value;
      else if (name === "class") node.className = value;
      else if (name === "dataset") Object.assign(node.dataset, value);
      else node.setAttribute(name, value === true ? "" : value);
    }
    for (const child of children || []) node.append(child);
    return node;
  }

  function fmtNumber(value, digits) {
    if (value === null || value === undefined || !Number.isFinite(value)) return "–";
    return value.toFixed(digits === undefined ? 2 : digits);
  }

  /** "12 s ago", "3 min ago", ... from an ISO time; "never" for null. */
  function fmtAgo(iso, nowMs) {
    if (!iso) return "never";
    const seconds = Math.max(0, ((nowMs || Date.now()) - Date.parse(iso)) / 1000);
    if (seconds < 60) return Math.round(seconds) + " s ago";
    if (seconds < 3600) return Math.round(seconds / 60) + " min ago";
    if (seconds < 86400) return (seconds / 3600).toFixed(1) + " h ago";
    return (seconds / 86400).toFixed(1) + " d ago";
  }

  function fmtTime(iso) {
    if (!iso) return "–";
    const d = new Date(iso);
    return d.toLocaleString(undefined, { hour12: false });
  }

  /** Show the confirmation dialog; resolves true when the action is confirmed. */
  function confirmAction(title, message, okLabel) {
    const dialog = document.getElementById("confirm");
    document.getElementById("confirm-title").textContent = title;
    document.getElementById("confirm-message").textContent = message;
    document.getElementById("confirm-ok").textContent = okLabel || "Confirm";
    const opener = document.activeElement;
    return new Promise((resolve) => {
      dialog.addEventListener("close", function onClose() {
        dialog.removeEventListener("close", onClose);
        if (opener && typeof opener.focus === "function") opener.focus();
        resolve(dialog.returnValue === "ok");
      });
      dialog.returnValue = "cancel";
      dialog.showModal();
      document.getElementById("confirm-cancel").focus(); // the safe choice has the focus
    });
  }

  /**
   * Ask for the key when there is none (or it was refused), check it with /whoami, then
   * call onReady(scopes). A 401 later (key removed on the server) asks again.
   */
  function start(onReady) {
    const panel = document.getElementById("key-panel");
    const main = document.getElementById("main");
    const keybox = document.getElementById("keybox");
    const form = document.getElementById("key-form");
    const input = document.getElementById("key-input");
    const error = document.getElementById("key-error");
    let started = false;

    function ask(message) {
      main.hidden = true;
      keybox.hidden = true;
      panel.hidden = false;
      error.textContent = message || "";
      input.value = "";
      input.focus();
    }

    async function check() {
      let who;
      try {
        who = await api("/whoami");
      } catch (e) {
        forgetKey();
        ask(e.status === 401 ? "The service does not know this key." : "Cannot reach the service: " + e.message);
        return;
      }
      const scopes = who.scopes || [];
      if (!scopes.includes("read")) {
        forgetKey();
        ask("This key has no read scope (it has: " + (scopes.join(", ") || "none") + "); the dashboard needs read.");
        return;
      }
      document.body.classList.toggle("is-admin", scopes.includes("admin"));
      document.getElementById("key-scopes").textContent = "Key scopes: " + (scopes.join(", ") || "none");
      panel.hidden = true;
      keybox.hidden = false;
      main.hidden = false;
      for (const node of document.querySelectorAll(".admin-only")) node.hidden = !scopes.includes("admin");
      if (!started) {
        started = true;
        onReady(scopes);
      }
    }

    form.addEventListener("submit", (event) => {
      event.preventDefault();
      const key = input.value.trim();
      if (!key) return;
      setKey(key);
      input.value = "";
      check();
    });
    document.getElementById("forget-key").addEventListener("click", () => {
      forgetKey();
      window.location.reload();
    });
    document.addEventListener("selfcal:unauthorized", () => {
      forgetKey();
      ask("The service refused the key (401). Enter it again.");
    });
    if (getKey()) check();
    else ask("");
  }

  return { api, el, fmtNumber, fmtAgo, fmtTime, confirmAction, start, ApiError };
})();
