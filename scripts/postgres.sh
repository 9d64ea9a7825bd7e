#!/usr/bin/env bash
# Make sure PostgreSQL server binaries (initdb, pg_ctl) exist, for the service tests on
# PostgreSQL and bench/service_scale.py. The tests start their own throw-away cluster
# (tests/pg_cluster.py); nothing here starts a server or touches the system's clusters.
# Installs Debian/Ubuntu's `postgresql` package when missing and we are root with apt-get.
# Exit 0: available (prints the folder); exit 1: not available (prints why).
set -uo pipefail
find_bin() {
  if command -v pg_ctl >/dev/null 2>&1 && command -v initdb >/dev/null 2>&1; then
    dirname "$(readlink -f "$(command -v pg_ctl)")"; return 0
  fi
  local d
  for d in $(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V -r); do
    if [ -x "$d/pg_ctl" ] && [ -x "$d/initdb" ]; then echo "$d"; return 0; fi
  done
  return 1
}
if dir=$(find_bin); then echo "postgresql: server binaries in $dir"; exit 0; fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "postgresql: installing the server (apt-get install postgresql)" >&2
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq >/dev/null && apt-get install -y -qq --no-install-recommends postgresql >/dev/null
  if dir=$(find_bin); then echo "postgresql: server binaries in $dir"; exit 0; fi
  echo "postgresql: apt-get install postgresql did not provide initdb/pg_ctl" >&2; exit 1
fi
echo "postgresql: no server binaries, and cannot install them here (needs root and apt-get;" \
     "or install PostgreSQL with your package manager)" >&2
exit 1
