// Nearest neighbours in 3-D through nanoflann (Debian libnanoflann-dev, header-only): a static KD-tree
// over a point set, queried one point at a time.
#pragma once

#include "pipeline/reconstruct/types.h"

#include <memory>

namespace simu::reconstruct {

class NearestNeighbors {
 public:
  // Builds the tree over the rows of P (copied). Throws simu::Error on an empty set.
  explicit NearestNeighbors(const Points& P);
  ~NearestNeighbors();
  NearestNeighbors(const NearestNeighbors&) = delete;
  NearestNeighbors& operator=(const NearestNeighbors&) = delete;
  // Index of the nearest row to q and its squared distance.
  int64_t nearest(const Vec3& q, double* dist2 = nullptr) const;
  const Points& points() const;
  int64_t size() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Mean over the rows a of A of min_b |a - b| (one-sided chamfer, Euclidean, not squared).
double one_sided_chamfer(const Points& A, const NearestNeighbors& B);

}  // namespace simu::reconstruct
