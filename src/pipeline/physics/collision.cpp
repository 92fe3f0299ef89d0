// Convex decomposition (CoACD C API), qhull hulls, hull filtering, cache, mass properties.
#include "pipeline/physics/collision.h"

extern "C" {
#include <libqhull_r/libqhull_r.h>
}

#include <Eigen/Eigenvalues>
#include <nlohmann/json.hpp>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <unordered_map>
#include <mutex>
#include <optional>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "pipeline/physics/mesh.h"

#ifdef SIMU_HAVE_COACD
#include <dlfcn.h>

// CoACD's C API (lib_coacd.so of the PyPI wheel coacd==1.0.14; layout as in its ctypes binding).
extern "C" {
struct CoACD_Mesh {
  double* vertices_ptr;
  uint64_t vertices_count;
  int* triangles_ptr;
  uint64_t triangles_count;
};
struct CoACD_MeshArray {
  CoACD_Mesh* meshes_ptr;
  uint64_t meshes_count;
};
}
#endif

namespace simu::physics {

using RowPoints = Eigen::Matrix<double, -1, 3, Eigen::RowMajor>;

Mesh convex_hull(const RowPoints& points) {
  SIMU_CHECK(points.rows() >= 4, "convex_hull: {} points, need at least 4", points.rows());
  SIMU_CHECK(points.allFinite(), "convex_hull: non-finite points");
  std::vector<coordT> pts(points.data(), points.data() + points.size());
  qhT qh_storage;
  qhT* qh = &qh_storage;
  qh_zero(qh, stderr);
  char flags[] = "qhull Qt";
  // Silence qhull's own messages (errors come back as the exit code).
  FILE* devnull = std::fopen("/dev/null", "w");
  const int code = qh_new_qhull(qh, 3, static_cast<int>(points.rows()), pts.data(), False, flags, nullptr, devnull);
  Mesh hull;
  std::string err;
  if (code == 0) {
    // Collect triangles (facets are simplicial with Qt) and the vertices they use.
    std::map<int, int> remap;
    std::vector<Eigen::Vector3i> faces;
    facetT* facet;
    FORALLfacets {
      if (facet->upperdelaunay) continue;
      int ids[3];
      int k = 0;
      vertexT *vertex, **vertexp;
      FOREACHvertex_(facet->vertices) {
        if (k < 3) ids[k] = qh_pointid(qh, vertex->point);
        ++k;
      }
      if (k != 3) continue;
      // Orient each triangle so its normal agrees with qhull's outward facet normal.
      const Vec3 a = points.row(ids[0]), b = points.row(ids[1]), c = points.row(ids[2]);
      const Vec3 n(facet->normal[0], facet->normal[1], facet->normal[2]);
      if ((b - a).cross(c - a).dot(n) < 0) std::swap(ids[1], ids[2]);
      Eigen::Vector3i f;
      for (int j = 0; j < 3; ++j) {
        auto it = remap.find(ids[j]);
        if (it == remap.end()) it = remap.emplace(ids[j], static_cast<int>(remap.size())).first;
        f[j] = it->second;
      }
      faces.push_back(f);
    }
    hull.V.resize(static_cast<Eigen::Index>(remap.size()), 3);
    for (const auto& [src, dst] : remap) hull.V.row(dst) = points.row(src);
    hull.F.resize(static_cast<Eigen::Index>(faces.size()), 3);
    for (size_t i = 0; i < faces.size(); ++i) hull.F.row(static_cast<Eigen::Index>(i)) = faces[i].transpose();
  } else {
    err = fmt::format("qhull exit code {} (flat or degenerate point set)", code);
  }
  qh_freeqhull(qh, !qh_ALL);
  int curlong, totlong;
  qh_memfreeshort(qh, &curlong, &totlong);
  if (devnull) std::fclose(devnull);
  if (!err.empty()) fail("convex_hull: {}", err);
  SIMU_CHECK(hull.F.rows() >= 4, "convex_hull: degenerate hull ({} faces)", hull.F.rows());
  return hull;
}

MassProps mass_properties(const std::vector<Mesh>& meshes, double density) {
  // Sum over tetrahedra (origin, a, b, c): volume, first and second moments.
  static const Mat3 C0 = (Mat3() << 2, 1, 1, 1, 2, 1, 1, 1, 2).finished() / 120.0;
  double vol = 0;
  Vec3 first = Vec3::Zero();
  Mat3 second = Mat3::Zero();  // integral of x x^T dV
  for (const auto& m : meshes) {
    for (Eigen::Index i = 0; i < m.F.rows(); ++i) {
      Mat3 A;
      A.col(0) = m.V.row(m.F(i, 0)).transpose();
      A.col(1) = m.V.row(m.F(i, 1)).transpose();
      A.col(2) = m.V.row(m.F(i, 2)).transpose();
      const double det = A.determinant();
      vol += det / 6.0;
      first += det / 24.0 * (A.col(0) + A.col(1) + A.col(2));
      second += det * A * C0 * A.transpose();
    }
  }
  MassProps p;
  p.volume = vol;
  if (!(vol > 0)) return p;
  p.com = first / vol;
  const Mat3 c = second - vol * p.com * p.com.transpose();  // about the centre of mass
  p.mass = density * vol;
  p.inertia = density * (c.trace() * Mat3::Identity() - c);
  return p;
}

std::vector<Mesh> transform_hulls(const std::vector<Mesh>& hulls, const Mat3& linear) {
  std::vector<Mesh> out;
  out.reserve(hulls.size());
  const bool flip = linear.determinant() < 0;
  for (const auto& h : hulls) {
    Mesh m = transform_mesh(h, linear, Vec3::Zero());
    if (flip) m.F.col(1).swap(m.F.col(2));  // keep outward winding under a reflection
    out.push_back(std::move(m));
  }
  return out;
}

bool is_closed_oriented(const Mesh& m) {
  if (m.F.rows() < 4) return false;
  // Directed edge (a, b) -> count; closed and oriented iff each appears once with its reverse once.
  std::unordered_map<uint64_t, int> edges;
  edges.reserve(static_cast<size_t>(3 * m.F.rows()));
  auto key = [](int a, int b) { return (static_cast<uint64_t>(static_cast<uint32_t>(a)) << 32) | static_cast<uint32_t>(b); };
  for (Eigen::Index f = 0; f < m.F.rows(); ++f)
    for (int k = 0; k < 3; ++k) {
      const int a = m.F(f, k), b = m.F(f, (k + 1) % 3);
      if (a == b || ++edges[key(a, b)] > 1) return false;
    }
  for (const auto& [k, n] : edges) {
    const int a = static_cast<int>(k >> 32), b = static_cast<int>(k & 0xffffffffu);
    if (!edges.count(key(b, a))) return false;
  }
  return true;
}

namespace {

// Thickness of a convex solid along its thinnest principal direction (slab estimate sqrt(12 var)).
double hull_thickness(const Mesh& hull, double* volume) {
  const MassProps p = mass_properties({hull}, 1.0);
  *volume = p.volume;
  if (!(p.volume > 0)) return 0;
  // Second moment about the centroid per unit volume: C = (tr(I)/2) I3 - I.
  const Mat3 c = (0.5 * p.inertia.trace() * Mat3::Identity() - p.inertia) / p.volume;
  Eigen::SelfAdjointEigenSolver<Mat3> es(c);
  return std::sqrt(std::max(0.0, 12.0 * es.eigenvalues().minCoeff()));
}

// The hull of a (possibly flat) point set: if qhull finds it flat, the points are offset by
// +-thickness/2 along their thinnest principal direction first.
Mesh hull_or_thickened(const RowPoints& pts, double thickness, bool* thickened) {
  *thickened = false;
  try {
    Mesh h = convex_hull(pts);
    double vol = 0;
    if (hull_thickness(h, &vol) >= thickness) return h;
  } catch (const Error&) {
  }
  // Thinnest direction of the point cloud.
  const Eigen::RowVector3d mean = pts.colwise().mean();
  const RowPoints d = pts.rowwise() - mean;
  Eigen::SelfAdjointEigenSolver<Mat3> es(d.transpose() * d);
  const Eigen::RowVector3d n = es.eigenvectors().col(0).transpose();
  RowPoints both(2 * pts.rows(), 3);
  both.topRows(pts.rows()) = pts.rowwise() + 0.5 * thickness * n;
  both.bottomRows(pts.rows()) = pts.rowwise() - 0.5 * thickness * n;
  *thickened = true;
  return convex_hull(both);
}

#ifdef SIMU_HAVE_COACD
std::mutex& coacd_mutex() {
  static std::mutex m;
  return m;
}

#if defined(__SANITIZE_ADDRESS__)
#define SIMU_ASAN 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define SIMU_ASAN 1
#endif
#endif
#ifndef SIMU_ASAN
#define SIMU_ASAN 0
#endif

// CoACD's entry points, from lib_coacd.so opened privately. The library carries its own copy of the
// C++ runtime and exports it (__cxa_throw, std:: symbols); linked normally, that copy serves every
// exception thrown in the process, and a yaml-cpp parse error aborted the program on the GPU image.
// RTLD_LOCAL keeps its symbols out of the process, RTLD_DEEPBIND makes it use its own.
struct CoacdApi {
  CoACD_MeshArray (*run)(const CoACD_Mesh&, double, int, int, int, int, int, int, int, bool, bool, bool, int, bool,
                         double, int, unsigned int, bool) = nullptr;
  void (*free_array)(CoACD_MeshArray) = nullptr;
  void (*set_log_level)(const char*) = nullptr;
  std::string error;  // why it is unavailable ("" when loaded)
};

const CoacdApi& coacd_api() {
  static const CoacdApi api = [] {
    CoacdApi a;
    const char* env = std::getenv("SIMU_COACD_LIBRARY");
    const std::string path = env && *env ? env : SIMU_COACD_LIBRARY;
#if SIMU_ASAN
    // AddressSanitizer cannot run a library opened with RTLD_DEEPBIND (google/sanitizers#611): sanitizer
    // builds (SIMU_SANITIZE) open it without, and CoACD then binds to the process's C++ runtime.
    void* h = dlopen(path.c_str(), RTLD_NOW | RTLD_LOCAL);
#else
    void* h = dlopen(path.c_str(), RTLD_NOW | RTLD_LOCAL | RTLD_DEEPBIND);
#endif
    if (!h) {
      a.error = fmt::format("cannot load CoACD from '{}' ({}); set SIMU_COACD_LIBRARY to lib_coacd.so of "
                            "pip's coacd==1.0.14", path, dlerror());
      return a;
    }
    a.run = reinterpret_cast<decltype(a.run)>(dlsym(h, "CoACD_run"));
    a.free_array = reinterpret_cast<decltype(a.free_array)>(dlsym(h, "CoACD_freeMeshArray"));
    a.set_log_level = reinterpret_cast<decltype(a.set_log_level)>(dlsym(h, "CoACD_setLogLevel"));
    if (!a.run || !a.free_array || !a.set_log_level)
      a.error = fmt::format("'{}' lacks CoACD_run / CoACD_freeMeshArray / CoACD_setLogLevel", path);
    else
      a.set_log_level("error");
    return a;
  }();
  return api;
}

// Runs CoACD and returns the raw parts' vertex sets.
std::vector<RowPoints> run_coacd(const Mesh& mesh, const CollisionConfig& cfg) {
  std::lock_guard<std::mutex> lock(coacd_mutex());
  const auto& api = coacd_api();
  SIMU_CHECK(api.error.empty(), "{}", api.error);
  const auto CoACD_run = api.run;
  const auto CoACD_freeMeshArray = api.free_array;
  RowPoints V = mesh.V;
  Eigen::Matrix<int, -1, 3, Eigen::RowMajor> F = mesh.F;
  CoACD_Mesh in{V.data(), static_cast<uint64_t>(V.rows()), F.data(), static_cast<uint64_t>(F.rows())};
  CoACD_MeshArray arr = CoACD_run(in, cfg.threshold, cfg.max_hulls, /*preprocess auto*/ 0, 50, cfg.resolution,
                                  cfg.mcts_nodes, cfg.mcts_iterations, cfg.mcts_depth, false, true,
                                  cfg.max_hull_vertices > 0, cfg.max_hull_vertices, false, 0.01, 0,
                                  static_cast<unsigned>(cfg.seed), false);
  std::vector<RowPoints> parts;
  for (uint64_t i = 0; i < arr.meshes_count; ++i) {
    const CoACD_Mesh& m = arr.meshes_ptr[i];
    parts.emplace_back(Eigen::Map<RowPoints>(m.vertices_ptr, static_cast<Eigen::Index>(m.vertices_count), 3));
  }
  CoACD_freeMeshArray(arr);
  return parts;
}
#endif

uint64_t config_hash(const CollisionConfig& c, bool coacd) {
  const std::string s = fmt::format("v2|{}|{}|{}|{}|{}|{}|{}|{}|{}|{}|{}|{}", coacd, c.threshold, c.max_hulls, c.resolution,
                                    c.mcts_iterations, c.mcts_nodes, c.mcts_depth, c.max_hull_vertices, c.seed,
                                    c.min_thickness, c.min_volume_fraction, c.convex_tolerance);
  return fnv1a64(s.data(), s.size());
}

nlohmann::json shape_to_json(const CollisionShape& s) {
  nlohmann::json j;
  j["method"] = s.method;
  j["dropped"] = s.dropped;
  j["hulls"] = nlohmann::json::array();
  for (const auto& h : s.hulls) {
    std::vector<double> v(h.V.data(), h.V.data() + h.V.size());
    std::vector<int> f(h.F.data(), h.F.data() + h.F.size());
    j["hulls"].push_back({{"V", v}, {"F", f}});
  }
  return j;
}

CollisionShape shape_from_json(const nlohmann::json& j) {
  CollisionShape s;
  s.method = j.at("method").get<std::string>();
  s.dropped = j.at("dropped").get<int>();
  for (const auto& h : j.at("hulls")) {
    const auto v = h.at("V").get<std::vector<double>>();
    const auto f = h.at("F").get<std::vector<int>>();
    Mesh m;
    m.V = Eigen::Map<const RowPoints>(v.data(), static_cast<Eigen::Index>(v.size() / 3), 3);
    m.F = Eigen::Map<const Eigen::Matrix<int, -1, 3, Eigen::RowMajor>>(f.data(), static_cast<Eigen::Index>(f.size() / 3), 3);
    SIMU_CHECK(mesh_problem(m).empty(), "cached hull is invalid: {}", mesh_problem(m));
    s.hulls.push_back(std::move(m));
  }
  SIMU_CHECK(!s.hulls.empty(), "cached shape has no hulls");
  return s;
}

// The mesh's own convex hull when the mesh is convex (closed, oriented, volume within
// cfg.convex_tolerance of its hull's and not flat); nullopt otherwise.
std::optional<Mesh> convex_self_hull(const Mesh& mesh, const CollisionConfig& cfg) {
  if (cfg.convex_tolerance < 0 || !is_closed_oriented(mesh)) return std::nullopt;
  try {
    Mesh hull = convex_hull(mesh.V);
    double hull_volume = 0;
    if (hull_thickness(hull, &hull_volume) < cfg.min_thickness || !(hull_volume > 0)) return std::nullopt;
    const double volume = signed_volume(mesh);
    if (std::abs(hull_volume - volume) <= cfg.convex_tolerance * hull_volume) return hull;
  } catch (const Error&) {
  }
  return std::nullopt;
}

// Computes the decomposition (no cache).
CollisionShape compute_shape(const Mesh& mesh, const CollisionConfig& cfg, bool coacd) {
  CollisionShape shape;
  // A convex mesh is its own hull: no decomposition.
  if (auto hull = convex_self_hull(mesh, cfg)) {
    shape.hulls.push_back(std::move(*hull));
    shape.method = "convex";
    return shape;
  }
  std::vector<RowPoints> parts;
#ifdef SIMU_HAVE_COACD
  if (coacd) {
    parts = run_coacd(mesh, cfg);
    shape.method = "coacd";
  }
#endif
  (void)coacd;
  // Re-hull every part (closed, outward), drop the flat and the tiny.
  std::vector<Mesh> hulls;
  std::vector<double> volumes;
  for (const auto& p : parts) {
    try {
      Mesh h = convex_hull(p);
      double vol = 0;
      const double thick = hull_thickness(h, &vol);
      if (thick < cfg.min_thickness) {
        ++shape.dropped;
        continue;
      }
      hulls.push_back(std::move(h));
      volumes.push_back(vol);
    } catch (const Error&) {
      ++shape.dropped;
    }
  }
  double total = 0;
  for (double v : volumes) total += v;
  for (size_t i = 0; i < hulls.size(); ++i) {
    if (volumes[i] < cfg.min_volume_fraction * total) {
      ++shape.dropped;
      continue;
    }
    shape.hulls.push_back(std::move(hulls[i]));
  }
  // Fallback (no CoACD, or every part filtered): the convex hull of the whole mesh.
  if (shape.hulls.empty()) {
    bool thickened = false;
    shape.hulls.push_back(hull_or_thickened(mesh.V, cfg.min_thickness, &thickened));
    shape.method = thickened ? "hull+thickened" : "hull";
  }
  return shape;
}

}  // namespace

std::optional<CollisionShape> map_shape(const Mesh& before, const Mesh& after, const CollisionShape& shape,
                                        const CollisionConfig& cfg) {
  const Eigen::Index n = before.V.rows();
  if (n < 4 || after.V.rows() != n || shape.hulls.empty()) return std::nullopt;
  // Least-squares affine fit [V 1] X = V' (X: 4 x 3), then its worst residual.
  Eigen::MatrixXd A(n, 4);
  A.leftCols(3) = before.V;
  A.col(3).setOnes();
  const Eigen::MatrixXd B = after.V;
  const Eigen::MatrixXd X = A.colPivHouseholderQr().solve(B);
  const double size = std::max(1e-12, (after.V.colwise().maxCoeff() - after.V.colwise().minCoeff()).maxCoeff());
  if (!X.allFinite() || (A * X - B).cwiseAbs().maxCoeff() > 1e-9 * size) return std::nullopt;
  CollisionShape out;
  out.method = shape.method + "+mapped";
  out.dropped = shape.dropped;
  for (const Mesh& h : shape.hulls) {
    Eigen::MatrixXd H(h.V.rows(), 4);
    H.leftCols(3) = h.V;
    H.col(3).setOnes();
    const RowPoints mapped = H * X;
    try {
      Mesh m = convex_hull(mapped);
      double vol = 0;
      if (hull_thickness(m, &vol) < cfg.min_thickness) return std::nullopt;
      out.hulls.push_back(std::move(m));
    } catch (const Error&) {
      return std::nullopt;
    }
  }
  return out;
}

CollisionShape decompose(const Mesh& canonical, const CollisionConfig& cfg) {
  const std::string problem = mesh_problem(canonical);
  SIMU_CHECK(problem.empty(), "decompose: {}", problem);
#ifdef SIMU_HAVE_COACD
  const bool coacd = cfg.use_coacd && coacd_api().error.empty();
  if (cfg.use_coacd && !coacd) {
    static std::once_flag once;
    std::call_once(once, [] { log::warn("collision: {}; each mesh becomes one convex hull", coacd_api().error); });
  }
#else
  const bool coacd = false;
#endif
  const uint64_t key = mesh_hash(canonical) ^ (config_hash(cfg, coacd) * 0x9E3779B97F4A7C15ULL);
  const std::string name = fmt::format("{:016x}.hulls.json", key);
  // In-memory cache shared by threads.
  static std::mutex mu;
  static std::map<uint64_t, CollisionShape> memory;
  {
    std::lock_guard<std::mutex> lock(mu);
    auto it = memory.find(key);
    if (it != memory.end()) return it->second;
  }
  // Disk cache.
  CollisionShape shape;
  bool found = false;
  const std::string file = cfg.cache_dir.empty() ? "" : cfg.cache_dir + "/" + name;
  if (!file.empty() && std::filesystem::exists(file)) {
    try {
      shape = shape_from_json(nlohmann::json::parse(fs::read_file(file)));
      found = true;
    } catch (const std::exception& e) {
      log::warn("collision cache {} unreadable ({}); recomputing", file, e.what());
    }
  }
  if (!found) {
    shape = compute_shape(clean_mesh(canonical), cfg, coacd);
    if (!file.empty()) {
      try {
        fs::atomic_write(file, shape_to_json(shape).dump());
      } catch (const std::exception& e) {
        log::warn("collision cache {} not written ({})", file, e.what());
      }
    }
  }
  std::lock_guard<std::mutex> lock(mu);
  memory[key] = shape;
  return shape;
}

}  // namespace simu::physics
