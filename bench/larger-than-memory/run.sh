#!/usr/bin/env bash
# A scene larger than this machine's memory, rendered by `render --local` and by a local
# cluster of 4 workers, to the same image hash (issue 20, item 6). The scene is Debian's
# invesalius-examples skull CT (256x256x108 int16) tiled 8 x 8 x 18 times into a
# 2048x2048x1944 volume, cut into 512 bricks of float voxels for direct volume rendering:
# 32.8 GiB of brick files. Every step prints its time, loads and peak memory; the scene and the
# raw volume are deleted at the end. Needs about 50 GiB of free disk in WORK while it runs.
#
# Environment: WORK (scratch directory, default ./target/larger-than-memory), RAYFARM_BIN (the
# directory of rayfarm, rayfarm-coordinator and rayfarm-worker, default ./target/release),
# CACHE (each worker's domain cache, default 2GiB), CACHE_LOCAL (render --local's, default 4GiB),
# SCHEDULES (default dynamic,domain,predictive), KEEP=1 keeps the scene.
set -euo pipefail

root=$(cd "$(dirname "$0")/../.." && pwd)
work=${WORK:-$root/target/larger-than-memory}
bin=${RAYFARM_BIN:-$root/target/release}
cache=${CACHE:-2GiB}
schedules=${SCHEDULES:-dynamic,domain,predictive}
ct=/usr/share/doc/invesalius-examples/examples/Cranium.inv3
if [[ ! -f $ct ]]; then
    echo "$ct not found. On Debian: sudo apt-get install invesalius-examples" >&2
    exit 1
fi
mkdir -p "$work"
cd "$work"
tar -xOf "$ct" --wildcards '*/matrix.dat' >cranium.raw

# x fastest: each row of the CT repeated 8 times along x, each slice 8 times along y, the
# slices 18 times along z (16.3 GB of int16).
python3 - <<'PY'
X, Y, Z = 256, 256, 108
KX, KY, KZ = 8, 8, 18
raw = open("cranium.raw", "rb").read()
assert len(raw) == X * Y * Z * 2, "unexpected size of the CT"
row = X * 2
with open("tiled.raw", "wb", buffering=1 << 24) as out:
    for z in range(Z * KZ):
        s = (z % Z) * X * Y * 2
        out.write(b"".join(raw[s + y * row : s + (y + 1) * row] * KX for y in range(Y)) * KY)
PY

timed() { /usr/bin/time -f "  wall %e s, peak RSS %M KiB" "$@"; }
rm -rf scene
timed "$bin/rayfarm" prepare tiled.raw --volume --dims 2048,2048,1944 --dtype i16 \
    --spacing 0.957,0.957,1.5 --bricks 512 --transfer ct-bone --out scene
rm tiled.raw
du -sh scene
free -h | head -2

timed "$bin/rayfarm" render --local --scene scene --width 256 --height 256 --spp 1 --depth 1 \
    --threads 2 --cache-bytes "${CACHE_LOCAL:-4GiB}" --out local.png --stats-json local.json
timed "$bin/rayfarm" bench --scene scene --workers 4 --threads 1 --schedules "$schedules" \
    --cache-bytes "$cache" --repeats 1 --width 256 --height 256 --spp 1 --depth 1 --csv cluster.csv

if [[ ${KEEP:-0} != 1 ]]; then
    rm -rf scene
fi
