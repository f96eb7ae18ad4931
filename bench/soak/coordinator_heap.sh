#!/usr/bin/env bash
# The coordinator's heap over a stream of jobs, without chaos: what grows, and who holds it.
#
# Starts a coordinator under heaptrack (Debian's `heaptrack`) with two workers on loopback,
# submits JOBS small jobs one after another (two frames, the five schedules in turn, as the
# soak does), and every EVERY jobs prints the coordinator's heap in use and held free (its
# /metrics, glibc's mallinfo2) and its anonymous resident memory. Then it kills the
# coordinator (SIGKILL) and prints heaptrack's allocations still live then, by call
# stack: what the coordinator holds after JOBS jobs.
#
#   bench/soak/coordinator_heap.sh [JOBS] [EVERY]     (defaults 2000 and 100)
#
# Needs `cargo build --release --bins`. Leaves its files in a temporary directory it names.
set -euo pipefail
cd "$(dirname "$0")/../.."
jobs=${1:-2000}
every=${2:-100}
bin=target/release
dir=$(mktemp -d /tmp/coordinator-heap.XXXXXX)
echo "files in $dir"
command -v heaptrack >/dev/null || { echo "heaptrack is missing (apt-get install heaptrack)" >&2; exit 1; }

pids=()
cleanup() { kill "${pids[@]}" 2>/dev/null || true; }
trap cleanup EXIT

"$bin/rayfarm" prepare --generate nbody --triangles 20000 --seed 1 --domains 8 \
    --out "$dir/scenes/nb" >/dev/null

# Waits for LINE in FILE; prints the line.
wait_for() {
    for _ in $(seq 1 600); do
        if grep -m1 "$2" "$1" 2>/dev/null; then return 0; fi
        sleep 0.1
    done
    echo "no '$2' in $1" >&2
    exit 1
}

heaptrack -o "$dir/coordinator" "$bin/rayfarm-coordinator" --listen 127.0.0.1:0 \
    --http 127.0.0.1:0 --data-dir "$dir/data" --scene-root "$dir/scenes" \
    --default-scene nb >"$dir/coordinator.log" 2>&1 &
pids+=($!)
addr=$(wait_for "$dir/coordinator.log" "listening on" | sed 's/.*listening on //; s/ .*//')
http=$(grep -m1 "http on" "$dir/coordinator.log" | sed 's/.*http on //; s/ .*//')
for w in 0 1; do
    "$bin/rayfarm-worker" --coordinator "http://$addr" --listen 127.0.0.1:0 \
        --scene-root "$dir/scenes" --threads 1 --cache-bytes 16MiB >"$dir/worker$w.log" 2>&1 &
    pids+=($!)
done
coordinator_pid=$(pgrep -n -f "rayfarm-coordinator --listen 127.0.0.1:0 --http 127.0.0.1:0 --data-dir $dir/data")

sample() {
    local metrics anon
    metrics=$(curl -s "http://$http/metrics")
    anon=$(awk '/^RssAnon:/ {print $2}' "/proc/$coordinator_pid/status")
    printf '%6d jobs: heap in use %8.3f MiB, free %8.3f MiB, RssAnon %8.3f MiB\n' "$1" \
        "$(echo "$metrics" | awk '/^rayfarm_heap_in_use_bytes / {print $2 / 1048576}')" \
        "$(echo "$metrics" | awk '/^rayfarm_heap_free_bytes / {print $2 / 1048576}')" \
        "$(echo "$anon" | awk '{print $1 / 1024}')"
}

schedules=(dynamic image-plane domain hybrid predictive)
for i in $(seq 1 "$jobs"); do
    if (( i % 2 )); then size=(--width 32 --height 32); else size=(--width 48 --height 24); fi
    "$bin/rayfarm" submit --coordinator "http://$addr" --wait --quiet "${size[@]}" --spp 1 \
        --schedule "${schedules[$(( i % 5 ))]}" -o "$dir/last.png" >/dev/null
    if (( i == 1 || i % every == 0 )); then sample "$i"; fi
done

# Killed, not stopped: a clean exit would free the state whose size is the question.
kill -KILL "$coordinator_pid"
wait "${pids[0]}" || true
heaptrack_print --print-leaks 1 --print-peaks 0 --print-allocators 0 --print-temporary 0 \
    --peak-limit 100000 --sub-peak-limit 100000 "$dir/coordinator.zst" > "$dir/live-at-exit.txt" || true
echo "allocations live at the kill, by call stack: $dir/live-at-exit.txt"
# heaptrack lists live bytes per allocation site, then per call stack; add the stacks up by
# their first frame in a crate (a dependency's or ours) rather than the standard library.
python3 - "$dir/live-at-exit.txt" <<'PY'
import re, sys, collections
units = {"": 1, "K": 1e3, "M": 1e6, "G": 1e9}
workspace = ("coordinator/", "node/", "core/", "machine/", "worker/", "proto/", "cli/")
total, by_site, size, site, func = 0.0, collections.Counter(), None, None, None
for line in open(sys.argv[1], errors="replace"):
    m = re.match(r"([\d.]+)([KMG]?)B? leaked over \d+ calls from:", line)
    if m:
        size, site = float(m[1]) * units[m[2]], None
        continue
    if size is None or site is not None:
        continue
    m = re.match(r"\s+at (\S+)", line)
    if not m:
        func = line.strip()
        continue
    path = m[1]
    crate = re.search(r"/registry/src/[^/]+/([^/]+)/(.*)", path)
    if crate:
        site = f"{crate[1]} {crate[2]} ({func})"
    elif path.startswith(workspace):
        site = f"{path} ({func})"
    if site:
        by_site[site] += size
        total += size
print(f"live at the kill by where it was allocated ({total / 1e6:.2f} MB):")
for where, b in by_site.most_common(15):
    print(f"  {b / 1e3:9.1f} kB  {where}")
PY
