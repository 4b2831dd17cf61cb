#!/usr/bin/env bash
# Fly the identification sequence (sim.response) on our own SITL vehicle, as scripts/px4-identify.sh
# flies it on PX4: a stand-in (no room to hit) facing north, as PX4 SIH starts.
# usage: scripts/sitl-identify.sh OUT.json [brake|land-at-speed]
set -euo pipefail
out=$1; ending=${2:-brake}
here=$(cd "$(dirname "$0")/.." && pwd)
python=${PYTHON:-$here/.venv/bin/python}
cd "$here"
port=$("$python" -c 'from sim.sitl_session import free_port; import socket; print(free_port(socket.SOCK_DGRAM))')
work=$(mktemp -d /tmp/sitl-ident-XXXXXX)
"$python" -m sim.sitl --stand-in --mavlink-port "$port" --heading-deg 90 --level 0 --seed 0 \
    --episode-json "$work/episode.json" --trace "$work/trace.json" >"$work/sitl.log" 2>&1 &
sitl_pid=$!
trap 'kill $sitl_pid 2>/dev/null; wait $sitl_pid 2>/dev/null || true; rm -rf "$work"' EXIT
"$python" -m sim.response fly --url "udpin://127.0.0.1:$port" --ending "$ending" -o "$out"
