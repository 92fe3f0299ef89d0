// simuscene.Scene (and its Camera, Plane, SceneObject, BaseBody) over physics::Scene, and the probe:
// simuscene._core.probe runs physics::run_probe, with an optional Stage1 as the in-process resampler
// (resample::make_probe_resample_fn, as the probe program's --resample).
#include <pybind11/stl_bind.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <unistd.h>

#include "bind.h"
#include "common/fs.h"
#include "common/log.h"
#include "data/depth_io.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/probe_batch.h"
#include "pipeline/physics/scene.h"
#include "pipeline/resample/default_model.h"
#include "pipeline/resample/probe_resampler.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#endif

PYBIND11_MAKE_OPAQUE(std::vector<simu::physics::SceneObject>)
PYBIND11_MAKE_OPAQUE(std::vector<simu::physics::Plane>)
PYBIND11_MAKE_OPAQUE(std::vector<simu::physics::BaseBody>)

namespace simu::py_bind {

namespace ph = simu::physics;
namespace stdfs = std::filesystem;

std::string temp_root() {
  static const std::string root = [] {
    const auto p = stdfs::temp_directory_path() / fmt::format("simuscene-{}", ::getpid());
    stdfs::create_directories(p);
    return p.string();
  }();
  return root;
}

// simu::fs::remove_tree, not std::filesystem::remove_all: the latter binds to libtorch.so's copy
// inside a Python process (torch loads it first, globally), which crashes on a non-empty folder.
// At interpreter exit a failure is reported on stderr, never thrown.
void remove_temp_root() {
  const auto p = stdfs::temp_directory_path() / fmt::format("simuscene-{}", ::getpid());
  try {
    simu::fs::remove_tree(p.string());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "simuscene: could not remove the temp folder: %s\n", e.what());
  }
}

