#include "pipeline/reconstruct/nn.h"

#include "common/error.h"

#include <nanoflann.hpp>

#include <cmath>

namespace simu::reconstruct {

namespace {
// nanoflann dataset adaptor over a row-major Points matrix.
struct Cloud {
  Points P;
  size_t kdtree_get_point_count() const { return size_t(P.rows()); }
  double kdtree_get_pt(size_t i, size_t d) const { return P(Eigen::Index(i), Eigen::Index(d)); }
  template <class B>
  bool kdtree_get_bbox(B&) const { return false; }
};
using Tree = nanoflann::KDTreeSingleIndexAdaptor<nanoflann::L2_Simple_Adaptor<double, Cloud>, Cloud, 3, size_t>;
}  // namespace

struct NearestNeighbors::Impl {
  Cloud cloud;
  std::unique_ptr<Tree> tree;
};

NearestNeighbors::NearestNeighbors(const Points& P) : impl_(new Impl) {
  SIMU_CHECK(P.rows() > 0, "NearestNeighbors: empty point set");
  impl_->cloud.P = P;
  impl_->tree = std::make_unique<Tree>(3, impl_->cloud, nanoflann::KDTreeSingleIndexAdaptorParams(10));
  impl_->tree->buildIndex();
}
NearestNeighbors::~NearestNeighbors() = default;

int64_t NearestNeighbors::nearest(const Vec3& q, double* dist2) const {
  size_t idx = 0;
  double d2 = 0;
  impl_->tree->knnSearch(q.data(), 1, &idx, &d2);
  if (dist2) *dist2 = d2;
  return int64_t(idx);
}
const Points& NearestNeighbors::points() const { return impl_->cloud.P; }
int64_t NearestNeighbors::size() const { return impl_->cloud.P.rows(); }

double one_sided_chamfer(const Points& A, const NearestNeighbors& B) {
  if (A.rows() == 0) return 0;
  double sum = 0;
  for (Eigen::Index i = 0; i < A.rows(); ++i) {
    double d2 = 0;
    B.nearest(A.row(i).transpose(), &d2);
    sum += std::sqrt(d2);
  }
  return sum / double(A.rows());
}

}  // namespace simu::reconstruct
