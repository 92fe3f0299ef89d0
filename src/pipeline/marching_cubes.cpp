#include "pipeline/marching_cubes.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <unordered_map>
#include <vector>

#include "common/error.h"
#include "common/fs.h"

namespace simu::pipeline {

namespace {

// Cube corner c has offsets (c & 1, (c >> 1) & 1, (c >> 2) & 1) along x, y, z.
int corner_bit(int corner, int axis) { return (corner >> axis) & 1; }

// Cube edge id = axis * 4 + (u + 2 v), where u, v are the offsets along the other two axes (in
// increasing axis order); the edge runs from the corner with offset 0 along `axis` to offset 1.
int edge_between(int c0, int c1) {
  const int diff = c0 ^ c1;
  const int axis = diff == 1 ? 0 : diff == 2 ? 1 : 2;
  const int lo = c0 & c1;  // the endpoint with 0 along axis, as corner bits
  int others[2], n = 0;
  for (int a = 0; a < 3; ++a)
    if (a != axis) others[n++] = corner_bit(lo, a);
  return axis * 4 + others[0] + 2 * others[1];
}
int edge_axis(int edge) { return edge / 4; }
// The endpoint corner of `edge` with offset 0 along the edge's axis.
int edge_start_corner(int edge) {
  const int axis = edge / 4, u = edge % 2, v = (edge / 2) % 2;
  int others[2], n = 0;
  for (int a = 0; a < 3; ++a)
    if (a != axis) others[n++] = a;
  return (u << others[0]) | (v << others[1]);
}

// Per configuration of the 8 inside flags: the surface loops as cube-edge sequences, and whether any
// face has two segments (diagonal inside corners).
struct CaseEntry {
  std::vector<std::vector<int>> loops;
  bool two_segment_face = false;
};

std::vector<CaseEntry> build_case_table() {
  // Faces: for axis a and side s, corners with offset s along a, in counter-clockwise order about the
  // outward normal (2s-1) e_a. With (b, c) the next axes cyclically, the (b, c) sequence
  // (0,0),(1,0),(1,1),(0,1) is counter-clockwise about e_b x e_c = e_a; reversed for s = 0.
  std::vector<std::array<int, 4>> faces;
  for (int a = 0; a < 3; ++a) {
    const int b = (a + 1) % 3, c = (a + 2) % 3;
    for (int s = 0; s < 2; ++s) {
      const int uv[4][2] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
      std::array<int, 4> f{};
      for (int k = 0; k < 4; ++k) f[k] = (s << a) | (uv[k][0] << b) | (uv[k][1] << c);
      if (s == 0) std::swap(f[1], f[3]);
      faces.push_back(f);
    }
  }
  std::vector<CaseEntry> table(256);
  for (int mask = 1; mask < 255; ++mask) {
    auto inside = [&](int corner) { return ((mask >> corner) & 1) != 0; };
    // Segments on each face: each maximal cyclic run of inside corners is cut off by one segment
    // from the edge entering the run to the edge leaving it (in counter-clockwise order).
    std::array<int, 12> next;
    next.fill(-1);
    CaseEntry& entry = table[mask];
    for (const auto& f : faces) {
      int crossings = 0;
      for (int k = 0; k < 4; ++k) crossings += inside(f[k]) != inside(f[(k + 1) % 4]);
      if (crossings == 4) entry.two_segment_face = true;
      for (int k = 0; k < 4; ++k) {
        const int prev = f[(k + 3) % 4], cur = f[k];
        if (!inside(cur) || inside(prev)) continue;  // k starts an inside run
        int end = k;
        while (inside(f[(end + 1) % 4])) end = (end + 1) % 4;
        const int enter = edge_between(prev, cur);
        const int exit = edge_between(f[end], f[(end + 1) % 4]);
        next[enter] = exit;
      }
    }
    // Follow the segments into closed loops.
    std::array<bool, 12> used{};
    for (int e = 0; e < 12; ++e) {
      if (next[e] < 0 || used[e]) continue;
      std::vector<int> loop;
      for (int cur = e; !used[cur]; cur = next[cur]) {
        used[cur] = true;
        loop.push_back(cur);
        if (next[cur] < 0) fail("marching cubes table: open loop in case {}", mask);
      }
      entry.loops.push_back(std::move(loop));
    }
  }
  return table;
}

const std::vector<CaseEntry>& case_table() {
  static const std::vector<CaseEntry> table = build_case_table();
  return table;
}

}  // namespace

TriangleMesh marching_cubes(const torch::Tensor& grid_in, const MarchingCubesOptions& options) {
  auto grid = grid_in;
  if (grid.dim() == 5) {
    SIMU_CHECK(grid.size(0) == 1 && grid.size(1) == 1, "marching_cubes: expected [1, 1, X, Y, Z], got {}", grid.sizes());
    grid = grid[0][0];
  }
  SIMU_CHECK(grid.dim() == 3, "marching_cubes: expected a 3-D grid [X, Y, Z], got {}", grid.sizes());
  const double iso = options.iso;
  // Pad with a one-cell border below iso so the surface closes at the grid boundary.
  const int64_t X = grid.size(0) + 2, Y = grid.size(1) + 2, Z = grid.size(2) + 2;
  auto padded = torch::full({X, Y, Z}, static_cast<float>(iso - 1.0), torch::kFloat32);
  padded.slice(0, 1, X - 1).slice(1, 1, Y - 1).slice(2, 1, Z - 1).copy_(grid.detach().to(torch::kCPU, torch::kFloat32));
  const float* v = padded.data_ptr<float>();
  const int64_t YZ = Y * Z;
  // Inside flags per grid point, and the index offsets of the 8 cube corners.
  std::vector<uint8_t> inside(static_cast<size_t>(X * YZ));
  for (size_t i = 0; i < inside.size(); ++i) inside[i] = static_cast<double>(v[i]) > iso;
  int64_t corner_off[8];
  for (int c = 0; c < 8; ++c) corner_off[c] = corner_bit(c, 0) * YZ + corner_bit(c, 1) * Z + corner_bit(c, 2);

  const auto& table = case_table();
  std::vector<std::array<double, 3>> verts;
  std::vector<std::array<int, 3>> faces;
  // One vertex per crossed grid edge, shared by the cubes around it: index (point * 3 + axis).
  std::vector<int> edge_vertex(static_cast<size_t>(X * YZ * 3), -1);
  auto vertex_on = [&](int64_t x, int64_t y, int64_t z, int edge) {
    const int c = edge_start_corner(edge), axis = edge_axis(edge);
    const int64_t px = x + corner_bit(c, 0), py = y + corner_bit(c, 1), pz = z + corner_bit(c, 2);
    const int64_t p0 = px * YZ + py * Z + pz;
    int& id = edge_vertex[static_cast<size_t>(p0 * 3 + axis)];
    if (id >= 0) return id;
    // Linear interpolation of the iso crossing along the edge; -1 undoes the padding.
    const double v0 = v[p0];
    const double v1 = v[p0 + (axis == 0 ? YZ : axis == 1 ? Z : 1)];
    const double t = (iso - v0) / (v1 - v0);
    std::array<double, 3> p{static_cast<double>(px - 1), static_cast<double>(py - 1), static_cast<double>(pz - 1)};
    p[axis] += t;
    id = static_cast<int>(verts.size());
    verts.push_back(p);
    return id;
  };

  std::vector<int> ids;
  for (int64_t x = 0; x + 1 < X; ++x)
    for (int64_t y = 0; y + 1 < Y; ++y)
      for (int64_t z = 0; z + 1 < Z; ++z) {
        // Configuration: bit c set when corner c is inside.
        const uint8_t* in = inside.data() + x * YZ + y * Z + z;
        int mask = 0;
        for (int c = 0; c < 8; ++c) mask |= in[corner_off[c]] << c;
        if (mask == 0 || mask == 255) continue;
        const auto& entry = table[mask];
        for (const auto& loop : entry.loops) {
          ids.clear();
          for (int e : loop) ids.push_back(vertex_on(x, y, z, e));
          const size_t n = ids.size();
          if (n == 3) {
            faces.push_back({ids[0], ids[1], ids[2]});
          } else if (!entry.two_segment_face) {
            // Fan from the first loop vertex.
            for (size_t k = 1; k + 1 < n; ++k) faces.push_back({ids[0], ids[k], ids[k + 1]});
          } else {
            // Fan from a new vertex at the loop's centroid (keeps every edge on two triangles).
            std::array<double, 3> c{0, 0, 0};
            for (int id : ids)
              for (int a = 0; a < 3; ++a) c[a] += verts[id][a] / static_cast<double>(n);
            const int centre = static_cast<int>(verts.size());
            verts.push_back(c);
            for (size_t k = 0; k < n; ++k) faces.push_back({ids[k], ids[(k + 1) % n], centre});
          }
        }
      }

  TriangleMesh mesh;
  mesh.V.resize(static_cast<Eigen::Index>(verts.size()), 3);
  for (size_t i = 0; i < verts.size(); ++i)
    for (int a = 0; a < 3; ++a) mesh.V(static_cast<Eigen::Index>(i), a) = verts[i][a];
  mesh.F.resize(static_cast<Eigen::Index>(faces.size()), 3);
  for (size_t i = 0; i < faces.size(); ++i)
    for (int a = 0; a < 3; ++a) mesh.F(static_cast<Eigen::Index>(i), a) = faces[i][a];
  return mesh;
}

void grid_to_voxel_frame(TriangleMesh& mesh, int64_t resolution) {
  SIMU_CHECK(resolution > 0, "grid_to_voxel_frame: resolution must be positive, got {}", resolution);
  mesh.V = (mesh.V.array() / static_cast<double>(resolution) - 0.5).matrix();
}

CanonicalTransform canonicalize_mesh(TriangleMesh& mesh) {
  CanonicalTransform tf;
  if (mesh.V.rows() == 0) return tf;
  const Eigen::Vector3d lo = mesh.V.colwise().minCoeff().transpose();
  const Eigen::Vector3d hi = mesh.V.colwise().maxCoeff().transpose();
  tf.centre = (lo + hi) / 2;
  const double longest = (hi - lo).maxCoeff();
  tf.factor = longest > 0 ? 1.0 / longest : 1.0;
  mesh.V = ((mesh.V.rowwise() - tf.centre.transpose()) * tf.factor).eval();
  return tf;
}

double mesh_signed_volume(const TriangleMesh& mesh) {
  double six_v = 0;
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    const Eigen::Vector3d a = mesh.V.row(mesh.F(f, 0)).transpose();
    const Eigen::Vector3d b = mesh.V.row(mesh.F(f, 1)).transpose();
    const Eigen::Vector3d c = mesh.V.row(mesh.F(f, 2)).transpose();
    six_v += a.dot(b.cross(c));
  }
  return six_v / 6.0;
}