namespace {

// FNV-1a 64 of a tensor's shape, dtype and bytes (content-addressed temp files).
std::string content_key(const at::Tensor& t) {
  const at::Tensor c = t.contiguous().cpu();
  uint64_t h = 1469598103934665603ull;
  auto mix = [&](const void* p, size_t n) {
    const auto* b = static_cast<const uint8_t*>(p);
    for (size_t i = 0; i < n; ++i) h = (h ^ b[i]) * 1099511628211ull;
  };
  for (auto s : c.sizes()) mix(&s, sizeof(s));
  const int dt = static_cast<int>(c.scalar_type());
  mix(&dt, sizeof(dt));
  mix(c.data_ptr(), c.nbytes());
  return fmt::format("{:016x}", h);
}

// A mesh from vertices [n, 3] and faces [m, 3] (numpy or torch), checked, naming `what`.
ph::Mesh mesh_from_py(py::handle vertices, py::handle faces, const std::string& what) {
  const at::Tensor v = as_tensor(vertices, what + " vertices").detach().to(torch::kCPU, torch::kFloat64).contiguous();
  const at::Tensor f = as_tensor(faces, what + " faces").detach().cpu();
  if (v.dim() != 2 || v.size(1) != 3 || v.size(0) < 3)
    raise(ErrorKind::Input, "{}: vertices must be [n, 3] with n >= 3, got {}", what, v.sizes());
  if (f.dim() != 2 || f.size(1) != 3 || f.size(0) < 1 || f.is_floating_point())
    raise(ErrorKind::Input, "{}: faces must be integer [m, 3] with m >= 1, got {} {}", what, f.sizes(), f.scalar_type());
  if (!torch::isfinite(v).all().item<bool>()) raise(ErrorKind::Input, "{}: vertices are not all finite", what);
  const at::Tensor fi = f.to(torch::kInt64).contiguous();
  if (fi.min().item<int64_t>() < 0 || fi.max().item<int64_t>() >= v.size(0))
    raise(ErrorKind::Input, "{}: a face index is outside [0, {})", what, v.size(0));
  ph::Mesh m;
  m.V.resize(v.size(0), 3);
  m.F.resize(fi.size(0), 3);
  std::memcpy(m.V.data(), v.data_ptr<double>(), sizeof(double) * v.numel());
  const int64_t* fp = fi.data_ptr<int64_t>();
  for (int64_t i = 0; i < fi.numel(); ++i) m.F.data()[i] = static_cast<int>(fp[i]);
  return m;
}

// Writes arrays the probe reads as files into the temp root once (content-addressed); returns the path.
std::string mesh_file(py::handle vertices, py::handle faces, const std::string& what) {
  const ph::Mesh m = mesh_from_py(vertices, faces, what);
  at::Tensor v = torch::from_blob(const_cast<double*>(m.V.data()), {m.V.rows(), 3}, torch::kFloat64);
  at::Tensor f = torch::from_blob(const_cast<int*>(m.F.data()), {m.F.rows(), 3}, torch::kInt32);
  const std::string path = temp_root() + "/mesh_" + content_key(torch::cat({v.flatten(), f.flatten().to(torch::kFloat64)})) + ".obj";
  if (!stdfs::exists(path)) ph::write_mesh(m, path);
  return path;
}

std::string png_file(const at::Tensor& pixels, const std::string& kind) {
#ifdef SIMU_HAVE_OPENCV
  const at::Tensor c = pixels.contiguous().cpu();
  const std::string path = temp_root() + "/" + kind + "_" + content_key(c) + ".png";
  if (!stdfs::exists(path)) {
    cv::Mat m;
    if (c.dim() == 2) {
      m = cv::Mat(static_cast<int>(c.size(0)), static_cast<int>(c.size(1)), CV_8UC1, c.data_ptr());
    } else {
      cv::cvtColor(cv::Mat(static_cast<int>(c.size(0)), static_cast<int>(c.size(1)), CV_8UC3, c.data_ptr()), m,
                   cv::COLOR_RGB2BGR);
    }
    const std::string tmp = path + fmt::format(".tmp-{}", ::getpid());
    if (!cv::imwrite(tmp + ".png", m)) raise(ErrorKind::Generic, "{}: cannot write", path);
    stdfs::rename(tmp + ".png", path);
  }
  return path;
#else
  (void)pixels;
  raise(ErrorKind::Generic, "{} arrays need OpenCV (built with SIMU_WITH_OPENCV=OFF): pass a file path", kind);
#endif
}

// A mask given as an array -> an 8-bit PNG (255 = object) in the temp root.
std::string mask_file(py::handle obj, const std::string& what) {
  const at::Tensor m = mask_from_py(obj, what);
  return png_file((m > 0).to(torch::kUInt8) * 255, "mask");
}

ph::PoseDof dof_from(const std::string& s, const std::string& what) {
  const auto d = ph::parse_pose_dof(s == "point" ? "point_anchored" : s == "line" ? "line_anchored" : s);
  if (!d) raise(ErrorKind::Input, "{}: dof must be free, point (point_anchored) or line (line_anchored), got '{}'", what, s);
  return *d;
}

// Reads a picture written by the probe as an RGB uint8 array [H, W, 3].
py::object read_picture(const std::string& path) {
#ifdef SIMU_HAVE_OPENCV
  cv::Mat bgr = cv::imread(path, cv::IMREAD_COLOR);
  if (bgr.empty()) return py::none();
  cv::Mat rgb;
  cv::cvtColor(bgr, rgb, cv::COLOR_BGR2RGB);
  py::array_t<uint8_t> a({rgb.rows, rgb.cols, 3});
  for (int r = 0; r < rgb.rows; ++r) std::memcpy(a.mutable_data(r, 0, 0), rgb.ptr<uint8_t>(r), static_cast<size_t>(rgb.cols) * 3);
  return a;
#else
  (void)path;
  return py::none();
#endif
}

// What simuscene._core.probe returns (the simuscene.ProbeResult wrapper reads it).
struct ProbeRun {
  ph::ProbeResult result;
  std::string out_dir;
  double settle_time = 0;  // the config's metrics_settle_time (the metrics table's header)
};

}  // namespace

