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
#pragma once

#include <string>
#include <vector>

#include "pipeline/physics/probe.h"

namespace simu::physics {

// Writes the pictures of r (its corrected scene, meshes and diagnostics) into dir; returns the files
// written (paths under dir). Objects without geometry are left out of the renders but listed.
std::vector<std::string> write_probe_pictures(const ProbeResult& r, const std::string& dir);

}  // namespace simu::physics
