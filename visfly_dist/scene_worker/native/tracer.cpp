// visfly-dist native packet tracer: primary rays through pixel centres with Embree 3 16-wide packets.
//
// One Embree scene per visfly scene (a triangle soup, robust flag, BVH built once by vf_scene_new).
// A scene with moving obstacles (vf_instanced_new) has two parts: the static triangles in a plain
// scene built once, exactly as a static scene is, and a top-level scene of instances, one per
// moving object (its triangles in its local frame, in a BVH built once). vf_instanced_move sets
// the instances' translations and commits that top-level scene alone (a BVH over a few boxes,
// tens of microseconds); the static BVH is never touched. A packet is traced through the static
// scene, then through the instances with tfar already cut to the static hit; a 4x4 tile that no
// moving object's (translated) box can show in skips the instances. (Measured, 20 moving
// stones in garage-stones, 64x64 depth, 1 thread: the static part as one more instance of the same
// top-level scene cost 15% more CPU than the static scene alone; the static triangles as a geometry
// of a dynamic top-level scene re-built their BVH on every commit, 8 ms.) A hit's triangle index is
// primID for the static part and prim_offsets[instID] + primID for a moving one: the index in the
// concatenation of the parts, so segmentation and shading read the same tables as a flat scene.
// vf_trace renders a list of batches (one batch = one camera of n drones of one scene) on its own
// threads: frames (batch, drone) are handed out through one shared counter, so the threads spread
// over every camera of every scene of the call. Each frame is traced in 4x4 pixel tiles with
// rtcIntersect16 and the coherent flag; then the other drones of the call (spheres) are drawn
// over it in float64, as the embreex path does in numpy.
//
// The ray maths repeats the project's embreex path operation for operation, in float32 and without
// fused multiply-adds (built with -ffp-contract=off), so depth is bit-identical to it:
//   dir   = (R[:,0] - down[i] * R[:,2]) + (-right[j]) * R[:,1]     (optical-axis component 1)
//   start = dir * near + origin,   tnear = 0,   tfar = (float)(far - near)
//   depth = hit ? near + t : far
//
// Plain C ABI for ctypes (which releases the GIL around every call). No exception crosses it:
// failures return non-zero and vf_last_error() says why.

#include "embree_device.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <mutex>
#include <stdexcept>
#include <string>
#include <system_error>
#include <thread>
#include <vector>

namespace {

thread_local std::string last_error;
std::mutex device_mutex;
RTCDevice device = nullptr;

void on_embree_error(void*, RTCError code, const char* str) {
  last_error = std::string("embree error ") + std::to_string(static_cast<int>(code)) + ": " + (str ? str : "");
}

}  // namespace

namespace visfly {

void set_error(const std::string& message) { last_error = message; }

RTCDevice shared_device() {
  std::lock_guard<std::mutex> lock(device_mutex);
  if (device == nullptr) {
    device = rtcNewDevice(nullptr);
    if (device == nullptr) {
      last_error = "rtcNewDevice failed: error " + std::to_string(static_cast<int>(rtcGetDeviceError(nullptr)));
      return nullptr;
    }
    rtcSetDeviceErrorFunction(device, on_embree_error, nullptr);
  }
  return device;
}

}  // namespace visfly

