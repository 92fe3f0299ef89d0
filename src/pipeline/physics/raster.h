// Z-buffer rasterisation of triangle meshes through the scene camera: per-object visible masks for
// the 2D IoU / ABO metrics, silhouettes, depth maps, and the resampler's auxiliary crop mask M'.
//
// Sampling: a pixel belongs to a triangle when its centre (see camera.h: pixel (c, r) is centred at
// (u, v) = (c, r)) lies inside or on the triangle's projection. Depth is interpolated
// perspective-correctly (1/z linear in the image). Triangles are clipped against the near plane
// z = near; back faces are drawn too (meshes need not be closed or consistently wound).
#pragma once

#include "pipeline/physics/geometry.h"
#include "pipeline/physics/scene.h"

#include <cstdint>
#include <vector>

namespace simu::physics {

// A binary image, row-major, 0 or 1 per pixel.
struct BinaryMask {
  int width = 0, height = 0;
  std::vector<uint8_t> data;

  BinaryMask() = default;
  BinaryMask(int w, int h) : width(w), height(h), data(size_t(w) * size_t(h), 0) {}
  uint8_t& at(int row, int col) { return data[size_t(row) * width + col]; }
  uint8_t at(int row, int col) const { return data[size_t(row) * width + col]; }
  // Number of set pixels.
  int64_t count() const;
  bool empty() const { return count() == 0; }
  // In-place union with a mask of the same size (throws simu::Error on a size mismatch).
  void unite(const BinaryMask& other);
  // Bounding box of the set pixels: {col0, row0, col1, row1} inclusive; all -1 when empty.
  std::array<int, 4> bbox() const;
};

// Joint rendering of several meshes: label(r, c) = index of the nearest mesh at that pixel, or -1;
// depth(r, c) = its camera-frame depth z (metres), +inf where nothing is drawn.
struct LabelImage {
  int width = 0, height = 0;
  std::vector<int32_t> label;
  std::vector<float> depth;
  // Visible mask of one mesh index.
  BinaryMask mask_of(int index) const;
};

// Renders world-frame meshes jointly (z-buffer). Null or empty meshes are skipped (their masks
// stay empty). Throws simu::Error when the camera is invalid.
LabelImage render_labels(const Camera& cam, const std::vector<const Mesh*>& world_meshes, double near = 1e-3);

// Joint rendering with flat Lambert shading for pictures: label image plus, per pixel, the
// brightness in [ambient, 1] of the nearest face (|cos| of its normal with the view ray, so
// inconsistently wound meshes shade the same).
struct ShadedImage {
  LabelImage labels;
  std::vector<float> shade;  // per pixel; 0 where nothing is drawn
};
ShadedImage render_shaded(const Camera& cam, const std::vector<const Mesh*>& world_meshes, double ambient = 0.3,
                          double near = 1e-3);

// Joint rendering that also records, per pixel, the index of the nearest face within its mesh (-1
// where nothing is drawn): for shading by face normals (the shape world's lighting).
struct FaceImage {
  LabelImage labels;
  std::vector<int32_t> face;  // per pixel: row of Mesh::F of mesh labels.label[pixel]
};
FaceImage render_faces(const Camera& cam, const std::vector<const Mesh*>& world_meshes, double near = 1e-3);

// Silhouette (coverage, no occlusion by other meshes) of one world-frame mesh.
BinaryMask render_silhouette(const Camera& cam, const Mesh& world_mesh, double near = 1e-3);

// The auxiliary crop mask of the resampling branch: M' = M (modal) united with the projection of
// lowest_part(d) (the slab of B_str below B_pre's gravity-most face, see geometry.h). With no
// lowest part (eta <= 0 and no margin) M' = M. A mask with the wrong size is an error.
BinaryMask auxiliary_crop_mask(const Camera& cam, const BinaryMask& modal, const Diagnosis& d,
                               const CorrectionConfig& config = {});

}  // namespace simu::physics
