// Pictures of a probe run for people, drawn with the project's rasteriser (raster.h), written as PNG
// next to report.json (needs OpenCV's PNG codec; without it write_probe_pictures throws saying so):
//  - before_after.png: the input camera view, input masks on the left and the final scene's shaded
//    meshes on the right, each object in its own colour (overlay_color, the MJCF's colours too), ids
//    on both sides and a legend (branch, displacement, flags) below; the view is rendered at least
//    480 pixels high and the text scales with it, so labels stay legible for small camera images;
//  - side_view.png: the final scene from the side (horizontal view across the camera's line of
//    sight, gravity pointing down), with the floor edge-on: floating and sinking show here;
//  - candidates_<id>.png for every resampled object with candidates: its input mask, then each
//    candidate rendered from the camera at the target OBB centre, the kept one framed and marked
//    KEPT, failed ones marked with why (when none passed the title says the input shape was kept).
// And eval_lift's per-object comparison (write_object_comparison_png): input crop, GT, predictions.
#pragma once

#include <string>
#include <vector>

#include "pipeline/physics/probe.h"

namespace simu::physics {

// Writes the pictures of r (its corrected scene, meshes and diagnostics) into dir; returns the files
// written (paths under dir). Objects without geometry are left out of the renders but listed.
std::vector<std::string> write_probe_pictures(const ProbeResult& r, const std::string& dir);

// One rendered panel of an object comparison: a world-frame mesh (null or empty: an empty panel, e.g.
// a failed prediction) and its caption.
struct MeshPanel {
  std::string caption;
  const Mesh* world_mesh = nullptr;
};

// eval_lift's picture of one object, one row of panels over the same crop of the camera view: the
// input image (rgb: uint8 [H, W, 3] RGB, the camera's size) with the modal mask outlined, then each
// panel's mesh rendered shaded from the camera in its own colour in front of the grey `environment`
// (floor, wall, table). The crop holds the modal mask and every panel mesh's silhouette (padded, made
// square where the image allows) and is rendered at least 240 pixels high; `title` goes above. Written as a PNG
// atomically. Throws simu::Error for an invalid camera, an image or mask of another size, or without
// OpenCV.
void write_object_comparison_png(const std::string& path, const Camera& cam, const std::vector<uint8_t>& rgb,
                                 const BinaryMask& modal, const std::vector<MeshPanel>& panels,
                                 const std::vector<const Mesh*>& environment, const std::string& title);

}  // namespace simu::physics
