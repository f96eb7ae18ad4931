#!/usr/bin/env bash
# rayfarm's BVH traversal against Embree 3 on one core: builds the Embree side, makes the
# one-domain benchmark scene if it is missing or older than `rayfarm`, and runs
# core/examples/embree_compare/. Extra arguments go to the example (--size N, --reps N, --high,
# --keep DIR to keep the mesh, ray and hit files).
#
# Environment: CARGO_TARGET_DIR (default ./target; the scene and the C++ binary live there too),
# TRIANGLES (generator's target count, default 1000000), SCENE (an existing one-domain scene to
# use instead; it is not rebuilt),
# BENCH_CPU (pin the whole run to this CPU with taskset, e.g. 1; default: no pinning),
# EMBREE_MAX_ISA (cap Embree's ISA: sse4.2, avx2, avx512, or native for the widest the CPU has;
# default avx2, the target machine's ISA: a VM may report AVX-512, which the target lacks),
# RAYFARM_KERNEL (force rayfarm's traversal kernel: scalar, sse, avx2; default: the widest).
set -euo pipefail

root=$(cd "$(dirname "$0")/../.." && pwd)
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$root/target}
triangles=${TRIANGLES:-1000000}
scene=${SCENE:-$CARGO_TARGET_DIR/bench-scenes/nbody-$triangles-1domain}
bin=$CARGO_TARGET_DIR/bench-embree/embree_trace
src=$root/bench/embree/embree_trace.cpp

# Probe with the compiler rather than a fixed path, so any include directory g++ knows works.
if ! echo '#include <embree3/rtcore.h>' | g++ -x c++ -fsyntax-only - 2>/dev/null; then
    echo "Embree 3 headers not found. On Debian/Ubuntu: sudo apt-get install libembree-dev" >&2
    exit 1
fi

if [[ ! -x $bin || $src -nt $bin ]]; then
    mkdir -p "$(dirname "$bin")"
    # -march=native only shapes this file's loop; the Embree library picks its own ISA at run time.
    g++ -O3 -march=native -std=c++17 -Wall -Wextra -o "$bin" "$src" -lembree3
fi

cd "$root"
if [[ -z ${SCENE:-} ]]; then
    # The scene is a product of the current `rayfarm` binary: the domain file format may change
    # between commits, so a scene older than the binary is made again (a few seconds).
    cargo build --release --bin rayfarm
    rayfarm=$CARGO_TARGET_DIR/release/rayfarm
    if [[ ! -f $scene/scene.toml || $rayfarm -nt $scene/scene.toml ]]; then
        "$rayfarm" prepare --generate nbody --triangles "$triangles" --domains 1 --force \
            --out "$scene"
    fi
fi

cargo build --release -p rayfarm-core --example embree_compare
example=$CARGO_TARGET_DIR/release/examples/embree_compare
# rayfarm must not use AVX-512 either (the target has none): no function of rayfarm's own code
# in the benchmark binary may name a 512-bit register. (A dependency may carry a run-time
# dispatched AVX-512 path outside the traced loop, e.g. crc32fast's for image files; those are
# listed, not refused.)
if command -v objdump >/dev/null; then
    wide=$(objdump -d -C --no-show-raw-insn "$example" |
        awk '/^[0-9a-f]+ <.*>:$/ { fn = $0 } /%zmm/ { print fn }' | sort -u)
    if grep -qE '<(rayfarm_|embree_compare)' <<<"$wide"; then
        echo "rayfarm code in $example uses AVX-512 (zmm registers); the target has none:" >&2
        grep -E '<(rayfarm_|embree_compare)' <<<"$wide" >&2
        exit 1
    fi
    if [[ -n $wide ]]; then
        echo "AVX-512 only in dependencies, outside the traced code:" >&2
        sed 's/^[0-9a-f]* /  /' <<<"$wide" >&2
    fi
fi
pin=()
if [[ -n ${BENCH_CPU:-} ]]; then
    pin=(taskset -c "$BENCH_CPU")
fi
# Run the built example directly (not `cargo run`) so a pinned run pins only the benchmark.
exec "${pin[@]}" "$example" "$scene" --embree "$bin" "$@"