std::string mesh_closedness_problem(const TriangleMesh& mesh) {
  // Count each directed edge; a closed, consistently oriented mesh has each exactly once, with its reverse.
  std::unordered_map<uint64_t, int> directed;
  const auto key = [](int a, int b) { return (static_cast<uint64_t>(static_cast<uint32_t>(a)) << 32) | static_cast<uint32_t>(b); };
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    for (int k = 0; k < 3; ++k) {
      const int a = mesh.F(f, k), b = mesh.F(f, (k + 1) % 3);
      if (a == b) return fmt::format("face {} repeats vertex {}", f, a);
      if (a < 0 || a >= mesh.V.rows()) return fmt::format("face {} uses vertex {} of {}", f, a, mesh.V.rows());
      ++directed[key(a, b)];
    }
  }
  for (const auto& [k, count] : directed) {
    const int a = static_cast<int>(k >> 32), b = static_cast<int>(k & 0xffffffffu);
    if (count != 1) return fmt::format("directed edge {}->{} used by {} faces", a, b, count);
    auto it = directed.find(key(b, a));
    if (it == directed.end()) return fmt::format("edge {}-{} is on one face only (boundary)", a, b);
  }
  return "";
}

void write_mesh_ply(const TriangleMesh& mesh, const std::string& path) {
  std::string out = fmt::format(
      "ply\nformat ascii 1.0\ncomment simuscene marching cubes mesh\nelement vertex {}\nproperty float x\n"
      "property float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
      mesh.V.rows(), mesh.F.rows());
  for (Eigen::Index i = 0; i < mesh.V.rows(); ++i)
    out += fmt::format("{} {} {}\n", static_cast<float>(mesh.V(i, 0)), static_cast<float>(mesh.V(i, 1)),
                       static_cast<float>(mesh.V(i, 2)));
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) out += fmt::format("3 {} {} {}\n", mesh.F(f, 0), mesh.F(f, 1), mesh.F(f, 2));
  simu::fs::atomic_write(path, out);
}

}  // namespace simu::pipeline
