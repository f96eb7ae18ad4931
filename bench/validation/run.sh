#!/bin/sh
# The simulator against the real cluster (README "Validation against the real cluster"):
# `rayfarm bench` of every schedule at 4 and 8 workers on the b32 scene with emulated storage,
# and `rayfarm sim` of the same frame, caches and storage, the model's defaults alone, then
# with the cluster's two shared cores (`--cores 2`), the wait of a pass for its tracing thread
# the bench measured (`--pass-start-us`) and a peer bundle's wait for the engine its workers'
# logs show (`--bundle-take-us`, transit.py), then that again over timing seeds; then the
# table of them all (compare.py). Every image must be e4a2c0ac999bd6c1.
#
#   bench/validation/run.sh OUT_DIR [REPEATS] [SEEDS]
#
# Needs `cargo build --release --bins` and the scene in scenes/b32
# (`rayfarm prepare --generate nbody --triangles 200000 --seed 5 --domains 32 --out scenes/b32`).
# Takes about 8 minutes on the 2-core machine; run it with nothing else running.
set -eu
out=${1:?usage: run.sh OUT_DIR [REPEATS] [SEEDS]}
repeats=${2:-5}
seeds=${3:-0..9}
here=$(cd "$(dirname "$0")" && pwd)
bin=${RAYFARM:-$here/../../target/release/rayfarm}
scene=${SCENE:-scenes/b32}
mkdir -p "$out"
frame="--width 128 --height 128 --spp 1 --depth 3 --cache-bytes 2MiB"
for w in 4 8; do
    "$bin" bench --scene "$scene" --workers $w --threads 1 \
        --schedules image-plane,domain,dynamic,hybrid,predictive --repeats "$repeats" $frame \
        --storage-bandwidth 10MiB/s --storage-latency 2ms --csv "$out/bench$w.csv" \
        > "$out/bench$w.txt" 2>&1
    sim="$bin sim --scene $scene --workers $w --schedule image-plane,domain,dynamic,hybrid,predictive \
        $frame --wave-rays 1048576 --pass-rays 262144 --threads 1 \
        --storage-bandwidth 1000000000000000 --node-storage-bandwidth 10MiB --storage-latency-us 2000"
    # One more frame of each schedule that moves rays, with the workers' debug logs: how long
    # a peer bundle takes from one machine to the next on this cluster.
    RUST_LOG=info,rayfarm_machine::worker=debug "$bin" bench --scene "$scene" --workers $w \
        --threads 1 --schedules domain,dynamic,hybrid,predictive --repeats 1 $frame \
        --storage-bandwidth 10MiB/s --storage-latency 2ms --keep-cluster-logs "$out/logs$w" \
        > "$out/bench$w-logs.txt" 2>&1
    python3 "$here/transit.py" "$out/logs$w" 130 > "$out/transit$w.txt"
    take=$(sed -n 's/^--bundle-take-us //p' "$out/transit$w.txt")
    # The cluster's two cores, the mean wait of a pass for its tracing thread that the bench
    # measured over all its passes, and a bundle's wait for the engine beyond the network.
    wait=$(python3 "$here/compare.py" --pass-wait-us "$out/bench$w.csv")
    cores="--cores 2 --pass-start-us $wait --bundle-take-us $take"
    $sim --csv "$out/sim$w.csv" > "$out/sim$w.txt" 2>&1
    $sim $cores --csv "$out/sim$w-cores.csv" > "$out/sim$w-cores.txt" 2>&1
    $sim $cores --timing-seeds "$seeds" --csv "$out/sim$w-seeds.csv" > "$out/sim$w-seeds.txt" 2>&1
    echo "$w workers: bench / sim / sim $cores / its timing seeds $seeds (medians)"
    python3 "$here/compare.py" "$out/bench$w.csv" "$out/sim$w.csv" "$out/sim$w-cores.csv" \
        "$out/sim$w-seeds.csv"
done