extern "C" {

// One camera of n drones of one scene. Arrays are C-contiguous; optional outputs may be null.
struct vf_batch {
  void* scene;            // from vf_scene_new; null: an empty scene (every ray misses)
  int32_t n;              // drones
  int32_t width, height;  // pixels
  double near_m, far_m;   // clip distances along the optical axis
  const float* right;     // (width,)  column slopes, camera_math.pixel_slopes
  const float* down;      // (height,) row slopes
  const float* origins;   // (n, 3) camera centres, world
  const float* rots;      // (n, 3, 3) camera-to-world rotations, row-major
  float* depth;           // (n, height, width) z-depth
  int32_t* prim;          // (n, height, width) triangle index, -1 where nothing is hit; optional
  float* uv;              // (n, height, width, 2) barycentric u, v of the hit; optional
  const uint16_t* seg_table;  // (triangles + 1,) id of triangle k at k + 1, 0 at 0; with seg
  uint16_t* seg;          // (n, height, width) segmentation id; optional
  // Other drones (spheres), drawn after the triangles; vis_offsets null: none. The spheres frame a
  // may see are entries vis_offsets[a] .. vis_offsets[a + 1] - 1, in the order they are drawn.
  const int32_t* vis_offsets;  // (n + 1,)
  const int32_t* vis_drone;    // (K,) index of the drone (its row in the call)
  const double* vis_centre;    // (K, 3) its centre in the camera frame of the frame seeing it
  const double* vis_dist2;     // (K,) squared distance of that centre
  double radius;               // sphere radius, metres
  double focal;                // focal length, pixels
  const double* right64;       // (width,) float64 column slopes (the sphere test is in float64)
  const double* down64;        // (height,) float64 row slopes
  int32_t* drone;              // (n, height, width) drone seen, -1: none; optional
  const double* rots64;        // (n, 3, 3) float64 camera-to-world rotations; with light
  const double* light_dir;     // (3,) unit vector towards the light; with light
  double ambient;              // share of the colour lit regardless of the light; with light
  double* light;               // (n, height, width) brightness of the drone seen; optional
  const int32_t* prim_offsets; // (parts,) first triangle of each part; null: no moving parts
  void* moving;                // top-level scene of the moving parts' instances, traced after `scene`
  // The moving parts' boxes: a tile whose pixels no box's image covers skips the moving pass.
  // moving_count 0: every tile traces it.
  int32_t moving_count;
  const double* moving_centres;  // (moving_count, 3) translations
  const double* moving_bounds;   // (moving_count, 2, 3) each part's axis-aligned box in its own frame
  double moving_focal;           // focal length, pixels
};

struct vf_instanced {
  RTCScene still = nullptr;           // the static part's BVH (null when it is empty)
  RTCScene top = nullptr;             // the moving parts' instances (geometry id = part index, from 1)
  std::vector<RTCScene> parts;        // each moving part's BVH (null for an empty part)
  std::vector<RTCGeometry> instances; // the instance geometry of each moving part in `top`
};

const char* vf_last_error(void) { return last_error.c_str(); }

int vf_version(void) { return 5; }

void* vf_scene_new(const float* triangles, int64_t count);

// A committed triangle geometry of a soup of `count` triangles (3 vertices, xyz), or null.
static RTCGeometry triangle_geometry(RTCDevice dev, const float* triangles, int64_t count) {
  if (count <= 0 || count > (int64_t{1} << 31) / 3 - 1) {
    last_error = "triangle count " + std::to_string(count) + " must be in [1, 2^31 / 3)";
    return nullptr;
  }
  RTCGeometry geom = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_TRIANGLE);
  auto* vertices = static_cast<float*>(rtcSetNewGeometryBuffer(
      geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), static_cast<size_t>(3 * count)));
  auto* indices = static_cast<uint32_t*>(rtcSetNewGeometryBuffer(
      geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(uint32_t), static_cast<size_t>(count)));
  if (vertices == nullptr || indices == nullptr) {
    rtcReleaseGeometry(geom);
    return nullptr;
  }
  std::memcpy(vertices, triangles, static_cast<size_t>(9 * count) * sizeof(float));
  for (int64_t k = 0; k < 3 * count; ++k) indices[k] = static_cast<uint32_t>(k);
  rtcCommitGeometry(geom);
  return geom;
}

void vf_scene_free(void* scene);

void vf_instanced_free(void* handle) {
  auto* inst = static_cast<vf_instanced*>(handle);
  if (inst == nullptr) return;
  for (RTCGeometry g : inst->instances) {
    if (g != nullptr) rtcReleaseGeometry(g);
  }
  for (RTCScene s : inst->parts) vf_scene_free(s);
  if (inst->top != nullptr) rtcReleaseScene(inst->top);
  vf_scene_free(inst->still);
  delete inst;
}

