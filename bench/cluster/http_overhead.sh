#!/usr/bin/env bash
# What metrics and the dashboard cost a frame, with and without, in one run: two loopback
# clusters of the same size on the same scene, A with `--http` on the coordinator and on every
# worker, B without. They render the same frame in turns, ABBA ABBA ... (so drift of the
# machine falls on both alike), one cluster idle while the other renders. During each of A's
# frames a scraper polls what an open dashboard page polls, at its rate (GET /api/jobs,
# /api/cluster and /api/history once a second, the running job's preview whenever its
# sequence number moved), and what Prometheus scrapes, once a second (15 s is its default):
# /metrics of the coordinator and of every worker. Nothing polls B.
#
# Printed per pair: both frames' wall times (the coordinator's, frame start to last tile) and
# the CPU seconds of the cluster's processes during the frame (coordinator and workers, from
# /proc: the farm's own cost, without the scraper's), then the ratios A/B: median, mean and
# min-max over the pairs. Every image must be the same. With SCRAPE=0 nothing polls A: what
# `--http` alone costs (nothing is served), or how far two idle-equal clusters differ.
# Build first: cargo build --release --bins
#
# usage: bench/cluster/http_overhead.sh SCENE_DIR WORKERS PAIRS CACHE_PER_WORKER [frame flags...]
# e.g.   bench/cluster/http_overhead.sh scenes/b48 4 8 64MiB --width 384 --height 384 --spp 8
set -euo pipefail
scene=$(realpath "$1") n=$2 pairs=$3 cache=$4
shift 4
frame=("$@")
bin=$(dirname "$(realpath "$0")")/../../target/release
work=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT

# start_cluster NAME [--http]: a coordinator and $n workers; the coordinator's gRPC address in
# $work/NAME.addr, its HTTP address and the workers' (with --http) in $work/NAME.http, the
# processes' ids in $work/NAME.pids.
start_cluster() {
    local name=$1 http=() d="$work/$1"
    [ "${2:-}" = --http ] && http=(--http 127.0.0.1:0)
    mkdir -p "$d"
    "$bin/rayfarm-coordinator" --listen 127.0.0.1:0 --data-dir "$d/data" \
        --scene-root "$(dirname "$scene")" "${http[@]}" >"$d/coordinator.out" 2>"$d/coordinator.log" &
    pids+=($!)
    echo $! >"$d.pids"
    until grep -q "listening on" "$d/coordinator.out" 2>/dev/null; do sleep 0.05; done
    awk '/listening on/ {print $3}' "$d/coordinator.out" >"$d.addr"
    for i in $(seq "$n"); do
        "$bin/rayfarm-worker" --coordinator "http://$(cat "$d.addr")" --listen 127.0.0.1:0 \
            --cache-bytes "$cache" --scene-root "$(dirname "$scene")" --threads 1 "${http[@]}" \
            >"$d/worker-$i.out" 2>"$d/worker-$i.log" &
        pids+=($!)
        echo $! >>"$d.pids"
    done
    "$bin/rayfarm" status --coordinator "$(cat "$d.addr")" --wait-workers "$n" --timeout 30 >/dev/null
    if [ ${#http[@]} -gt 0 ]; then
        for f in "$d/coordinator.out" "$d"/worker-*.out; do
            until grep -q "http on" "$f" 2>/dev/null; do sleep 0.05; done
            awk '/http on/ {print $3}' "$f"
        done >"$d.http"
    fi
}

# cpu_ticks NAME [coordinator|workers]: user + system clock ticks of the cluster's processes
# (or of its coordinator, or of its workers) so far.
cpu_ticks() {
    local total=0 p pids
    pids=$(cat "$work/$1.pids")
    case "${2:-}" in
        coordinator) pids=$(head -1 "$work/$1.pids") ;;
        workers) pids=$(tail -n +2 "$work/$1.pids") ;;
    esac
    for p in $pids; do
        # Fields 14 and 15 of /proc/PID/stat, counted after the command name's closing paren.
        total=$((total + $(sed 's/.*) //' "/proc/$p/stat" | awk '{print $12 + $13}')))
    done
    echo "$total"
}

