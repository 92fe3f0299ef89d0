// Shared pieces of the simuscene._core bindings (python/src/*.cpp): the error kinds raised into Python,
// array conversions (torch.Tensor and numpy in, numpy views and torch tensors out) and the per-file
// registration functions called by module.cpp.
#pragma once

#include <torch/extension.h>

#include <fmt/ranges.h>
#include <pybind11/numpy.h>
#include <pybind11/stl.h>

#include <Eigen/Core>

#include <optional>
#include <string>
#include <utility>

#include "common/cancel.h"
#include "common/error.h"
#include "pipeline/physics/probe.h"
#include "pipeline/resample/resampler.h"

#include <memory>
#include <mutex>

// torch dtypes in fmt messages ("Float", "Byte", ...).
template <>
struct fmt::formatter<c10::ScalarType> : fmt::formatter<std::string_view> {
  auto format(c10::ScalarType t, fmt::format_context& ctx) const {
    return fmt::formatter<std::string_view>::format(c10::toString(t), ctx);
  }
};

namespace simu::py_bind {

namespace py = pybind11;

// Which Python exception a binding error becomes (simuscene.errors): Error, ConfigError (also a
// ValueError), InputError (also a ValueError), MissingFileError (also a FileNotFoundError).
enum class ErrorKind { Generic, Config, Input, MissingFile };

// A simu::Error with the Python exception class it maps to (and the file, for MissingFileError).
class BindError : public Error {
 public:
  BindError(ErrorKind kind, const std::string& message, std::string hint = "", std::string filename = "")
      : Error(message, std::move(hint)), kind_(kind), filename_(std::move(filename)) {}
  ErrorKind kind() const { return kind_; }
  const std::string& filename() const { return filename_; }

 private:
  ErrorKind kind_;
  std::string filename_;
};

// Throws BindError(kind) with a fmt-formatted message.
template <typename... Args>
[[noreturn]] void raise(ErrorKind kind, fmt::format_string<Args...> f, Args&&... args) {
  throw BindError(kind, fmt::format(f, std::forward<Args>(args)...));
}
// MissingFileError naming `what` (e.g. "generator_weights") when path does not exist.
void require_file(const std::string& path, const std::string& what);
// Runs fn, turning any simu::Error it throws (not already a BindError or Cancelled) into `kind`.
template <typename F>
auto reraise_as(ErrorKind kind, F&& fn) -> decltype(fn()) {
  try {
    return fn();
  } catch (const BindError&) {
    throw;
  } catch (const Error& e) {
    if (dynamic_cast<const Cancelled*>(&e) != nullptr) throw;
    throw BindError(kind, e.what(), e.hint());
  }
}

// ---- Arrays in ----

// A torch.Tensor as it is (same storage), or anything numpy.asarray takes as a CPU tensor sharing the
// numpy buffer (torch.from_numpy semantics: no copy; a copy only for negative strides). InputError
// naming `what` otherwise.
at::Tensor as_tensor(py::handle obj, const std::string& what);
// An RGB image for the Stage-1 path: uint8 [H, W, 3] (converted as the programs convert 8-bit files,
// data::rgb_from_uint8) or float [H, W, 3] in [0, 1] (used as it is) -> [3, H, W] float32.
at::Tensor image_from_py(py::handle obj, const std::string& what);
// A mask [H, W]: bool -> {0, 1}; uint8 -> k / 255 as an 8-bit mask file (data::mask_from_uint8), except
// 0/1 masks, taken as {0, 1}; float in [0, 1] as it is. -> [H, W] float32.
at::Tensor mask_from_py(py::handle obj, const std::string& what);
// Intrinsics from a 3x3 matrix (numpy, torch, nested lists) or a dict {fx, fy, cx, cy}.
struct Intrinsics4 {
  double fx, fy, cx, cy;
};
Intrinsics4 intrinsics_from_py(py::handle obj, const std::string& what);

// ---- Arrays out ----

// A numpy view of an Eigen row-major matrix moved onto the heap and owned by the array (no copy).
py::array numpy_owning(Eigen::Matrix<double, -1, 3, Eigen::RowMajor>&& m);
py::array numpy_owning(Eigen::Matrix<int, -1, 3, Eigen::RowMajor>&& m);
// Small fixed-size values as fresh numpy arrays.
py::array numpy_vec(const Eigen::Vector3d& v);
py::array numpy_mat(const Eigen::Matrix3d& m);
Eigen::Vector3d vec3_from_py(py::handle obj, const std::string& what);
Eigen::Matrix3d mat3_from_py(py::handle obj, const std::string& what);
// nlohmann::json <-> Python objects (through the json module: exact doubles both ways).
py::object json_to_py(const std::string& dumped);
std::string py_to_json_text(py::handle obj);

// ---- Shared objects ----

// simuscene.Stage1: the loaded models, the lock every model call takes (one model, calls from many
// threads take turns), the default seed and preprocessing preset.
struct Stage1 {
  std::unique_ptr<resample::Resampler> resampler;
  std::mutex mutex;
  std::string banner;  // RANDOM WEIGHTS banner ("" with every weight file given)
};

// The folder where arrays handed in for the probe (meshes, masks, images, depth) are written once, named
// by a hash of their content (the probe reads files); removed at interpreter exit.
std::string temp_root();
void remove_temp_root();

// A path given as str / os.PathLike ("" for None).
std::string path_arg(py::handle obj);
// The probe config of a call: a YAML file ("" = the defaults) with "a.b=v" overrides from a dict;
// ConfigError naming the file and key; the hull cache as the program picks it.
physics::ProbeConfig probe_config_from(const std::string& path, const py::object& overrides);

// ---- Registration (one per source file) ----
void bind_io(py::module_& m);
void bind_scene(py::module_& m);
void bind_stage1(py::module_& m);
void bind_data(py::module_& m);

}  // namespace simu::py_bind
