// simuscene._core: the module, its exception translation, the log sink into Python's logging, the
// Ctrl-C hook, and the array conversions shared by the other binding files (bind.h).
#include <torch/csrc/autograd/python_variable.h>
#include <torch/csrc/utils/tensor_numpy.h>

#include <filesystem>
#include <memory>

#include "bind.h"
#include "common/cancel.h"
#include "common/log.h"
#include "data/pair_cache.h"
#include "data/preprocess.h"

namespace simu::py_bind {

std::string path_arg(py::handle obj) {
  if (obj.is_none()) return "";
  return py::str(py::module_::import("os").attr("fspath")(obj)).cast<std::string>();
}

void require_file(const std::string& path, const std::string& what) {
  if (!std::filesystem::exists(path))
    throw BindError(ErrorKind::MissingFile, fmt::format("{}: file not found ({})", path, what), "", path);
}

at::Tensor as_tensor(py::handle obj, const std::string& what) {
  if (obj.is_none()) raise(ErrorKind::Input, "{}: expected an array or a torch.Tensor, got None", what);
  if (THPVariable_Check(obj.ptr())) return THPVariable_Unpack(obj.ptr());
  py::module_ np = py::module_::import("numpy");
  py::object arr;
  try {
    arr = np.attr("asarray")(obj);
  } catch (py::error_already_set& e) {
    raise(ErrorKind::Input, "{}: not an array ({})", what, e.what());
  }
  if (py::str(arr.attr("dtype").attr("kind")).cast<std::string>() == "O")
    raise(ErrorKind::Input, "{}: not a numeric array (dtype object)", what);
  try {
    return torch::utils::tensor_from_numpy(arr.ptr(), /*warn_if_not_writeable=*/false);
  } catch (const std::exception&) {
    // Negative strides (a flipped view) or an odd byte order: one contiguous native copy.
    PyErr_Clear();
    py::object c = np.attr("ascontiguousarray")(arr, py::arg("dtype") = arr.attr("dtype").attr("newbyteorder")("="));
    try {
      return torch::utils::tensor_from_numpy(c.ptr(), false);
    } catch (const std::exception& e) {
      PyErr_Clear();
      raise(ErrorKind::Input, "{}: unsupported array ({})", what, e.what());
    }
  }
}

at::Tensor image_from_py(py::handle obj, const std::string& what) {
  const at::Tensor t = as_tensor(obj, what);
  if (t.dim() != 3 || t.size(2) != 3)
    raise(ErrorKind::Input, "{}: expected an RGB image [H, W, 3], got shape {}", what, t.sizes());
  if (t.scalar_type() == torch::kUInt8) return data::rgb_from_uint8(t.cpu(), what);
  if (!t.is_floating_point())
    raise(ErrorKind::Input, "{}: expected uint8 or float in [0, 1], got {}", what, t.scalar_type());
  const at::Tensor f = t.detach().to(torch::kCPU, torch::kFloat32);
  if (!torch::isfinite(f).all().item<bool>() || f.min().item<float>() < 0 || f.max().item<float>() > 1)
    raise(ErrorKind::Input, "{}: a float image must be finite and in [0, 1]", what);
  return f.permute({2, 0, 1}).contiguous();
}

at::Tensor mask_from_py(py::handle obj, const std::string& what) {
  const at::Tensor t = as_tensor(obj, what);
  if (t.dim() != 2) raise(ErrorKind::Input, "{}: expected a mask [H, W], got shape {}", what, t.sizes());
  const at::Tensor c = t.detach().cpu();
  if (c.scalar_type() == torch::kBool) return c.to(torch::kFloat32);
  if (c.scalar_type() == torch::kUInt8) {
    if (c.numel() > 0 && c.max().item<int>() <= 1) return c.to(torch::kFloat32);
    return data::mask_from_uint8(c, what);
  }
  if (!c.is_floating_point())
    raise(ErrorKind::Input, "{}: expected a bool, uint8 or float mask, got {} (a label map goes in as the one masks "
                            "argument)", what, c.scalar_type());
  const at::Tensor f = c.to(torch::kFloat32);
  if (!torch::isfinite(f).all().item<bool>() || (f.numel() > 0 && (f.min().item<float>() < 0 || f.max().item<float>() > 1)))
    raise(ErrorKind::Input, "{}: a float mask must be finite and in [0, 1]", what);
  return f.contiguous();
}

Intrinsics4 intrinsics_from_py(py::handle obj, const std::string& what) {
  Intrinsics4 k{};
  if (py::isinstance<py::dict>(obj)) {
    auto d = obj.cast<py::dict>();
    for (const char* key : {"fx", "fy", "cx", "cy"})
      if (!d.contains(key)) raise(ErrorKind::Input, "{}: dict without key '{}' (expected fx, fy, cx, cy)", what, key);
    k = {d["fx"].cast<double>(), d["fy"].cast<double>(), d["cx"].cast<double>(), d["cy"].cast<double>()};
  } else {
    const at::Tensor t = as_tensor(obj, what).detach().to(torch::kCPU, torch::kFloat64);
    if (t.dim() != 2 || t.size(0) != 3 || t.size(1) != 3)
      raise(ErrorKind::Input, "{}: expected a 3x3 matrix K or a dict {{fx, fy, cx, cy}}, got shape {}", what, t.sizes());
    const auto a = t.accessor<double, 2>();
    if (a[0][1] != 0 || a[1][0] != 0 || a[2][0] != 0 || a[2][1] != 0 || a[2][2] != 1)
      raise(ErrorKind::Input, "{}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]", what);
    k = {a[0][0], a[1][1], a[0][2], a[1][2]};
  }
  if (!(std::isfinite(k.fx) && std::isfinite(k.fy) && std::isfinite(k.cx) && std::isfinite(k.cy) && k.fx > 0 && k.fy > 0))
    raise(ErrorKind::Input, "{}: fx, fy must be positive and every value finite", what);
  return k;
}

namespace {
template <typename M>
py::array numpy_owning_impl(M&& m) {
  using Scalar = typename std::decay_t<M>::Scalar;
  auto* held = new std::decay_t<M>(std::move(m));
  py::capsule owner(held, [](void* p) { delete static_cast<std::decay_t<M>*>(p); });
  const auto rows = static_cast<py::ssize_t>(held->rows());
  return py::array_t<Scalar>({rows, py::ssize_t{3}},
                             {static_cast<py::ssize_t>(3 * sizeof(Scalar)), static_cast<py::ssize_t>(sizeof(Scalar))},
                             held->data(), owner);
}
}  // namespace

py::array numpy_owning(Eigen::Matrix<double, -1, 3, Eigen::RowMajor>&& m) { return numpy_owning_impl(std::move(m)); }
py::array numpy_owning(Eigen::Matrix<int, -1, 3, Eigen::RowMajor>&& m) { return numpy_owning_impl(std::move(m)); }

py::array numpy_vec(const Eigen::Vector3d& v) {
  py::array_t<double> a(3);
  for (int i = 0; i < 3; ++i) a.mutable_at(i) = v(i);
  return a;
}

py::array numpy_mat(const Eigen::Matrix3d& m) {
  py::array_t<double> a({3, 3});
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) a.mutable_at(r, c) = m(r, c);
  return a;
}

