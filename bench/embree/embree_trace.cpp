// embree_trace: the Embree 3 half of `common/examples/embree_compare.rs`.
//
// Reads the mesh and ray files the example writes, builds an Embree scene, traces every ray
// set with rtcIntersect1 on one thread (a set named "shadow" with rtcOccluded1, any hit), and prints the timings as ONE JSON line on stdout
// (anything else goes to stderr, so the example can parse stdout). The hits of the first build
// are written to OUT_DIR/NAME.hits for the example's correctness check.
//
// Usage: embree_trace [--reps N] [--high] [--verbose] MESH OUT_DIR NAME:RAYS [NAME:RAYS ...]
//
// File formats (little-endian, shared with the example):
//   mesh:  u64 vertex count, u64 triangle count, f32[3] per vertex, u32[3] per triangle
//   rays:  u64 count, then per ray f32 origin[3], t_min, dir[3], t_max
//   hits:  per ray f32 t (inf on a miss), u32 primID (0xffffffff on a miss); for a shadow set
//          t 0 and primID 0 when occluded

#include <embree3/rtcore.h>

#include <algorithm>
#include <chrono>
#include <ctime>
#include <cinttypes>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

namespace {

struct Ray {
    float org[3];
    float t_min;
    float dir[3];
    float t_max;
};
static_assert(sizeof(Ray) == 32, "ray layout is shared with the Rust example");

struct Hit {
    float t;
    uint32_t prim;
};
static_assert(sizeof(Hit) == 8, "hit layout is shared with the Rust example");

struct RaySet {
    std::string name;
    std::vector<Ray> rays;
};

[[noreturn]] void die(const std::string& msg) {
    std::fprintf(stderr, "embree_trace: %s\n", msg.c_str());
    std::exit(1);
}

std::vector<char> read_file(const std::string& path) {
    FILE* f = std::fopen(path.c_str(), "rb");
    if (!f) die("cannot open " + path);
    std::fseek(f, 0, SEEK_END);
    long size = std::ftell(f);
    std::fseek(f, 0, SEEK_SET);
    std::vector<char> bytes(static_cast<size_t>(size));
    if (size > 0 && std::fread(bytes.data(), 1, bytes.size(), f) != bytes.size())
        die("short read from " + path);
    std::fclose(f);
    return bytes;
}

// Copies `count` items of type T from `bytes` at `offset`, checking the file is long enough.
template <typename T>
std::vector<T> take(const std::vector<char>& bytes, size_t& offset, uint64_t count,
                    const std::string& path) {
    if (count > (bytes.size() - offset) / sizeof(T)) die(path + " is truncated");
    std::vector<T> out(count);
    std::memcpy(out.data(), bytes.data() + offset, count * sizeof(T));
    offset += count * sizeof(T);
    return out;
}

// JSON number with enough digits for sub-millisecond timings (std::to_string keeps 6 decimals).
std::string num(double x) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.9g", x);
    return buf;
}

uint64_t take_u64(const std::vector<char>& bytes, size_t& offset, const std::string& path) {
    return take<uint64_t>(bytes, offset, 1, path)[0];
}

void on_embree_error(void*, RTCError code, const char* msg) {
    die("Embree error " + std::to_string(static_cast<int>(code)) + ": " + (msg ? msg : ""));
}

const char* quality_name(RTCBuildQuality q) {
    return q == RTC_BUILD_QUALITY_HIGH ? "high" : "medium";
}

// CPU time of this thread: on a shared machine, time spent descheduled is not the tracer's.
double thread_seconds() {
    timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return double(ts.tv_sec) + double(ts.tv_nsec) * 1e-9;
}

// One closest-hit pass over `rays`; returns the thread CPU seconds spent in the tracing loop only.
double trace(RTCScene scene, const std::vector<Ray>& rays, std::vector<Hit>& hits) {
    hits.resize(rays.size());
    RTCIntersectContext context;
    rtcInitIntersectContext(&context);
    const double start = thread_seconds();
    for (size_t i = 0; i < rays.size(); ++i) {
        const Ray& r = rays[i];
        // RTCRayHit is declared 16-byte aligned; rtcIntersect1 overwrites it, so fill it per ray.
        RTCRayHit rh;
        rh.ray.org_x = r.org[0];
        rh.ray.org_y = r.org[1];
        rh.ray.org_z = r.org[2];
        rh.ray.tnear = r.t_min;
        rh.ray.dir_x = r.dir[0];
        rh.ray.dir_y = r.dir[1];
        rh.ray.dir_z = r.dir[2];
        rh.ray.time = 0.0f;
        rh.ray.tfar = r.t_max;
        rh.ray.mask = 0xffffffffu;
        rh.ray.id = 0;
        rh.ray.flags = 0;
        rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
        rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
        rtcIntersect1(scene, &context, &rh);
        const bool hit = rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
        hits[i] = hit ? Hit{rh.ray.tfar, rh.hit.primID}
                      : Hit{std::numeric_limits<float>::infinity(), 0xffffffffu};
    }
    return thread_seconds() - start;
}