ph::ProbeConfig probe_config_from(const std::string& path, const py::object& overrides) {
  std::vector<std::string> sets;
  if (!overrides.is_none()) {
    if (!py::isinstance<py::dict>(overrides))
      raise(ErrorKind::Config, "probe overrides: expected a dict {{'physics.timestep': 0.002, ...}}");
    for (auto item : overrides.cast<py::dict>()) {
      const std::string key = py::str(item.first).cast<std::string>();
      py::handle v = item.second;
      std::string value;
      if (py::isinstance<py::bool_>(v)) value = v.cast<bool>() ? "true" : "false";
      else if (py::isinstance<py::str>(v)) value = v.cast<std::string>();
      else value = py::repr(v).cast<std::string>();
      sets.push_back(key + "=" + value);
    }
  }
  if (!path.empty()) require_file(path, "probe config");
  auto cfg = reraise_as(ErrorKind::Config, [&] { return ph::ProbeConfig::load(path, sets); });
  if (cfg.collision.cache_dir.empty()) {
    if (const char* env = std::getenv("SIMU_HULL_CACHE")) cfg.collision.cache_dir = env;
    else if (const char* home = std::getenv("HOME")) cfg.collision.cache_dir = std::string(home) + "/.cache/simuscene/hulls";
  }
  return cfg;
}