Eigen::Vector3d vec3_from_py(py::handle obj, const std::string& what) {
  const at::Tensor t = as_tensor(obj, what).detach().to(torch::kCPU, torch::kFloat64).contiguous();
  if (t.numel() != 3) raise(ErrorKind::Input, "{}: expected 3 numbers, got shape {}", what, t.sizes());
  const double* p = t.data_ptr<double>();
  return {p[0], p[1], p[2]};
}

Eigen::Matrix3d mat3_from_py(py::handle obj, const std::string& what) {
  const at::Tensor t = as_tensor(obj, what).detach().to(torch::kCPU, torch::kFloat64).contiguous();
  if (t.dim() != 2 || t.size(0) != 3 || t.size(1) != 3)
    raise(ErrorKind::Input, "{}: expected a 3x3 matrix, got shape {}", what, t.sizes());
  const double* p = t.data_ptr<double>();
  Eigen::Matrix3d m;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) m(r, c) = p[3 * r + c];
  return m;
}

py::object json_to_py(const std::string& dumped) { return py::module_::import("json").attr("loads")(dumped); }

std::string py_to_json_text(py::handle obj) {
  return py::module_::import("json").attr("dumps")(obj).cast<std::string>();
}

namespace {

// Whether the interpreter is shutting down (no more calls into Python).
bool finalizing() {
#if PY_VERSION_HEX >= 0x030D0000
  return Py_IsFinalizing() != 0;
#else
  return _Py_IsFinalizing() != 0;
#endif
}

// Raises the simuscene.errors class of `kind` with the message, the hint and the file.
void set_python_error(ErrorKind kind, const char* message, const std::string& hint, const std::string& filename) {
  static const char* names[] = {"Error", "ConfigError", "InputError", "MissingFileError"};
  try {
    py::object cls = py::module_::import("simuscene.errors").attr(names[static_cast<int>(kind)]);
    py::object exc = cls(message, hint, filename.empty() ? py::object(py::none()) : py::object(py::str(filename)));
    PyErr_SetObject(cls.ptr(), exc.ptr());
  } catch (py::error_already_set& e) {
    e.restore();  // the errors module itself failed: that error is more useful than nothing
  }
}

// Python's logging level of a toolkit level.
int python_level(log::Level l) {
  switch (l) {
    case log::Level::Debug: return 10;
    case log::Level::Info: return 20;
    case log::Level::Warn: return 30;
    default: return 40;
  }
}

void install_hooks() {
  // Log lines -> logging.getLogger("simuscene"), from whichever thread logs (GIL taken for the call).
  log::set_sink([](log::Level level, const std::string& line) {
    if (!Py_IsInitialized() || finalizing()) return;
    py::gil_scoped_acquire gil;
    try {
      py::module_::import("logging").attr("getLogger")("simuscene").attr("log")(python_level(level), line);
    } catch (py::error_already_set& e) {
      e.discard_as_unraisable("simuscene log sink");
    }
  });
  // Ctrl-C: the long loops call check_cancel(); a pending SIGINT (Python's handler set its flag while the
  // GIL was released) stops the call with Cancelled, raised into Python as KeyboardInterrupt.
  set_cancel_hook([] {
    if (!Py_IsInitialized() || finalizing()) return;
    py::gil_scoped_acquire gil;
    if (PyErr_CheckSignals() != 0) {
      PyErr_Clear();
      throw Cancelled("interrupted (KeyboardInterrupt)");
    }
  });
}

void remove_hooks() {
  log::set_sink(nullptr);
  set_cancel_hook(nullptr);
}

}  // namespace

}  // namespace simu::py_bind

