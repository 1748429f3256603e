// Measures tinybvh's BVH8_CPU (built with BuildHQ, its SBVH builder) on a scene and ray sets
// written by rayd, so that it can be compared with rayd's cores on exactly the same
// triangles and rays. tinybvh is a peer for measurement only: it is not part of rayd, and
// this file only calls its public API (the header comes from $TINYBVH_DIR, see run.sh).
//
//   harness SCENE.tri PASSES RAYS.ray [RAYS.ray ...]
//
// SCENE.tri: TRI1 (examples/export_view.rs writes a bench view's triangles);
// RAYS.ray: RAY1 sets from `rayd bench --dump DIR`; when RAYS.hit (HIT1, format 0, the
// bench reference) lies beside one, the hits are compared with it.
//
// Per set it prints one line: rays, build ms (once per process), median Mray/s by wall
// time and by thread CPU time over PASSES passes, hit count, a checksum of the hit
// triangle ids, and the agreement with the reference (same triangle, or the same t
// within 1e-5 relative, as rayd bench counts it).
#define TINYBVH_IMPLEMENTATION
#define NO_THREADED_BUILDS  // one thread, as rayd's side of the comparison
#include "tiny_bvh.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <fstream>
#include <string>
#include <vector>

namespace {

// Reads a whole file, or exits with a message naming it.
std::vector<uint8_t> read_file(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) {
    std::fprintf(stderr, "harness: cannot open %s\n", path.c_str());
    std::exit(1);
  }
  return std::vector<uint8_t>((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
}

// Checks a 16-byte RAY1/HIT1/TRI1 header (magic, version 1, format, u64 count) against
// the file length and returns the count; exits naming the file and what is wrong.
uint64_t header(const std::vector<uint8_t>& b, const char* magic, uint16_t format, size_t rec,
                const std::string& path) {
  if (b.size() < 16 || std::memcmp(b.data(), magic, 4) != 0) {
    std::fprintf(stderr, "harness: %s: not a %s file\n", path.c_str(), magic);
    std::exit(1);
  }
  uint16_t version, fmt;
  uint64_t count;
  std::memcpy(&version, b.data() + 4, 2);
  std::memcpy(&fmt, b.data() + 6, 2);
  std::memcpy(&count, b.data() + 8, 8);
  if (version != 1 || fmt != format || b.size() != 16 + count * rec) {
    std::fprintf(stderr, "harness: %s: version %u format %u count %llu do not match its %zu bytes\n",
                 path.c_str(), version, fmt, (unsigned long long)count, b.size());
    std::exit(1);
  }
  return count;
}

struct RayRec { float org[3], tmin, dir[3], tmax; };
struct HitRec { float t; uint32_t prim; float u, v; };

double thread_cpu_seconds() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 4) {
    std::fprintf(stderr, "usage: harness SCENE.tri PASSES RAYS.ray [RAYS.ray ...]\n");
    return 2;
  }
  const std::string tri_path = argv[1];
  const int passes = std::max(1, std::atoi(argv[2]));
  std::vector<uint8_t> tb = read_file(tri_path);
  const uint64_t ntri = header(tb, "TRI1", 0, 36, tri_path);
  std::vector<tinybvh::bvhvec4> verts(ntri * 3);
  for (uint64_t i = 0; i < ntri * 3; i++) {
    float p[3];
    std::memcpy(p, tb.data() + 16 + 12 * i, 12);
    verts[i] = tinybvh::bvhvec4(p[0], p[1], p[2], 0);
  }
  tinybvh::BVH8_CPU bvh;
  const auto b0 = std::chrono::steady_clock::now();
  bvh.BuildHQ(verts.data(), (uint32_t)ntri);
  const double build_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - b0).count();
  std::printf("tinybvh %d.%d.%d BVH8_CPU BuildHQ: %llu triangles, build %.1f ms\n",
              TINY_BVH_VERSION_MAJOR, TINY_BVH_VERSION_MINOR, TINY_BVH_VERSION_SUB,
              (unsigned long long)ntri, build_ms);
  for (int a = 3; a < argc; a++) {
    const std::string ray_path = argv[a];
    std::vector<uint8_t> rb = read_file(ray_path);
    const uint64_t n = header(rb, "RAY1", 0, 32, ray_path);
    std::vector<RayRec> in(n);
    std::memcpy(in.data(), rb.data() + 16, n * 32);
    // The rays as tinybvh wants them, made once: its constructor would normalise the
    // direction (changing t), so the fields are set directly. tinybvh has no tmin (it
    // takes t > 0); the bench's sets start at 0 or at a tiny offset past a hit.
    std::vector<tinybvh::Ray> rays(n);
    for (uint64_t i = 0; i < n; i++) {
      tinybvh::Ray& r = rays[i];
      std::memset(&r, 0, sizeof r);
      r.O = tinybvh::bvhvec3(in[i].org[0], in[i].org[1], in[i].org[2]);
      r.D = tinybvh::bvhvec3(in[i].dir[0], in[i].dir[1], in[i].dir[2]);
      r.rD = tinybvh::tinybvh_rcp(r.D);
      r.mask = RAY_MASK_INTERSECT_ALL;
      r.hit.t = std::isfinite(in[i].tmax) ? in[i].tmax : BVH_FAR;
      r.hit.prim = UINT32_MAX;
    }
    std::vector<tinybvh::Ray> work(n);
    std::vector<double> wall, cpu;
    for (int p = 0; p < passes; p++) {
      std::memcpy(work.data(), rays.data(), n * sizeof(tinybvh::Ray));
      const auto t0 = std::chrono::steady_clock::now();
      const double c0 = thread_cpu_seconds();
      for (uint64_t i = 0; i < n; i++) bvh.Intersect(work[i]);
      cpu.push_back(thread_cpu_seconds() - c0);
      wall.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    }
    uint64_t hits = 0, checksum = 0;
    for (uint64_t i = 0; i < n; i++) {
      if (work[i].hit.t < BVH_FAR && work[i].hit.prim != UINT32_MAX) {
        hits++;
        checksum = checksum * 1000003u + work[i].hit.prim + 1;
      } else {
        checksum = checksum * 1000003u;
      }
    }
    std::string agree = "-";
    std::string hit_path = ray_path.substr(0, ray_path.size() - 4) + ".hit";
    std::ifstream probe(hit_path, std::ios::binary);
    if (ray_path.size() > 4 && probe) {
      probe.close();
      std::vector<uint8_t> hb = read_file(hit_path);
      uint16_t fmt;
      std::memcpy(&fmt, hb.data() + 6, 2);
      if (fmt == 0 && header(hb, "HIT1", 0, 16, hit_path) == n) {
        std::vector<HitRec> ref(n);
        std::memcpy(ref.data(), hb.data() + 16, n * 16);
        uint64_t same = 0;
        for (uint64_t i = 0; i < n; i++) {
          const bool ref_hit = ref[i].prim != UINT32_MAX;
          const bool hit = work[i].hit.prim != UINT32_MAX && work[i].hit.t < BVH_FAR;
          if (!ref_hit && !hit) same++;
          else if (ref_hit && hit &&
                   (ref[i].prim == work[i].hit.prim ||
                    std::fabs(ref[i].t - work[i].hit.t) <= 1e-5f * std::fabs(ref[i].t)))
            same++;
        }
        char buf[64];
        std::snprintf(buf, sizeof buf, "%.6f", (double)same / (double)n);
        agree = buf;
      }
    }
    std::printf("%s: %llu rays, median %.3f Mray/s (per CPU-second %.3f), hits %llu, checksum %016llx, agreement %s\n",
                ray_path.c_str(), (unsigned long long)n, n / median(wall) / 1e6, n / median(cpu) / 1e6,
                (unsigned long long)hits, (unsigned long long)checksum, agree.c_str());
  }
  return 0;
}
