// MJCF text generation and MuJoCo loading from memory.
#include "pipeline/physics/mjcf.h"

#include <mujoco/mujoco.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <memory>
#include <sstream>

#include "common/error.h"
#include "common/log.h"

#include <cstdlib>
#include <map>
#include <mutex>

namespace simu::physics {

void MjModelDeleter::operator()(mjModel_* m) const { mj_deleteModel(m); }
void MjDataDeleter::operator()(mjData_* d) const { mj_deleteData(d); }

namespace {

std::string num(double v) { return fmt::format("{:.9g}", v); }
std::string v3(const Vec3& v) { return fmt::format("{:.9g} {:.9g} {:.9g}", v[0], v[1], v[2]); }
std::string quat(const Mat3& R) {
  Eigen::Quaterniond q(R);
  q.normalize();
  return fmt::format("{:.12g} {:.12g} {:.12g} {:.12g}", q.w(), q.x(), q.y(), q.z());
}
// XML attribute escaping for names.
std::string esc(const std::string& s) {
  std::string o;
  for (char c : s) {
    switch (c) {
      case '&': o += "&amp;"; break;
      case '<': o += "&lt;"; break;
      case '>': o += "&gt;"; break;
      case '"': o += "&quot;"; break;
      default: o += c;
    }
  }
  return o;
}

}  // namespace

std::string write_mjcf(const MjScene& scene, const PhysicsConfig& cfg, bool detect) {
  const double margin = detect ? cfg.detect_margin : cfg.margin;
  const double gap = detect ? cfg.detect_margin : cfg.gap;
  std::ostringstream x;
  x << "<mujoco model=\"simuscene\">\n";
  // Compiler: explicit inertials (MuJoCo's mesh inertia is wrong for open meshes).
  x << "  <compiler angle=\"radian\" inertiafromgeom=\"false\" boundmass=\"1e-6\" boundinertia=\"1e-12\"/>\n";
  x << "  <option timestep=\"" << num(cfg.timestep) << "\" gravity=\"" << v3(scene.gravity) << "\" integrator=\""
    << cfg.integrator << "\">\n";
  x << "    <flag multiccd=\"" << (cfg.multiccd ? "enable" : "disable") << "\"/>\n  </option>\n";
  x << "  <size nconmax=\"" << cfg.nconmax << "\" njmax=\"" << cfg.njmax << "\"/>\n";
  // Contact defaults of the paper; collision hulls in group 3 (hidden by default in the viewer),
  // visual meshes in group 2 without contacts.
  x << "  <default>\n    <geom condim=\"" << cfg.condim << "\" friction=\"" << v3(cfg.friction) << "\" solref=\""
    << num(cfg.solref_timeconst) << " " << num(cfg.solref_dampratio) << "\" margin=\"" << num(margin) << "\" gap=\""
    << num(gap) << "\"/>\n";
  x << "    <equality solref=\"" << num(cfg.eq_timeconst) << " " << num(cfg.eq_dampratio) << "\"/>\n";
  x << "    <default class=\"collision\">\n      <geom group=\"3\"/>\n    </default>\n";
  x << "    <default class=\"visual\">\n      <geom group=\"2\" contype=\"0\" conaffinity=\"0\"/>\n    </default>\n";
  x << "  </default>\n";
  // Mesh assets: hulls inline, visual meshes from OBJ files.
  x << "  <asset>\n";
  for (const auto& b : scene.bodies) {
    for (size_t k = 0; k < b.hulls.size() && b.collide; ++k) {
      const Mesh& h = b.hulls[k];
      x << "    <mesh name=\"" << esc(b.name) << "/" << k << "\" vertex=\"";
      for (Eigen::Index i = 0; i < h.V.rows(); ++i) x << (i ? " " : "") << v3(h.V.row(i).transpose());
      x << "\" face=\"";
      for (Eigen::Index i = 0; i < h.F.rows(); ++i) x << (i ? " " : "") << h.F(i, 0) << " " << h.F(i, 1) << " " << h.F(i, 2);
      x << "\"/>\n";
    }
    if (!b.visual_file.empty())
      x << "    <mesh name=\"" << esc(b.name) << "/visual\" file=\"" << esc(b.visual_file) << "\" scale=\""
        << v3(b.visual_scale) << "\"/>\n";
  }
  x << "  </asset>\n  <worldbody>\n";
  // Planes: floor and walls; size is only for drawing.
  for (const auto& p : scene.planes) {
    const Mat3 R = Eigen::Quaterniond::FromTwoVectors(Vec3::UnitZ(), p.normal).toRotationMatrix();
    x << "    <geom name=\"plane:" << esc(p.id) << "\" type=\"plane\" size=\"10 10 0.1\" pos=\"" << v3(p.point)
      << "\" quat=\"" << quat(R) << "\" rgba=\"0.85 0.85 0.8 1\"/>\n";
  }
  // Bodies.
  for (const auto& b : scene.bodies) {
    x << "    <body name=\"" << esc(b.name) << "\" pos=\"" << v3(b.pos) << "\" quat=\"" << quat(b.R) << "\">\n";
    if (b.dynamic) {
      x << "      <freejoint name=\"" << esc(b.name) << ":free\"/>\n";
      const Mat3& I = b.mass.inertia;
      x << "      <inertial pos=\"" << v3(b.mass.com) << "\" mass=\"" << num(b.mass.mass) << "\" fullinertia=\""
        << num(I(0, 0)) << " " << num(I(1, 1)) << " " << num(I(2, 2)) << " " << num(I(0, 1)) << " " << num(I(0, 2)) << " "
        << num(I(1, 2)) << "\"/>\n";
    }
    for (size_t k = 0; k < b.hulls.size() && b.collide; ++k)
      x << "      <geom name=\"" << esc(b.name) << "/" << k << "\" class=\"collision\" type=\"mesh\" mesh=\""
        << esc(b.name) << "/" << k << "\" rgba=\"" << b.rgba << "\"/>\n";
    if (!b.visual_file.empty())
      x << "      <geom name=\"" << esc(b.name) << "/visual\" class=\"visual\" type=\"mesh\" mesh=\"" << esc(b.name)
        << "/visual\" rgba=\"" << b.rgba << "\"/>\n";
    x << "    </body>\n";
  }
  x << "  </worldbody>\n";
  // Pins: each holds a body point at its current world position (MuJoCo 2.2 connect semantics).
  bool any_pin = false;
  for (const auto& b : scene.bodies) any_pin = any_pin || !b.pins.empty();
  if (any_pin) {
    x << "  <equality>\n";
    for (const auto& b : scene.bodies)
      for (size_t k = 0; k < b.pins.size(); ++k)
        x << "    <connect name=\"" << esc(b.name) << ":pin" << k << "\" body1=\"" << esc(b.name) << "\" anchor=\""
          << v3(b.pins[k]) << "\"/>\n";
    x << "  </equality>\n";
  }
  x << "</mujoco>\n";
  return x.str();
}

namespace {
// MuJoCo 2.2 repeats a warning at every step while its cause lasts: the first few of each kind are
// logged, then one line says the rest are suppressed.
void mujoco_warning(const char* msg) {
  static std::mutex mu;
  static std::map<std::string, int> seen;
  std::string kind(msg);
  if (const auto p = kind.find(" Time ="); p != std::string::npos) kind.resize(p);
  int count;
  {
    std::lock_guard<std::mutex> lock(mu);
    count = ++seen[kind];
  }
  if (count <= 3) log::warn("MuJoCo: {}", msg);
  else if (count == 4) log::warn("MuJoCo: further warnings '{}' are not shown", kind);
}
[[noreturn]] void mujoco_error(const char* msg) {
  // MuJoCo's errors are fatal by contract (the default handler exits); say so through the logger.
  log::error("MuJoCo fatal error: {}", msg);
  std::exit(1);
}
}  // namespace

void install_mujoco_log_handlers() {
  static std::once_flag once;
  std::call_once(once, [] {
    mju_user_warning = mujoco_warning;
    mju_user_error = mujoco_error;
  });
}

MjModelPtr load_mjcf_string(const std::string& xml, const std::string& name) {
  install_mujoco_log_handlers();
  // mjVFS is ~2 MB: keep it on the heap.
  auto vfs = std::make_unique<mjVFS>();
  mj_defaultVFS(vfs.get());
  SIMU_CHECK(mj_makeEmptyFileVFS(vfs.get(), name.c_str(), static_cast<int>(xml.size())) == 0,
             "MuJoCo VFS: cannot create {}", name);
  const int idx = mj_findFileVFS(vfs.get(), name.c_str());
  std::memcpy(vfs->filedata[idx], xml.data(), xml.size());
  char err[1000] = "";
  mjModel* m = mj_loadXML(name.c_str(), vfs.get(), err, sizeof(err));
  mj_deleteVFS(vfs.get());
  if (!m) fail("MuJoCo could not compile the generated model {}: {}", name, err);
  return MjModelPtr(m);
}

MjModelPtr load_mjcf_file(const std::string& path) {
  install_mujoco_log_handlers();
  SIMU_CHECK(std::filesystem::exists(path), "MJCF file {} does not exist", path);
  char err[1000] = "";
  mjModel* m = mj_loadXML(path.c_str(), nullptr, err, sizeof(err));
  if (!m) fail("MuJoCo could not load {}: {}", path, err);
  return MjModelPtr(m);
}

MjDataPtr make_data(const mjModel_* m) {
  mjData* d = mj_makeData(m);
  SIMU_CHECK(d != nullptr, "MuJoCo: mj_makeData failed (out of memory?)");
  return MjDataPtr(d);
}

int take_warnings(mjData_* d) {
  int mask = 0;
  for (int i = 0; i < mjNWARNING; ++i) {
    if (d->warning[i].number > 0) mask |= 1 << i;
    d->warning[i].number = 0;
  }
  return mask;
}

std::string describe_warnings(int mask) {
  static const char* names[] = {"inertia", "contactfull", "cnstrfull", "vgeomfull", "badqpos", "badqvel", "badqacc", "badctrl"};
  std::string s;
  for (int i = 0; i < mjNWARNING && i < 8; ++i)
    if (mask & (1 << i)) s += (s.empty() ? "" : ",") + std::string(names[i]);
  return s;
}

}  // namespace simu::physics
