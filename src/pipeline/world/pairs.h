// Preference pairs from world scenes (issue 36; the paper's two kinds, supplementary "SAM3D Fine-tuning
// Details"; docs/world.md "Pairs"). A scene yields:
//   occlusion completion: an object hidden 20-60% by other objects (SceneConfig::targets makes them).
//     x- comes from the scene image with its modal mask; x+ from the edited image (render_without its
//     occluders) with its now full mask, which must show at least full_min of its silhouette.
//   clean preservation: an object with no occluder, >= preserve_min visible and off the image border.
//     x+ comes from its true mask; x- from a corrupted copy (corrupt_mask: eroded, cut or shifted).
// Torch-free; `world pairs` writes the files and the build_pairs manifest.
//
//   auto s = world::make_scene(cfg, seed, world::Split::Train);
//   for (const auto& p : world::plan_pairs(s, {}, seed)) ...   // p.object, p.completion, p.edited, ...
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "pipeline/physics/raster.h"
#include "pipeline/world/scene.h"

namespace simu::world {

struct PairPlanConfig {
  double completion_min = 0.2, completion_max = 0.6;  // visible fraction of a completion target
  double full_min = 0.9;       // its visible fraction in the edited image (occluders removed)
  double preserve_min = 0.95;  // visible fraction of a preservation object
  int min_pixels = 200;        // smaller modal masks are not used (either kind)
  int border = 2;              // pixels: a preservation mask touching the border this close is truncated
};

// One pair of a scene.
struct PlannedPair {
  int object = -1;          // index into WorldScene::objects
  bool completion = false;  // occlusion completion (else clean preservation)
  // Completion: the edited scene (occluders removed) and the object's mask in it.
  WorldScene edited;
  physics::BinaryMask full_mask;
  // Preservation: the corrupted mask and how it was made ("erode", "cut" or "shift").
  physics::BinaryMask corrupted;
  std::string corruption;
};

// The pairs a scene offers, in object order (every qualifying object; the caller takes what it
// needs). seed draws the mask corruptions (per object: seed ^ object index).
std::vector<PlannedPair> plan_pairs(const WorldScene& s, const PairPlanConfig& config, uint64_t seed);

// A corrupted copy of a mask, drawn by seed among three kinds:
//   erode: every pixel within r of the background removed, r = max(1, round(0.08 sqrt(area)));
//   cut:   the pixels on one side of a random line removed, keeping 50-75% of the area;
//   shift: the mask moved by 15-30% of its bounding box in a random direction (pixels leaving the
//          image are dropped).
// The result is non-empty and differs from the input (a cut is used when another kind fails).
// `how` (optional) receives the kind. Throws simu::Error for an empty mask.
physics::BinaryMask corrupt_mask(const physics::BinaryMask& mask, uint64_t seed, std::string* how = nullptr);

}  // namespace simu::world
