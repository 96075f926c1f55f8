#!/usr/bin/env bash
# A three-host site on loopback: one Zenoh router and the agents of hostA, hostB and hostC
# in client mode behind it (configurations beside this script).  Prints the realm as
# `uma services` sees it, then runs until Ctrl-C, and stops everything it started.
#
#   deploy/start_site.sh [SECONDS]     # SECONDS: stop by itself after that long
#
# Services join the site by connecting to the router, e.g.
#   uma service run sim --realm site --agent hostA --connect tcp/127.0.0.1:7447
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
cd "$here/.."
py="${PYTHON:-python3}"
uma=("$py" -m agent.cli)
router="tcp/127.0.0.1:7447"
pids=()

stop() {
  for pid in "${pids[@]}"; do kill -TERM "$pid" 2>/dev/null || true; done
  for pid in "${pids[@]}"; do wait "$pid" 2>/dev/null || true; done
}
trap stop EXIT
trap 'exit 130' INT TERM

"${uma[@]}" router --config "$here/router.json5" &
pids+=($!)
for _ in $(seq 50); do  # until the router accepts connections (at most ~5 s)
  (exec 3<>/dev/tcp/127.0.0.1/7447) 2>/dev/null && break
  sleep 0.1
done
for host in hostA hostB hostC; do
  "${uma[@]}" agent --config "$here/$host.toml" &
  pids+=($!)
done
sleep 2
"${uma[@]}" services --realm site --connect "$router"
if [[ $# -ge 1 ]]; then
  sleep "$1"
else
  echo "site running; Ctrl-C stops it"
  wait
fi
