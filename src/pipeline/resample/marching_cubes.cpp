#include "pipeline/resample/marching_cubes.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <limits>
#include <unordered_map>
#include <vector>

#include "common/error.h"
#include "common/fs.h"

namespace simu::resample {

using physics::Mesh;

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

// The grid as [X, Y, Z] ([1, 1, X, Y, Z] is accepted too); anything else is an error.
torch::Tensor grid_3d(const torch::Tensor& grid_in) {
  auto grid = grid_in;
  if (grid.dim() == 5) {
    SIMU_CHECK(grid.size(0) == 1 && grid.size(1) == 1, "marching_cubes: expected [1, 1, X, Y, Z], got {}", grid.sizes());
    grid = grid[0][0];
  }
  SIMU_CHECK(grid.dim() == 3, "marching_cubes: expected a 3-D grid [X, Y, Z], got {}", grid.sizes());
  return grid;
}

}  // namespace

Mesh marching_cubes_reference(const torch::Tensor& grid_in, const MarchingCubesOptions& options) {
  const auto grid = grid_3d(grid_in);
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

  Mesh mesh;
  mesh.V.resize(static_cast<Eigen::Index>(verts.size()), 3);
  for (size_t i = 0; i < verts.size(); ++i)
    for (int a = 0; a < 3; ++a) mesh.V(static_cast<Eigen::Index>(i), a) = verts[i][a];
  mesh.F.resize(static_cast<Eigen::Index>(faces.size()), 3);
  for (size_t i = 0; i < faces.size(); ++i)
    for (int a = 0; a < 3; ++a) mesh.F(static_cast<Eigen::Index>(i), a) = faces[i][a];
  return mesh;
}

namespace {

// The case table flattened for the fast path: per configuration, the loops' cube edges back to back.
struct FlatCase {
  uint8_t n_loops = 0;
  uint8_t loop_len[4] = {0, 0, 0, 0};
  uint8_t edges[12] = {};
  bool two_segment_face = false;
};

const std::array<FlatCase, 256>& flat_case_table() {
  static const std::array<FlatCase, 256> flat = [] {
    std::array<FlatCase, 256> out{};
    const auto& table = case_table();
    for (int mask = 0; mask < 256; ++mask) {
      FlatCase& f = out[mask];
      SIMU_CHECK(table[mask].loops.size() <= 4, "marching cubes table: case {} has {} loops", mask, table[mask].loops.size());
      int k = 0;
      for (const auto& loop : table[mask].loops) {
        f.loop_len[f.n_loops++] = static_cast<uint8_t>(loop.size());
        for (int e : loop) f.edges[k++] = static_cast<uint8_t>(e);
      }
      f.two_segment_face = table[mask].two_segment_face;
    }
    return out;
  }();
  return flat;
}

// One slab of cubes (x in [x_begin, x_end)): its new vertices in order of first use and its faces.
// A face index >= 0 is a vertex of this slab; < 0 encodes -(edge key + 1) of a vertex that the previous
// slab created (the crossings on the plane x = x_begin along y and z, shared with cubes x_begin - 1).
struct Slab {
  int64_t x_begin = 0, x_end = 0;
  std::vector<double> verts;  // [n, 3] flattened
  std::vector<int> faces;     // [m, 3] flattened
};

// The fast path's view of the grid: values padded by one cell below iso (the surface closes at the
// boundary), inside flags, and per cube corner / edge the index offsets it reads.
struct PaddedGrid {
  int64_t X = 0, Y = 0, Z = 0, YZ = 0;
  double iso = 0;
  std::vector<float> values;   // [X, Y, Z]
  std::vector<uint8_t> inside;  // values > iso
  int64_t corner_off[8] = {};
  // Per cube edge: axis, start point offset, start corner, and whether it lies on the cube's x = 0
  // face across y or z (shared with the cube before it along x).
  int64_t edge_start[12] = {};
  int edge_ax[12] = {}, edge_corner[12] = {};
  bool edge_on_low_x[12] = {};
  int64_t axis_stride[3] = {};

