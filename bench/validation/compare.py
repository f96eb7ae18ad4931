#!/usr/bin/env python3
"""The simulator against the real cluster, side by side (README "Validation against the real
cluster"): loads, rays migrated and each schedule's time over image-plane's, from the CSVs of
`rayfarm bench --csv` (medians over its repeats, their range in brackets) and of `rayfarm sim
--csv` (the clean run, and the medians of its timing seeds when it ran any).

    compare.py BENCH.csv[,BENCH2.csv...] SIM.csv [SIM2.csv ...]
    compare.py --pass-wait-us BENCH.csv[,...]   # the mean wait of a pass for its thread

Several bench CSVs (of the same binaries and commands) are pooled: a bench invocation's
median moves between invocations by more than the bounds on the timing-sensitive figures.

Marks in bold what is outside the issue's bounds: 15% for loads and rays migrated, 25% for
time ratios."""
import csv
import statistics
import sys

SCHEDULES = ["domain", "dynamic", "hybrid", "predictive"]
HASHES = set()


def bench_rows(paths):
    """Every row of the bench CSVs named in `paths` (comma-separated), pooled."""
    return [r for path in paths.split(",") for r in csv.DictReader(open(path))]


def bench(paths):
    """Runs by schedule, pooled over the bench CSVs named in `paths` (comma-separated)."""
    rows = {}
    for r in bench_rows(paths):
        HASHES.add(r["image_hash"])
        if r["ok"] != "true":
            continue
        rows.setdefault(r["schedule"], []).append(
            (float(r["wall_seconds"]), int(r["domain_loads"]), int(r["rays_migrated"])))
    return rows


def sim(path):
    """{(schedule, kind): [(ms, loads, migrated)]} with kind "clean" or "seeds"."""
    rows = {}
    for r in csv.DictReader(open(path)):
        kind = "clean" if r["seed"] == "clean" else "seeds" if r["faults"] == "timing only" else None
        if kind is None:
            continue
        HASHES.add(r["image_hash"])
        rows.setdefault((r["schedule"], kind), []).append(
            (float(r["virtual_ms"]) / 1e3, int(r["loads"]), int(r["rays_migrated"])))
    return rows


def med(values):
    return statistics.median(values)


def cell(real, simulated, bound, fmt):
    off = (simulated - real) / real * 100 if real else 0.0
    text = f"{fmt(simulated)} ({off:+.1f}%)"
    return f"**{text}**" if abs(off) > bound else text


def pass_wait_us(path):
    """The mean wait of a pass for its tracing thread over every pass of every run, in
    microseconds: what `rayfarm sim --pass-start-us` charges each pass."""
    waits = passes = 0.0
    for r in bench_rows(path):
        if r["ok"] == "true" and r.get("passes"):
            waits += float(r["pass_start_wait_seconds"])
            passes += int(r["passes"])
    return round(waits / passes * 1e6) if passes else 0


# A worker's frame in parts, per worker, as the bench's CSV and the simulator's name them:
# (label, bench columns summed, simulator columns summed).
PARTS = [
    ("frame", ["frame_seconds"], ["frame_seconds"]),
    ("loading", ["load_seconds"], ["loading_seconds"]),
    ("pass waiting for a thread", ["pass_start_wait_seconds"], ["thread_wait_seconds"]),
    ("finished pass waiting", ["pass_wait_seconds"], ["shell_wait_seconds"]),
    ("idle: rays queued", ["idle_queued_seconds"], ["idle_queued_seconds"]),
    ("idle: verdicts", ["idle_verdicts_seconds"], ["idle_verdicts_seconds"]),
    ("idle: nothing queued", ["idle_empty_seconds"], ["idle_empty_seconds"]),
]


def split(paths, sim_path, workers):
    """Where a worker's frame went, seconds per worker, medians over the bench's repeats and
    the simulator's runs (its timing seeds when it ran any), when both CSVs carry the parts."""
    real = [r for r in bench_rows(paths) if r["ok"] == "true"]
    sim_rows = list(csv.DictReader(open(sim_path)))
    if not real or "idle_empty_seconds" not in real[0] or not sim_rows \
            or "frame_seconds" not in sim_rows[0]:
        return
    seeded = any(r["faults"] == "timing only" for r in sim_rows)
    sim_rows = [r for r in sim_rows
                if (r["faults"] == "timing only") == seeded and (seeded or r["seed"] == "clean")]
    print("\nwhere a worker's frame went, seconds a worker: bench / sim")
    print("| schedule | " + " | ".join(label for label, _, _ in PARTS) + " |")
    print("|---" * (len(PARTS) + 1) + "|")
    for s in SCHEDULES:
        b = [r for r in real if r["schedule"] == s]
        m = [r for r in sim_rows if r["schedule"] == s]
        if not b or not m:
            continue
        cells = []
        for _, bc, sc in PARTS:
            bv = med([sum(float(r[c]) for c in bc) / workers for r in b])
            sv = med([sum(float(r[c]) for c in sc) / int(r["frames"]) for r in m])
            cells.append(f"{bv:.3f} / {sv:.3f}")
        print(f"| {s} | " + " | ".join(cells) + " |")


def main():
    if sys.argv[1] == "--pass-wait-us":
        print(pass_wait_us(sys.argv[2]))
        return
    b = bench(sys.argv[1])
    sims = [sim(p) for p in sys.argv[2:]]
    base = med([t for t, _, _ in b["image-plane"]])
    print("| schedule | loads: bench / " + " / ".join(f"sim {i + 1}" for i in range(len(sims)))
          + " | rays migrated: bench / ... | time / image-plane: bench / ... |")
    print("|---|---|---|---|")
    for s in SCHEDULES:
        if s not in b:
            continue
        runs = b[s]
        loads = [l for _, l, _ in runs]
        mig = [m for _, _, m in runs]
        ratio = med([t for t, _, _ in runs]) / base
        lc = [f"{med(loads):,.0f} [{min(loads):,}-{max(loads):,}]"]
        mc = [f"{med(mig):,.0f} [{min(mig):,}-{max(mig):,}]"]
        tc = [f"{ratio:.4f}"]
        for one in sims:
            kind = "seeds" if (s, "seeds") in one else "clean"
            rs = one.get((s, kind))
            ip = one.get(("image-plane", kind))
            if not rs or not ip:
                continue
            lc.append(cell(med(loads), med([l for _, l, _ in rs]), 15, lambda v: f"{v:,.0f}"))
            mc.append(cell(med(mig), med([m for _, _, m in rs]), 15, lambda v: f"{v:,.0f}"))
            r = med([t for t, _, _ in rs]) / med([t for t, _, _ in ip])
            tc.append(cell(ratio, r, 25, lambda v: f"{v:.4f}"))
        print(f"| {s} | " + " / ".join(lc) + " | " + " / ".join(mc) + " | " + " / ".join(tc) + " |")
    print(f"images: {', '.join(sorted(HASHES))}")
    if len(HASHES) != 1:
        sys.exit("the images differ")
    workers = {int(r["workers"]) for r in bench_rows(sys.argv[1])}
    if len(workers) == 1:
        split(sys.argv[1], sys.argv[-1], workers.pop())


if __name__ == "__main__":
    main()