// One any-hit pass over `rays` (shadow rays); occluded rays are written as a hit at t 0 on
// primitive 0, the others as misses. Thread CPU seconds of the tracing loop only.
double occluded(RTCScene scene, const std::vector<Ray>& rays, std::vector<Hit>& hits) {
    hits.resize(rays.size());
    RTCIntersectContext context;
    rtcInitIntersectContext(&context);
    const double start = thread_seconds();
    for (size_t i = 0; i < rays.size(); ++i) {
        const Ray& r = rays[i];
        RTCRay ray;
        ray.org_x = r.org[0];
        ray.org_y = r.org[1];
        ray.org_z = r.org[2];
        ray.tnear = r.t_min;
        ray.dir_x = r.dir[0];
        ray.dir_y = r.dir[1];
        ray.dir_z = r.dir[2];
        ray.time = 0.0f;
        ray.tfar = r.t_max;
        ray.mask = 0xffffffffu;
        ray.id = 0;
        ray.flags = 0;
        rtcOccluded1(scene, &context, &ray);
        // Embree sets tfar to -inf when the ray is occluded.
        hits[i] = ray.tfar < 0.0f ? Hit{0.0f, 0}
                                  : Hit{std::numeric_limits<float>::infinity(), 0xffffffffu};
    }
    return thread_seconds() - start;
}

}  // namespace