void bind_scene(py::module_& m) {
  py::bind_vector<std::vector<ph::SceneObject>>(m, "SceneObjectList", "The objects of a Scene (a list-like view).");
  py::bind_vector<std::vector<ph::Plane>>(m, "PlaneList", "The walls of a Scene (a list-like view).");
  py::bind_vector<std::vector<ph::BaseBody>>(m, "BaseBodyList", "The fixed colliders of a Scene (a list-like view).");

  py::class_<ph::Camera>(m, "Camera", "Pinhole camera: intrinsics (pixels), image size, pose in the world "
                                      "(p_world = R_world_cam @ p_cam + t_world_cam, OpenCV camera frame).")
      .def(py::init([](double fx, double fy, double cx, double cy, int width, int height, py::object R, py::object t) {
             ph::Camera c;
             c.fx = fx, c.fy = fy, c.cx = cx, c.cy = cy, c.width = width, c.height = height;
             if (!R.is_none()) c.R_world_cam = mat3_from_py(R, "Camera R_world_cam");
             if (!t.is_none()) c.t_world_cam = vec3_from_py(t, "Camera t_world_cam");
             return c;
           }),
           py::arg("fx") = 0.0, py::arg("fy") = 0.0, py::arg("cx") = 0.0, py::arg("cy") = 0.0, py::arg("width") = 0,
           py::arg("height") = 0, py::arg("R_world_cam") = py::none(), py::arg("t_world_cam") = py::none())
      .def_readwrite("fx", &ph::Camera::fx)
      .def_readwrite("fy", &ph::Camera::fy)
      .def_readwrite("cx", &ph::Camera::cx)
      .def_readwrite("cy", &ph::Camera::cy)
      .def_readwrite("width", &ph::Camera::width)
      .def_readwrite("height", &ph::Camera::height)
      .def_property("R_world_cam", [](const ph::Camera& c) { return numpy_mat(c.R_world_cam); },
                    [](ph::Camera& c, py::object v) { c.R_world_cam = mat3_from_py(v, "Camera R_world_cam"); })
      .def_property("t_world_cam", [](const ph::Camera& c) { return numpy_vec(c.t_world_cam); },
                    [](ph::Camera& c, py::object v) { c.t_world_cam = vec3_from_py(v, "Camera t_world_cam"); })
      .def("valid", &ph::Camera::valid, "True when the intrinsics and the size are usable.");

  py::class_<ph::Plane>(m, "Plane", "An infinite plane through `point` whose `normal` points into the room.")
      .def(py::init([](const std::string& id, py::object point, py::object normal) {
             ph::Plane p;
             p.id = id;
             p.point = vec3_from_py(point, "Plane point");
             p.normal = vec3_from_py(normal, "Plane normal").normalized();
             return p;
           }),
           py::arg("id"), py::arg("point"), py::arg("normal"))
      .def_readwrite("id", &ph::Plane::id)
      .def_property("point", [](const ph::Plane& p) { return numpy_vec(p.point); },
                    [](ph::Plane& p, py::object v) { p.point = vec3_from_py(v, "Plane point"); })
      .def_property("normal", [](const ph::Plane& p) { return numpy_vec(p.normal); },
                    [](ph::Plane& p, py::object v) { p.normal = vec3_from_py(v, "Plane normal").normalized(); });

  // Pose and scale setters shared by objects and bases.
  auto scale3 = [](py::handle v, const std::string& what) -> Eigen::Vector3d {
    if (py::isinstance<py::float_>(v) || py::isinstance<py::int_>(v)) return Eigen::Vector3d::Constant(v.cast<double>());
    return vec3_from_py(v, what);
  };

  py::class_<ph::BaseBody>(m, "BaseBody", "A fixed collider (table, shelf): a mesh placed like an object, never moved.")
      .def(py::init([scale3](const std::string& id, py::object mesh, py::object vertices, py::object faces, py::object R,
                             py::object t, py::object scale) {
             ph::BaseBody b;
             b.id = id;
             b.mesh_path = vertices.is_none() ? path_arg(mesh) : mesh_file(vertices, faces, "base '" + id + "'");
             if (b.mesh_path.empty()) raise(ErrorKind::Input, "base '{}': give mesh=PATH or vertices= and faces=", id);
             if (vertices.is_none()) require_file(b.mesh_path, "base '" + id + "' mesh");
             b.R = R.is_none() ? Eigen::Matrix3d::Identity() : mat3_from_py(R, "base '" + id + "' R");
             b.t = t.is_none() ? Eigen::Vector3d::Zero() : vec3_from_py(t, "base '" + id + "' t");
             b.scale = scale3(scale, "base '" + id + "' scale");
             return b;
           }),
           py::arg("id"), py::arg("mesh") = py::none(), py::kw_only(), py::arg("vertices") = py::none(),
           py::arg("faces") = py::none(), py::arg("R") = py::none(), py::arg("t") = py::none(), py::arg("scale") = 1.0)
      .def_readwrite("id", &ph::BaseBody::id)
      .def_readwrite("mesh", &ph::BaseBody::mesh_path)
      .def_property("R", [](const ph::BaseBody& b) { return numpy_mat(b.R); },
                    [](ph::BaseBody& b, py::object v) { b.R = mat3_from_py(v, "base R"); })
      .def_property("t", [](const ph::BaseBody& b) { return numpy_vec(b.t); },
                    [](ph::BaseBody& b, py::object v) { b.t = vec3_from_py(v, "base t"); })
      .def_property("scale", [](const ph::BaseBody& b) { return numpy_vec(b.scale); },
                    [scale3](ph::BaseBody& b, py::object v) { b.scale = scale3(v, "base scale"); });

  py::class_<ph::SceneObject>(m, "SceneObject",
                              "One object: a canonical mesh (AABB-centred, longest side 1) placed by "
                              "world = R @ (scale * c) + t; dof free | point | line (anchored to a wall).")
      .def(py::init([scale3](const std::string& id, py::object mesh, py::object vertices, py::object faces, py::object R,
                             py::object t, py::object scale, const std::string& dof, const std::string& wall,
                             const std::string& label, py::object mask, double density) {
             ph::SceneObject o;
             const std::string what = "object '" + id + "'";
             o.id = id;
             o.label = label;
             o.mesh_path = vertices.is_none() ? path_arg(mesh) : mesh_file(vertices, faces, what);
             if (o.mesh_path.empty()) raise(ErrorKind::Input, "{}: give mesh=PATH or vertices= and faces=", what);
             if (vertices.is_none()) require_file(o.mesh_path, what + " mesh");
             o.R = R.is_none() ? Eigen::Matrix3d::Identity() : mat3_from_py(R, what + " R");
             o.t = t.is_none() ? Eigen::Vector3d::Zero() : vec3_from_py(t, what + " t");
             o.scale = scale3(scale, what + " scale");
             o.dof = dof_from(dof, what);
             o.wall_id = wall;
             if (!mask.is_none()) {
               if (py::isinstance<py::str>(mask) || py::hasattr(mask, "__fspath__")) {
                 o.mask_path = path_arg(mask);
                 require_file(o.mask_path, what + " mask");
               } else {
                 o.mask_path = mask_file(mask, what + " mask");
               }
             }
             if (!(density > 0)) raise(ErrorKind::Input, "{}: density must be positive, got {}", what, density);
             o.density = density;
             return o;
           }),
           py::arg("id"), py::arg("mesh") = py::none(), py::kw_only(), py::arg("vertices") = py::none(),
           py::arg("faces") = py::none(), py::arg("R") = py::none(), py::arg("t") = py::none(), py::arg("scale") = 1.0,
           py::arg("dof") = "free", py::arg("wall") = "", py::arg("label") = "", py::arg("mask") = py::none(),
           py::arg("density") = 500.0)
      .def_readwrite("id", &ph::SceneObject::id)
      .def_readwrite("label", &ph::SceneObject::label)
      .def_readwrite("mesh", &ph::SceneObject::mesh_path, "Path of the canonical mesh (arrays handed in are written to "
                                                          "a content-addressed temp file).")
      .def_readwrite("mask", &ph::SceneObject::mask_path)
      .def_readwrite("wall", &ph::SceneObject::wall_id)
      .def_readwrite("density", &ph::SceneObject::density)
      .def_readonly("error", &ph::SceneObject::error, "Why the entry is unusable ('' when it is fine).")
      .def_property("dof", [](const ph::SceneObject& o) { return std::string(ph::to_string(o.dof)); },
                    [](ph::SceneObject& o, const std::string& s) { o.dof = dof_from(s, "object '" + o.id + "'"); })
      .def_property("R", [](const ph::SceneObject& o) { return numpy_mat(o.R); },
                    [](ph::SceneObject& o, py::object v) { o.R = mat3_from_py(v, "object '" + o.id + "' R"); })
      .def_property("t", [](const ph::SceneObject& o) { return numpy_vec(o.t); },
                    [](ph::SceneObject& o, py::object v) { o.t = vec3_from_py(v, "object '" + o.id + "' t"); })
      .def_property("scale", [](const ph::SceneObject& o) { return numpy_vec(o.scale); },
                    [scale3](ph::SceneObject& o, py::object v) { o.scale = scale3(v, "object '" + o.id + "' scale"); })
      .def("set_mesh", [](ph::SceneObject& o, py::object vertices, py::object faces) {
             o.mesh_path = mesh_file(vertices, faces, "object '" + o.id + "'");
           }, py::arg("vertices"), py::arg("faces"), "Uses arrays as the canonical mesh (written once to a temp file).");

  py::class_<ph::Scene>(m, "Scene", "A scene for the probe (docs/scene_format.md): camera, gravity, floor, walls, "
                                    "fixed bases, objects. Scene.load / save read and write scene.json.")
      .def(py::init([](std::optional<ph::Camera> camera, py::object gravity, double g, std::optional<ph::Plane> floor,
                       py::object image, py::object depth) {
             ph::Scene s;
             if (camera) s.camera = *camera;
             s.gravity = vec3_from_py(gravity, "Scene gravity");
             if (!(s.gravity.norm() > 0)) raise(ErrorKind::Input, "Scene gravity: must be a non-zero direction");
             s.gravity.normalize();
             s.gravity_magnitude = g;
             s.floor = floor;
             if (!image.is_none()) {
               if (py::isinstance<py::str>(image) || py::hasattr(image, "__fspath__")) {
                 s.image_path = path_arg(image);
                 require_file(s.image_path, "scene image");
               } else {
                 const at::Tensor t = as_tensor(image, "scene image");
                 if (t.dim() != 3 || t.size(2) != 3 || t.scalar_type() != torch::kUInt8)
                   raise(ErrorKind::Input, "scene image: expected uint8 [H, W, 3], got {} {}", t.sizes(), t.scalar_type());
                 s.image_path = png_file(t, "image");
               }
             }
             if (!depth.is_none()) {
               if (py::isinstance<py::str>(depth) || py::hasattr(depth, "__fspath__")) {
                 s.depth_path = path_arg(depth);
                 require_file(s.depth_path, "scene depth");
               } else {
                 const at::Tensor t = as_tensor(depth, "scene depth").detach().to(torch::kCPU, torch::kFloat32).contiguous();
                 if (!(t.dim() == 2 || (t.dim() == 3 && t.size(2) == 3)))
                   raise(ErrorKind::Input, "scene depth: expected depth [H, W] (m) or a point map [H, W, 3], got {}", t.sizes());
                 s.depth_path = temp_root() + "/depth_" + content_key(t) + ".npy";
                 if (!stdfs::exists(s.depth_path)) data::write_npy(s.depth_path, t);
               }
             }
             return s;
           }),
           py::arg("camera") = py::none(), py::arg("gravity") = std::vector<double>{0, 0, -1},
           py::arg("gravity_magnitude") = 9.81, py::arg("floor") = py::none(), py::arg("image") = py::none(),
           py::arg("depth") = py::none())
      .def_static("load", [](py::object path) {
             const std::string p = path_arg(path);
             require_file(p, "scene");
             py::gil_scoped_release release;
             return reraise_as(ErrorKind::Input, [&] { return ph::load_scene(p); });
           }, py::arg("path"), "Reads a scene.json (paths inside resolve against its folder).")
      .def("save", [](const ph::Scene& s, py::object path) {
             const std::string p = path_arg(path);
             py::gil_scoped_release release;
             ph::save_scene(s, p);
           }, py::arg("path"), "Writes scene.json atomically (paths below its folder become relative).")
      .def_static("from_dict", [](py::object d, py::object base_dir) {
             const std::string text = py_to_json_text(d);
             return reraise_as(ErrorKind::Input, [&] {
               return ph::scene_from_json(nlohmann::json::parse(text), path_arg(base_dir), "scene (dict)");
             });
           }, py::arg("data"), py::arg("base_dir") = ".", "A scene from the scene.json structure as Python objects.")
      .def("to_dict", [](const ph::Scene& s, py::object out_dir) {
             return json_to_py(ph::scene_to_json(s, path_arg(out_dir)).dump());
           }, py::arg("out_dir") = ".", "The scene.json structure (paths relative to out_dir when below it).")
      .def_readwrite("camera", &ph::Scene::camera)
      .def_readwrite("floor", &ph::Scene::floor)
      .def_readwrite("objects", &ph::Scene::objects)
      .def_readwrite("walls", &ph::Scene::walls)
      .def_readwrite("bases", &ph::Scene::bases)
      .def_readwrite("image", &ph::Scene::image_path)
      .def_readwrite("depth", &ph::Scene::depth_path)
      .def_readonly("path", &ph::Scene::path)
      .def_readwrite("gravity_magnitude", &ph::Scene::gravity_magnitude)
      .def_property("gravity", [](const ph::Scene& s) { return numpy_vec(s.gravity); },
                    [](ph::Scene& s, py::object v) { s.gravity = vec3_from_py(v, "Scene gravity").normalized(); })
      .def("find_object", &ph::Scene::find_object, py::arg("id"), "Index of the object with this id, or -1.");

  py::class_<ProbeRun, std::shared_ptr<ProbeRun>>(m, "ProbeRun", "The raw outcome of _core.probe (see simuscene.ProbeResult).")
      .def_property_readonly("report_json", [](const ProbeRun& r) { return ph::report_json(r.result).dump(); })
      .def_property_readonly("summary", [](const ProbeRun& r) { return ph::probe_summary(r.result); })
      .def_property_readonly("scene", [](const ProbeRun& r) { return r.result.scene; })
      .def_property_readonly("mjcf", [](const ProbeRun& r) { return r.result.mjcf; })
      .def_property_readonly("out_dir", [](const ProbeRun& r) { return r.out_dir; })
      .def_property_readonly("metrics_table", [](const ProbeRun& r) {
             return ph::format_headline(r.result.before, r.result.after, r.settle_time);
           })
      .def_property_readonly("headline_before", [](const ProbeRun& r) { return json_to_py(ph::headline_json(r.result.before).dump()); })
      .def_property_readonly("headline_after", [](const ProbeRun& r) { return json_to_py(ph::headline_json(r.result.after).dump()); })
      .def("mesh", [](const ProbeRun& r, int i) -> py::object {
             if (i < 0 || i >= static_cast<int>(r.result.meshes.size())) throw py::index_error("object index out of range");
             ph::Mesh m = r.result.meshes[i];
             if (m.empty()) return py::none();
             return py::make_tuple(numpy_owning(std::move(m.V)), numpy_owning(std::move(m.F)));
           }, py::arg("index"))
      .def_property_readonly("pictures", [](const ProbeRun& r) {
             py::dict d;
             for (const auto& p : r.result.pictures) d[py::str(stdfs::path(p).stem().string())] = read_picture(p);
             if (!r.out_dir.empty() && stdfs::exists(r.out_dir + "/overlay.png"))
               d["overlay"] = read_picture(r.out_dir + "/overlay.png");
             return d;
           });

  m.def(
      "probe",
      [](const ph::Scene& scene, py::object config, py::object overrides, py::object out, bool overwrite,
         std::shared_ptr<Stage1> stage1, uint64_t seed, const std::string& preprocess) {
        const std::string out_dir = path_arg(out);
        ph::ProbeConfig cfg = probe_config_from(path_arg(config), overrides);
        cfg.overwrite = overwrite;
        for (const auto& o : scene.objects)
          if (!o.error.empty()) log::warn("object '{}': {}", o.id, o.error);
        const auto preset = reraise_as(ErrorKind::Config, [&] {
          return stage1 ? simu::resample::preprocess_choice(preprocess, stage1->resampler->config())
                        : data::PreprocessConfig::preset_named(preprocess == "model" ? "released" : preprocess);
        });
        auto run = std::make_shared<ProbeRun>();
        run->settle_time = cfg.metrics_settle_time;
        run->out_dir = out_dir.empty() ? "" : stdfs::absolute(out_dir).lexically_normal().string();
        py::gil_scoped_release release;
        ph::ResampleFn fn;
        if (stage1) {
          if (!stage1->resampler->embedder())
            raise(ErrorKind::Config, "probe: the Stage1 resampler has no condition embedder (embedder_config)");
          resample::ProbeResamplerOptions ropt;
          ropt.seed = seed;
          ropt.preprocess = preset;
          auto inner = resample::make_probe_resample_fn(*stage1->resampler, scene, ropt);
          fn = [inner, stage1](const std::vector<ph::ProbeResampleRequest>& rq) {
            std::lock_guard<std::mutex> lock(stage1->mutex);
            return inner(rq);
          };
        }
        auto progress = [](int done, int total, const std::string& id, const std::string& status) {
          log::info("[{}/{}] {}: {}", done, total, id, status);
          check_cancel();
        };
        run->result = ph::run_probe(scene, cfg, out_dir, fn, progress);
        return run;
      },
      py::arg("scene"), py::kw_only(), py::arg("config") = py::none(), py::arg("overrides") = py::none(),
      py::arg("out") = py::none(), py::arg("overwrite") = false, py::arg("resampler") = nullptr, py::arg("seed") = 0,
      py::arg("preprocess") = "model", "Runs the physics probe (simuscene.probe wraps it).");
}

}  // namespace simu::py_bind
