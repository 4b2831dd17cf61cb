#!/usr/bin/env bash
# Fly the identification sequence (sim.response) on a fresh PX4 v1.16 SITL (SIH quadrotor).
# usage: scripts/px4-identify.sh PX4_BUILD_DIR OUT.json [brake|land-at-speed]
# PX4_BUILD_DIR is PX4-Autopilot/build/px4_sitl_default (docs/px4-sitl.md says how to build it).
# PX4 is started in an empty working folder and stopped by its PID, whatever happens.
set -euo pipefail
build=$(realpath "$1"); out=$2; ending=${3:-brake}
here=$(cd "$(dirname "$0")/.." && pwd)
python=${PYTHON:-$here/.venv/bin/python}
[ -x "$build/bin/px4" ] || { echo "error: no PX4 binary at $build/bin/px4: build PX4 as docs/px4-sitl.md says" >&2; exit 2; }
rootfs=$(mktemp -d /tmp/px4-ident-XXXXXX)
(cd "$rootfs" && PX4_SYS_AUTOSTART=10040 PX4_SIM_MODEL=sihsim_quadx exec "$build/bin/px4" -d "$build/etc" \
    >"$rootfs/px4.log" 2>&1 </dev/null) &
px4_pid=$!
trap 'kill $px4_pid 2>/dev/null; wait $px4_pid 2>/dev/null || true; rm -rf "$rootfs"' EXIT
cd "$here"
"$python" -m sim.response fly --url udpin://127.0.0.1:14540 --ending "$ending" -o "$out"
