#!/usr/bin/env bash
# Builds the rayfarm container image without pulling anything: release binaries (stripped)
# plus exactly the shared libraries `ldd` says they need, on `FROM scratch`. Works wherever
# Docker runs, with or without a registry.
#
# usage: deploy/build-image.sh [TAG]     (default rayfarm:latest)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
tag=${1:-rayfarm:latest}
cd "$root"
cargo build --release --bins
context=$(mktemp -d)
trap 'rm -rf "$context"' EXIT
bins=(rayfarm rayfarm-coordinator rayfarm-worker)
mkdir -p "$context/rootfs/usr/local/bin" "$context/rootfs/etc" \
    "$context/owned/data" "$context/owned/scenes" "$context/owned/tmp" \
    "$context/owned/secrets"
for b in "${bins[@]}"; do
    strip --strip-debug -o "$context/rootfs/usr/local/bin/$b" "target/release/$b"
done
# Every library the binaries load, at the path the dynamic loader looks for it.
for lib in $(ldd "${bins[@]/#/target/release/}" | awk '/=>/ && $3 ~ /^\// {print $3} /^[ \t]*\// {print $1}' | sort -u); do
    mkdir -p "$context/rootfs$(dirname "$lib")"
    cp -L "$lib" "$context/rootfs$lib"
done
echo "rayfarm:x:10001:10001:rayfarm:/data:/nonexistent" >"$context/rootfs/etc/passwd"
echo "rayfarm:x:10001:" >"$context/rootfs/etc/group"
cp deploy/Dockerfile "$context/Dockerfile"
docker build --quiet -t "$tag" "$context" >/dev/null
docker image ls "$tag" --format '{{.Repository}}:{{.Tag}} {{.Size}}'
