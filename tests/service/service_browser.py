"""Headless Chromium for the dashboard tests: Playwright for Python driving Debian's
``chromium`` (``scripts/chromium.sh`` installs it); never a downloaded browser.

Whether a missing browser skips or fails: under ``CI=true``, as root with ``apt-get``
(a machine that could have installed it), it fails; anywhere else the UI tests skip
with the reason.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

#: Flags for a headless run on a machine without network or GPU (and as root: no sandbox).
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]


def chromium_executable() -> str | None:
    """``SELFCAL_CHROMIUM``, else ``chromium`` on PATH, else ``/usr/bin/chromium``; None if none runs."""
    for candidate in (os.environ.get("SELFCAL_CHROMIUM"), shutil.which("chromium"), "/usr/bin/chromium"):
        if candidate and Path(candidate).is_file() and os.access(candidate, os.X_OK):
            return candidate
    return None


def browser_required() -> bool:
    """CI on a machine that could install Chromium (root, apt-get): a missing browser is a failure."""
    return os.environ.get("CI") == "true" and os.geteuid() == 0 and shutil.which("apt-get") is not None


def browser_unavailable() -> str | None:
    """Why the UI tests cannot run here, or None."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install -e '.[dev]')"
    if chromium_executable() is None:
        return "no Chromium: run scripts/chromium.sh (apt-get install chromium) or set SELFCAL_CHROMIUM"
    return None


#: WCAG 2.x contrast of every rendered text node against its composed background:
#: returns {checked, failures: [{text, ratio, need, color, background}]}. Large text
#: (>= 24 px, or >= 18.66 px bold) needs 3:1, the rest 4.5:1 (AA).
CONTRAST_JS = """
() => {
  function parse(c) {
    const m = c.match(/rgba?\\(([^)]+)\\)/);
    if (!m) return null;
    const p = m[1].split(/[\\s,\\/]+/).filter(Boolean).map(Number);
    return { r: p[0], g: p[1], b: p[2], a: p.length > 3 ? p[3] : 1 };
  }
  function over(top, base) {
    return { r: top.r * top.a + base.r * (1 - top.a), g: top.g * top.a + base.g * (1 - top.a),
             b: top.b * top.a + base.b * (1 - top.a), a: 1 };
  }
  function lum(c) {
    const f = (v) => { v /= 255; return v <= 0.03928 ? v / 12.92 : Math.pow((v + 0.055) / 1.055, 2.4); };
    return 0.2126 * f(c.r) + 0.7152 * f(c.g) + 0.0722 * f(c.b);
  }
  function background(el) {
    const layers = [];
    for (let e = el; e; e = e.parentElement) {
      const c = parse(getComputedStyle(e).backgroundColor);
      if (c && c.a > 0) { layers.push(c); if (c.a >= 1) break; }
    }
    let base = { r: 255, g: 255, b: 255, a: 1 };
    for (const c of layers.reverse()) base = over(c, base);
    return base;
  }
  const failures = [];
  let checked = 0;
  const walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  for (let n = walker.nextNode(); n; n = walker.nextNode()) {
    const text = n.textContent.trim();
    if (!text) continue;
    const el = n.parentElement;
    const box = el.getBoundingClientRect();
    const cs = getComputedStyle(el);
    if (!box.width || !box.height || cs.visibility === "hidden" || el.closest(".visually-hidden")) continue;
    const bg = background(el);
    const fg = over(parse(cs.color), bg);
    const l1 = lum(fg), l2 = lum(bg);
    const ratio = (Math.max(l1, l2) + 0.05) / (Math.min(l1, l2) + 0.05);
    const size = parseFloat(cs.fontSize);
    const large = size >= 24 || (Number(cs.fontWeight) >= 700 && size >= 18.66);
    const need = large ? 3 : 4.5;
    checked += 1;
    if (ratio < need) failures.push({ text: text.slice(0, 40), ratio: Math.round(ratio * 100) / 100, need,
                                      color: cs.color, background: `rgb(${bg.r}, ${bg.g}, ${bg.b})` });
  }
  return { checked, failures };
}
"""