  // Crossing point of the grid edge (point p0 = (px, py, pz), axis): same arithmetic as the reference.
  void edge_point(int64_t p0, int64_t px, int64_t py, int64_t pz, int axis, double* out) const {
    const double v0 = values[static_cast<size_t>(p0)];
    const double v1 = values[static_cast<size_t>(p0 + axis_stride[axis])];
    const double t = (iso - v0) / (v1 - v0);
    out[0] = static_cast<double>(px - 1);
    out[1] = static_cast<double>(py - 1);
    out[2] = static_cast<double>(pz - 1);
    out[axis] += t;
  }
};

PaddedGrid pad_grid(const torch::Tensor& grid, double iso) {
  PaddedGrid g;
  g.iso = iso;
  g.X = grid.size(0) + 2;
  g.Y = grid.size(1) + 2;
  g.Z = grid.size(2) + 2;
  g.YZ = g.Y * g.Z;
  g.values.assign(static_cast<size_t>(g.X * g.YZ), static_cast<float>(iso - 1.0));
  {
    const auto src = grid.detach().to(torch::kCPU, torch::kFloat32).contiguous();
    const float* s = src.data_ptr<float>();
    const int64_t gy = grid.size(1), gz = grid.size(2);
    at::parallel_for(0, g.X - 2, 8, [&](int64_t b, int64_t e) {
      for (int64_t x = b; x < e; ++x)
        for (int64_t y = 0; y < gy; ++y)
          std::copy_n(s + (x * gy + y) * gz, gz, g.values.data() + (x + 1) * g.YZ + (y + 1) * g.Z + 1);
    });
  }
  const float* v = g.values.data();
  g.inside.resize(g.values.size());
  at::parallel_for(0, static_cast<int64_t>(g.values.size()), 32768, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) g.inside[static_cast<size_t>(i)] = static_cast<double>(v[i]) > iso;
  });
  for (int c = 0; c < 8; ++c) g.corner_off[c] = corner_bit(c, 0) * g.YZ + corner_bit(c, 1) * g.Z + corner_bit(c, 2);
  for (int e = 0; e < 12; ++e) {
    g.edge_corner[e] = edge_start_corner(e);
    g.edge_ax[e] = edge_axis(e);
    g.edge_start[e] = g.corner_off[edge_start_corner(e)];
    g.edge_on_low_x[e] = g.edge_ax[e] != 0 && corner_bit(edge_start_corner(e), 0) == 0;
  }
  g.axis_stride[0] = g.YZ;
  g.axis_stride[1] = g.Z;
  g.axis_stride[2] = 1;
  return g;
}

// The faces of cube (x, y, z) (grid index `base`) with configuration `mask` into `slab`: its loops'
// vertices (existing in edge_vertex, created here in order of first use, or the previous slab's when
// shared_low_x), each loop fanned into triangles.
void emit_cube(const PaddedGrid& g, const FlatCase& entry, int64_t x, int64_t y, int64_t z, int64_t base,
               bool shared_low_x, Slab& slab, std::vector<int>& edge_vertex) {
  auto& verts = slab.verts;
  auto& faces = slab.faces;
  int ids[12];
  const uint8_t* edges = entry.edges;
  for (int l = 0; l < entry.n_loops; ++l) {
    const int n = entry.loop_len[l];
    for (int k = 0; k < n; ++k) {
      const int e = edges[k];
      const int64_t p0 = base + g.edge_start[e];
      const int64_t key = p0 * 3 + g.edge_ax[e];
      if (shared_low_x && g.edge_on_low_x[e]) {
        ids[k] = -static_cast<int>(key) - 1;
        continue;
      }
      int& id = edge_vertex[static_cast<size_t>(key)];
      if (id < 0) {
        id = static_cast<int>(verts.size() / 3);
        verts.resize(verts.size() + 3);
        const int sc = g.edge_corner[e];
        g.edge_point(p0, x + corner_bit(sc, 0), y + corner_bit(sc, 1), z + corner_bit(sc, 2), g.edge_ax[e],
                     verts.data() + verts.size() - 3);
      }
      ids[k] = id;
    }
    if (n == 3) {
      faces.insert(faces.end(), {ids[0], ids[1], ids[2]});
    } else if (!entry.two_segment_face) {
      // Fan from the first loop vertex.
      for (int k = 1; k + 1 < n; ++k) faces.insert(faces.end(), {ids[0], ids[k], ids[k + 1]});
    } else {
      // Fan from a new vertex at the loop's centroid (keeps every edge on two triangles).
      double c[3] = {0, 0, 0};
      for (int k = 0; k < n; ++k) {
        double p[3];
        if (ids[k] >= 0) {
          std::copy_n(verts.data() + 3 * ids[k], 3, p);
        } else {
          const int64_t key = -static_cast<int64_t>(ids[k]) - 1;
          const int64_t p0 = key / 3;
          g.edge_point(p0, p0 / g.YZ, (p0 / g.Z) % g.Y, p0 % g.Z, static_cast<int>(key % 3), p);
        }
        for (int a = 0; a < 3; ++a) c[a] += p[a] / static_cast<double>(n);
      }
      const int centre = static_cast<int>(verts.size() / 3);
      verts.insert(verts.end(), {c[0], c[1], c[2]});
      for (int k = 0; k < n; ++k) faces.insert(faces.end(), {ids[k], ids[(k + 1) % n], centre});
    }
    edges += n;
  }
}

