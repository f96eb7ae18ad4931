#!/usr/bin/env bash
# The schedules on a real scanned mesh nobody here made (issue 20: the scanned-mesh floor):
# the Stanford bunny as Debian's libcgal-demo ships it (CGAL's data/meshes/bunny00.off, 75,408
# triangles), cut into 64 domains, rendered by a local cluster of 4 workers with caches of two
# of its largest domains and storage emulated at 100 MiB/s, under every schedule, cold caches,
# every image checked identical by `rayfarm bench`. rayfarm reads PLY, OBJ and STL, so the OFF
# file is first rewritten as ASCII PLY (same vertices and triangles, in order).
#
# Environment: WORK (scratch directory, default ./target/scanned-mesh), RAYFARM_BIN (the
# directory of rayfarm, rayfarm-coordinator and rayfarm-worker, default ./target/release),
# MESH (a mesh of data/meshes/ in CGAL's archive, default bunny00; armadillo and
# refined_elephant are others), DOMAINS (default 64), SCHEDULES (default all five), REPEATS
# (default 1). Extra arguments go to `rayfarm bench` (e.g. --csv FILE).
set -euo pipefail

root=$(cd "$(dirname "$0")/../.." && pwd)
work=${WORK:-$root/target/scanned-mesh}
bin=${RAYFARM_BIN:-$root/target/release}
mesh=${MESH:-bunny00}
domains=${DOMAINS:-64}
schedules=${SCHEDULES:-image-plane,domain,dynamic,hybrid,predictive}
data=/usr/share/doc/libcgal-dev/data.tar.gz
if [[ ! -f $data ]]; then
    echo "$data not found. On Debian: sudo apt-get install libcgal-demo" >&2
    exit 1
fi
mkdir -p "$work"
cd "$work"
tar -xzf "$data" "data/meshes/$mesh.off"

# OFF: "OFF", then "vertices faces edges", then the vertices, then each face as its corner
# count and indices; polygons become fans of triangles. Comments (#) and blank lines skipped.
awk '
    /^[ \t]*(#|$)/ { next }
    !magic { magic = 1; next }
    !counts { nv = $1; nf = $2; counts = 1; next }
    v < nv { verts[v++] = $1 " " $2 " " $3; next }
    { for (k = 2; k < $1; k++) tris[t++] = $2 " " $(k + 1) " " $(k + 2) }
    END {
        print "ply\nformat ascii 1.0\nelement vertex " nv
        print "property float x\nproperty float y\nproperty float z"
        print "element face " t "\nproperty list uchar int vertex_indices\nend_header"
        for (i = 0; i < nv; i++) print verts[i]
        for (i = 0; i < t; i++) print "3 " tris[i]
    }' "data/meshes/$mesh.off" >"$mesh.ply"

"$bin/rayfarm" prepare "$mesh.ply" --out "$mesh-$domains" --domains "$domains" --force
largest=$(stat -c %s "$mesh-$domains"/domain-*.rfd | sort -n | tail -1)
"$bin/rayfarm" bench --scene "$mesh-$domains" --workers 4 --threads 1 --schedules "$schedules" \
    --cache-bytes $((2 * largest)) --storage-bandwidth 100MiB/s --repeats "${REPEATS:-1}" \
    --width 256 --height 256 --spp 4 --depth 3 "$@"
