#!/usr/bin/env bash
# Builds the rayfarm container image without pulling anything: release binaries (stripped)
# plus exactly the shared libraries `ldd` says they need, on `FROM scratch`. Works wherever
# Docker runs, with or without a registry.
#
# usage: deploy/build-image.sh [TAG]     (default rayfarm:latest)
# RAYFARM_BINARIES=DIR takes the three binaries from DIR as they are, building nothing (the
# compose test passes the binaries it tests, built already by README's test command).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
tag=${1:-rayfarm:latest}
cd "$root"
bin_dir=${RAYFARM_BINARIES:-target/release}
if [[ -z ${RAYFARM_BINARIES:-} ]]; then
    cargo build --release --bins
fi
context=$(mktemp -d)
trap 'rm -rf "$context"' EXIT
bins=(rayfarm rayfarm-coordinator rayfarm-worker)
mkdir -p "$context/rootfs/usr/local/bin" "$context/rootfs/etc" \
    "$context/owned/data" "$context/owned/scenes" "$context/owned/tmp" \
    "$context/owned/secrets"
for b in "${bins[@]}"; do
    strip --strip-debug -o "$context/rootfs/usr/local/bin/$b" "$bin_dir/$b"
done
# Every library the binaries load, at the path the dynamic loader looks for it.
for lib in $(ldd "${bins[@]/#/$bin_dir/}" | awk '/=>/ && $3 ~ /^\// {print $3} /^[ \t]*\// && !/:$/ {print $1}' | sort -u); do
    mkdir -p "$context/rootfs$(dirname "$lib")"
    cp -L "$lib" "$context/rootfs$lib"
done
echo "rayfarm:x:10001:10001:rayfarm:/data:/nonexistent" >"$context/rootfs/etc/passwd"
echo "rayfarm:x:10001:" >"$context/rootfs/etc/group"
cp deploy/Dockerfile "$context/Dockerfile"
docker build --quiet -t "$tag" "$context" >/dev/null
docker image ls "$tag" --format '{{.Repository}}:{{.Tag}} {{.Size}}'