// A scene with moving parts from `parts` triangle soups laid end to end in `triangles` (part k
// has counts[k] triangles; part 0, the static one, may have 0). Part 0 is a plain scene, built once
// (vf_instanced_scene); part k >= 1 is an instance (id k) of its own scene in a top-level scene of
// instances only (vf_instanced_moving), at the identity until moved. Returns null on failure.
void* vf_instanced_new(const float* triangles, const int64_t* counts, int32_t parts) {
  vf_instanced* inst = nullptr;
  try {
    RTCDevice dev = visfly::shared_device();
    if (dev == nullptr) return nullptr;
    inst = new vf_instanced();
    inst->top = rtcNewScene(dev);
    if (inst->top == nullptr) throw std::runtime_error("rtcNewScene failed");
    rtcSetSceneFlags(inst->top, static_cast<RTCSceneFlags>(RTC_SCENE_FLAG_ROBUST | RTC_SCENE_FLAG_DYNAMIC));
    rtcSetSceneBuildQuality(inst->top, RTC_BUILD_QUALITY_LOW);
    if (parts > 0 && counts[0] > 0) {
      inst->still = static_cast<RTCScene>(vf_scene_new(triangles, counts[0]));
      if (inst->still == nullptr) throw std::runtime_error(last_error);
    }
    const float identity[12] = {1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0};  // column-major 3x4
    int64_t start = parts > 0 ? counts[0] : 0;
    for (int32_t k = 1; k < parts; ++k) {
      RTCScene part = counts[k] > 0 ? static_cast<RTCScene>(vf_scene_new(triangles + 9 * start, counts[k])) : nullptr;
      if (counts[k] > 0 && part == nullptr) throw std::runtime_error(last_error);
      start += counts[k];
      inst->parts.push_back(part);
      RTCGeometry g = nullptr;
      if (part != nullptr) {
        g = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_INSTANCE);
        rtcSetGeometryInstancedScene(g, part);
        rtcSetGeometryTransform(g, 0, RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR, identity);
        rtcCommitGeometry(g);
        rtcAttachGeometryByID(inst->top, g, static_cast<unsigned>(k));
      }
      inst->instances.push_back(g);
    }
    rtcCommitScene(inst->top);
    if (rtcGetDeviceError(dev) != RTC_ERROR_NONE) throw std::runtime_error(last_error);
    return inst;
  } catch (const std::exception& e) {
    last_error = std::string("instanced scene: ") + e.what();
    vf_instanced_free(inst);
    return nullptr;
  }
}

// Translate moving part k (1-based, as in vf_instanced_new) by translations[3(k-1)..3(k-1)+2] and
// commit the top-level scene. Returns 0, or non-zero with vf_last_error() set.
int vf_instanced_move(void* handle, const float* translations) {
  auto* inst = static_cast<vf_instanced*>(handle);
  for (size_t k = 0; k < inst->instances.size(); ++k) {
    RTCGeometry g = inst->instances[k];
    if (g == nullptr) continue;
    const float* t = translations + 3 * k;
    const float xfm[12] = {1, 0, 0, 0, 1, 0, 0, 0, 1, t[0], t[1], t[2]};
    rtcSetGeometryTransform(g, 0, RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR, xfm);
    rtcCommitGeometry(g);
  }
  rtcCommitScene(inst->top);
  return rtcGetDeviceError(rtcGetSceneDevice(inst->top)) == RTC_ERROR_NONE ? 0 : 1;
}

// The static part of an instanced scene (a batch's `scene`; null when empty).
void* vf_instanced_scene(void* handle) { return static_cast<vf_instanced*>(handle)->still; }

// The top-level scene of the moving parts' instances (a batch's `moving`).
void* vf_instanced_moving(void* handle) { return static_cast<vf_instanced*>(handle)->top; }

// Build a robust Embree scene from a triangle soup (triangles, 3 vertices, xyz) and its BVH.
void* vf_scene_new(const float* triangles, int64_t count) {
  try {
    RTCDevice dev = visfly::shared_device();
    if (dev == nullptr) return nullptr;
    if (count <= 0 || count > (int64_t{1} << 31) / 3 - 1) {
      last_error = "triangle count " + std::to_string(count) + " must be in [1, 2^31 / 3)";
      return nullptr;
    }
    RTCScene scene = rtcNewScene(dev);
    if (scene == nullptr) return nullptr;
    rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST);
    RTCGeometry geom = triangle_geometry(dev, triangles, count);
    if (geom == nullptr) {
      rtcReleaseScene(scene);
      return nullptr;
    }
    rtcAttachGeometry(scene, geom);
    rtcReleaseGeometry(geom);
    rtcCommitScene(scene);
    if (rtcGetDeviceError(dev) != RTC_ERROR_NONE) {
      rtcReleaseScene(scene);
      return nullptr;
    }
    return scene;
  } catch (const std::exception& e) {
    last_error = e.what();
    return nullptr;
  }
}

void vf_scene_free(void* scene) {
  if (scene != nullptr) rtcReleaseScene(static_cast<RTCScene>(scene));
}

}  // extern "C"

