// simuscene I/O helpers (images, masks, depth, point maps, K, meshes as the programs read them), the pair
// cache writer and reader (data/pair_cache.h, both condition modes), build_pairs, export_adapter and
// in-process FM-DPO training on one rank (training/train_run.h).
#include <atomic>
#include <filesystem>
#include <fstream>

#include "bind.h"
#include "common/log.h"
#include "data/depth_io.h"
#include "data/pair_cache.h"
#include "data/preprocess.h"
#include "lora/adapter_export.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/resample/pair_builder.h"
#include "training/train_config.h"
#include "training/train_run.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#endif

namespace simu::py_bind {

namespace stdfs = std::filesystem;

namespace {

torch::ScalarType storage_dtype(const std::string& name, const std::string& what) {
  if (name == "float16" || name == "f16") return torch::kFloat16;
  if (name == "float32" || name == "f32") return torch::kFloat32;
  raise(ErrorKind::Input, "{}: dtype must be float16 or float32, got '{}'", what, name);
}

data::PairKind kind_from(const std::string& s, const std::string& what) {
  if (s == "occlusion_completion") return data::PairKind::OcclusionCompletion;
  if (s == "clean_preservation") return data::PairKind::CleanPreservation;
  raise(ErrorKind::Input, "{}: kind must be occlusion_completion or clean_preservation, got '{}'", what, s);
}

py::dict info_dict(const data::CacheInfo& i) {
  py::dict d;
  d["path"] = i.path, d["schema_version"] = i.schema_version, d["size"] = i.size, d["cond_mode"] = i.cond_mode;
  d["latent_shape"] = i.latent_shape, d["cond_shape"] = i.cond_shape, d["latent_dtype"] = i.latent_dtype;
  d["created_by"] = i.created_by;
  d["counts"] = py::make_tuple(i.counts[0], i.counts[1]);
  if (i.inputs_mode()) {
    d["input_size"] = i.input_size, d["image_dtype"] = i.image_dtype, d["pointmap_dtype"] = i.pointmap_dtype;
  }
  return d;
}

// The writer, closable from Python (a writer dropped without finish() removes its temporary file).
struct Writer {
  std::unique_ptr<data::PairCacheWriter> w;
  data::PairCacheWriter& get() {
    if (!w) raise(ErrorKind::Input, "PairCacheWriter: already finished or closed");
    return *w;
  }
};

}  // namespace

void bind_io(py::module_& m) {
  m.def("read_image", [](py::object path) {
        const std::string p = path_arg(path);
        require_file(p, "image");
        at::Tensor rgb;
        {
          py::gil_scoped_release release;
          rgb = data::read_image_rgb(p);  // [3, H, W] in [0, 1]
        }
        return rgb;
      }, py::arg("path"), "An image file as the programs read it: torch float32 [3, H, W] in [0, 1].");
  m.def("read_mask", [](py::object path) {
        const std::string p = path_arg(path);
        require_file(p, "mask");
        return data::read_mask(p);
      }, py::arg("path"), "A mask file as the programs read it: torch float32 [H, W] in [0, 1].");
  m.def("read_depth", [](py::object path) {
        const std::string p = path_arg(path);
        require_file(p, "depth");
        return reraise_as(ErrorKind::Input, [&] { return data::read_depth(p); });
      }, py::arg("path"), "Depth (.npy float m | uint16 mm, 16-bit PNG mm, EXR m): torch float32 [H, W], NaN invalid.");
  m.def("read_pointmap", [](py::object path) {
        const std::string p = path_arg(path);
        require_file(p, "point map");
        return reraise_as(ErrorKind::Input, [&] { return data::read_pointmap(p); });
      }, py::arg("path"), "A MoGe-style point map .npy [H, W, 3] (OpenCV camera): torch float32.");
  m.def("read_intrinsics", [](py::object path) {
        const std::string p = path_arg(path);
        require_file(p, "intrinsics");
        const auto k = reraise_as(ErrorKind::Input, [&] { return data::read_intrinsics_json(p); });
        py::dict d;
        d["fx"] = k.fx, d["fy"] = k.fy, d["cx"] = k.cx, d["cy"] = k.cy;
        return d;
      }, py::arg("path"), "A K JSON file: {fx, fy, cx, cy}.");
  m.def("write_image", [](py::object path, py::object pixels) {
#ifdef SIMU_HAVE_OPENCV
        const std::string p = path_arg(path);
        const at::Tensor t = as_tensor(pixels, "pixels").detach().cpu().contiguous();
        if (t.scalar_type() != torch::kUInt8 && t.scalar_type() != torch::kUInt16)
          raise(ErrorKind::Input, "write_image: expected uint8 or uint16 pixels, got {}", t.scalar_type());
        const int depth = t.scalar_type() == torch::kUInt8 ? CV_8U : CV_16U;
        cv::Mat out;
        if (t.dim() == 2) {
          out = cv::Mat(static_cast<int>(t.size(0)), static_cast<int>(t.size(1)), CV_MAKETYPE(depth, 1), t.data_ptr());
        } else if (t.dim() == 3 && t.size(2) == 3) {
          cv::cvtColor(cv::Mat(static_cast<int>(t.size(0)), static_cast<int>(t.size(1)), CV_MAKETYPE(depth, 3), t.data_ptr()),
                       out, cv::COLOR_RGB2BGR);
        } else {
          raise(ErrorKind::Input, "write_image: expected [H, W] or [H, W, 3] (RGB), got {}", t.sizes());
        }
        if (!cv::imwrite(p, out)) raise(ErrorKind::Generic, "{}: cannot write the image", p);
#else
        raise(ErrorKind::Generic, "write_image needs OpenCV (built with SIMU_WITH_OPENCV=OFF)");
#endif
      }, py::arg("path"), py::arg("pixels"), "Writes uint8/uint16 pixels ([H, W] or RGB [H, W, 3]) as the extension says.");
  m.def("read_mesh", [](py::object path) {
        const std::string p = path_arg(path);
        require_file(p, "mesh");
        auto mesh = reraise_as(ErrorKind::Input, [&] { return physics::read_mesh(p); });
        return py::make_tuple(numpy_owning(std::move(mesh.V)), numpy_owning(std::move(mesh.F)));
      }, py::arg("path"), "A mesh file (OBJ/PLY/GLB through assimp): (vertices float64 [n, 3], faces int32 [m, 3]).");

  // ---- Pair cache ----
  py::class_<Writer>(m, "PairCacheWriter", "Writes an FM-DPO pair cache atomically (docs/pair_cache.md).")
      .def(py::init([](py::object path, std::vector<int64_t> latent_shape, std::vector<int64_t> cond_shape,
                       const std::string& dtype, const std::string& mode, int64_t image_size, int64_t pointmap_size,
                       const std::string& storage, bool resume, const std::string& created_by) {
             const std::string p = path_arg(path);
             Writer w;
             const auto dt = storage_dtype(dtype, p);
             reraise_as(ErrorKind::Input, [&] {
               if (mode == "tokens") {
                 w.w = std::make_unique<data::PairCacheWriter>(p, latent_shape, cond_shape, dt, resume);
               } else if (mode == "inputs") {
                 const auto layout = data::InputsLayout::storage_named(storage, image_size, pointmap_size);
                 w.w = std::make_unique<data::PairCacheWriter>(p, latent_shape, cond_shape, dt, layout, resume);
               } else {
                 raise(ErrorKind::Input, "{}: mode must be tokens or inputs, got '{}'", p, mode);
               }
               return 0;
             });
             if (!created_by.empty()) w.w->set_created_by(created_by);
             return w;
           }),
           py::arg("path"), py::arg("latent_shape"), py::arg("cond_shape"), py::kw_only(), py::arg("dtype") = "float16",
           py::arg("mode") = "tokens", py::arg("image_size") = 518, py::arg("pointmap_size") = 518,
           py::arg("storage") = "exact", py::arg("resume") = false, py::arg("created_by") = "simuscene (Python)")
      .def("append", [](Writer& w, const std::string& id, py::object latent_pos, py::object latent_neg, py::object cond,
                        py::object inputs, const std::string& kind, std::optional<float> weight) {
             data::PairRecord r;
             r.id = id;
             r.kind = kind_from(kind, "pair '" + id + "'");
             r.weight = weight ? *weight : data::default_weight(r.kind);
             r.latent_pos = as_tensor(latent_pos, "pair '" + id + "' latent_pos");
             r.latent_neg = as_tensor(latent_neg, "pair '" + id + "' latent_neg");
             if (!cond.is_none()) r.cond = as_tensor(cond, "pair '" + id + "' cond");
             if (!inputs.is_none()) {
               if (!py::isinstance<py::dict>(inputs)) raise(ErrorKind::Input, "pair '{}': inputs must be a dict", id);
               for (auto item : inputs.cast<py::dict>()) {
                 const std::string k = py::str(item.first).cast<std::string>();
                 r.inputs[k] = as_tensor(item.second, "pair '" + id + "' input " + k);
               }
             }
             auto& writer = w.get();
             py::gil_scoped_release release;
             writer.append(r);
           }, py::arg("id"), py::arg("latent_pos"), py::arg("latent_neg"), py::kw_only(), py::arg("cond") = py::none(),
           py::arg("inputs") = py::none(), py::arg("kind") = "occlusion_completion", py::arg("weight") = py::none())
      .def("contains", [](Writer& w, const std::string& id) { return w.get().contains(id); }, py::arg("id"))
      .def("__len__", [](Writer& w) { return w.get().size(); })
      .def("finish", [](Writer& w) {
             auto& writer = w.get();
             {
               py::gil_scoped_release release;
               writer.finish();
             }
             w.w.reset();
           }, "Commits the cache (atomic rename over path).")
      .def("close", [](Writer& w) { w.w.reset(); }, "Drops an unfinished writer: its temporary file is removed.")
      .def_property_readonly("path", [](Writer& w) { return w.get().path(); });

  py::class_<data::PairCacheReader>(m, "PairCacheReader", "Reads a pair cache (either condition mode).")
      .def(py::init([](py::object path) {
             const std::string p = path_arg(path);
             require_file(p, "pair cache");
             return reraise_as(ErrorKind::Input, [&] { return data::PairCacheReader::open(p); });
           }), py::arg("path"))
      .def_property_readonly("info", [](const data::PairCacheReader& r) { return info_dict(r.info()); })
      .def("__len__", &data::PairCacheReader::size)
      .def("read", [](const data::PairCacheReader& r, int64_t i) {
             if (i < 0) i += r.size();
             if (i < 0 || i >= r.size()) throw py::index_error(fmt::format("{}: no record {} (size {})", r.path(), i, r.size()));
             data::PairRecord rec;
             {
               py::gil_scoped_release release;
               rec = r.read(i);
             }
             py::dict d;
             d["id"] = rec.id, d["index"] = rec.index, d["kind"] = data::kind_name(rec.kind), d["weight"] = rec.weight;
             d["latent_pos"] = rec.latent_pos, d["latent_neg"] = rec.latent_neg;
             d["cond"] = rec.cond.defined() ? py::cast(rec.cond) : py::object(py::none());
             d["inputs"] = rec.inputs;
             return d;
           }, py::arg("index"))
      .def("ids", &data::PairCacheReader::ids)
      .def("kinds", &data::PairCacheReader::kinds)
      .def("weights", &data::PairCacheReader::weights);
  m.def("validate_pair_cache", [](py::object path) {
        const std::string p = path_arg(path);
        require_file(p, "pair cache");
        py::gil_scoped_release release;
        const auto info = reraise_as(ErrorKind::Input, [&] { return data::validate_cache(p); });
        py::gil_scoped_acquire gil;
        return info_dict(info);
      }, py::arg("path"), "Full scan of a cache (every record decoded and checked); its info.");
}

void bind_data(py::module_& m) {
  m.def(
      "build_pairs",
      [](py::object manifest, py::object out, std::shared_ptr<Stage1> stage1, const std::string& cond_mode,
         const std::string& dtype, const std::string& inputs_storage, int64_t batch, uint64_t seed, bool resume,
         int64_t commit_every, const std::string& preprocess) {
        const std::string man = path_arg(manifest);
        require_file(man, "manifest");
        resample::PairBuilderConfig cfg;
        cfg.out = path_arg(out);
        cfg.dtype = storage_dtype(dtype, "build_pairs");
        cfg.cond_mode = cond_mode;
        cfg.inputs_storage = inputs_storage;
        cfg.batch = batch;
        cfg.seed = seed;
        cfg.resume = resume;
        cfg.commit_every = commit_every;
        cfg.created_by = "build_pairs (simuscene Python)";
        cfg.preprocess = reraise_as(ErrorKind::Config, [&] { return data::PreprocessConfig::preset_named(preprocess); });
        if (!stage1 || !stage1->resampler->embedder())
          raise(ErrorKind::Config, "build_pairs: needs a Stage1 with a condition embedder (embedder_config)");
        cfg.resampler = stage1->resampler->config();
        std::atomic<bool> stop{false};
        int64_t last_decile = -1;
        auto progress = [&](int64_t done, int64_t total) {
          const int64_t decile = total > 0 ? done * 10 / total : 10;
          if (decile != last_decile) log::info("build_pairs {}/{} records", done, total);
          last_decile = decile;
          try {
            check_cancel();
          } catch (const Cancelled&) {
            stop = true;  // commit what is done, then raise KeyboardInterrupt below
          }
        };
        resample::PairBuildReport rep;
        {
          py::gil_scoped_release release;
          std::lock_guard<std::mutex> lock(stage1->mutex);
          rep = reraise_as(ErrorKind::Input, [&] {
            return resample::build_pairs(man, cfg, *stage1->resampler, progress, &stop);
          });
        }
        if (rep.interrupted)
          throw Cancelled(fmt::format("build_pairs interrupted: {} pairs committed to {} (run again to continue)",
                                      rep.cache_size, cfg.out));
        py::dict d;
        d["records"] = rep.records, d["written"] = rep.written, d["skipped_existing"] = rep.skipped_existing;
        d["cache_size"] = rep.cache_size, d["seconds"] = rep.seconds;
        py::list issues;
        for (const auto& i : rep.issues) {
          py::dict e;
          e["line"] = i.line, e["id"] = i.id, e["message"] = i.message;
          issues.append(e);
        }
        d["issues"] = issues;
        return d;
      },
      py::arg("manifest"), py::arg("out"), py::kw_only(), py::arg("stage1"), py::arg("cond_mode") = "tokens",
      py::arg("dtype") = "float16", py::arg("inputs_storage") = "exact", py::arg("batch") = 4, py::arg("seed") = 0,
      py::arg("resume") = true, py::arg("commit_every") = 256, py::arg("preprocess") = "released",
      "build_pairs on a manifest with a loaded Stage1 (simuscene.build_pairs wraps it).");

  m.def(
      "export_adapter",
      [](py::object source, py::object out, bool merge, bool overwrite, py::object model_config, py::object weights,
         py::object run_config, std::vector<std::string> sets, const std::string& description) {
        lora::ExportOptions o;
        o.merge = merge, o.overwrite = overwrite, o.model_config = path_arg(model_config), o.weights = path_arg(weights);
        o.run_config = path_arg(run_config), o.sets = std::move(sets), o.description = description;
        const std::string src = path_arg(source), dst = path_arg(out);
        require_file(src, "adapter source");
        for (const auto& [p, what] : {std::pair{o.model_config, "model_config"}, {o.weights, "weights"}, {o.run_config, "run_config"}})
          if (!p.empty()) require_file(p, what);
        py::gil_scoped_release release;
        reraise_as(ErrorKind::Input, [&] { lora::export_adapter(src, dst, o); return 0; });
      },
      py::arg("source"), py::arg("out"), py::kw_only(), py::arg("merge") = false, py::arg("overwrite") = false,
      py::arg("model_config") = py::none(), py::arg("weights") = py::none(), py::arg("run_config") = py::none(),
      py::arg("sets") = std::vector<std::string>{}, py::arg("description") = "",
      "The export_adapter program as a call.");

  m.def(
      "train_fmdpo",
      [](py::object config, std::vector<std::string> overrides, const std::string& resume, bool overwrite) {
        const std::string path = path_arg(config);
        require_file(path, "training config");
        const auto cfg = reraise_as(ErrorKind::Config, [&] { return training::TrainConfig::load(path, overrides); });
        training::TrainRunOptions opt;
        opt.resume = resume;
        opt.overwrite = overwrite;  // env: one rank (rank 0 of a world of one)
        int64_t steps = 0;
        {
          py::gil_scoped_release release;
          steps = training::run_training(cfg, opt);
        }
        py::dict d;
        d["steps"] = steps;
        d["out_dir"] = cfg.run.out_dir;
        d["adapter"] = cfg.run.out_dir + "/adapter";
        return d;
      },
      py::arg("config"), py::arg("overrides") = std::vector<std::string>{}, py::kw_only(), py::arg("resume") = "",
      py::arg("overwrite") = false, "FM-DPO training on one rank in this process (simuscene.train_fmdpo wraps it).");
}

}  // namespace simu::py_bind
