#!/usr/bin/env python3
"""How long peer bundles took from the sending worker's machine handing a bundle to its shell
to the receiving worker's machine taking it in, read from debug logs: a real cluster's
(`RUST_LOG=info,rayfarm_machine::worker=debug rayfarm bench ... --keep-cluster-logs DIR`) and
optionally the simulator's (`RUST_LOG=rayfarm_sim=debug,rayfarm_machine::worker=debug rayfarm
sim ... 2> SIM_LOG`: its lines carry each worker's node and virtual time). Each machine logs
"bundle sent" with its peer and "bundle taken" with its sender; a sender's bundles to one
peer travel one stream, in order, so the k-th sent is the k-th taken.

    transit.py LOG_DIR [SIM_LOG]

Prints the count, median, 90th percentile and mean in microseconds of each, and with SIM_LOG
the cluster's mean less the simulator's: what the simulator's model leaves out of a bundle's
way, which `rayfarm sim --bundle-take-us` charges (never below zero)."""
import datetime
import glob
import os
import re
import statistics
import sys

SENT = re.compile(r"bundle sent peer=(\S+) tier=(\S+)")
TAKEN = re.compile(r"bundle taken sender=(\S+) verdicts=(\S+)")


def stamp(line):
    return datetime.datetime.strptime(line[:26], "%Y-%m-%dT%H:%M:%S.%f").timestamp() * 1e6


def note(line, me, t, sent, taken):
    """Files a "bundle sent" or "bundle taken" line of worker `me` at `t` microseconds."""
    m = SENT.search(line)
    if m:
        sent.setdefault((me, m[1]), []).append((t, m[2] == "Results"))
    m = TAKEN.search(line)
    if m:
        taken.setdefault((m[1], me), []).append((t, m[2] == "true"))


def paired(sent, taken):
    """Each bundle's time from sent to taken."""
    times = []
    for pair, out in sent.items():
        for (t0, results), (t1, verdicts) in zip(out, taken.get(pair, [])):
            if results != verdicts:
                sys.exit(f"bundles of {pair} out of step: the logs are incomplete")
            times.append(t1 - t0)
    return times


def cluster(log_dir):
    """Transit times in a cluster's worker logs, one file a worker."""
    sent, taken = {}, {}
    for path in sorted(glob.glob(os.path.join(log_dir, "worker-*.log"))):
        me = None
        for line in open(path):
            if me is None:
                m = re.search(r"worker up bound=(\S+)", line)
                me = m and m[1]
                continue
            note(line, me, stamp(line), sent, taken)
    return paired(sent, taken)


def simulated(path):
    """Transit times in a simulator's log: worker node N is `sim-w{N-1}:7000`; a run starts
    where virtual time goes back, and bundles pair within a run."""
    times, sent, taken, last = [], {}, {}, 0
    span = re.compile(r"sim worker\{node=(\d+) virtual_us=(\d+)\}")
    for line in open(path):
        m = span.search(line)
        if not m:
            continue
        t = int(m[2])
        if t < last:
            times += paired(sent, taken)
            sent, taken = {}, {}
        last = t
        note(line, f"sim-w{int(m[1]) - 1}:7000", t, sent, taken)
    return times + paired(sent, taken)


def summary(label, times):
    if not times:
        sys.exit(f"no bundle sent and taken in the {label} logs (is rayfarm_machine::worker "
                 "at debug?)")
    times = sorted(times)
    mean = statistics.mean(times)
    print(f"{label}: {len(times)} bundles: median {statistics.median(times):.0f} us, "
          f"90th percentile {times[int(len(times) * 0.9)]:.0f} us, mean {mean:.0f} us")
    return mean


def main():
    real = summary("cluster", cluster(sys.argv[1]))
    if len(sys.argv) > 2:
        model = summary("simulator", simulated(sys.argv[2]))
        print(f"--bundle-take-us {max(0, round(real - model))}")


if __name__ == "__main__":
    main()