# frame NAME TAG: renders the frame on cluster NAME; prints "wall_seconds cpu_seconds hash
# coordinator_cpu_seconds".
frame() {
    local name=$1 tag=$2 before after c_before c_after
    before=$(cpu_ticks "$name")
    c_before=$(cpu_ticks "$name" coordinator)
    "$bin/rayfarm" submit --coordinator "$(cat "$work/$name.addr")" --scene "$(basename "$scene")" \
        "${frame[@]}" --wait --quiet -o "$work/$tag.png" --stats-json "$work/$tag.json" >/dev/null
    after=$(cpu_ticks "$name")
    c_after=$(cpu_ticks "$name" coordinator)
    python3 -c 'import json,sys; s=json.load(open(sys.argv[1])); t=int(sys.argv[6]); print(s["wall_seconds"], (int(sys.argv[3])-int(sys.argv[2]))/t, s["image_hash"], (int(sys.argv[5])-int(sys.argv[4]))/t)' \
        "$work/$tag.json" "$before" "$after" "$c_before" "$c_after" "$(getconf CLK_TCK)"
}

start_cluster a --http
start_cluster b

# The scraper: one process, keep-alive connections, reads every byte and parses only the
# job list (to find the running job's preview sequence), as the page does.
cat >"$work/scraper.py" <<'PY'
import http.client, json, sys, time
coordinator, *workers = [l.strip() for l in open(sys.argv[1]) if l.strip()]
conns = {}
def get(addr, path):
    c = conns.get(addr) or http.client.HTTPConnection(addr, timeout=10)
    conns[addr] = c
    try:
        c.request("GET", path)
        r = c.getresponse()
        return r.read()
    except (OSError, http.client.HTTPException):
        conns.pop(addr, None).close()
        return b""
shown = (None, None)
requests = 0
while True:
    tick = time.monotonic()
    jobs = get(coordinator, "/api/jobs")
    get(coordinator, "/api/cluster")
    get(coordinator, "/api/history")
    get(coordinator, "/metrics")
    requests += 4
    for w in workers:
        get(w, "/metrics")
        requests += 1
    try:
        running = [j for j in json.loads(jobs) if j.get("state") == "running"]
    except ValueError:
        running = []
    if running and (running[0]["job_id"], running[0].get("preview_sequence")) != shown:
        shown = (running[0]["job_id"], running[0].get("preview_sequence"))
        get(coordinator, f"/api/jobs/{shown[0]}/preview")
        requests += 1
    with open(sys.argv[2], "w") as f:
        f.write(str(requests))
    time.sleep(max(0.0, 1.0 - (time.monotonic() - tick)))
PY

# One frame on each first, not counted: the scene's files in the page cache, both warmed up.
frame a warm-a >/dev/null
frame b warm-b >/dev/null
echo "pair  A wall  B wall  A/B   A cpu  B cpu  A/B   A coord B coord  scraper requests"
: >"$work/pairs"
for i in $(seq "$pairs"); do
    order="a b"
    [ $((i % 2)) -eq 0 ] && order="b a"
    for c in $order; do
        if [ "$c" = a ]; then
            echo 0 >"$work/requests"
            # SCRAPE=0: nothing polls A either (what --http alone costs, or the clusters'
            # difference).
            if [ "${SCRAPE:-1}" = 1 ]; then
                python3 "$work/scraper.py" "$work/a.http" "$work/requests" &
                scraper=$!
                pids+=($scraper)
            fi
            read -r wa ca ha xa < <(frame a "a-$i")
            if [ "${SCRAPE:-1}" = 1 ]; then
                kill "$scraper"
                wait "$scraper" 2>/dev/null || true
            fi
        else
            read -r wb cb hb xb < <(frame b "b-$i")
        fi
    done
    echo "$i $wa $wb $ca $cb $ha $hb $(cat "$work/requests") $xa $xb" >>"$work/pairs"
    tail -1 "$work/pairs" | awk '{printf "%4d %6.2f s %6.2f s %.3f %6.2f s %6.2f s %.3f %5.2f s %5.2f s %d\n", $1, $2, $3, $2/$3, $4, $5, $4/$5, $9, $10, $8}'
done

python3 - "$work/pairs" <<'PY'
import statistics, sys
rows = [l.split() for l in open(sys.argv[1])]
hashes = {h for r in rows for h in r[5:7]}
for name, a, b in (("wall time", 1, 2), ("cluster CPU", 3, 4), ("coordinator CPU", 8, 9)):
    r = [float(x[a]) / float(x[b]) for x in rows]
    print(f"{name} A/B over {len(r)} pairs: median {statistics.median(r):.3f}, "
          f"mean {statistics.mean(r):.3f} (sd {statistics.stdev(r) if len(r) > 1 else 0:.3f}), "
          f"min-max {min(r):.3f}-{max(r):.3f}")
print("identical images:", len(hashes) == 1, sorted(hashes))
PY
