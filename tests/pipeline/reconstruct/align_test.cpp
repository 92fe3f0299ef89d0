// Tests the translation-scale alignment (align.h): a box observed through a rendered depth map, its
// lifted copy given a wrong scale (+-25%), a translation error along the viewing ray and the true
// rotation; the alignment must recover the true scale and centre. Also the per-object failure flags.
#include <gtest/gtest.h>

#include "pipeline/reconstruct/align.h"
#include "pipeline/reconstruct/nn.h"
#include "reconstruct_test_util.h"
#include "tolerance.h"

using namespace simu::reconstruct;
using namespace simu::reconstruct::testing;

namespace {
struct Truth {
  Points C;
  Faces F;
  Mat3 R;
  double s;
  Vec3 t;
};

// Observed points and mask of the truth, rendered alone.
AlignInput observe(const Truth& g, const Pinhole& K, PointMap& map) {
  const Points W = transform(g.C, Similarity{g.s, g.R, g.t});
  Points Wd = W;
  Faces Fd = g.F;
  const auto depth = render_depth(Wd, Fd, K);
  map = unproject(depth, K);
  AlignInput in;
  in.K = K;
  in.mask = silhouette(depth, K);
  in.observed = masked_points(map, in.mask, "truth");
  in.canonical = g.C;
  in.faces = g.F;
  in.R_init = g.R;
  in.depth = &map;
  return in;
}
}  // namespace

// The nanoflann wrapper returns the brute-force nearest neighbour.
TEST(ReconstructNN, MatchesBruteForce) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1, 1);
  Points P(500, 3);
  for (int i = 0; i < 500; ++i) P.row(i) << u(rng), u(rng), u(rng);
  NearestNeighbors nn(P);
  for (int q = 0; q < 50; ++q) {
    const Vec3 x(u(rng), u(rng), u(rng));
    Eigen::Index best = 0;
    (P.rowwise() - x.transpose()).rowwise().squaredNorm().minCoeff(&best);
    double d2 = 0;
    EXPECT_EQ(nn.nearest(x, &d2), int64_t(best));
    EXPECT_NEAR(d2, (P.row(best).transpose() - x).squaredNorm(), simu::testing::kFp64Chain);
  }
}

// Scale factors 0.75 and 1.25 with a 10 cm error along the ray are recovered to 3% and 1 cm.
TEST(ReconstructAlign, RecoversScaleAndTranslationOfABox) {
  const Pinhole K = camera();
  Truth g;
  box_mesh(Vec3(1.0, 0.6, 0.8), g.C, g.F);
  g.R = rot(Vec3(0, 1, 0), 30) * rot(Vec3(1, 0, 0), -20);
  g.s = 0.3;
  g.t = Vec3(0.05, 0.02, 1.6);
  for (double f : {0.75, 1.25}) {
    for (double dz : {-0.1, 0.1}) {
      PointMap map;
      AlignInput in = observe(g, K, map);
      in.id = "box";
      in.s_init = g.s * f;
      in.t_init = g.t + dz * g.t.normalized();
      const AlignResult r = align_translation_scale(in);
      ASSERT_TRUE(r.ok) << r.message;
      EXPECT_EQ(r.candidates.size(), 4u);
      // The fit's resolution, not rounding: the observed points are the box's visible faces sampled at
      // the camera's pixels (~1.5 mm apart at 1.6 m), and the chamfer optimum is flat to within a pixel
      // pitch over the ~0.3 m object: 3% of scale and 1 cm of translation.
      EXPECT_NEAR(r.s / g.s, 1.0, 0.03) << "factor " << f << " dz " << dz;
      EXPECT_LT((r.t - g.t).norm(), 0.01) << "factor " << f << " dz " << dz;
      // The loss of the chosen candidate is small compared with the object (a few mm: the pixel pitch).
      EXPECT_LT(r.candidates[size_t(r.best)].chamfer, 0.005);
    }
  }
}

// Too few depth points under the mask: not aligned, the object named, the input pose returned.
TEST(ReconstructAlign, TooFewPointsIsAFlagNotAnError) {
  AlignInput in;
  in.id = "cup";
  in.K = camera();
  in.mask = Mask(in.K.width, in.K.height);
  box_mesh(Vec3(1, 1, 1), in.canonical, in.faces);
  in.s_init = 0.2;
  in.t_init = Vec3(0, 0, 1);
  in.observed = Points(5, 3);
  in.observed.setConstant(1.0);
  const AlignResult r = align_translation_scale(in);
  EXPECT_FALSE(r.ok);
  EXPECT_NE(r.message.find("cup"), std::string::npos);
  EXPECT_NE(r.message.find("5 valid depth points"), std::string::npos);
  EXPECT_EQ(r.s, 0.2);
  EXPECT_EQ(r.t, Vec3(0, 0, 1));
}