// Pass 1 for one slab: cubes in (x, y, z) order, vertices numbered in order of first use.
void march_slab(const PaddedGrid& g, Slab& slab, std::vector<int>& edge_vertex) {
  const auto& table = flat_case_table();
  const int64_t n_cubes = (slab.x_end - slab.x_begin) * (g.Y - 1) * (g.Z - 1);
  // Room for 2 vertices and 4 triangles per cube (random occupancy gives ~1.7 and ~3.3): no regrowth.
  slab.verts.reserve(static_cast<size_t>(n_cubes) * 6);
  slab.faces.reserve(static_cast<size_t>(n_cubes) * 12);
  for (int64_t x = slab.x_begin; x < slab.x_end; ++x) {
    const bool shared_low_x = x == slab.x_begin && x > 0;
    for (int64_t y = 0; y + 1 < g.Y; ++y) {
      const int64_t row = x * g.YZ + y * g.Z;
      // Configuration: bit c set when corner c is inside; corners 0-3 (z) are the previous cube's
      // corners 4-7 (z + 1), so each step reads only the 4 new corners.
      const uint8_t* in_row = g.inside.data() + row;
      int low = 0;
      for (int c = 0; c < 4; ++c) low |= in_row[g.corner_off[c]] << c;
      for (int64_t z = 0; z + 1 < g.Z; ++z) {
        const uint8_t* in = in_row + z + 1;
        int high = 0;
        for (int c = 0; c < 4; ++c) high |= in[g.corner_off[c]] << c;
        const int mask = low | (high << 4);
        low = high;
        if (mask == 0 || mask == 255) continue;
        emit_cube(g, table[mask], x, y, z, row + z, shared_low_x, slab, edge_vertex);
      }
    }
  }
}

// Pass 2: the slabs' vertices and faces back to back (global first-use order), shared vertices resolved.
Mesh join_slabs(const std::vector<Slab>& slabs, const std::vector<int>& edge_vertex) {
  const int64_t n_slabs = static_cast<int64_t>(slabs.size());
  std::vector<int64_t> vert_offset(static_cast<size_t>(n_slabs) + 1, 0), face_offset(static_cast<size_t>(n_slabs) + 1, 0);
  for (int64_t s = 0; s < n_slabs; ++s) {
    vert_offset[s + 1] = vert_offset[s] + static_cast<int64_t>(slabs[s].verts.size() / 3);
    face_offset[s + 1] = face_offset[s] + static_cast<int64_t>(slabs[s].faces.size() / 3);
  }
  SIMU_CHECK(vert_offset.back() < std::numeric_limits<int>::max(), "marching_cubes: {} vertices overflow int indices",
             vert_offset.back());
  Mesh mesh;
  mesh.V.resize(static_cast<Eigen::Index>(vert_offset.back()), 3);
  mesh.F.resize(static_cast<Eigen::Index>(face_offset.back()), 3);
  at::parallel_for(0, n_slabs, 1, [&](int64_t sb, int64_t se) {
    for (int64_t s = sb; s < se; ++s) {
      const Slab& slab = slabs[static_cast<size_t>(s)];
      std::copy(slab.verts.begin(), slab.verts.end(), mesh.V.data() + 3 * vert_offset[s]);
      int* f = mesh.F.data() + 3 * face_offset[s];
      const int own = static_cast<int>(vert_offset[s]);
      const int prev = s > 0 ? static_cast<int>(vert_offset[s - 1]) : 0;
      for (size_t i = 0; i < slab.faces.size(); ++i) {
        const int id = slab.faces[i];
        if (id >= 0) {
          f[i] = id + own;
        } else {
          const int prev_id = edge_vertex[static_cast<size_t>(-static_cast<int64_t>(id) - 1)];
          SIMU_CHECK(prev_id >= 0, "marching_cubes: shared crossing missing in the previous slab (internal error)");
          f[i] = prev_id + prev;
        }
      }
    }
  });
  return mesh;
}

}  // namespace

Mesh marching_cubes(const torch::Tensor& grid_in, const MarchingCubesOptions& options) {
  const PaddedGrid g = pad_grid(grid_3d(grid_in), options.iso);
  // Slabs along x: more than threads for balance; the result does not depend on the split.
  const int64_t cubes_x = g.X - 1;
  const int64_t n_slabs =
      std::min<int64_t>(cubes_x, std::max<int64_t>(1, options.slabs > 0 ? options.slabs : 4 * at::get_num_threads()));
  std::vector<Slab> slabs(static_cast<size_t>(n_slabs));
  for (int64_t s = 0; s < n_slabs; ++s) {
    slabs[s].x_begin = cubes_x * s / n_slabs;
    slabs[s].x_end = cubes_x * (s + 1) / n_slabs;
  }
  // One vertex per crossed grid edge, shared by the cubes around it: index (point * 3 + axis) -> the
  // vertex's index within the slab that created it.
  std::vector<int> edge_vertex(static_cast<size_t>(g.X * g.YZ * 3), -1);
  at::parallel_for(0, n_slabs, 1, [&](int64_t sb, int64_t se) {
    for (int64_t s = sb; s < se; ++s) march_slab(g, slabs[static_cast<size_t>(s)], edge_vertex);
  });
  return join_slabs(slabs, edge_vertex);
}

