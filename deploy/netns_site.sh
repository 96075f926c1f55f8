#!/usr/bin/env bash
# A site of N real hosts on one Linux machine: network namespaces joined by veth pairs to
# one bridge (itself in a namespace of its own), so uma can be tried across hosts, addresses
# and links that drop without several machines.  Nothing is added to the machine's own
# namespace.  Needs root and iproute2 (`ip`).  The tests build the same thing
# (tests/agent_helpers/site.py).
#
#   deploy/netns_site.sh up N [NAME] [SUBNET]  # hosts NAME-h0 .. NAME-h<N-1>, 10.77.SUBNET.1..N
#   deploy/netns_site.sh cut NAME HOST         # take HOST's link down (e.g. h1) ...
#   deploy/netns_site.sh heal NAME HOST        # ... and up again
#   deploy/netns_site.sh down [NAME]           # stop what runs in the site's hosts, remove it
#
# NAME defaults to "lab" and SUBNET to 100; the namespaces are named umasite-NAME-*.
set -euo pipefail

usage() { sed -n '2,13p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2; }

need_root() {
  [[ $(id -u) -eq 0 ]] || { echo "netns_site.sh: needs root (network namespaces)" >&2; exit 1; }
  command -v ip >/dev/null || { echo "netns_site.sh: needs the ip command (iproute2)" >&2; exit 1; }
}

site_namespaces() {  # the namespaces of site $1, hosts first, the bridge last
  ip netns list | awk '{print $1}' | grep -E "^umasite-$1-h[0-9]+$" || true
  ip netns list | awk '{print $1}' | grep -Fx "umasite-$1-br" || true
}

up() {
  local n=$1 name=${2:-lab} subnet=${3:-100} i ns addr
  local br="umasite-${name}-br"
  [[ $n =~ ^[0-9]+$ && $n -ge 1 && $n -le 250 ]] || { echo "N must be 1..250, not $n" >&2; exit 2; }
  [[ $subnet =~ ^[0-9]+$ && $subnet -le 255 ]] || { echo "SUBNET must be 0..255" >&2; exit 2; }
  [[ $name =~ ^[A-Za-z0-9_]+$ ]] || { echo "NAME: letters, digits and _ only" >&2; exit 2; }
  if ip netns list | grep -q "^$br"; then
    echo "site $name exists already; remove it first: $0 down $name" >&2; exit 1
  fi
  trap 'echo "building site $name failed; removing it" >&2; down "$name"' ERR
  ip netns add "$br"
  ip -n "$br" link set lo up
  ip -n "$br" link add br0 type bridge
  ip -n "$br" link set br0 up
  for ((i = 0; i < n; i++)); do
    ns="umasite-${name}-h$i"
    addr="10.77.$subnet.$((i + 1))"
    ip netns add "$ns"
    ip -n "$ns" link set lo up
    ip -n "$br" link add "p$i" type veth peer name eth0 netns "$ns"
    ip -n "$br" link set "p$i" master br0 up
    ip -n "$ns" addr add "$addr/24" dev eth0
    ip -n "$ns" link set eth0 up
  done
  trap - ERR
  local seed="tcp/10.77.$subnet.1:7447"
  cat <<EOF
site $name: $n hosts umasite-$name-h0 .. umasite-$name-h$((n - 1)), addresses 10.77.$subnet.1 .. 10.77.$subnet.$n

Run one agent per host (each in a terminal of its own, or with & and a log file); this
test site is plain TCP on purpose, hence --insecure (a real site: README "Deploying a site"):
  ip netns exec umasite-$name-h0 uma agent --realm site --id h0 --listen $seed --insecure
  ip netns exec umasite-$name-h1 uma agent --realm site --id h1 --listen tcp/10.77.$subnet.2:7447 --connect $seed --insecure
  ...
Services connect to the agent of their host:
  ip netns exec umasite-$name-h1 uma service run sim --realm site --agent h1 --connect tcp/10.77.$subnet.2:7447
Look at the realm from any host:
  ip netns exec umasite-$name-h0 uma services --realm site --connect $seed
Pull a cable: $0 cut $name h1 (and heal $name h1).  Remove the site: $0 down $name
EOF
}

link() {  # link NAME HOST up|down
  local br="umasite-$1-br" port
  [[ $2 =~ ^h([0-9]+)$ ]] || { echo "HOST is h0, h1, ..., not $2" >&2; exit 2; }
  port="p${BASH_REMATCH[1]}"
  ip -n "$br" link set "$port" "$3"
}

down() {
  local name=${1:-lab} ns pids namespaces
  namespaces=$(site_namespaces "$name")
  [[ -n $namespaces ]] || { echo "no site $name" >&2; return 0; }
  for ns in $namespaces; do  # the processes people started inside the site's hosts
    pids=$(ip netns pids "$ns")
    [[ -z $pids ]] || kill -TERM $pids 2>/dev/null || true
  done
  for ns in $namespaces; do
    for _ in $(seq 50); do [[ -z $(ip netns pids "$ns") ]] && break; sleep 0.1; done
    pids=$(ip netns pids "$ns")
    [[ -z $pids ]] || kill -KILL $pids 2>/dev/null || true
    ip netns del "$ns"
  done
  echo "site $name removed"
}

[[ $# -ge 1 ]] || usage
cmd=$1; shift
need_root
case $cmd in
  up) [[ $# -ge 1 ]] || usage; up "$@" ;;
  down) down "$@" ;;
  cut) [[ $# -eq 2 ]] || usage; link "$1" "$2" down ;;
  heal) [[ $# -eq 2 ]] || usage; link "$1" "$2" up ;;
  *) usage ;;
esac
