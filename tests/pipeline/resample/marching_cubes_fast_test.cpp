// Fast marching cubes (slab-parallel) against the sequential reference: identical meshes (same vertex
// values, vertex order and triangle order) on random and smooth grids, for any slab count and thread
// count; the parallel frame transforms against the plain Eigen formulas.
#include <ATen/Parallel.h>

#include "models/ss_decoder.h"
#include "pipeline/resample/marching_cubes.h"
#include "pipeline/resample/resampler.h"
#include "test_util.h"

using namespace simu::physics;
using namespace simu::resample;

namespace {
// Exact equality of two meshes; on a difference, says where.
::testing::AssertionResult same_mesh(const Mesh& got, const Mesh& want) {
  if (got.V.rows() != want.V.rows() || got.F.rows() != want.F.rows())
    return ::testing::AssertionFailure() << "sizes: got " << got.V.rows() << " vertices / " << got.F.rows()
                                         << " faces, want " << want.V.rows() << " / " << want.F.rows();
  for (Eigen::Index i = 0; i < want.V.rows(); ++i)
    for (int a = 0; a < 3; ++a)
      if (got.V(i, a) != want.V(i, a))
        return ::testing::AssertionFailure() << "vertex " << i << " coord " << a << ": got " << got.V(i, a) << ", want "
                                             << want.V(i, a);
  for (Eigen::Index f = 0; f < want.F.rows(); ++f)
    for (int a = 0; a < 3; ++a)
      if (got.F(f, a) != want.F(f, a))
        return ::testing::AssertionFailure() << "face " << f << " index " << a << ": got " << got.F(f, a) << ", want "
                                             << want.F(f, a);
  return ::testing::AssertionSuccess();
}

// Restores the ATen thread count on scope exit.
struct ThreadsGuard {
  int saved = at::get_num_threads();
  ~ThreadsGuard() { at::set_num_threads(saved); }
};

// Test grids: uncorrelated noise with ~42% above 0 (what random decoder weights give), the same noise
// box-smoothed, and a non-cubic grid.
std::vector<std::pair<std::string, torch::Tensor>> grids() {
  torch::manual_seed(11);
  const auto noise = torch::randn({64, 64, 64});
  const auto smooth = torch::avg_pool3d(noise.view({1, 1, 64, 64, 64}), 3, 1, 1).view({64, 64, 64});
  return {{"random64", noise - 0.2}, {"smoothed64", smooth}, {"odd", torch::randn({23, 17, 31})}};
}
}  // namespace

// Every single-cube configuration: the fast path gives exactly the reference mesh.
TEST(MarchingCubesFast, AllCasesMatchReference) {
  for (int mask = 1; mask < 256; ++mask) {
    auto g = torch::empty({2, 2, 2});
    for (int c = 0; c < 8; ++c) g[c & 1][(c >> 1) & 1][(c >> 2) & 1] = ((mask >> c) & 1) ? 1.0 : -1.0;
    ASSERT_TRUE(same_mesh(marching_cubes(g), marching_cubes_reference(g))) << "case " << mask;
  }
}

// Random and smooth grids, several slab counts (1 = no merge; up to one slab per cube layer) and
// iso levels: identical to the reference; and the fast mesh is closed.
TEST(MarchingCubesFast, RandomGridsMatchReferenceForAnySlabCount) {
  for (const auto& [name, grid] : grids()) {
    for (double iso : {0.0, 0.3}) {
      const auto want = marching_cubes_reference(grid, {iso});
      ASSERT_GT(want.F.rows(), 1000) << name;
      for (int slabs : {0, 1, 2, 7, 1000}) {
        MarchingCubesOptions o;
        o.iso = iso;
        o.slabs = slabs;
        EXPECT_TRUE(same_mesh(marching_cubes(grid, o), want)) << name << " iso " << iso << " slabs " << slabs;
      }
    }
  }
  torch::manual_seed(5);
  const auto small = torch::randn({20, 24, 22});
  MarchingCubesOptions o;
  o.slabs = 5;
  EXPECT_EQ(mesh_closedness_problem(marching_cubes(small, o)), "");
}

// One thread and two threads (and the default count) give the same mesh, for the default slab split.
TEST(MarchingCubesFast, ThreadCountDoesNotChangeMesh) {
  ThreadsGuard guard;
  for (const auto& [name, grid] : grids()) {
    at::set_num_threads(1);
    const auto one = marching_cubes(grid);
    at::set_num_threads(2);
    const auto two = marching_cubes(grid);
    at::set_num_threads(guard.saved);
    const auto all = marching_cubes(grid);
    EXPECT_TRUE(same_mesh(two, one)) << name;
    EXPECT_TRUE(same_mesh(all, one)) << name;
  }
}

// mesh_from_logits = reference marching cubes, then p / R - 0.5, then (p - AABB centre) / longest side,
// written as plain Eigen expressions here; the parallel transforms must agree exactly, at 1 and 2 threads.
TEST(MarchingCubesFast, MeshFromLogitsMatchesPlainFrames) {
  ThreadsGuard guard;
  const auto logits = grids()[0].second;
  Mesh want = marching_cubes_reference(logits);
  want.V = (want.V.array() / 64.0 - 0.5).matrix();
  const Eigen::Vector3d lo = want.V.colwise().minCoeff().transpose(), hi = want.V.colwise().maxCoeff().transpose();
  const Eigen::Vector3d centre = (lo + hi) / 2;
  const double factor = 1.0 / (hi - lo).maxCoeff();
  want.V = ((want.V.rowwise() - centre.transpose()) * factor).eval();
  for (int threads : {1, 2}) {
    at::set_num_threads(threads);
    ResampledShape out;
    mesh_from_logits(logits.view({1, 1, 64, 64, 64}), out);
    ASSERT_TRUE(out.ok) << out.message;
    EXPECT_TRUE(same_mesh(out.mesh, want)) << threads << " threads";
    EXPECT_EQ(out.canonical.centre, centre);
    EXPECT_EQ(out.canonical.factor, factor);
    // Occupied voxels as models::occupied_coords (argwhere order), batch column dropped.
    const auto coords = simu::models::occupied_coords(logits.view({1, 1, 64, 64, 64})).slice(1, 1, 4);
    EXPECT_TRUE(torch::equal(out.coords, coords));
  }
}