void grid_to_voxel_frame(Mesh& mesh, int64_t resolution) {
  SIMU_CHECK(resolution > 0, "grid_to_voxel_frame: resolution must be positive, got {}", resolution);
  // p / resolution - 0.5 per coordinate (row blocks in parallel).
  const double r = static_cast<double>(resolution);
  double* p = mesh.V.data();
  at::parallel_for(0, static_cast<int64_t>(mesh.V.size()), 1 << 16, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) p[i] = p[i] / r - 0.5;
  });
}

CanonicalTransform canonicalize_mesh(Mesh& mesh) {
  CanonicalTransform tf;
  const int64_t n = mesh.V.rows();
  if (n == 0) return tf;
  // Axis-aligned bounding box (per-block min / max, then combined: exact in any order).
  const int64_t grain = 1 << 14;
  const int64_t n_blocks = (n + grain - 1) / grain;
  std::vector<Eigen::Vector3d> lo_b(static_cast<size_t>(n_blocks)), hi_b(static_cast<size_t>(n_blocks));
  at::parallel_for(0, n_blocks, 1, [&](int64_t bb, int64_t be) {
    for (int64_t blk = bb; blk < be; ++blk) {
      const int64_t r0 = blk * grain, rows = std::min(grain, n - r0);
      lo_b[blk] = mesh.V.middleRows(r0, rows).colwise().minCoeff().transpose();
      hi_b[blk] = mesh.V.middleRows(r0, rows).colwise().maxCoeff().transpose();
    }
  });
  Eigen::Vector3d lo = lo_b[0], hi = hi_b[0];
  for (int64_t blk = 1; blk < n_blocks; ++blk) {
    lo = lo.cwiseMin(lo_b[blk]);
    hi = hi.cwiseMax(hi_b[blk]);
  }
  tf.centre = (lo + hi) / 2;
  const double longest = (hi - lo).maxCoeff();
  tf.factor = longest > 0 ? 1.0 / longest : 1.0;
  // (v - centre) * factor per coordinate.
  double* p = mesh.V.data();
  const double c[3] = {tf.centre(0), tf.centre(1), tf.centre(2)};
  const double f = tf.factor;
  at::parallel_for(0, n, grain, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i)
      for (int a = 0; a < 3; ++a) p[3 * i + a] = (p[3 * i + a] - c[a]) * f;
  });
  return tf;
}

double mesh_signed_volume(const Mesh& mesh) {
  double six_v = 0;
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    const Eigen::Vector3d a = mesh.V.row(mesh.F(f, 0)).transpose();
    const Eigen::Vector3d b = mesh.V.row(mesh.F(f, 1)).transpose();
    const Eigen::Vector3d c = mesh.V.row(mesh.F(f, 2)).transpose();
    six_v += a.dot(b.cross(c));
  }
  return six_v / 6.0;
}

std::string mesh_closedness_problem(const Mesh& mesh) {
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

void write_mesh_ply(const Mesh& mesh, const std::string& path) {
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

void offset_surface(Mesh& mesh, double distance) {
  if (distance == 0 || mesh.empty()) return;
  // Area-weighted vertex normals: each triangle adds its (unnormalised) cross product to its corners.
  Eigen::Matrix<double, -1, 3, Eigen::RowMajor> N = Eigen::Matrix<double, -1, 3, Eigen::RowMajor>::Zero(mesh.V.rows(), 3);
  for (int64_t f = 0; f < mesh.F.rows(); ++f) {
    const Eigen::Vector3d a = mesh.V.row(mesh.F(f, 0)), b = mesh.V.row(mesh.F(f, 1)), c = mesh.V.row(mesh.F(f, 2));
    const Eigen::RowVector3d n = (b - a).cross(c - a).transpose();
    for (int j = 0; j < 3; ++j) N.row(mesh.F(f, j)) += n;
  }
  for (int64_t v = 0; v < mesh.V.rows(); ++v) {
    const double l = N.row(v).norm();
    if (l > 0) mesh.V.row(v) -= (distance / l) * N.row(v);
  }
}

}  // namespace simu::resample
