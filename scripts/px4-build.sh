#!/usr/bin/env bash
# Build PX4 v1.16.0 SITL (SIH, no Gazebo) from local git copies, outside the project tree.
#
#   scripts/px4-build.sh DEST PX4_GIT MAVLINK_GIT GPSDRIVERS_GIT LIBEVENTS_GIT HEATSHRINK_GIT
#
# DEST: an empty or absent folder; the build lands in DEST/build/px4_sitl_default (the BUILD that
# scripts/px4-campaign.sh and scripts/px4-identify.sh take). Each *_GIT is a git directory (a bare
# mirror or a clone's .git) holding the commit v1.16.0 pins for that submodule: PX4-Autopilot (any
# fork carrying the upstream tag), mavlink/mavlink, PX4/PX4-GPSDrivers, mavlink/libevents,
# PX4/heatshrink. This is the route of docs/px4-sitl.md §1 for a machine that cannot clone
# recursively; with full network access `git clone --recursive --branch v1.16.0` needs none of it.
# Needs cmake, ninja, g++ and the Python packages it installs into a venv of its own (DEST/.venv).
set -euo pipefail

if [[ $# -ne 6 ]]; then
    sed -n '2,13p' "$0" >&2
    exit 2
fi
DEST=$1 PX4_GIT=$2
TAG=v1.16.0
declare -A SUBMODULE_GIT=(
    [src/modules/mavlink/mavlink]=$3
    [src/drivers/gps/devices]=$4
    [src/lib/events/libevents]=$5
    [src/lib/heatshrink/heatshrink]=$6
)
for tool in cmake ninja g++ make python3; do
    command -v "$tool" >/dev/null || { echo "px4-build: $tool is not installed (apt-get install cmake ninja-build g++ make)" >&2; exit 1; }
done
if [[ -e "$DEST" && -n "$(ls -A "$DEST")" ]]; then
    echo "px4-build: $DEST is not empty; give a new folder" >&2
    exit 1
fi
mkdir -p "$DEST"
DEST=$(cd "$DEST" && pwd)

echo "px4-build: extracting $TAG from $PX4_GIT"
# Paths whose blobs a partial fork may lack (docs, the FFT module's CMSIS copy): SIH needs neither.
git -C "$PX4_GIT" archive "$TAG" -- . ':!docs' ':!src/modules/gyro_fft/CMSIS_5' | tar -x -C "$DEST"

for path in "${!SUBMODULE_GIT[@]}"; do
    commit=$(git -C "$PX4_GIT" ls-tree "$TAG" "$path" | awk '{print $3}')
    src=${SUBMODULE_GIT[$path]}
    git -C "$src" cat-file -e "$commit^{commit}" 2>/dev/null \
        || { echo "px4-build: $src lacks commit $commit that $TAG pins for $path" >&2; exit 1; }
    echo "px4-build: $path at $commit"
    rm -rf "${DEST:?}/$path"
    mkdir -p "$DEST/$path"
    git -C "$src" archive "$commit" | tar -x -C "$DEST/$path"
    # The build asks each submodule for its git state; one local commit answers it.
    git -C "$DEST/$path" init -q
    git -C "$DEST/$path" add -A
    git -C "$DEST/$path" -c user.name=px4-build -c user.email=px4-build@localhost commit -qm "$commit"
done

python3 -m venv "$DEST/.venv"
"$DEST/.venv/bin/pip" install -q empy==3.3.4 kconfiglib jinja2 pyros-genmsg jsonschema pyyaml pymavlink==2.4.50 future lxml numpy packaging
# mavlink's own pymavlink submodule: the PyPI package carries the generator PX4 calls.
pymavlink_dir=$("$DEST/.venv/bin/python" -c 'import os, pymavlink; print(os.path.dirname(pymavlink.__file__))')
rm -rf "$DEST/src/modules/mavlink/mavlink/pymavlink"
cp -r "$pymavlink_dir" "$DEST/src/modules/mavlink/mavlink/pymavlink"

# Modules whose submodules are not fetched; SIH needs none of them.
sed -i -E 's/^(CONFIG_MODULES_(GYRO_FFT|UXRCE_DDS_CLIENT|SIMULATION_GZ_MSGS|SIMULATION_GZ_BRIDGE|SIMULATION_GZ_PLUGINS))=y/\1=n/' \
    "$DEST/boards/px4/sitl/default.px4board"

# PX4 reads its version from git: a repository tagged v1.16.0 reports it.
git -C "$DEST" init -q
printf '%s\n' .venv build > "$DEST/.git/info/exclude"
git -C "$DEST" add -A
git -C "$DEST" -c user.name=px4-build -c user.email=px4-build@localhost commit -qm "PX4 $TAG (extracted)"
git -C "$DEST" tag "$TAG"

start=$(date +%s)
(cd "$DEST" && PATH="$DEST/.venv/bin:$PATH" GIT_SUBMODULES_ARE_EVIL=1 make -j"$(nproc)" px4_sitl_default)
echo "px4-build: built in $(( $(date +%s) - start )) s: $DEST/build/px4_sitl_default"
