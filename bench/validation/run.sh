#!/bin/sh
# The simulator against the real cluster (README "Validation against the real cluster"):
# `rayfarm bench` of every schedule at 4 and 8 workers on the b32 scene with emulated storage,
# and `rayfarm sim` of the same frame, caches and storage, the model's defaults alone, then
# with what the bench measured of its cluster: its two shared cores (`--cores 2`), the mean
# wait of a pass for its tracing thread (`--pass-start-us`), the CPU its workers spend outside
# tracing as prices of the shells' bundles and finished passes (`--cost`, fitted by
# `compare.py --fit-cost`), its heartbeats and acknowledgement deadline, and whatever of a
# peer bundle's way from machine to machine the model still leaves out (`--bundle-take-us`,
# transit.py: the cluster's workers' debug logs against the simulator's); then that again
# over timing seeds; then the table of them all (compare.py). Every image must be
# e4a2c0ac999bd6c1. The bench runs INVOCATIONS times, each a cluster of its own: one
# invocation's median moves between invocations by as much as the bounds, so everything
# measured of the cluster and its column of the table pool them all.
#
#   bench/validation/run.sh OUT_DIR [REPEATS] [SEEDS] [INVOCATIONS]
#
# Needs `cargo build --release --bins` and the scene in scenes/b32
# (`rayfarm prepare --generate nbody --triangles 200000 --seed 5 --domains 32 --out scenes/b32`).
# Takes about 22 minutes with the defaults (3 x 7 repeats) on the 2-core machine; run it
# with nothing else running.
set -eu
out=${1:?usage: run.sh OUT_DIR [REPEATS] [SEEDS] [INVOCATIONS]}
repeats=${2:-7}
seeds=${3:-0..9}
invocations=${4:-3}
here=$(cd "$(dirname "$0")" && pwd)
bin=${RAYFARM:-$here/../../target/release/rayfarm}
scene=${SCENE:-scenes/b32}
mkdir -p "$out"
frame="--width 128 --height 128 --spp 1 --depth 3 --cache-bytes 2MiB"
all=image-plane,domain,dynamic,hybrid,predictive
moving=domain,dynamic,hybrid,predictive
for w in 4 8; do
    benches=
    for i in $(seq "$invocations"); do
        "$bin" bench --scene "$scene" --workers $w --threads 1 --schedules $all \
            --repeats "$repeats" $frame --storage-bandwidth 10MiB/s --storage-latency 2ms \
            --csv "$out/bench$w-$i.csv" > "$out/bench$w-$i.txt" 2>&1
        benches="$benches${benches:+,}$out/bench$w-$i.csv"
    done
    sim="$bin sim --scene $scene --workers $w $frame --wave-rays 1048576 --pass-rays 262144 \
        --threads 1 --storage-bandwidth 1000000000000000 --node-storage-bandwidth 10MiB \
        --storage-latency-us 2000"
    # One more frame of each schedule that moves rays, with the workers' debug logs: how long
    # a peer bundle takes from one machine to the next on this cluster.
    RUST_LOG=info,rayfarm_machine::worker=debug "$bin" bench --scene "$scene" --workers $w \
        --threads 1 --schedules $moving --repeats 1 $frame \
        --storage-bandwidth 10MiB/s --storage-latency 2ms --keep-cluster-logs "$out/logs$w" \
        > "$out/bench$w-logs.txt" 2>&1
    # The cluster as the bench measured it: two cores, the mean wait of a pass for its
    # tracing thread over all its passes, its workers' CPU outside tracing as the shells'
    # prices, and the workers' heartbeats (1 s) and acknowledgement deadline (30 s).
    wait=$(python3 "$here/compare.py" --pass-wait-us "$benches")
    python3 "$here/compare.py" --fit-cost "$benches" "$here/../../sim/calibration.toml" \
        > "$out/cost$w.toml" 2> "$out/fit$w.txt"
    model="--cores 2 --pass-start-us $wait --cost $out/cost$w.toml --heartbeat-ms 1000 \
        --peer-ack-timeout-ms 30000"
    # The same frames in the simulator with that model and debug logs: what of a bundle's
    # way the model leaves out is charged as its wait for the engine.
    RUST_LOG=rayfarm_sim=debug,rayfarm_machine::worker=debug $sim --schedule $moving $model \
        > /dev/null 2> "$out/simlog$w.txt"
    python3 "$here/transit.py" "$out/logs$w" "$out/simlog$w.txt" > "$out/transit$w.txt"
    take=$(sed -n 's/^--bundle-take-us //p' "$out/transit$w.txt")
    cores="$model --bundle-take-us $take"
    $sim --schedule $all --csv "$out/sim$w.csv" > "$out/sim$w.txt" 2>&1
    $sim --schedule $all $cores --csv "$out/sim$w-cores.csv" > "$out/sim$w-cores.txt" 2>&1
    $sim --schedule $all $cores --timing-seeds "$seeds" --csv "$out/sim$w-seeds.csv" \
        > "$out/sim$w-seeds.txt" 2>&1
    echo "$w workers: bench / sim / sim $cores / its timing seeds $seeds (medians)"
    cat "$out/fit$w.txt"
    python3 "$here/compare.py" "$benches" "$out/sim$w.csv" "$out/sim$w-cores.csv" \
        "$out/sim$w-seeds.csv"
done
