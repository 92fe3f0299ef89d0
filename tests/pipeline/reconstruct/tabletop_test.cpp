// Tests the tabletop refinement (tabletop.h): a table rendered from a pitched camera, its lifted pose
// tilted, raised, turned and scaled; after hard_snap + table_refine the top lies on the true top plane
// (normal within 0.5 degree, height within 5 mm) and the fit improved. And the three sanity checks.
#include <gtest/gtest.h>

#include "pipeline/reconstruct/planes.h"
#include "pipeline/reconstruct/tabletop.h"
#include "reconstruct_test_util.h"

using namespace simu::reconstruct;
using namespace simu::reconstruct::testing;

namespace {
struct TableScene {
  Pinhole K = camera(320, 240, 280);
  Mat3 Rr = rot(Vec3(1, 0, 0), 30);  // room (y down) -> camera: the camera looks down 30 degrees
  Vec3 up = Rr * Vec3(0, -1, 0);
  Points C;
  Faces F;
  Mat3 R;
  Vec3 t;
  PointMap map;
  Mask mask;
  double top_height = 0;  // up . (a point of the true top)
  TableScene() {
    box_mesh(Vec3(1.0, 0.6, 0.7), C, F);  // canonical, y the up/down axis
    R = Rr * rot(Vec3(0, 1, 0), 20);
    t = Rr * Vec3(0.1, 1.0, 2.4);
    const Points W = place(C, Vec3::Ones(), R, t);
    const auto depth = render_depth(W, F, K);
    map = unproject(depth, K);
    mask = silhouette(depth, K);
    top_height = up.dot(t) + 0.3;
  }
  TabletopInput input() const {
    TabletopInput in;
    in.id = "table";
    in.canonical = C;
    in.faces = F;
    in.points = &map;
    in.mask = mask;
    in.K = K;
    in.up = up;
    return in;
  }
};
}  // namespace

// A 3-degree tilt, 3 cm rise, 4-degree turn and 4% scale error: the top ends on the true plane.
TEST(ReconstructTabletop, SnapAndRefinePutTheTopOnThePlane) {
  TableScene sc;
  TabletopInput in = sc.input();
  const Vec3 side = sc.up.unitOrthogonal();
  in.R = rot(side, 3) * rot(sc.up, 4) * sc.R;
  in.t = sc.t + 0.03 * sc.up + 0.02 * side;
  in.scale = Vec3::Constant(1.04);
  const TabletopResult r = refine_tabletop(in);
  ASSERT_TRUE(r.ok) << r.message;
  // The support plane fitted to the top face's sampled points (pixel pitch ~2 mm, no noise): a
  // fraction of a degree, and the height to a few mm.
  EXPECT_LT(angle_deg(r.support.normal, sc.up), 0.5);
  EXPECT_NEAR(sc.up.dot(r.support.point), sc.top_height, 0.005);
  // The refined top face: canonical top normal (0, -1, 0) and the highest vertex.
  EXPECT_LT(angle_deg(r.R * Vec3(0, -1, 0), sc.up), 0.5);
  const Points W = place(sc.C, r.scale, r.R, r.t);
  double top = -1e9;
  for (Eigen::Index i = 0; i < W.rows(); ++i) top = std::max(top, sc.up.dot(W.row(i).transpose()));
  EXPECT_NEAR(top, sc.top_height, 0.005);
  EXPECT_LE(r.chamfer_after, r.chamfer_before);
}

// Sanity checks: no upward-facing support (a mask on the front face only), a tilted detected plane
// (the wrong up), a plane at the floor's height: each rejected with its reason, pose unchanged.
TEST(ReconstructTabletop, SanityChecksReject) {
  TableScene sc;
  {
    TabletopInput in = sc.input();
    in.R = sc.R;
    in.t = sc.t;
    const auto normals = point_map_normals(sc.map);
    for (size_t i = 0; i < in.mask.data.size(); ++i)
      if (in.mask.data[i] && normals[i].allFinite() && normals[i].dot(sc.up) > 0.5) in.mask.data[i] = 0;
    const TabletopResult r = refine_tabletop(in);
    EXPECT_FALSE(r.ok);
    EXPECT_NE(r.message.find("insufficient plane support"), std::string::npos) << r.message;
    EXPECT_EQ(r.t, sc.t);
  }
  {
    TabletopInput in = sc.input();
    in.R = sc.R;
    in.t = sc.t;
    in.up = rot(sc.up.unitOrthogonal(), 20) * sc.up;
    TabletopConfig cfg;
    cfg.band = 1.0;  // the band would cut a plane tilted against up down to a strip first
    const TabletopResult r = refine_tabletop(in, cfg);
    EXPECT_FALSE(r.ok);
    EXPECT_NE(r.message.find("non-horizontal"), std::string::npos) << r.message;
  }
  {
    TabletopInput in = sc.input();
    in.R = sc.R;
    in.t = sc.t;
    in.floor = PlaneFit{sc.t + 0.31 * sc.up, sc.up, 0, 0};
    const TabletopResult r = refine_tabletop(in);
    EXPECT_FALSE(r.ok);
    EXPECT_NE(r.message.find("floor degeneracy"), std::string::npos) << r.message;
  }
  EXPECT_TRUE(is_table_label("Dining Table"));
  EXPECT_TRUE(is_table_label("desk"));
  EXPECT_FALSE(is_table_label("chair"));
}