PYBIND11_MODULE(_core, m) {
  namespace sb = simu::py_bind;
  m.doc() = "simuscene._core: the C++ toolkit's bindings (use the simuscene package; docs/python.md)";
  py::register_exception_translator([](std::exception_ptr p) {
    try {
      if (p) std::rethrow_exception(p);
    } catch (const simu::Cancelled& e) {
      PyErr_SetString(PyExc_KeyboardInterrupt, e.what());
    } catch (const sb::BindError& e) {
      sb::set_python_error(e.kind(), e.what(), e.hint(), e.filename());
    } catch (const simu::data::RecordRefused& e) {
      sb::set_python_error(sb::ErrorKind::Input, e.what(), e.hint(), "");
    } catch (const simu::Error& e) {
      sb::set_python_error(sb::ErrorKind::Generic, e.what(), e.hint(), "");
    }
  });
  sb::install_hooks();
  m.attr("source_dir") = SIMU_SOURCE_DIR;
  m.def("_shutdown", [] { sb::remove_hooks(); sb::remove_temp_root(); }, "Removes the log sink, the Ctrl-C hook and the temp folder (called at interpreter exit).");
  m.def(
      "set_log_level",
      [](const std::string& level) {
        simu::log::set_level(sb::reraise_as(sb::ErrorKind::Input, [&] { return simu::log::parse_level(level); }));
      },
      py::arg("level"),
      "Sets the toolkit's minimum level (debug, info, warn, error, off) before lines reach Python's logging.");
  m.def("_check_cancel", [] {
    py::gil_scoped_release release;
    simu::check_cancel();
  }, "Runs the Ctrl-C hook once (tests).");
  sb::bind_io(m);
  sb::bind_scene(m);
  sb::bind_stage1(m);
  sb::bind_data(m);
}
