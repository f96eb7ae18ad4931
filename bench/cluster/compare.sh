#!/usr/bin/env bash
# The cost of distribution, side by side in one run: renders one frame with
# `rayfarm render --local`, then on a loopback cluster (a coordinator and N workers), and prints
# both rates and their ratio. Build first: cargo build --release --bins
#
# usage: bench/cluster/compare.sh SCENE_DIR WIDTH HEIGHT SPP CACHE_PER_WORKER WORKERS [coordinator flags...]
# e.g.   bench/cluster/compare.sh rayfarm-demo/nbody-300000-16 1024 1024 16 64MiB 2
# The local renderer uses all cores and the same cache budget as one worker.
set -euo pipefail
scene=$(realpath "$1") w=$2 h=$3 spp=$4 cache=$5 n=$6
shift 6
bin=$(dirname "$(realpath "$0")")/../../target/release
work=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
frame=(--width "$w" --height "$h" --spp "$spp" --depth 3)

"$bin/rayfarm" render --local --scene "$scene" "${frame[@]}" --cache-bytes "$cache" \
    --out "$work/local.png" --stats-json "$work/local.json" --quiet

"$bin/rayfarm-coordinator" --listen 127.0.0.1:0 --data-dir "$work/data" \
    --scene-root "$(dirname "$scene")" "$@" >"$work/coordinator.out" 2>"$work/coordinator.log" &
pids+=($!)
until grep -q "listening on" "$work/coordinator.out" 2>/dev/null; do sleep 0.05; done
addr=$(awk '/listening on/ {print $3}' "$work/coordinator.out")
for i in $(seq "$n"); do
    "$bin/rayfarm-worker" --coordinator "http://$addr" --listen 127.0.0.1:0 --cache-bytes "$cache" \
        --scene-root "$(dirname "$scene")" --threads 1 >/dev/null 2>"$work/worker-$i.log" &
    pids+=($!)
done
"$bin/rayfarm" status --coordinator "$addr" --wait-workers "$n" --timeout 30 >/dev/null
"$bin/rayfarm" submit --coordinator "$addr" --scene "$(basename "$scene")" "${frame[@]}" \
    --wait --quiet -o "$work/cluster.png" --stats-json "$work/cluster.json" >/dev/null

python3 - "$work/local.json" "$work/cluster.json" <<'PY'
import json, sys
l, c = (json.load(open(p)) for p in sys.argv[1:3])
mig = next((t for t in c["tiers"] if t["tier"] == "migrated"), {"bundles": 0})
print(f"local   {l['wall_seconds']:7.2f} s  {l['rays_per_s']/1e6:5.2f} Mrays/s  loads {l['cache']['loads']}")
print(f"cluster {c['wall_seconds']:7.2f} s  {c['rays_per_s']/1e6:5.2f} Mrays/s  loads {c['cache']['loads']}  "
      f"rounds {c['rounds']}  rays moved {c['rays_migrated']} ({c['bytes_migrated']/2**20:.0f} MiB)  "
      f"migrated bundles {mig['bundles']}")
print(f"cluster / local: {c['rays_per_s']/l['rays_per_s']:.2f}   identical image: {l['image_hash'] == c['image_hash']}")
print("worker idle fractions:", [round(w["idle_fraction"], 2) for w in c["per_worker"]])
PY
