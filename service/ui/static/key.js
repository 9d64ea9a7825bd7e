// selfcal dashboard: take an API key handed over in the URL fragment (/ui#key=...).
// Runs first and synchronously: the key goes to this tab's sessionStorage and leaves the
// address bar and the history entry (history.replaceState) before anything else runs.
// A fragment is never sent to the server, so the key reaches no request line and no log.
"use strict";
(function takeKeyFromFragment() {
  var hash = window.location.hash;
  if (!hash || hash.length < 2) return;
  var params = new URLSearchParams(hash.slice(1));
  if (!params.has("key")) return;
  var key = (params.get("key") || "").trim();
  params.delete("key");
  try {
    if (key) window.sessionStorage.setItem("selfcal.apiKey", key);
  } catch (e) {
    // storage blocked: the page asks for the key instead
  }
  var rest = params.toString();
  window.history.replaceState(window.history.state, "",
    window.location.pathname + window.location.search + (rest ? "#" + rest : ""));
})();
