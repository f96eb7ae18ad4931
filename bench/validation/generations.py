#!/usr/bin/env python3
"""Which ray generation each domain load served, and how much tracing each load bought, read
from the workers' debug logs: the simulator's (`RUST_LOG=rayfarm_machine::worker::machine=debug,
rayfarm_sim=debug rayfarm sim ... 2> LOG`: each line names its worker's node) or a real
cluster's (`RUST_LOG=info,rayfarm_machine::worker::machine=debug rayfarm bench ...
--keep-cluster-logs DIR`: a file per worker).

Each worker logs "pass handed over" with the pass's domain, whether it was mapped then
(`mapped=Some(false)`: the pass loads it) and its rays of each generation, oldest first. A
load's residency is every pass of that domain on that worker until the domain's next load
there (a domain is traced only while mapped, so those passes are exactly the ones the load
served). The load counts under the generation the schedule made it for: the oldest of its
first pass, or the next one there when the oldest are a few stragglers (at most 200 rays, as
the predictive schedule's `speculative::scheduled_generation` counts them). Prefetched loads are
made beside passes and are not seen: read logs of runs without --prefetch.

    generations.py LOG [LOG ...]

Prints, per generation: loads, distinct domains loaded, distinct domains traced for it (any
pass holding a ray of that generation: what the generation needed, loaded or kept mapped),
rays traced in the residencies its loads began; then how many residencies traced fewer than
10, 50 and 200 rays."""
import collections
import re
import sys

PASS = re.compile(
    r"pass handed over domain=Some\((\d+)\) rays=\d+ primaries=\d+ "
    r"mapped=Some\((true|false)\) generations=Some\(\[([\d, ]*)\]\)"
)
NODE = re.compile(r"node=(\d+)")


def passes(paths):
    """(worker, domain, loads, rays of each generation) of every pass, in log order."""
    for path in paths:
        with open(path, errors="replace") as log:
            for line in log:
                m = PASS.search(line)
                if not m:
                    continue
                node = NODE.search(line)
                worker = (path, node.group(1) if node else "")
                counts = [int(c) for c in m.group(3).split(",") if c.strip()]
                yield worker, int(m.group(1)), m.group(2) == "false", counts


STRAGGLER_RAYS = 200


def made_for(counts):
    """The generation a pass's load was made for (see the module documentation)."""
    present = [g for g, n in enumerate(counts) if n]
    if not present:
        return 0
    if counts[present[0]] <= STRAGGLER_RAYS and len(present) > 1:
        return present[1]
    return present[0]


def residencies(paths):
    """(generation, domain, rays traced) of each load."""
    open_ = {}
    done = []
    for worker, domain, loads, counts in passes(paths):
        key = (worker, domain)
        if loads:
            if key in open_:
                done.append(open_[key])
            open_[key] = [made_for(counts), domain, 0]
        if key in open_:
            open_[key][2] += sum(counts)
    return done + list(open_.values())


def traced(paths):
    """The domains traced for each generation: those of passes holding a ray of it."""
    needed = collections.defaultdict(set)
    for _, domain, _, counts in passes(paths):
        for g, n in enumerate(counts):
            if n:
                needed[g].add(domain)
    return needed


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    loads = residencies(sys.argv[1:])
    needed = traced(sys.argv[1:])
    if not loads:
        sys.exit("no 'pass handed over' lines with mapped= and generations= in these logs")
    by_generation = collections.defaultdict(list)
    for generation, domain, rays in loads:
        by_generation[generation].append((domain, rays))
    print("generation  loads  domains loaded  domains traced  rays traced")
    for g in sorted(set(by_generation) | set(needed)):
        rows = by_generation.get(g, [])
        print(
            f"{g:>10}  {len(rows):>5}  {len({d for d, _ in rows}):>14}  {len(needed[g]):>14}"
            f"  {sum(r for _, r in rows):>11}"
        )
    print(f"{'all':>10}  {len(loads):>5}")
    for limit in (10, 50, 200):
        few = sum(1 for _, _, rays in loads if rays < limit)
        print(f"loads that traced fewer than {limit} rays: {few} ({100 * few / len(loads):.0f}%)")


if __name__ == "__main__":
    main()
