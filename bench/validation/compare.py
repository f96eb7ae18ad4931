#!/usr/bin/env python3
"""The simulator against the real cluster, side by side (README "Validation against the real
cluster"): loads, rays migrated and each schedule's time over image-plane's, from the CSVs of
`rayfarm bench --csv` (medians over its repeats, their range in brackets) and of `rayfarm sim
--csv` (the clean run, and the medians of its timing seeds when it ran any).

    compare.py BENCH.csv[,BENCH2.csv...] SIM.csv [SIM2.csv ...]
    compare.py --pass-wait-us BENCH.csv[,...]   # the mean wait of a pass for its thread
    compare.py --fit-cost BENCH.csv[,...] BASE.toml > COST.toml   # the shells' CPU, fitted

Several bench CSVs (of the same binaries and commands) are pooled: a bench invocation's
median moves between invocations by more than the bounds on the timing-sensitive figures.

Marks in bold what is outside the issue's bounds: 15% for loads and rays migrated, 25% for
time ratios."""
import csv
import statistics
import sys
import tomllib

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


def solve(rows, ys):
    """Least squares of `ys` on the columns of `rows`, no coefficient negative: every subset
    of the columns fitted by its normal equations (Gaussian elimination), the best of those
    whose coefficients are all non-negative kept; a column left out fits zero."""
    n = len(rows[0])
    best = (float("inf"), [0.0] * n)
    for mask in range(1, 1 << n):
        cols = [j for j in range(n) if mask >> j & 1]
        a = [[sum(r[i] * r[j] for r in rows) for j in cols] for i in cols]
        b = [sum(r[i] * y for r, y in zip(rows, ys)) for i in cols]
        k = len(cols)
        for p in range(k):
            pivot = max(range(p, k), key=lambda q: abs(a[q][p]))
            if abs(a[pivot][p]) < 1e-30:
                break
            a[p], a[pivot], b[p], b[pivot] = a[pivot], a[p], b[pivot], b[p]
            for q in range(k):
                if q != p:
                    f = a[q][p] / a[p][p]
                    a[q] = [x - f * y for x, y in zip(a[q], a[p])]
                    b[q] -= f * b[p]
        else:
            coef = [0.0] * n
            for p, j in enumerate(cols):
                coef[j] = b[p] / a[p][p]
            if min(coef) >= 0:
                err = sum((sum(c * x for c, x in zip(coef, r)) - y) ** 2 for r, y in zip(rows, ys))
                best = min(best, (err, coef))
    return best[1]


def fit_cost(paths, base_path):
    """A calibration file for the simulator whose shells spend what this cluster's workers
    spend outside tracing: each run's CPU outside tracing (`cpu_seconds - trace_cpu_seconds`,
    every worker summed) fitted, relative to itself, as k x what the base prices charge its
    peer bundles (per bundle and per byte, sender's and receiver's) + a price a pass + a
    price a domain load, none negative. The bundles' four prices are the base's times k, the
    finished pass's (`finished_pass_ns`) the fitted one; a load's CPU is fitted so that it
    does not land on the others, and the simulator does not charge it (it overlaps the
    loading it comes with). Prints the file; the fit and its error go to stderr."""
    with open(base_path, "rb") as f:
        base = tomllib.load(f)
    per_bundle = base["bundle_send_ns"] + base["bundle_receive_ns"]
    per_byte = base["bundle_send_byte_ns"] + base["bundle_receive_byte_ns"]
    rows, ys = [], []
    for r in bench_rows(paths):
        if r["ok"] != "true" or not r.get("cpu_seconds"):
            continue
        out = float(r["cpu_seconds"]) - float(r["trace_cpu_seconds"])
        bundles = sum(int(r[c]) for c in ("bundles_migrated", "bundles_results", "bundles_tasks"))
        priced = (bundles * per_bundle + int(r["bytes_migrated"]) * per_byte) * 1e-9
        if out > 0:
            rows.append([priced / out, int(r["passes"]) / out, int(r["domain_loads"]) / out])
            ys.append(1.0)
    if not rows:
        sys.exit("no run with the workers' CPU in the bench CSVs (cpu_seconds)")
    k, per_pass, per_load = solve(rows, ys)
    misses = [abs(sum(c * x for c, x in zip((k, per_pass, per_load), row)) - 1) for row in rows]
    rms = (sum(m * m for m in misses) / len(misses)) ** 0.5
    print(f"{len(rows)} runs: the shells' CPU outside tracing = {k:.3f} x the priced bundles "
          f"+ {per_pass * 1e6:.1f} us a pass + {per_load * 1e6:.1f} us a load "
          f"(relative error {rms * 100:.1f}% rms)", file=sys.stderr)
    scaled = {"bundle_send_ns", "bundle_receive_ns", "bundle_send_byte_ns",
              "bundle_receive_byte_ns"}
    print(f"# {base_path} with the peer bundles' prices x {k:.3f} and a finished pass at "
          f"{per_pass * 1e9:.0f} ns: the CPU outside tracing of the workers of {paths} "
          f"(bench/validation/compare.py --fit-cost; relative error {rms * 100:.1f}% rms)")
    for line in open(base_path):
        key = line.partition("=")[0].strip()
        if key in scaled:
            line = f"{key} = {base[key] * k}\n"
        elif key == "finished_pass_ns":
            continue
        print(line, end="")
    print(f"finished_pass_ns = {per_pass * 1e9}")


def main():
    if sys.argv[1] == "--pass-wait-us":
        print(pass_wait_us(sys.argv[2]))
        return
    if sys.argv[1] == "--fit-cost":
        fit_cost(sys.argv[2], sys.argv[3])
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
