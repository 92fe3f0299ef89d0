// A small z-buffer for the alignment steps: depth of a camera-frame triangle mesh per pixel, vertex
// visibility against it, and the silhouette. Pixel centres as in types.h; perspective-correct depth
// (1/z linear in the image); triangles with a vertex behind z = near are skipped (objects lie in
// front of the camera); both faces drawn.
#pragma once

#include "pipeline/reconstruct/types.h"

#include <vector>

namespace simu::reconstruct {

// Depth image (row-major, +inf where nothing is drawn) of the camera-frame mesh (V, F); optionally the
// index of the face drawn at each pixel (-1 where none).
std::vector<float> render_depth(const Points& V_cam, const Faces& F, const Pinhole& K, double near = 1e-3,
                                std::vector<int32_t>* face_id = nullptr);

// The visible vertex subset V^vis of the paper: the vertices of every face that wins at least one
// pixel of the z-buffer, plus the vertices (of faces smaller than a pixel) whose depth is within `tol`
// of the z-buffer at their own pixel. Returns their indices, ascending.
std::vector<int64_t> visible_vertices(const Points& V_cam, const Faces& F, const Pinhole& K, double tol);

// Silhouette of a depth image (finite pixels).
Mask silhouette(const std::vector<float>& depth, const Pinhole& K);

}  // namespace simu::reconstruct
