// simuscene.Stage1 over resample::Resampler (models loaded once, the same flags-to-config path as the
// lift program: resample::finish_model_options), its lift / sample / embed calls and LoRA switches, and
// simuscene._core.reconstruct over reconstruct::reconstruct.
#include <filesystem>
#include <fstream>

#include "bind.h"
#include "common/log.h"
#include "lora/lora.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/scene.h"
#include "pipeline/resample/default_model.h"
#include "pipeline/resample/lift.h"
#include "pipeline/resample/model_options.h"
#include "pipeline/reconstruct/run.h"

namespace simu::py_bind {

namespace rs = simu::resample;
namespace stdfs = std::filesystem;

namespace {

// One sampled shape with its scene pose (when it came from a lift) and the occupancy grid's side.
struct Shape {
  rs::ResampledShape s;
  bool has_scene_pose = false;
  rs::ScenePose pose;
  int64_t resolution = 64;
};
using ShapePtr = std::shared_ptr<Shape>;

// A lift: its inputs (kept: the point map handed in is this tensor), result and what write() records.
struct LiftRun {
  rs::LiftInputs inputs;
  rs::LiftResult result;
  int64_t resolution = 64;
  nlohmann::json run_info;
  std::string banner;
  std::vector<std::vector<ShapePtr>> shapes;  // [object][sample]
};
using LiftRunPtr = std::shared_ptr<LiftRun>;

struct LiftedView {
  LiftRunPtr run;
  size_t index;
  const rs::LiftedObject& o() const { return run->result.objects[index]; }
};

py::object pose_dict(const Shape& sh) {
  py::dict sam;
  const auto& s = sh.s;
  py::array_t<double> q(4);
  for (int i = 0; i < 4; ++i) q.mutable_at(i) = s.quaternion(i);
  sam["rotation_wxyz"] = q;
  sam["rotation"] = numpy_mat(s.rotation);
  sam["translation"] = numpy_vec(s.translation);
  sam["scale"] = numpy_vec(s.scale);
  sam["scale_canonical"] = numpy_vec(s.scale_canonical);
  sam["translation_canonical"] = numpy_vec(s.translation_canonical);
  return sam;
}

// The masks argument of lift: a label map [H, W] (ids label_<k>), a dict {id: mask} or a list of masks
// (ids object_<i>); per-object problems become that object's error as in the program.
std::vector<rs::LiftObjectInput> objects_from_py(py::handle masks, py::handle crop_masks) {
  std::vector<rs::LiftObjectInput> out;
  auto add = [&](const std::string& id, py::handle mask) {
    rs::LiftObjectInput o;
    o.id = id;
    try {
      o.mask = mask_from_py(mask, "object '" + id + "' mask");
    } catch (const BindError& e) {
      o.error = e.what();
    }
    out.push_back(std::move(o));
  };
  if (py::isinstance<py::dict>(masks)) {
    for (auto item : masks.cast<py::dict>()) add(py::str(item.first).cast<std::string>(), item.second);
  } else if (py::isinstance<py::list>(masks) || py::isinstance<py::tuple>(masks)) {
    int i = 0;
    for (auto mk : masks) add(fmt::format("object_{}", i++), mk);
  } else {
    const at::Tensor labels = as_tensor(masks, "masks").detach().cpu();
    if (labels.dim() != 2 || labels.is_floating_point() || labels.scalar_type() == torch::kBool)
      raise(ErrorKind::Input, "masks: a single array is a label map [H, W] of integers (0 = background, k = object "
                              "k), got {} {}; give one mask per object as a dict or a list", labels.sizes(), labels.scalar_type());
    const at::Tensor l = labels.to(torch::kInt64);
    const auto values = std::get<0>(torch::_unique(l.flatten(), /*sorted=*/true));
    for (int64_t k = 0; k < values.numel(); ++k) {
      const int64_t v = values[k].item<int64_t>();
      if (v == 0) continue;
      out.push_back({fmt::format("label_{}", v), (l == v).to(torch::kFloat32), {}, ""});
    }
    if (out.empty()) raise(ErrorKind::Input, "masks: the label map has no object (every pixel is 0)");
  }
  if (out.empty()) raise(ErrorKind::Input, "masks: no object given");
  if (!crop_masks.is_none()) {
    if (!py::isinstance<py::dict>(crop_masks)) raise(ErrorKind::Input, "crop_masks: expected a dict {id: mask}");
    for (auto item : crop_masks.cast<py::dict>()) {
      const std::string id = py::str(item.first).cast<std::string>();
      auto it = std::find_if(out.begin(), out.end(), [&](const auto& o) { return o.id == id; });
      if (it == out.end()) raise(ErrorKind::Input, "crop_masks: no object '{}' among the masks", id);
      it->crop_mask = mask_from_py(item.second, "object '" + id + "' crop mask");
    }
  }
  return out;
}

// The image and geometry of a lift (or reconstruct) from arrays, through resample::set_lift_geometry.
rs::LiftInputs lift_inputs_from_py(py::handle image, py::handle masks, py::handle pointmap, py::handle depth, py::handle K,
                                   py::handle crop_masks) {
  rs::LiftInputs in;
  in.rgb = image_from_py(image, "image");
  if (pointmap.is_none() == depth.is_none())
    raise(ErrorKind::Input, "lift: pass exactly one of pointmap= [H, W, 3] and depth= [H, W] (with K=)");
  std::optional<data::Intrinsics> intr;
  if (!K.is_none()) {
    const auto k = intrinsics_from_py(K, "K");
    intr = data::Intrinsics{k.fx, k.fy, k.cx, k.cy};
  }
  at::Tensor pm, dp;
  if (!pointmap.is_none()) {
    pm = as_tensor(pointmap, "pointmap");
    if (pm.dim() != 3 || pm.size(2) != 3 || !pm.is_floating_point())
      raise(ErrorKind::Input, "pointmap: expected float [H, W, 3] (OpenCV camera, inf/NaN invalid), got {} {}", pm.sizes(),
            pm.scalar_type());
    pm = pm.detach().to(torch::kCPU, torch::kFloat32).contiguous();  // the same tensor when it already is
  } else {
    if (!intr) raise(ErrorKind::Input, "depth: a depth map needs the intrinsics K=");
    dp = as_tensor(depth, "depth");
    if (dp.dim() != 2 || !dp.is_floating_point())
      raise(ErrorKind::Input, "depth: expected float metres [H, W], got {} {}", dp.sizes(), dp.scalar_type());
    dp = data::clean_depth(dp.detach().cpu());
  }
  reraise_as(ErrorKind::Input, [&] {
    rs::set_lift_geometry(in, pm, dp, intr, pointmap.is_none() ? "depth" : "pointmap", "image");
    return 0;
  });
  in.objects = objects_from_py(masks, crop_masks);
  return in;
}

LiftRunPtr run_lift(Stage1& st, rs::LiftInputs inputs, uint64_t seed, const std::string& preprocess) {
  auto run = std::make_shared<LiftRun>();
  run->inputs = std::move(inputs);
  rs::LiftOptions opt;
  opt.seed = seed;
  opt.preprocess = reraise_as(ErrorKind::Config, [&] { return rs::preprocess_choice(preprocess, st.resampler->config()); });
  {
    py::gil_scoped_release release;
    std::lock_guard<std::mutex> lock(st.mutex);
    run->result = rs::lift_objects(*st.resampler, run->inputs, opt);
    run->resolution = rs::occupancy_resolution(*st.resampler);
    run->run_info = rs::lift_run_info(*st.resampler, opt, st.resampler->config().precision,
                                      st.resampler->config().random_weights);
  }
  run->banner = st.banner;
  for (const auto& o : run->result.objects) {
    std::vector<ShapePtr> row;
    for (size_t k = 0; k < o.samples.size(); ++k) {
      auto sh = std::make_shared<Shape>();
      sh->s = o.samples[k];
      sh->has_scene_pose = k < o.scene_poses.size();
      if (sh->has_scene_pose) sh->pose = o.scene_poses[k];
      sh->resolution = run->resolution;
      row.push_back(sh);
    }
    run->shapes.push_back(std::move(row));
  }
  return run;
}

}  // namespace

void bind_stage1(py::module_& m) {
  py::class_<Shape, ShapePtr>(m, "Shape", "One sampled shape: the canonical mesh (AABB-centred, longest side 1), "
                                          "the occupancy and SAM 3D's decoded pose (and the scene pose after a lift).")
      .def_property_readonly("ok", [](const Shape& s) { return s.s.ok; })
      .def_property_readonly("message", [](const Shape& s) { return s.s.message; })
      .def_property_readonly("vertices", [](const Shape& s) { auto V = s.s.mesh.V; return numpy_owning(std::move(V)); },
                             "float64 [n, 3], canonical frame (a fresh array per access)")
      .def_property_readonly("faces", [](const Shape& s) { auto F = s.s.mesh.F; return numpy_owning(std::move(F)); },
                             "int32 [m, 3] (a fresh array per access)")
      .def_property_readonly("coords", [](const Shape& s) { return s.s.coords; },
                             "torch int32 [N, 3]: occupied voxels (x, y, z); the result's own tensor (no copy)")
      .def_property_readonly("occupancy", [](const Shape& s) {
             return s.s.coords.defined() ? rs::occupancy_grid(s.s.coords, s.resolution)
                                         : torch::zeros({s.resolution, s.resolution, s.resolution}, torch::kUInt8);
           }, "torch uint8 [R, R, R], index (x, y, z), as occupancy.npy of the lift program")
      .def_property_readonly("latents", [](const Shape& s) { return s.s.latents; },
                             "dict name -> torch float32 [1, T, ch] (the result's own tensors)")
      .def_property_readonly("sam3d_pose", &pose_dict,
                             "SAM 3D's pose: rotation_wxyz (official, row vectors), rotation (3x3, column vectors, "
                             "PyTorch3D camera), translation, scale (voxel frame) and the canonical-mesh versions")
      .def_property_readonly("pose", [](const Shape& s) -> py::object {
             if (!s.has_scene_pose) return py::none();
             py::dict d;
             d["R"] = numpy_mat(s.pose.R);
             d["scale"] = numpy_vec(s.pose.scale);
             d["t"] = numpy_vec(s.pose.t);
             return d;
           }, "Scene-convention pose {R, scale, t}: world = R @ (scale * c) + t (None when not from a lift)")
      .def_property_readonly("canonical", [](const Shape& s) {
             py::dict d;
             d["centre"] = numpy_vec(s.s.canonical.centre);
             d["factor"] = s.s.canonical.factor;
             return d;
           }, "The voxel-frame -> canonical transform: c = (v - centre) * factor");

  py::class_<LiftedView>(m, "LiftedObject", "The lift's outcome for one object (in input order).")
      .def_property_readonly("id", [](const LiftedView& v) { return v.o().id; })
      .def_property_readonly("ok", [](const LiftedView& v) { return v.o().ok; })
      .def_property_readonly("error", [](const LiftedView& v) { return v.o().error; }, "Why not ok, naming the object")
      .def_property_readonly("crop_box", [](const LiftedView& v) -> py::object {
             if (!v.o().has_crop_box) return py::none();
             const auto& b = v.o().crop_box;
             return py::make_tuple(b.x1, b.y1, b.x2, b.y2);
           }, "(x1, y1, x2, y2) condition crop window in pixels, or None")
      .def_property_readonly("scene_scale", [](const LiftedView& v) { return v.o().scene_scale; })
      .def_property_readonly("scene_shift", [](const LiftedView& v) {
             return numpy_vec({v.o().scene_shift[0], v.o().scene_shift[1], v.o().scene_shift[2]});
           })
      .def_property_readonly("samples", [](const LiftedView& v) { return v.run->shapes[v.index]; });

  py::class_<LiftRun, LiftRunPtr>(m, "LiftRun", "The raw outcome of Stage1.lift (see simuscene.LiftResult).")
      .def_property_readonly("objects", [](const LiftRunPtr& r) {
             std::vector<LiftedView> v;
             for (size_t i = 0; i < r->result.objects.size(); ++i) v.push_back({r, i});
             return v;
           })
      .def_property_readonly("failed", [](const LiftRun& r) { return r.result.failed(); })
      .def_property_readonly("sampling_calls", [](const LiftRun& r) { return r.result.sampling_calls; })
      .def_property_readonly("seconds", [](const LiftRun& r) {
             const auto& s = r.result.seconds;
             py::dict d;
             d["preprocess"] = s.preprocess, d["embed"] = s.embed, d["sample"] = s.sample, d["decode"] = s.decode;
             d["mesh"] = s.mesh, d["pose"] = s.pose, d["total"] = s.total();
             return d;
           })
      .def_property_readonly("pointmap", [](const LiftRun& r) { return r.inputs.pointmap; },
                             "The point map used, [H, W, 3] (the tensor handed in when it was float32 CPU contiguous)")
      .def_property_readonly("image", [](const LiftRun& r) { return r.inputs.rgb; }, "The image used, [3, H, W] float")
      .def_property_readonly("K", [](const LiftRun& r) {
             py::dict d;
             d["fx"] = r.inputs.camera.fx, d["fy"] = r.inputs.camera.fy, d["cx"] = r.inputs.camera.cx,
             d["cy"] = r.inputs.camera.cy;
             return d;
           })
      .def("write", [](const LiftRun& r, py::object out, bool overwrite, py::object image_path, py::object depth_path) {
             rs::LiftWriteOptions w;
             w.out_dir = path_arg(out);
             w.overwrite = overwrite;
             w.image_path = path_arg(image_path);
             w.depth_path = path_arg(depth_path);
             w.banner = r.banner;
             w.run_info = r.run_info;
             reraise_as(ErrorKind::Input, [&] { rs::check_output_dir(w.out_dir, overwrite); return 0; });
             py::gil_scoped_release release;
             rs::write_lift_outputs(r.result, r.inputs, w, r.resolution);
           }, py::arg("out"), py::arg("overwrite") = false, py::arg("image_path") = py::none(),
           py::arg("depth_path") = py::none(),
           "Writes what the lift program writes (scene.json, report.json, objects/<id>/...).");

  py::class_<Stage1, std::shared_ptr<Stage1>>(m, "Stage1Core", "Loaded Stage-1 models (see simuscene.Stage1).")
      .def(py::init([](py::dict files, bool random_weights, const std::string& device, const std::string& precision,
                       int steps, int num_samples, py::object adapter) {
             rs::ModelOptions mo;
             auto& c = mo.config;
             auto get = [&](const char* key) {
               return files.contains(key) && !files[key].is_none() ? path_arg(files[key]) : std::string();
             };
             c.generator_config = get("generator_config");
             c.generator_weights = get("generator_weights");
             c.decoder_config = get("decoder_config");
             c.decoder_weights = get("decoder_weights");
             c.embedder_config = get("embedder_config");
             c.embedder_weights = get("embedder_weights");
             for (const char* key : {"generator_config", "decoder_config", "embedder_config", "generator_weights",
                                     "decoder_weights", "embedder_weights"})
               if (!get(key).empty()) require_file(get(key), key);
             c.adapter_dir = path_arg(adapter);
             if (!c.adapter_dir.empty()) require_file(c.adapter_dir + "/adapter_config.json", "adapter");
             c.device = device;
             c.steps = steps;
             c.num_samples = num_samples;
             if (steps <= 0 || num_samples <= 0)
               raise(ErrorKind::Input, "Stage1: steps and num_samples must be positive (got {}, {})", steps, num_samples);
             mo.precision = precision;
             mo.random_weights = random_weights;
             auto st = std::make_shared<Stage1>();
             st->banner = reraise_as(ErrorKind::Config, [&] { return rs::finish_model_options(mo); });
             py::gil_scoped_release release;
             st->resampler = std::make_unique<rs::Resampler>(mo.config);
             return st;
           }),
           py::arg("files"), py::arg("random_weights"), py::arg("device"), py::arg("precision"), py::arg("steps"),
           py::arg("num_samples"), py::arg("adapter"))
      .def_property_readonly("device", [](const Stage1& s) { return s.resampler->device().str(); })
      .def_property_readonly("precision", [](const Stage1& s) { return rs::effective_precision(*s.resampler); })
      .def_property_readonly("has_adapter", [](const Stage1& s) { return s.resampler->has_adapter(); })
      .def_property_readonly("random_weights_banner", [](const Stage1& s) { return s.banner; })
      .def_property_readonly("config", [](const Stage1& s) {
             const auto& c = s.resampler->config();
             py::dict d;
             d["generator_config"] = c.generator_config, d["generator_weights"] = c.generator_weights;
             d["decoder_config"] = c.decoder_config, d["decoder_weights"] = c.decoder_weights;
             d["embedder_config"] = c.embedder_config, d["embedder_weights"] = c.embedder_weights;
             d["adapter"] = c.adapter_dir, d["steps"] = c.steps, d["num_samples"] = c.num_samples;
             d["random_weights"] = c.random_weights;
             return d;
           })
      .def("load_adapter", [](Stage1& s, py::object dir) {
             const std::string d = path_arg(dir);
             require_file(d + "/adapter_config.json", "PEFT adapter");
             py::gil_scoped_release release;
             std::lock_guard<std::mutex> lock(s.mutex);
             reraise_as(ErrorKind::Input, [&] { s.resampler->load_adapter(d); return 0; });
           }, py::arg("path"))
      .def("set_adapter_enabled", [](Stage1& s, bool on) {
             if (!s.resampler->has_adapter()) raise(ErrorKind::Input, "Stage1: no adapter loaded (load_adapter first)");
             py::gil_scoped_release release;
             std::lock_guard<std::mutex> lock(s.mutex);
             lora::set_lora_enabled(*s.resampler->generator(), on);
           }, py::arg("enabled"))
      .def("merge_adapter", [](Stage1& s) {
             if (!s.resampler->has_adapter()) raise(ErrorKind::Input, "Stage1: no adapter loaded (load_adapter first)");
             py::gil_scoped_release release;
             std::lock_guard<std::mutex> lock(s.mutex);
             reraise_as(ErrorKind::Input, [&] { lora::merge_lora(*s.resampler->generator()); return 0; });
           })
      .def("unmerge_adapter", [](Stage1& s) {
             py::gil_scoped_release release;
             std::lock_guard<std::mutex> lock(s.mutex);
             lora::unmerge_lora(*s.resampler->generator());
           })
      .def("lift", [](Stage1& s, py::object image, py::object masks, py::object pointmap, py::object depth, py::object K,
                      py::object crop_masks, uint64_t seed, const std::string& preprocess) {
             if (!s.resampler->embedder())
               raise(ErrorKind::Config, "Stage1.lift: no condition embedder (embedder_config)");
             return run_lift(s, lift_inputs_from_py(image, masks, pointmap, depth, K, crop_masks), seed, preprocess);
           }, py::arg("image"), py::arg("masks"), py::kw_only(), py::arg("pointmap") = py::none(), py::arg("depth") = py::none(),
           py::arg("K") = py::none(), py::arg("crop_masks") = py::none(), py::arg("seed") = 0,
           py::arg("preprocess") = "model")
      .def("sample", [](Stage1& s, std::vector<at::Tensor> conds, uint64_t seed) {
             std::vector<rs::ResampleRequest> rq;
             const int64_t C = s.resampler->generator()->config().backbone.cond_channels;
             for (size_t i = 0; i < conds.size(); ++i) {
               if (conds[i].dim() != 2 || conds[i].size(1) != C || !conds[i].is_floating_point())
                 raise(ErrorKind::Input, "sample: condition {} must be float [L, {}], got {} {}", i, C, conds[i].sizes(),
                       conds[i].scalar_type());
               rs::ResampleRequest r;
               r.cond = conds[i];
               rq.push_back(std::move(r));
             }
             rs::ResampleResult res;
             int64_t R = 0;
             {
               py::gil_scoped_release release;
               std::lock_guard<std::mutex> lock(s.mutex);
               res = s.resampler->resample(rq, seed);
               R = rs::occupancy_resolution(*s.resampler);
             }
             std::vector<std::vector<ShapePtr>> out;
             for (auto& row : res.objects) {
               std::vector<ShapePtr> r;
               for (auto& shape : row) {
                 auto sh = std::make_shared<Shape>();
                 sh->s = std::move(shape);
                 sh->resolution = R;
                 r.push_back(sh);
               }
               out.push_back(std::move(r));
             }
             return out;
           }, py::arg("conds"), py::arg("seed") = 0)
      .def("embed", [](Stage1& s, std::map<std::string, at::Tensor> inputs) {
             if (!s.resampler->embedder()) raise(ErrorKind::Config, "Stage1.embed: no condition embedder (embedder_config)");
             rs::ResampleRequest r;
             r.inputs = std::move(inputs);
             py::gil_scoped_release release;
             std::lock_guard<std::mutex> lock(s.mutex);
             return reraise_as(ErrorKind::Input, [&] { return s.resampler->conditions({r}).at(0); });
           }, py::arg("inputs"));

  m.def(
      "reconstruct",
      [](py::object image, py::object masks, py::object pointmap, py::object depth, py::object K, py::object objects,
         std::shared_ptr<Stage1> stage1, py::object out, bool overwrite, py::object probe_config, py::object overrides,
         bool run_probe, uint64_t seed, int lift_samples) {
        if (lift_samples < 0) raise(ErrorKind::Input, "reconstruct: lift_samples must be >= 0 (got {})", lift_samples);
        reconstruct::ReconstructInputs in;
        in.lift = lift_inputs_from_py(image, masks, pointmap, depth, K, py::none());
        if (!objects.is_none()) {
          std::string sidecar;
          if (py::isinstance<py::str>(objects) || py::hasattr(objects, "__fspath__")) {
            sidecar = path_arg(objects);
            require_file(sidecar, "objects (sidecar)");
          } else {
            // Entries given as Python objects go through the sidecar parser as the file would.
            const std::string text = py_to_json_text(objects);
            sidecar = temp_root() + "/sidecar_" + std::to_string(std::hash<std::string>{}(text)) + ".json";
            std::ofstream(sidecar) << text;
          }
          in.specs = reraise_as(ErrorKind::Input, [&] { return reconstruct::read_sidecar(sidecar, &in.messages); });
          in.sidecar_name = sidecar;
        }
        reconstruct::ReconstructOptions opt;
        opt.probe = probe_config_from(path_arg(probe_config), overrides);
        opt.run_probe = run_probe;
        opt.overwrite = overwrite;
        opt.lift.seed = seed;
        opt.lift.samples = lift_samples;
        const std::string out_dir = path_arg(out);
        reraise_as(ErrorKind::Input, [&] { rs::check_output_dir(out_dir, overwrite); return 0; });
        reconstruct::ReconstructResult res;
        {
          py::gil_scoped_release release;
          std::unique_lock<std::mutex> lock;
          if (stage1) lock = std::unique_lock<std::mutex>(stage1->mutex);
          res = reconstruct::reconstruct(in, opt, stage1 ? stage1->resampler.get() : nullptr, out_dir);
        }
        py::dict d;
        d["scene"] = res.scene;
        py::list objs;
        for (const auto& o : res.objects) objs.append(json_to_py(o.to_json().dump()));
        d["objects"] = objs;
        d["messages"] = res.messages;
        d["timings"] = json_to_py(res.timings.dump());
        d["up"] = numpy_vec(res.planes.up);
        d["probe_report"] = res.probe ? json_to_py(physics::report_json(*res.probe).dump()) : py::object(py::none());
        d["out_dir"] = stdfs::absolute(out_dir).lexically_normal().string();
        return d;
      },
      py::arg("image"), py::arg("masks"), py::kw_only(), py::arg("pointmap") = py::none(), py::arg("depth") = py::none(),
      py::arg("K") = py::none(), py::arg("objects") = py::none(), py::arg("stage1") = nullptr, py::arg("out"),
      py::arg("overwrite") = false, py::arg("probe_config") = py::none(), py::arg("overrides") = py::none(),
      py::arg("run_probe") = true, py::arg("seed") = 0, py::arg("lift_samples") = rs::kFirstLiftSamples,
      "The reconstruct program's steps on arrays (simuscene.reconstruct wraps it).");
}

}  // namespace simu::py_bind
