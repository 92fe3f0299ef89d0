// Floor and walls (supplementary "Floor and wall plane extraction with Manhattan rectification",
// "Post-fit plane re-extraction").
//
//   floor  RANSAC on the floor mask's points, 5 cm residual, the normal oriented up: towards -y of the
//          OpenCV camera (the paper's "normal points downward in OpenCV" is the image's upward
//          direction, y being down) and required within max_floor_tilt of it;
//   walls  RANSAC per wall mask, 1 cm residual, normals oriented towards the camera (into the room);
//          orientation clusters by DBSCAN on the angle between wall lines (|n_i . n_j|); clusters not
//          orthogonal (within orthogonality_tol) to the best-covered cluster are dropped; the top
//          four walls by coverage (RANSAC inliers) kept;
//   up     Manhattan rectification, by priority: the cross product of two orthogonal walls (signed to
//          agree with the floor, else with -y), else the floor's normal, else a mesh-derived up
//          (the caller's); every wall normal made perpendicular to up, the floor normal set to up;
//   snap   after the objects are fitted, the floor offset moves to the lowest vertex (along up) of the
//          union of the fitted meshes;
//   fallback  without floor and wall masks: sequential RANSAC on the whole point map for planes
//          facing up (within max_floor_tilt of -y), each with at least min_support points; the lowest
//          one (along up) is the floor, with a message saying so.
#pragma once

#include "pipeline/reconstruct/types.h"

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace simu::reconstruct {

struct RansacConfig {
  double threshold = 0.05;  // inlier residual (m)
  int iterations = 500;
  uint64_t seed = 1;
  int64_t min_inliers = 30;
  // Optional orientation constraint: |angle(n, axis)| <= max_angle_deg (sign-agnostic) when axis != 0.
  Vec3 axis = Vec3::Zero();
  double max_angle_deg = 90;
};

// RANSAC plane followed by a least-squares refit on the inliers (smallest principal axis). nullopt
// when no hypothesis reaches min_inliers. The returned normal's sign is arbitrary (orient it after).
std::optional<PlaneFit> ransac_plane(const Points& P, const RansacConfig& config);

// DBSCAN over unit line directions (sign-agnostic), distance = angle between the lines in degrees.
// Returns a cluster id per input (-1 = noise; with min_points = 1 there is no noise).
std::vector<int> dbscan_directions(const std::vector<Vec3>& dirs, double eps_deg, int min_points);

struct PlanesConfig {
  double floor_threshold = 0.05;   // m (paper)
  double wall_threshold = 0.01;    // m (paper)
  int iterations = 500;
  uint64_t seed = 1;
  double max_floor_tilt_deg = 60;  // floor normal within this of the camera's up (-y)
  int64_t min_support = 50;        // points a plane needs
  double dbscan_eps_deg = 10;
  double orthogonality_tol_deg = 10;
  int max_walls = 4;               // top walls by coverage (paper: four)
  int fallback_planes = 4;         // planes tried by the fallback
  double max_floor_snap = 0.10;    // m: a larger floor snap is refused (a mesh far below the floor is wrong, not the floor)
};

// One wall's input: its id and the points of its mask.
struct WallInput {
  std::string id;
  Points points;
};

struct NamedPlane {
  std::string id;
  PlaneFit plane;
};

struct PlanesResult {
  std::optional<NamedPlane> floor;
  std::vector<NamedPlane> walls;      // kept walls, rectified
  Vec3 up = -Vec3::UnitY();           // the chosen up (gravity = -up)
  std::string up_source;              // "walls", "floor", "mesh", "camera"
  bool fallback = false;              // floor from the point map (no floor mask)
  std::vector<std::string> messages;  // what was dropped or assumed, and why
};

// First pass: floor (floor_points may be empty: no floor mask), walls, rectification. `mesh_up` is the
// fallback up when neither walls nor floor decide it (e.g. the mean up axis of the lifted objects; zero
// = the camera's -y). `all_points` is the point map's valid points, used only for the fallback floor.
PlanesResult fit_planes(const Points& floor_points, const std::vector<WallInput>& walls, const Points& all_points,
                        const Vec3& mesh_up, const PlanesConfig& config = {});

// Second pass: moves the floor plane along `up` to the lowest vertex of `meshes` (world vertices of the
// fitted objects and bases that stand on the floor). Adds a floor (normal = up) when there is none.
// Returns the snap distance (m, positive = floor moved up); a snap longer than max_snap is refused (the
// floor stays, a message names the distance) and 0 returned.
double snap_floor_to_meshes(PlanesResult& planes, const std::vector<Points>& meshes, double max_snap = 0.10);

// Angle between two directions in degrees (sign-sensitive) and between two lines (sign-agnostic).
double angle_deg(const Vec3& a, const Vec3& b);
double line_angle_deg(const Vec3& a, const Vec3& b);

}  // namespace simu::reconstruct