namespace {

struct Box {
  int64_t i0, i1, j0, j1;  // pixel rows and columns, inclusive
};

// The pixel boxes of the moving parts that may show in frame `agent`: the pixels whose centres lie
// in the image of the part's (translated) box, from its 8 corners; a box reaching behind the
// camera plane covers the whole image. Parts wholly outside the view frustum (their box's bounding
// sphere, camera_math.spheres_in_view's test) are left out.
std::vector<Box> moving_boxes(const vf_batch& b, int32_t agent) {
  std::vector<Box> out;
  const float* o = b.origins + 3 * static_cast<size_t>(agent);
  const float* m = b.rots + 9 * static_cast<size_t>(agent);
  const double f = b.moving_focal, w = b.width, h = b.height;
  const double sw = 0.5 * w / f, sh = 0.5 * h / f;
  auto to_camera = [&](const double* p, double* c) {  // c = R^T (p - o)
    const double d[3] = {p[0] - o[0], p[1] - o[1], p[2] - o[2]};
    for (int a = 0; a < 3; ++a) c[a] = m[a] * d[0] + m[3 + a] * d[1] + m[6 + a] * d[2];
  };
  for (int32_t k = 0; k < b.moving_count; ++k) {
    const double* t = b.moving_centres + 3 * static_cast<size_t>(k);
    const double* lo = b.moving_bounds + 6 * static_cast<size_t>(k);
    const double* hi = lo + 3;
    double centre[3], c[3], r2 = 0.0;
    for (int a = 0; a < 3; ++a) {
      centre[a] = t[a] + 0.5 * (lo[a] + hi[a]);
      r2 += 0.25 * (hi[a] - lo[a]) * (hi[a] - lo[a]);
    }
    const double r = std::sqrt(r2);
    to_camera(centre, c);
    if (c[0] + r < b.near_m || c[0] - r > b.far_m) continue;
    if (sw * c[0] - std::fabs(c[1]) < -r * std::hypot(1.0, sw) || sh * c[0] - std::fabs(c[2]) < -r * std::hypot(1.0, sh)) continue;
    double xmin = INFINITY, ymin = INFINITY, ymax = -INFINITY, zmin = INFINITY, zmax = -INFINITY;
    for (int corner = 0; corner < 8; ++corner) {
      const double p[3] = {t[0] + (corner & 1 ? hi[0] : lo[0]), t[1] + (corner & 2 ? hi[1] : lo[1]),
                           t[2] + (corner & 4 ? hi[2] : lo[2])};
      double q[3];
      to_camera(p, q);
      xmin = std::min(xmin, q[0]);
      ymin = std::min(ymin, q[1] / q[0]);
      ymax = std::max(ymax, q[1] / q[0]);
      zmin = std::min(zmin, q[2] / q[0]);
      zmax = std::max(zmax, q[2] / q[0]);
    }
    Box box{0, b.height - 1, 0, b.width - 1};
    if (xmin > 1e-6) {  // in front of the camera plane: the corners' image holds the box's image
      box = {static_cast<int64_t>(std::ceil(0.5 * h - f * zmax - 0.5)), static_cast<int64_t>(std::floor(0.5 * h - f * zmin - 0.5)),
             static_cast<int64_t>(std::ceil(0.5 * w - f * ymax - 0.5)), static_cast<int64_t>(std::floor(0.5 * w - f * ymin - 0.5))};
      if (box.i0 > box.i1 || box.j0 > box.j1) continue;  // no pixel centre inside
      if (box.i1 < 0 || box.j1 < 0 || box.i0 >= b.height || box.j0 >= b.width) continue;
    }
    out.push_back(box);
  }
  return out;
}

bool covers(const std::vector<Box>& boxes, int32_t ti, int32_t tj) {
  for (const Box& box : boxes) {
    if (box.i0 <= ti + 3 && ti <= box.i1 && box.j0 <= tj + 3 && tj <= box.j1) return true;
  }
  return false;
}

void trace_frame(const vf_batch& b, int32_t agent) {
  const int32_t w = b.width, h = b.height;
  const size_t frame = static_cast<size_t>(agent) * static_cast<size_t>(w) * static_cast<size_t>(h);
  const float* o = b.origins + 3 * static_cast<size_t>(agent);
  const float* r = b.rots + 9 * static_cast<size_t>(agent);
  const float nearf = static_cast<float>(b.near_m), farf = static_cast<float>(b.far_m);
  const float span = static_cast<float>(b.far_m - b.near_m);
  RTCScene scene = static_cast<RTCScene>(b.scene);
  RTCScene moving = static_cast<RTCScene>(b.moving);
  const std::vector<Box> boxes = moving != nullptr ? moving_boxes(b, agent) : std::vector<Box>();
  if (moving != nullptr && b.moving_count > 0 && boxes.empty()) moving = nullptr;
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  context.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
  alignas(64) int valid[16];
  alignas(64) RTCRayHit16 rh;
  for (int32_t ti = 0; ti < h; ti += 4) {
    for (int32_t tj = 0; tj < w; tj += 4) {
      for (int k = 0; k < 16; ++k) {
        const int32_t i = ti + k / 4, j = tj + k % 4;
        const bool inside = i < h && j < w;
        valid[k] = inside ? -1 : 0;
        const float down = b.down[inside ? i : ti], right = -b.right[inside ? j : tj];
        const float dx = (r[0] - down * r[2]) + right * r[1];
        const float dy = (r[3] - down * r[5]) + right * r[4];
        const float dz = (r[6] - down * r[8]) + right * r[7];
        rh.ray.org_x[k] = dx * nearf + o[0];
        rh.ray.org_y[k] = dy * nearf + o[1];
        rh.ray.org_z[k] = dz * nearf + o[2];
        rh.ray.dir_x[k] = dx;
        rh.ray.dir_y[k] = dy;
        rh.ray.dir_z[k] = dz;
        rh.ray.tnear[k] = 0.0f;
        rh.ray.tfar[k] = span;
        rh.ray.time[k] = 0.0f;
        rh.ray.mask[k] = 0xFFFFFFFFu;
        rh.ray.id[k] = 0;
        rh.ray.flags[k] = 0;
        rh.hit.geomID[k] = RTC_INVALID_GEOMETRY_ID;
        rh.hit.primID[k] = RTC_INVALID_GEOMETRY_ID;
        rh.hit.instID[0][k] = RTC_INVALID_GEOMETRY_ID;
      }
      if (scene != nullptr) rtcIntersect16(valid, scene, &context, &rh);
      // the moving parts, only nearer than what the static part hit (tfar was cut to that hit)
      if (moving != nullptr && (b.moving_count == 0 || covers(boxes, ti, tj))) {
        rtcIntersect16(valid, moving, &context, &rh);
      }
      for (int k = 0; k < 16; ++k) {
        if (!valid[k]) continue;
        const size_t p = frame + static_cast<size_t>(ti + k / 4) * w + (tj + k % 4);
        const bool hit = rh.hit.geomID[k] != RTC_INVALID_GEOMETRY_ID;
        int32_t prim = hit ? static_cast<int32_t>(rh.hit.primID[k]) : -1;
        if (hit && b.prim_offsets != nullptr && rh.hit.instID[0][k] != RTC_INVALID_GEOMETRY_ID) {
          prim += b.prim_offsets[rh.hit.instID[0][k]];  // a moving part; the static part's hits start at 0
        }
        b.depth[p] = hit ? nearf + rh.ray.tfar[k] : farf;
        if (b.prim != nullptr) b.prim[p] = prim;
        if (b.uv != nullptr) {
          b.uv[2 * p] = hit ? rh.hit.u[k] : 0.0f;
          b.uv[2 * p + 1] = hit ? rh.hit.v[k] : 0.0f;
        }
        if (b.seg != nullptr) b.seg[p] = b.seg_table[prim + 1];
        if (b.drone != nullptr) b.drone[p] = -1;
        if (b.light != nullptr) b.light[p] = 0.0;
      }
    }
  }
}

// The other drones' spheres over frame `agent`, as render_raycast.RaycastRenderer._overlay_drones
// does it in numpy: float64 maths in the camera frame, pixels inside the sphere's image box only,
// the nearer hit winning (against the depth so far, float32).
void draw_drones(const vf_batch& b, int32_t agent) {
  const int32_t w = b.width, h = b.height;
  const size_t frame = static_cast<size_t>(agent) * static_cast<size_t>(w) * static_cast<size_t>(h);
  const double r = b.radius, f = b.focal;
  for (int32_t k = b.vis_offsets[agent]; k < b.vis_offsets[agent + 1]; ++k) {
    const double* c = b.vis_centre + 3 * static_cast<size_t>(k);
    int64_t i0 = 0, i1 = h - 1, j0 = 0, j1 = w - 1;
    if (c[0] - r > 1e-9) {  // bounding box of the sphere's image, from its box's corners
      const double xs[2] = {c[0] - r, c[0] + r};
      double ymin = INFINITY, ymax = -INFINITY, zmin = INFINITY, zmax = -INFINITY;
      for (double x : xs) {
        for (double s : {-r, r}) {
          ymin = std::min(ymin, (c[1] + s) / x);
          ymax = std::max(ymax, (c[1] + s) / x);
          zmin = std::min(zmin, (c[2] + s) / x);
          zmax = std::max(zmax, (c[2] + s) / x);
        }
      }
      j0 = std::max<int64_t>(static_cast<int64_t>(std::ceil(0.5 * w - f * ymax - 0.5)), 0);
      j1 = std::min<int64_t>(static_cast<int64_t>(std::floor(0.5 * w - f * ymin - 0.5)), w - 1);
      i0 = std::max<int64_t>(static_cast<int64_t>(std::ceil(0.5 * h - f * zmax - 0.5)), 0);
      i1 = std::min<int64_t>(static_cast<int64_t>(std::floor(0.5 * h - f * zmin - 0.5)), h - 1);
    }
    const double d2 = b.vis_dist2[k], rr = d2 - r * r;
    for (int64_t i = i0; i <= i1; ++i) {
      for (int64_t j = j0; j <= j1; ++j) {
        const double dy = -b.right64[j], dz = -b.down64[i];
        const double qa = (1.0 + dy * dy) + dz * dz;
        const double qb = (c[0] + dy * c[1]) + dz * c[2];
        const double disc = qb * qb - qa * rr;
        const double root = std::sqrt(std::max(disc, 0.0));
        double t = (qb - root) / qa;
        if (!(t >= b.near_m)) t = (qb + root) / qa;  // near side clipped (or camera inside): far side
        const size_t p = frame + static_cast<size_t>(i) * w + static_cast<size_t>(j);
        if (!(disc >= 0 && t >= b.near_m && t < b.far_m && t < static_cast<double>(b.depth[p]))) continue;
        const int32_t seen = b.vis_drone[k];
        b.depth[p] = static_cast<float>(t);
        if (b.prim != nullptr) b.prim[p] = -1;
        if (b.seg != nullptr) b.seg[p] = static_cast<uint16_t>(65535 - seen);
        if (b.drone != nullptr) b.drone[p] = seen;
        if (b.light != nullptr) {
          const double n[3] = {(t - c[0]) / r, (t * dy - c[1]) / r, (t * dz - c[2]) / r};  // camera frame
          const double* m = b.rots64 + 9 * static_cast<size_t>(agent);
          double dot = 0.0;
          for (int a = 0; a < 3; ++a) dot += (m[3 * a] * n[0] + m[3 * a + 1] * n[1] + m[3 * a + 2] * n[2]) * b.light_dir[a];
          b.light[p] = b.ambient + (1.0 - b.ambient) * std::fabs(dot);
        }
      }
    }
  }
}

}  // namespace

extern "C" {

// Trace every frame of every batch on `threads` threads (the caller's thread is one of them).
// Returns 0, or non-zero with vf_last_error() set.
int vf_trace(const vf_batch* batches, int32_t count, int32_t threads) {
  try {
    std::vector<int64_t> first(static_cast<size_t>(count) + 1, 0);  // frame index where batch k starts
    for (int32_t k = 0; k < count; ++k) first[k + 1] = first[k] + batches[k].n;
    const int64_t frames = first[count];
    std::atomic<int64_t> next{0};
    auto work = [&]() {
      size_t k = 0;
      for (int64_t f = next.fetch_add(1); f < frames; f = next.fetch_add(1)) {
        while (first[k + 1] <= f) ++k;  // frames are handed out in order: k only moves forward
        trace_frame(batches[k], static_cast<int32_t>(f - first[k]));
        if (batches[k].vis_offsets != nullptr) draw_drones(batches[k], static_cast<int32_t>(f - first[k]));
      }
    };
    visfly::run_on_threads(std::min<int64_t>(std::max(threads, 1), frames) - 1, work);
    return 0;
  } catch (const std::exception& e) {
    last_error = e.what();
    return 1;
  }
}

}  // extern "C"
