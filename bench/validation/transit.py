#!/usr/bin/env python3
"""How long peer bundles took on a real cluster from the sending worker's machine handing a
bundle to its shell to the receiving worker's machine taking it in, read from the workers'
debug logs (`RUST_LOG=info,rayfarm_machine::worker=debug rayfarm bench ... --keep-cluster-logs
DIR`: each machine logs "bundle sent" with its peer and "bundle taken" with its sender; a
sender's bundles to one peer travel one stream, in order, so the k-th sent is the k-th taken).

    transit.py LOG_DIR [SIMULATED_US]

Prints the count, median, 90th percentile and mean in microseconds, and with SIMULATED_US
(what the simulator's own network and decoding take, about 130) the mean less it: what
`rayfarm sim --bundle-take-us` charges a bundle."""
import datetime
import glob
import os
import re
import statistics
import sys


def stamp(line):
    return datetime.datetime.strptime(line[:26], "%Y-%m-%dT%H:%M:%S.%f").timestamp() * 1e6


def main():
    logs = sorted(glob.glob(os.path.join(sys.argv[1], "worker-*.log")))
    sent, taken = {}, {}
    for path in logs:
        me = None
        for line in open(path):
            if me is None:
                m = re.search(r"worker up bound=(\S+)", line)
                me = m and m[1]
                continue
            m = re.search(r"bundle sent peer=(\S+) tier=(\S+)", line)
            if m:
                sent.setdefault((me, m[1]), []).append((stamp(line), m[2] == "Results"))
            m = re.search(r"bundle taken sender=(\S+) verdicts=(\S+)", line)
            if m:
                taken.setdefault((m[1], me), []).append((stamp(line), m[2] == "true"))
    times = []
    for pair, out in sent.items():
        for (t0, results), (t1, verdicts) in zip(out, taken.get(pair, [])):
            if results != verdicts:
                sys.exit(f"bundles of {pair} out of step: the logs are incomplete")
            times.append(t1 - t0)
    if not times:
        sys.exit("no bundle sent and taken in the logs (is rayfarm_machine::worker at debug?)")
    times.sort()
    mean = statistics.mean(times)
    print(f"{len(times)} bundles: median {statistics.median(times):.0f} us, "
          f"90th percentile {times[int(len(times) * 0.9)]:.0f} us, mean {mean:.0f} us")
    if len(sys.argv) > 2:
        print(f"--bundle-take-us {max(0, round(mean - float(sys.argv[2])))}")


if __name__ == "__main__":
    main()