int main(int argc, char** argv) {
    int reps = 5;
    bool high = false;
    bool verbose = false;
    std::vector<std::string> positional;
    for (int i = 1; i < argc; ++i) {
        std::string a = argv[i];
        if (a == "--reps" && i + 1 < argc) {
            reps = std::max(1, std::atoi(argv[++i]));
        } else if (a == "--high") {
            high = true;
        } else if (a == "--verbose") {
            verbose = true;
        } else if (a.rfind("--", 0) == 0) {
            die("unknown option " + a);
        } else {
            positional.push_back(a);
        }
    }
    if (positional.size() < 3)
        die("usage: embree_trace [--reps N] [--high] [--verbose] MESH OUT_DIR NAME:RAYS ...");
    const std::string mesh_path = positional[0];
    const std::string out_dir = positional[1];

    const std::vector<char> mesh = read_file(mesh_path);
    size_t at = 0;
    const uint64_t vertex_count = take_u64(mesh, at, mesh_path);
    const uint64_t triangle_count = take_u64(mesh, at, mesh_path);
    const std::vector<float> vertices = take<float>(mesh, at, vertex_count * 3, mesh_path);
    const std::vector<uint32_t> indices = take<uint32_t>(mesh, at, triangle_count * 3, mesh_path);
    for (uint32_t v : indices)
        if (v >= vertex_count) die(mesh_path + " has an index past the vertices");

    std::vector<RaySet> sets;
    for (size_t k = 2; k < positional.size(); ++k) {
        const std::string& arg = positional[k];
        const size_t colon = arg.find(':');
        if (colon == std::string::npos) die("expected NAME:RAYS, got " + arg);
        RaySet set{arg.substr(0, colon), {}};
        const std::string path = arg.substr(colon + 1);
        const std::vector<char> bytes = read_file(path);
        size_t off = 0;
        const uint64_t n = take_u64(bytes, off, path);
        set.rays = take<Ray>(bytes, off, n, path);
        sets.push_back(std::move(set));
    }

    // One thread for the build and the trace: the comparison is per core. Embree picks its
    // widest ISA at run time, whatever -march this file was compiled with, so it is capped:
    // the target machine (AMD EPYC, AVX2 + FMA) has no AVX-512, while a VM this runs on may
    // report it, and rayfarm never uses it. EMBREE_MAX_ISA (sse2, sse4.2, avx, avx2, avx512)
    // sets another cap; "native" lets Embree take the widest the CPU has.
    const char* max_isa_env = std::getenv("EMBREE_MAX_ISA");
    const std::string max_isa = max_isa_env && *max_isa_env ? max_isa_env : "avx2";
    const std::string config = std::string("threads=1") + (verbose ? ",verbose=1" : "") +
                               (max_isa == "native" ? "" : ",max_isa=" + max_isa);
    RTCDevice device = rtcNewDevice(config.c_str());
    if (!device) die("rtcNewDevice failed");
    rtcSetDeviceErrorFunction(device, on_embree_error, nullptr);

    std::vector<RTCBuildQuality> qualities{RTC_BUILD_QUALITY_MEDIUM};
    if (high) qualities.push_back(RTC_BUILD_QUALITY_HIGH);

    std::string json = "{\"embree\":\"" RTC_VERSION_STRING "\",\"max_isa\":\"" + max_isa +
                       "\",\"threads\":1,\"reps\":" +
                       std::to_string(reps) + ",\"vertices\":" + std::to_string(vertex_count) +
                       ",\"triangles\":" + std::to_string(triangle_count) + ",\"builds\":[";
    std::vector<Hit> hits;
    for (size_t qi = 0; qi < qualities.size(); ++qi) {
        const RTCBuildQuality quality = qualities[qi];
        const auto build_start = std::chrono::steady_clock::now();
        RTCScene scene = rtcNewScene(device);
        rtcSetSceneBuildQuality(scene, quality);
        RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
        rtcSetGeometryBuildQuality(geom, quality);
        // Embree-allocated buffers carry the padding its SIMD loads need past the last vertex.
        auto* vb = static_cast<float*>(rtcSetNewGeometryBuffer(
            geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), vertex_count));
        std::memcpy(vb, vertices.data(), vertices.size() * sizeof(float));
        auto* ib = static_cast<uint32_t*>(rtcSetNewGeometryBuffer(
            geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(uint32_t),
            triangle_count));
        std::memcpy(ib, indices.data(), indices.size() * sizeof(uint32_t));
        rtcCommitGeometry(geom);
        rtcAttachGeometry(scene, geom);
        rtcReleaseGeometry(geom);
        rtcCommitScene(scene);
        const double build_s =
            std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count();
        // How much of the process the kernel backs with huge pages once the BVH is built
        // (Embree's allocator asks for them with madvise; rayfarm's side prints the same).
        if (std::FILE* smaps = std::fopen("/proc/self/smaps_rollup", "r")) {
            char line[256];
            while (std::fgets(line, sizeof line, smaps))
                if (std::strstr(line, "AnonHugePages"))
                    std::fprintf(stderr, "embree_trace: %s BVH built, %s", quality_name(quality),
                                 line);
            std::fclose(smaps);
        }

        json += std::string(qi ? "," : "") + "{\"quality\":\"" + quality_name(quality) +
                "\",\"build_seconds\":" + num(build_s) + ",\"sets\":[";
        for (size_t si = 0; si < sets.size(); ++si) {
            const RaySet& set = sets[si];
            std::vector<double> seconds;
            const bool any = set.name == "shadow";
            for (int r = 0; r < reps; ++r)
                seconds.push_back(any ? occluded(scene, set.rays, hits)
                                      : trace(scene, set.rays, hits));
            if (qi == 0) {
                const std::string path = out_dir + "/" + set.name + ".hits";
                FILE* f = std::fopen(path.c_str(), "wb");
                if (!f || std::fwrite(hits.data(), sizeof(Hit), hits.size(), f) != hits.size())
                    die("cannot write " + path);
                std::fclose(f);
            }
            std::vector<double> sorted = seconds;
            std::sort(sorted.begin(), sorted.end());
            const double n = static_cast<double>(set.rays.size());
            const double median = sorted[sorted.size() / 2];
            json += std::string(si ? "," : "") + "{\"name\":\"" + set.name +
                    "\",\"rays\":" + std::to_string(set.rays.size()) + ",\"seconds\":[";
            for (size_t r = 0; r < seconds.size(); ++r)
                json += std::string(r ? "," : "") + num(seconds[r]);
            json += "],\"mrays_median\":" + num(n / median / 1e6) +
                    ",\"mrays_best\":" + num(n / sorted.front() / 1e6) + "}";
        }
        json += "]}";
        rtcReleaseScene(scene);
    }
    json += "]}";
    rtcReleaseDevice(device);
    std::printf("%s\n", json.c_str());
    return 0;
}
