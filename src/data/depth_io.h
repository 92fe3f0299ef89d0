// Readers for the geometry inputs of `lift` and the probe: NumPy .npy arrays, depth maps (npy, 16-bit
// PNG in millimetres, OpenEXR), point maps (MoGe's npy in the OpenCV camera), camera intrinsics (JSON),
// label images; and the depth -> point-map unprojection. Every reader checks what it reads against
// what the file declares before allocating, and throws simu::Error naming the file and what was
// expected.
//
//   auto K = simu::data::read_intrinsics_json("K.json");          // {"fx":..,"fy":..,"cx":..,"cy":..}
//   auto z = simu::data::read_depth("depth.png");                 // [H, W] metres, NaN = invalid
//   auto p = simu::data::unproject_depth(z, K);                   // [H, W, 3] OpenCV camera points
//   auto q = simu::data::read_pointmap("moge_points.npy");        // [H, W, 3] as MoGe wrote it
//
// Camera frame of every point map here: OpenCV (x right, y down, z forward), invalid = NaN or +-inf.
// (data::pointmap_from_opencv_camera turns one into the PyTorch3D frame SAM 3D reads.)
#pragma once

#include <torch/torch.h>

#include <nlohmann/json.hpp>

#include <cstdint>
#include <string>
#include <vector>

namespace simu::data {

// ---- NumPy .npy (format versions 1.0, 2.0, 3.0) ----

// What a .npy header declares.
struct NpyHeader {
  std::string descr;            // e.g. "<f4"
  bool fortran_order = false;
  std::vector<int64_t> shape;   // () for a scalar
  uint64_t data_offset = 0;     // bytes before the array data
  int64_t item_size = 0;        // bytes per element
};

// Parses and checks the header of `path`: magic, version, a dict with exactly descr / fortran_order /
// shape, a supported dtype (b1, i1, u1, i2, u2, i4, i8, f2, f4, f8; little-, big- or not-applicable
// byte order), non-negative dimensions whose byte count fits in 64 bits and equals the file's size
// after the header. Throws simu::Error naming the file and what was expected.
NpyHeader read_npy_header(const std::string& path);

// Reads a whole .npy array into a C-contiguous CPU tensor of the matching dtype (u2 -> int32, the
// other dtypes as themselves; big-endian data is byte-swapped; Fortran-ordered data is transposed
// into C order). The data size is checked against the file length before anything is allocated.
torch::Tensor read_npy(const std::string& path);

// Writes a CPU tensor (bool, uint8, int8, int16, int32, int64, float16, float32, float64) as a
// little-endian C-order .npy (version 1.0), atomically. numpy.load opens it.
void write_npy(const std::string& path, const torch::Tensor& tensor);

// ---- Camera intrinsics ----

struct Intrinsics {
  double fx = 0, fy = 0, cx = 0, cy = 0;  // pixels (OpenCV: pixel (c, r) has its centre at (c, r))
};

// Accepted JSON layouts (numbers in pixels):
//   {"fx": 500, "fy": 500, "cx": 320, "cy": 240}                       (extra keys such as width/height ok)
//   {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]}   (also "intrinsics" / "camera_matrix", or 9 numbers)
//   [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]          (the bare matrix)
// Checks: finite, fx, fy > 0, a K matrix with zero skew and last row (0, 0, 1).
Intrinsics intrinsics_from_json(const nlohmann::json& j, const std::string& what);
Intrinsics read_intrinsics_json(const std::string& path);

// ---- Depth and point maps ----

// Depth map [H, W] float32 in metres, NaN where invalid (<= 0, NaN or inf in the file).
//   .npy: float (metres) or uint16 (millimetres); shape [H, W], [H, W, 1] or [1, H, W];
//   .png/.tif: 16-bit single channel, millimetres (an 8-bit PNG is refused: no depth fits in 8 bits);
//   .exr: float, metres (first channel); needs an OpenCV with OpenEXR, enabled here through
//         OPENCV_IO_ENABLE_OPENEXR=1 (set for this process unless the user set it).
torch::Tensor read_depth(const std::string& path);
// Depth values [H, W] (metres, any float dtype) as read_depth returns them: float32, every non-positive
// or non-finite value made NaN.
torch::Tensor clean_depth(torch::Tensor z);

// Point map [H, W, 3] float32 from an .npy of shape [H, W, 3] (MoGe's `points`, float32 or float64),
// read as it is: OpenCV camera, +-inf / NaN kept (they mark invalid points).
torch::Tensor read_pointmap(const std::string& path);

// Unprojects depth [H, W] (metres, NaN = invalid) through K into OpenCV camera points [H, W, 3]:
// x = (u - cx) / fx * z, y = (v - cy) / fy * z, z = z at pixel (u, v) = (column, row). NaN where invalid.
torch::Tensor unproject_depth(const torch::Tensor& depth, const Intrinsics& K);

// Pinhole intrinsics fitted to a point map [H, W, 3] (OpenCV camera) by least squares on its valid
// points (z > 0): u = fx * x / z + cx, v = fy * y / z + cy for pixel (u, v) = (column, row). For a point
// map without a K file (MoGe's points are pinhole). Throws when fewer than 16 valid points or no spread.
Intrinsics estimate_intrinsics(const torch::Tensor& pointmap, const std::string& what);

// A label image [H, W] int64 (8- or 16-bit single-channel PNG; 0 = background, k = object k).
torch::Tensor read_label_image(const std::string& path);

}  // namespace simu::data
