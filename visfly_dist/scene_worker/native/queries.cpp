// visfly-dist native closest-point queries: the nearest point of a triangle mesh to many positions
// in one call (the batched form of ObstacleQueries' python-fcl distance, one call per position).
//
// One Embree scene per mesh (vf_points_new): a user geometry of one primitive per triangle whose
// bounds are the triangle's float64 box rounded outwards to float32, so the BVH never culls a
// triangle that is nearer than the best one so far. vf_closest runs rtcPointQuery per position
// with an unbounded radius; the callback computes the closest point on the triangle in float64
// (Ericson, Real-Time Collision Detection, 5.1.5) and shrinks the query radius (rounded up) to the
// best distance so far. Positions are handed out in chunks through one shared counter, so any
// number of threads (the caller's included) share the work.
//
// Plain C ABI for ctypes (which releases the GIL around every call). No exception crosses it:
// failures return non-zero or null and vf_last_error() says why.

#include "embree_device.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <exception>
#include <limits>
#include <stdexcept>
#include <string>
#include <system_error>
#include <thread>
#include <vector>

namespace {

constexpr int64_t CHUNK = 64;  // positions a thread takes from the shared counter at a time

struct V3 {
  double x, y, z;
};
V3 operator-(V3 a, V3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
V3 operator+(V3 a, V3 b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
V3 operator*(double s, V3 a) { return {s * a.x, s * a.y, s * a.z}; }
double dot(V3 a, V3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

struct Mesh {
  RTCScene scene = nullptr;
  std::vector<V3> vertices;
  std::vector<int32_t> faces;  // 3 vertex indices per triangle
};

struct Query {  // the user data of one rtcPointQuery
  const Mesh* mesh;
  V3 p;
  double best2;  // squared distance of the best point so far
  V3 best;
};

V3 closest_on_segment(V3 p, V3 a, V3 b) {
  const V3 ab = b - a;
  const double len2 = dot(ab, ab);
  const double t = len2 > 0 ? std::clamp(dot(p - a, ab) / len2, 0.0, 1.0) : 0.0;
  return a + t * ab;
}

// The point of triangle abc nearest to p: Ericson's Voronoi-region walk. A degenerate triangle
// (no area) that reaches the face region is answered by its nearest edge.
V3 closest_on_triangle(V3 p, V3 a, V3 b, V3 c) {
  const V3 ab = b - a, ac = c - a, ap = p - a;
  const double d1 = dot(ab, ap), d2 = dot(ac, ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const V3 bp = p - b;
  const double d3 = dot(ab, bp), d4 = dot(ac, bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return a + (d1 / (d1 - d3)) * ab;
  const V3 cp = p - c;
  const double d5 = dot(ab, cp), d6 = dot(ac, cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return a + (d2 / (d2 - d6)) * ac;
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b);
  const double sum = va + vb + vc;
  if (!(sum > 0)) {
    V3 best = closest_on_segment(p, a, b);
    for (V3 q : {closest_on_segment(p, b, c), closest_on_segment(p, c, a)}) {
      if (dot(q - p, q - p) < dot(best - p, best - p)) best = q;
    }
    return best;
  }
  return a + (vb / sum) * ab + (vc / sum) * ac;
}

float round_down(double x) {
  float f = static_cast<float>(x);
  return static_cast<double>(f) > x ? std::nextafter(f, -std::numeric_limits<float>::infinity()) : f;
}

float round_up(double x) {
  float f = static_cast<float>(x);
  return static_cast<double>(f) < x ? std::nextafter(f, std::numeric_limits<float>::infinity()) : f;
}

void triangle_bounds(const RTCBoundsFunctionArguments* args) {
  const auto* mesh = static_cast<const Mesh*>(args->geometryUserPtr);
  const int32_t* f = &mesh->faces[3 * static_cast<size_t>(args->primID)];
  V3 lo = mesh->vertices[f[0]], hi = lo;
  for (int k = 1; k < 3; ++k) {
    const V3 v = mesh->vertices[f[k]];
    lo = {std::min(lo.x, v.x), std::min(lo.y, v.y), std::min(lo.z, v.z)};
    hi = {std::max(hi.x, v.x), std::max(hi.y, v.y), std::max(hi.z, v.z)};
  }
  RTCBounds* out = args->bounds_o;
  out->lower_x = round_down(lo.x), out->lower_y = round_down(lo.y), out->lower_z = round_down(lo.z);
  out->upper_x = round_up(hi.x), out->upper_y = round_up(hi.y), out->upper_z = round_up(hi.z);
}

bool visit_triangle(RTCPointQueryFunctionArguments* args) {
  auto* q = static_cast<Query*>(args->userPtr);
  const Mesh& m = *q->mesh;
  const int32_t* f = &m.faces[3 * static_cast<size_t>(args->primID)];
  const V3 c = closest_on_triangle(q->p, m.vertices[f[0]], m.vertices[f[1]], m.vertices[f[2]]);
  const V3 d = c - q->p;
  const double d2 = dot(d, d);
  if (!(d2 < q->best2)) return false;
  q->best2 = d2;
  q->best = c;
  args->query->radius = round_up(std::sqrt(d2));  // never below the true distance: no nearer triangle is culled
  return true;
}

void closest_one(const Mesh& mesh, const double* position, double* dist, double* nearest) {
  Query q{&mesh, {position[0], position[1], position[2]}, std::numeric_limits<double>::infinity(), {}};
  q.best = q.p;
  RTCPointQuery query;
  query.x = static_cast<float>(q.p.x), query.y = static_cast<float>(q.p.y), query.z = static_cast<float>(q.p.z);
  query.time = 0.0f;
  query.radius = std::numeric_limits<float>::infinity();
  RTCPointQueryContext context;
  rtcInitPointQueryContext(&context);
  rtcPointQuery(mesh.scene, &query, &context, visit_triangle, &q);
  *dist = std::sqrt(q.best2);
  nearest[0] = q.best.x, nearest[1] = q.best.y, nearest[2] = q.best.z;
}

}  // namespace

extern "C" {

// A mesh (float64 vertices, int32 triangles) for vf_closest, with its BVH built. Null on failure.
void* vf_points_new(const double* vertices, int64_t num_vertices, const int32_t* faces, int64_t num_faces) {
  Mesh* mesh = nullptr;
  try {
    RTCDevice dev = visfly::shared_device();
    if (dev == nullptr) return nullptr;
    if (num_faces <= 0 || num_faces > std::numeric_limits<int32_t>::max() / 3) {
      visfly::set_error("triangle count " + std::to_string(num_faces) + " must be in [1, 2^31 / 3)");
      return nullptr;
    }
    for (int64_t k = 0; k < 3 * num_faces; ++k) {
      if (faces[k] < 0 || faces[k] >= num_vertices) {
        visfly::set_error("face index " + std::to_string(faces[k]) + " is outside [0, " + std::to_string(num_vertices) + ")");
        return nullptr;
      }
    }
    mesh = new Mesh;
    mesh->vertices.resize(static_cast<size_t>(num_vertices));
    for (int64_t k = 0; k < num_vertices; ++k) mesh->vertices[k] = {vertices[3 * k], vertices[3 * k + 1], vertices[3 * k + 2]};
    mesh->faces.assign(faces, faces + 3 * num_faces);
    mesh->scene = rtcNewScene(dev);
    if (mesh->scene == nullptr) throw std::runtime_error("rtcNewScene failed");
    RTCGeometry geom = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_USER);
    if (geom == nullptr) throw std::runtime_error("rtcNewGeometry failed");
    rtcSetGeometryUserPrimitiveCount(geom, static_cast<unsigned int>(num_faces));
    rtcSetGeometryUserData(geom, mesh);
    rtcSetGeometryBoundsFunction(geom, triangle_bounds, nullptr);
    rtcCommitGeometry(geom);
    rtcAttachGeometry(mesh->scene, geom);
    rtcReleaseGeometry(geom);
    rtcCommitScene(mesh->scene);
    if (rtcGetDeviceError(dev) != RTC_ERROR_NONE) throw std::runtime_error("building the BVH failed");
    return mesh;
  } catch (const std::exception& e) {
    visfly::set_error(e.what());
    if (mesh != nullptr && mesh->scene != nullptr) rtcReleaseScene(mesh->scene);
    delete mesh;
    return nullptr;
  }
}

void vf_points_free(void* mesh) {
  auto* m = static_cast<Mesh*>(mesh);
  if (m == nullptr) return;
  rtcReleaseScene(m->scene);
  delete m;
}

// For each of n positions (n, 3): the distance to the nearest triangle, and that nearest point
// (n, 3), on `threads` threads (the caller's thread is one of them). Returns 0, or non-zero with
// vf_last_error() set.
int vf_closest(const void* mesh, const double* positions, int64_t n, int32_t threads, double* dist, double* nearest) {
  try {
    const Mesh& m = *static_cast<const Mesh*>(mesh);
    std::atomic<int64_t> next{0};
    auto work = [&]() {
      for (int64_t start = next.fetch_add(CHUNK); start < n; start = next.fetch_add(CHUNK)) {
        for (int64_t i = start; i < std::min(start + CHUNK, n); ++i) closest_one(m, positions + 3 * i, dist + i, nearest + 3 * i);
      }
    };
    visfly::run_on_threads(std::min<int64_t>(std::max(threads, 1), (n + CHUNK - 1) / CHUNK) - 1, work);
    return 0;
  } catch (const std::exception& e) {
    visfly::set_error(e.what());
    return 1;
  }
}

// The same over rows of several meshes in one call: row i is answered against meshes[group[i]]
// (so a worker's scenes share one call, one GIL release and one set of threads).
int vf_closest_many(const void* const* meshes, const int32_t* group, const double* positions, int64_t n,
                    int32_t threads, double* dist, double* nearest) {
  try {
    std::atomic<int64_t> next{0};
    auto work = [&]() {
      for (int64_t start = next.fetch_add(CHUNK); start < n; start = next.fetch_add(CHUNK)) {
        for (int64_t i = start; i < std::min(start + CHUNK, n); ++i) {
          const Mesh& m = *static_cast<const Mesh*>(meshes[group[i]]);
          closest_one(m, positions + 3 * i, dist + i, nearest + 3 * i);
        }
      }
    };
    visfly::run_on_threads(std::min<int64_t>(std::max(threads, 1), (n + CHUNK - 1) / CHUNK) - 1, work);
    return 0;
  } catch (const std::exception& e) {
    visfly::set_error(e.what());
    return 1;
  }
}

}  // extern "C"
