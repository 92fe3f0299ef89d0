// Writing world scenes as the inputs `lift` reads plus their ground truth (apps/world.cpp; the .npy
// point map is written by the program through data::write_npy, the one torch-side step):
//   DIR/image.png             RGB (8-bit)
//   DIR/labels.png            16-bit label image (0 nothing, 1 floor, 2 wall, 3 table, 4 + i object i)
//   DIR/masks/<id>.png        modal mask per object (255 = visible), DIR/amodal/<id>.png amodal mask
//   DIR/pointmap.npy          float32 [H, W, 3] OpenCV camera, NaN invalid (clean, or corrupted)
//   DIR/pointmap_clean.npy    the clean one when pointmap.npy is corrupted
//   DIR/intrinsics.json       {"fx", "fy", "cx", "cy", "width", "height", "K"} (data::read_intrinsics_json)
//   DIR/gt.json               scene_gt_json below
//   DIR/meshes/<name>.obj     each instance's canonical mesh
#pragma once

#include "pipeline/world/scene.h"

#include <nlohmann/json.hpp>
#include <string>

namespace simu::world {

// {"fx", "fy", "cx", "cy", "width", "height", "K": 3x3}.
nlohmann::json intrinsics_json(const physics::Camera& camera);

// The ground truth of a scene: seed, split, camera (intrinsics and world pose), gravity, light, and per
// object: id, label, family, instance name / id / seed, split, held_out, rest, on_floor, size_m,
// albedo, pose in the world frame (R, scale, t) and in the camera frame (R_cam, t_cam), modal / amodal
// pixels, visible_fraction, occluders (ids), occluded_by_table, target, usable, mask file and
// mesh file (relative to the scene folder); plus "corruption" when given.
nlohmann::json scene_gt_json(const WorldScene& s, const CorruptionRecord* corruption = nullptr);

// Writes image.png, labels.png, masks/, amodal/, meshes/, intrinsics.json and gt.json into dir
// (created; each file atomically). Needs OpenCV (SIMU_HAVE_OPENCV); throws simu::Error otherwise.
void write_scene_files(const WorldScene& s, const std::string& dir, const CorruptionRecord* corruption = nullptr);

// A picture of every object of s side by side (contact sheets, docs); uint8 [H, W, 3] with its size.
struct Picture {
  int width = 0, height = 0;
  std::vector<uint8_t> rgb;
};
// Writes an RGB picture as PNG atomically (OpenCV).
void write_png(const std::string& path, const Picture& p);
// Every family's instance(s) rendered alone on a grey ground, `per_family` instances per row.
Picture family_contact_sheet(int per_family, int cell, uint64_t seed);

}  // namespace simu::world
