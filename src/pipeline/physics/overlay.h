// Images for people and for the resampler hand-off: binary mask PNG read/write and the probe's
// overlay PNG (object masks tinted, projected OBBs B_pre / B_str as wireframes, auxiliary crop masks
// M' outlined). PNG coding needs OpenCV (SIMU_HAVE_OPENCV); without it these functions throw
// simu::Error saying so.
#pragma once

#include "pipeline/physics/geometry.h"
#include "pipeline/physics/raster.h"
#include "pipeline/physics/scene.h"

#include <optional>
#include <string>
#include <vector>

namespace simu::physics {

// Reads an 8-bit (or any depth, any channel count) image; non-zero pixels -> 1. Throws simu::Error
// naming the file when it is missing or unreadable.
BinaryMask read_mask(const std::string& path);
// Writes a mask as an 8-bit PNG (0 / 255), atomically.
void write_mask(const std::string& path, const BinaryMask& mask);

// One object on the overlay; every member is optional.
struct OverlayItem {
  std::string label;                    // drawn at the mask's top-left corner
  const BinaryMask* mask = nullptr;     // tinted with the object's colour
  std::optional<Obb> obb;               // B_pre, solid wireframe
  std::optional<Obb> obb_target;        // B_str (resample) or the stretched box, dashed wireframe
  const BinaryMask* aux_mask = nullptr; // M', white outline
};

// Renders the overlay at the camera's image size over the scene image (grey when image_path is
// empty or unreadable) and writes it as a PNG atomically.
void write_overlay_png(const std::string& path, const Camera& cam, const std::string& image_path,
                       const std::vector<OverlayItem>& items);

// Distinct colour (B, G, R) for object index i.
std::array<uint8_t, 3> overlay_color(int i);

}  // namespace simu::physics
