#!/usr/bin/env bash
# Make sure a Chromium exists for the dashboard's end-to-end tests (tests/service/test_service_ui.py:
# Playwright for Python driving it headless) and bench/ui_weight.py. Never a downloaded browser
# (no `playwright install`: the tests run offline): installs Debian/Ubuntu's `chromium` package
# (with a font for the screenshots) when missing and we are root with apt-get.
# Exit 0: available (prints the executable); exit 1: not available (prints why).
set -uo pipefail
find_bin() {
  local c
  for c in "${SELFCAL_CHROMIUM:-}" "$(command -v chromium 2>/dev/null)" /usr/bin/chromium; do
    if [ -n "$c" ] && [ -f "$c" ] && [ -x "$c" ]; then echo "$c"; return 0; fi
  done
  return 1
}
if bin=$(find_bin); then echo "chromium: $bin"; exit 0; fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "chromium: installing it (apt-get install chromium)" >&2
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq >/dev/null && apt-get install -y -qq --no-install-recommends chromium fonts-dejavu-core >/dev/null
  if bin=$(find_bin); then echo "chromium: $bin"; exit 0; fi
  echo "chromium: apt-get install chromium did not provide a chromium executable" >&2; exit 1
fi
echo "chromium: not found, and cannot install it here (needs root and apt-get; or install Chromium" \
     "with your package manager and point SELFCAL_CHROMIUM at it)" >&2
exit 1
