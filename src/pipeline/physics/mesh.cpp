// Mesh reading/writing through assimp and mesh utilities.
#include "pipeline/physics/mesh.h"

#include <assimp/Exporter.hpp>
#include <assimp/Importer.hpp>
#include <assimp/postprocess.h>
#include <assimp/scene.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>
#include <vector>

#include "common/error.h"
#include "common/fs.h"

#include <map>

namespace simu::physics {

namespace {

// Bytes per value of a PLY scalar type (0: not a PLY type).
int ply_type_size(const std::string& t) {
  if (t == "char" || t == "uchar" || t == "int8" || t == "uint8") return 1;
  if (t == "short" || t == "ushort" || t == "int16" || t == "uint16") return 2;
  if (t == "int" || t == "uint" || t == "int32" || t == "uint32" || t == "float" || t == "float32") return 4;
  if (t == "double" || t == "float64") return 8;
  return 0;
}
bool ply_integer_type(const std::string& t) { return ply_type_size(t) && t.rfind("float", 0) != 0 && t != "double"; }
// Largest list length a PLY count type can hold (counts are never negative).
uint64_t ply_count_max(const std::string& t) {
  const int b = ply_type_size(t);
  const bool is_signed = t == "char" || t == "int8" || t == "short" || t == "int16" || t == "int" || t == "int32";
  return (uint64_t{1} << (8 * b - (is_signed ? 1 : 0))) - 1;
}

// A PLY element of a header: its count and properties (list_count[k]: the count type of list property k,
// "" for a scalar).
struct PlyElement {
  std::string name;
  uint64_t count = 0;
  uint64_t min_bytes = 0;  // per element, in the file's format
  std::vector<std::string> props, list_count;
};

// Walks an ASCII PLY body as the header declares it: every value a number, every list length an integer
// that its count type holds, and the file holding that many values. assimp 5.2 allocates a list from its
// length unchecked: "3611295284" as a uchar length asked for 29 GB
// (fuzz/regressions/fuzz_scene/assimp_ply_ascii_list_count_oom.bin).
void check_ply_ascii_body(const std::string& path, std::ifstream& in, uint64_t pos, const std::vector<PlyElement>& elements) {
  in.clear();
  in.seekg(static_cast<std::streamoff>(pos));
  std::string tok;
  auto number = [&](const PlyElement& e, uint64_t i, const std::string& prop) {
    SIMU_CHECK(static_cast<bool>(in >> tok), "mesh file {}: ASCII PLY data ends in {} {} (property '{}'): fewer values than the "
               "header declares", path, e.name, i, prop);
    char* end = nullptr;
    const double v = std::strtod(tok.c_str(), &end);
    SIMU_CHECK(end == tok.c_str() + tok.size(), "mesh file {}: ASCII PLY value '{}' in {} {} (property '{}') is not a number",
               path, tok.substr(0, 32), e.name, i, prop);
    return v;
  };
  for (const auto& e : elements)
    for (uint64_t i = 0; i < e.count; ++i)
      for (size_t k = 0; k < e.props.size(); ++k) {
        const double v = number(e, i, e.props[k]);
        if (e.list_count[k].empty()) continue;
        const uint64_t max = ply_count_max(e.list_count[k]);
        SIMU_CHECK(v >= 0 && v <= static_cast<double>(max) && v == std::floor(v),
                   "mesh file {}: ASCII PLY list length '{}' in {} {} (property '{}') is not an integer in [0, {}] (its "
                   "type {})", path, tok.substr(0, 32), e.name, i, e.props[k], max, e.list_count[k]);
        for (uint64_t j = 0; j < static_cast<uint64_t>(v); ++j) number(e, i, e.props[k]);
      }
}

// Checks a PLY file's header before assimp sees it: assimp 5.2's PLY reader loops forever on some
// malformed headers (an unknown property type, no end_header: fuzz/regressions/fuzz_scene/). Checks:
// "ply", a format line (ascii | binary_little_endian | binary_big_endian 1.0), only printable ASCII,
// element / property / comment / obj_info lines with known scalar types (list count and index types
// integer), "end_header" within the first 64 KiB, a "vertex" element with x, y, z, and element counts
// that fit in the bytes after the header (every element needs at least 1 byte per fixed-size value or
// list count in binary, 2 per property in ASCII). Throws simu::Error naming the file, line and problem.
// One function on purpose (~120 lines): a single pass over the header lines, each kind of line checked
// where it is met, as the PLY grammar reads.
void check_ply_header(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  SIMU_CHECK(in.good(), "mesh file {}: cannot open it", path);
  std::error_code ec;
  const uint64_t file_size = std::filesystem::file_size(path, ec);
  SIMU_CHECK(!ec, "mesh file {}: cannot read its size ({})", path, ec.message());
  constexpr size_t kMaxHeader = 64 * 1024;
  std::string head(static_cast<size_t>(std::min<uint64_t>(file_size, kMaxHeader)), '\0');
  in.read(head.data(), static_cast<std::streamsize>(head.size()));
  head.resize(static_cast<size_t>(in.gcount()));
  auto bad = [&](int line, const std::string& why) {
    fail_hint("write the PLY with a standard tool (trimesh, Open3D, MeshLab, Blender)",
              "mesh file {}: malformed PLY header (line {}): {}", path, line, why);
  };
  std::vector<PlyElement> elements;
  bool binary = false, have_format = false, ended = false;
  size_t pos = 0;
  int line_no = 0;
  while (pos < head.size() && !ended) {
    size_t end = head.find('\n', pos);
    if (end == std::string::npos) bad(line_no + 1, "no 'end_header' line in the first 64 KiB");
    std::string line = head.substr(pos, end - pos);
    pos = end + 1;
    ++line_no;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    for (unsigned char c : line)
      if (c < 0x20 ? c != '\t' : c > 0x7e) bad(line_no, fmt::format("byte 0x{:02x} is not printable ASCII", c));
    std::istringstream ss(line);
    std::vector<std::string> tok;
    for (std::string t; ss >> t;) tok.push_back(t);
    if (line_no == 1) {
      if (tok.size() != 1 || tok[0] != "ply") bad(1, "the first line must be 'ply'");
      continue;
    }
    if (line_no == 2) {
      if (tok.size() != 3 || tok[0] != "format" || tok[2] != "1.0" ||
          (tok[1] != "ascii" && tok[1] != "binary_little_endian" && tok[1] != "binary_big_endian"))
        bad(2, "expected 'format ascii|binary_little_endian|binary_big_endian 1.0'");
      binary = tok[1] != "ascii";
      have_format = true;
      continue;
    }
    if (tok.empty() || tok[0] == "comment" || tok[0] == "obj_info") continue;
    if (tok[0] == "end_header") {
      if (tok.size() != 1) bad(line_no, "'end_header' takes nothing after it");
      ended = true;
    } else if (tok[0] == "element") {
      if (tok.size() != 3) bad(line_no, "expected 'element NAME COUNT'");
      const std::string& c = tok[2];
      if (c.empty() || c.size() > 10 || c.find_first_not_of("0123456789") != std::string::npos ||
          std::stoull(c) > std::numeric_limits<uint32_t>::max())
        bad(line_no, fmt::format("element '{}' count '{}' is not an integer in [0, 2^32)", tok[1], c));
      elements.push_back({tok[1], std::stoull(c), 0, {}, {}});
    } else if (tok[0] == "property") {
      if (elements.empty()) bad(line_no, "a property before any element");
      auto& e = elements.back();
      if (tok.size() >= 2 && tok[1] == "list") {
        if (tok.size() != 5 || !ply_integer_type(tok[2]) || !ply_integer_type(tok[3]))
          bad(line_no, "expected 'property list COUNT_TYPE INDEX_TYPE NAME' with integer types (uchar, int, ...)");
        e.min_bytes += binary ? static_cast<uint64_t>(ply_type_size(tok[2])) : 2;
        e.props.push_back(tok[4]);
        e.list_count.push_back(tok[2]);
      } else {
        if (tok.size() != 3 || !ply_type_size(tok[1]))
          bad(line_no, "expected 'property TYPE NAME' with TYPE one of char uchar short ushort int uint float double "
                       "(or int8 ... float64)");
        e.min_bytes += binary ? static_cast<uint64_t>(ply_type_size(tok[1])) : 2;
        e.props.push_back(tok[2]);
        e.list_count.push_back("");
      }
    } else {
      bad(line_no, fmt::format("unknown keyword '{}' (expected element, property, comment, obj_info, end_header)",
                               tok[0]));
    }
  }
  if (!ended) bad(line_no, "no 'end_header' line");
  if (!have_format) bad(2, "no format line");
  // An ASCII body is text: a NUL or other control byte makes assimp 5.2 allocate gigabytes
  // (fuzz/regressions/fuzz_scene/assimp_ply_ascii_nul_oom.bin).
  if (!binary) {
    in.clear();
    in.seekg(static_cast<std::streamoff>(pos));
    char buf[65536];
    uint64_t offset = pos;
    while (in.read(buf, sizeof buf) || in.gcount() > 0) {
      for (std::streamsize k = 0; k < in.gcount(); ++k) {
        const unsigned char c = static_cast<unsigned char>(buf[k]);
        SIMU_CHECK(!(c < 0x20 ? c != '\t' && c != '\n' && c != '\r' : c > 0x7e),
                   "mesh file {}: ASCII PLY data holds byte 0x{:02x} at offset {} (expected text: numbers and spaces)",
                   path, c, offset + static_cast<uint64_t>(k));
      }
      offset += static_cast<uint64_t>(in.gcount());
    }
  }
  // Element counts against the data bytes after the header.
  const uint64_t data_bytes = file_size - pos;
  uint64_t need = 0;
  bool have_xyz = false;
  for (const auto& e : elements) {
    if (e.count > 0 && e.props.empty())
      bad(line_no, fmt::format("element '{}' has {} entries but no properties", e.name, e.count));
    // count < 2^32 and min_bytes < 2^16 * 8 (the header is < 64 KiB): no overflow.
    const uint64_t b = e.count * e.min_bytes;
    SIMU_CHECK(need + b <= data_bytes,
               "mesh file {}: PLY header declares {} {} element(s) needing at least {} bytes, but only {} bytes follow "
               "the header (truncated file or wrong counts)",
               path, e.count, e.name, b, data_bytes);
    need += b;
    if (e.name == "vertex") {
      auto has = [&](const char* n) { return std::find(e.props.begin(), e.props.end(), n) != e.props.end(); };
      have_xyz = has("x") && has("y") && has("z");
    }
  }
  SIMU_CHECK(have_xyz, "mesh file {}: the PLY header declares no 'vertex' element with x, y, z properties", path);
  if (!binary) check_ply_ascii_body(path, in, pos, elements);
}

}  // namespace

Mesh read_mesh(const std::string& path) {
  SIMU_CHECK(std::filesystem::is_regular_file(path), "mesh file {} does not exist", path);
  {
    // Assimp picks the PLY reader from the extension or the "ply" magic: check those headers first.
    std::string ext = std::filesystem::path(path).extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
    char magic[3] = {};
    std::ifstream(path, std::ios::binary).read(magic, 3);
    if (ext == ".ply" || std::memcmp(magic, "ply", 3) == 0) check_ply_header(path);
  }
  Assimp::Importer importer;
  // Import and validate first (face indices inside the vertex array, no empty faces, ...): assimp's
  // post-processing steps trust the data and abort() or read out of bounds on a malformed file.
  const aiScene* sc = importer.ReadFile(path, aiProcess_ValidateDataStructure);
  if (!sc || !sc->mRootNode) fail("mesh file {}: assimp could not read it ({})", path, importer.GetErrorString());
  // Validation skips some face checks when an importer left the primitive types unset (PLY), and a
  // face with no indices then fails an ai_assert (abort) in assimp 5.2's triangulation step
  // (fuzz/regressions/fuzz_scene/assimp_triangulate_assert.bin): check every face here, then set the
  // primitive types from the faces.
  for (unsigned m = 0; m < sc->mNumMeshes; ++m) {
    aiMesh* am = sc->mMeshes[m];
    SIMU_CHECK(am && (am->mNumFaces == 0 || am->mFaces), "mesh file {}: sub-mesh {} has no face array", path, m);
    unsigned types = 0;
    for (unsigned i = 0; i < am->mNumFaces; ++i) {
      const aiFace& face = am->mFaces[i];
      SIMU_CHECK(face.mNumIndices > 0 && face.mIndices, "mesh file {}: face {} of sub-mesh {} has no vertex indices",
                 path, i, m);
      for (unsigned k = 0; k < face.mNumIndices; ++k)
        SIMU_CHECK(face.mIndices[k] < am->mNumVertices,
                   "mesh file {}: face {} of sub-mesh {} uses vertex index {}, expected < {} (its vertex count)", path,
                   i, m, face.mIndices[k], am->mNumVertices);
      const unsigned n = face.mNumIndices;
      types |= n == 1 ? aiPrimitiveType_POINT : n == 2 ? aiPrimitiveType_LINE : n == 3 ? aiPrimitiveType_TRIANGLE
                                                                                        : aiPrimitiveType_POLYGON;
    }
    am->mPrimitiveTypes = types;
  }
  // Triangulate, bake node transforms into the vertices, merge duplicated vertices.
  sc = importer.ApplyPostProcessing(aiProcess_Triangulate | aiProcess_PreTransformVertices |
                                    aiProcess_JoinIdenticalVertices | aiProcess_SortByPType);
  if (!sc || !sc->mRootNode) fail("mesh file {}: assimp could not process it ({})", path, importer.GetErrorString());
  // Concatenate the triangles of every sub-mesh.
  // Every vertex finite, every face index inside its sub-mesh, the total within int's range.
  std::vector<double> v;
  std::vector<int> f;
  for (unsigned m = 0; m < sc->mNumMeshes; ++m) {
    const aiMesh* am = sc->mMeshes[m];
    SIMU_CHECK(am && (am->mNumVertices == 0 || am->mVertices), "mesh file {}: sub-mesh {} has no vertex array", path, m);
    SIMU_CHECK(v.size() / 3 + am->mNumVertices <= static_cast<size_t>(std::numeric_limits<int>::max()),
               "mesh file {}: more than 2^31 - 1 vertices", path);
    const int base = static_cast<int>(v.size() / 3);
    for (unsigned i = 0; i < am->mNumVertices; ++i) {
      const aiVector3D& p = am->mVertices[i];
      SIMU_CHECK(std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z),
                 "mesh file {}: vertex {} of sub-mesh {} is not finite ({}, {}, {})", path, i, m, p.x, p.y, p.z);
      v.push_back(p.x);
      v.push_back(p.y);
      v.push_back(p.z);
    }
    for (unsigned i = 0; i < am->mNumFaces; ++i) {
      const aiFace& face = am->mFaces[i];
      if (face.mNumIndices != 3) continue;  // points and lines
      for (int k = 0; k < 3; ++k) {
        SIMU_CHECK(face.mIndices[k] < am->mNumVertices,
                   "mesh file {}: face {} of sub-mesh {} uses vertex index {}, expected < {} (its vertex count)", path,
                   i, m, face.mIndices[k], am->mNumVertices);
        f.push_back(base + static_cast<int>(face.mIndices[k]));
      }
    }
  }
  SIMU_CHECK(!v.empty(), "mesh file {}: no vertices", path);
  SIMU_CHECK(!f.empty(), "mesh file {}: no triangles", path);
  Mesh mesh;
  mesh.V = Eigen::Map<Eigen::Matrix<double, -1, 3, Eigen::RowMajor>>(v.data(), static_cast<Eigen::Index>(v.size() / 3), 3);
  mesh.F = Eigen::Map<Eigen::Matrix<int, -1, 3, Eigen::RowMajor>>(f.data(), static_cast<Eigen::Index>(f.size() / 3), 3);
  return mesh;
}

void write_mesh(const Mesh& mesh, const std::string& path) {
  SIMU_CHECK(!mesh.empty(), "write_mesh {}: empty mesh", path);
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
  const char* format = nullptr;
  if (ext == ".obj") format = "objnomtl";
  else if (ext == ".ply") format = "plyb";
  else if (ext == ".glb") format = "glb2";
  else if (ext == ".gltf") format = "gltf2";
  else if (ext == ".stl") format = "stlb";
  else fail_hint("use .obj, .ply, .glb, .gltf or .stl", "write_mesh {}: unknown extension '{}'", path, ext);
  // Build a one-mesh aiScene (the scene owns and frees the arrays).
  aiScene sc;
  sc.mRootNode = new aiNode();
  sc.mMaterials = new aiMaterial*[1];
  sc.mMaterials[0] = new aiMaterial();
  sc.mNumMaterials = 1;
  sc.mMeshes = new aiMesh*[1];
  sc.mNumMeshes = 1;
  auto* am = new aiMesh();
  sc.mMeshes[0] = am;
  am->mMaterialIndex = 0;
  am->mPrimitiveTypes = aiPrimitiveType_TRIANGLE;
  sc.mRootNode->mMeshes = new unsigned[1];
  sc.mRootNode->mMeshes[0] = 0;
  sc.mRootNode->mNumMeshes = 1;
  am->mNumVertices = static_cast<unsigned>(mesh.V.rows());
  am->mVertices = new aiVector3D[am->mNumVertices];
  for (unsigned i = 0; i < am->mNumVertices; ++i)
    am->mVertices[i] = aiVector3D(static_cast<ai_real>(mesh.V(i, 0)), static_cast<ai_real>(mesh.V(i, 1)),
                                  static_cast<ai_real>(mesh.V(i, 2)));
  am->mNumFaces = static_cast<unsigned>(mesh.F.rows());
  am->mFaces = new aiFace[am->mNumFaces];
  for (unsigned i = 0; i < am->mNumFaces; ++i) {
    am->mFaces[i].mNumIndices = 3;
    am->mFaces[i].mIndices = new unsigned[3];
    for (int k = 0; k < 3; ++k) am->mFaces[i].mIndices[k] = static_cast<unsigned>(mesh.F(i, k));
  }
  // Export into memory, then write atomically.
  Assimp::Exporter exporter;
  const aiExportDataBlob* blob = exporter.ExportToBlob(&sc, format);
  if (!blob) fail("write_mesh {}: assimp export failed ({})", path, exporter.GetErrorString());
  fs::atomic_write(path, std::string_view(static_cast<const char*>(blob->data), blob->size));
}

Aabb mesh_aabb(const Mesh& mesh) {
  Aabb b;
  if (mesh.V.rows() == 0) return b;
  b.min = mesh.V.colwise().minCoeff().transpose();
  b.max = mesh.V.colwise().maxCoeff().transpose();
  return b;
}

int nonmanifold_edges(const Mesh& mesh) {
  std::map<std::pair<int, int>, int> uses;
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f)
    for (int k = 0; k < 3; ++k) {
      const int a = mesh.F(f, k), b = mesh.F(f, (k + 1) % 3);
      ++uses[{std::min(a, b), std::max(a, b)}];
    }
  int n = 0;
  for (const auto& [e, c] : uses) n += c > 2;
  return n;
}

std::string mesh_problem(const Mesh& mesh) {
  if (mesh.V.rows() == 0) return "mesh has no vertices";
  if (mesh.F.rows() == 0) return "mesh has no faces";
  if (!mesh.V.allFinite()) return "mesh has non-finite vertex coordinates";
  if (mesh.F.minCoeff() < 0 || mesh.F.maxCoeff() >= mesh.V.rows())
    return fmt::format("mesh face index out of range [0, {})", mesh.V.rows());
  const auto b = mesh_aabb(mesh);
  if (b.size().maxCoeff() <= 0) return "mesh has zero extent";
  return "";
}

Mesh clean_mesh(const Mesh& mesh, double area_eps) {
  // Keep faces with three distinct in-range indices and non-zero area.
  std::vector<int> keep;
  for (Eigen::Index i = 0; i < mesh.F.rows(); ++i) {
    const int a = mesh.F(i, 0), b = mesh.F(i, 1), c = mesh.F(i, 2);
    if (a == b || b == c || a == c) continue;
    if (std::min({a, b, c}) < 0 || std::max({a, b, c}) >= mesh.V.rows()) continue;
    const Vec3 pa = mesh.V.row(a), pb = mesh.V.row(b), pc = mesh.V.row(c);
    const double area = 0.5 * (pb - pa).cross(pc - pa).norm();
    if (!(area > area_eps)) continue;
    keep.push_back(static_cast<int>(i));
  }
  // Reindex the referenced vertices.
  std::vector<int> remap(mesh.V.rows(), -1);
  int nv = 0;
  for (int i : keep)
    for (int k = 0; k < 3; ++k)
      if (remap[mesh.F(i, k)] < 0) remap[mesh.F(i, k)] = nv++;
  Mesh out;
  out.V.resize(nv, 3);
  for (Eigen::Index i = 0; i < mesh.V.rows(); ++i)
    if (remap[i] >= 0) out.V.row(remap[i]) = mesh.V.row(i);
  out.F.resize(static_cast<Eigen::Index>(keep.size()), 3);
  for (size_t j = 0; j < keep.size(); ++j)
    for (int k = 0; k < 3; ++k) out.F(j, k) = remap[mesh.F(keep[j], k)];
  return out;
}

double canonicalize(Mesh& mesh) {
  const auto b = mesh_aabb(mesh);
  const double longest = b.size().maxCoeff();
  SIMU_CHECK(longest > 0 && std::isfinite(longest), "canonicalize: mesh has zero or non-finite extent");
  const double factor = 1.0 / longest;
  const Eigen::RowVector3d c = b.center().transpose();
  for (Eigen::Index i = 0; i < mesh.V.rows(); ++i) mesh.V.row(i) = (mesh.V.row(i) - c) * factor;
  return factor;
}

double signed_volume(const Mesh& mesh) {
  double vol = 0;
  for (Eigen::Index i = 0; i < mesh.F.rows(); ++i) {
    const Vec3 a = mesh.V.row(mesh.F(i, 0)), b = mesh.V.row(mesh.F(i, 1)), c = mesh.V.row(mesh.F(i, 2));
    vol += a.dot(b.cross(c));
  }
  return vol / 6.0;
}

Mesh box_mesh(const Vec3& h) {
  Mesh m;
  m.V.resize(8, 3);
  for (int i = 0; i < 8; ++i) m.V.row(i) << ((i & 1) ? h.x() : -h.x()), ((i & 2) ? h.y() : -h.y()), ((i & 4) ? h.z() : -h.z());
  // Two triangles per face, counter-clockwise seen from outside.
  m.F.resize(12, 3);
  m.F << 0, 2, 3, 0, 3, 1,  // -z
      4, 5, 7, 4, 7, 6,     // +z
      0, 1, 5, 0, 5, 4,     // -y
      2, 6, 7, 2, 7, 3,     // +y
      0, 4, 6, 0, 6, 2,     // -x
      1, 3, 7, 1, 7, 5;     // +x
  return m;
}

Mesh prism_mesh(const std::vector<Eigen::Vector2d>& poly, double hh) {
  const int n = static_cast<int>(poly.size());
  SIMU_CHECK(n >= 3, "prism_mesh: polygon needs 3 or more vertices, got {}", n);
  Mesh m;
  m.V.resize(2 * n, 3);
  for (int i = 0; i < n; ++i) {
    m.V.row(i) << poly[i].x(), poly[i].y(), -hh;      // bottom ring
    m.V.row(n + i) << poly[i].x(), poly[i].y(), hh;   // top ring
  }
  std::vector<Eigen::Vector3i> f;
  // Caps: fans from vertex 0 (top counter-clockwise seen from +z, bottom reversed).
  for (int i = 1; i + 1 < n; ++i) {
    f.emplace_back(n, n + i, n + i + 1);
    f.emplace_back(0, i + 1, i);
  }
  // Sides: two triangles per edge, outward.
  for (int i = 0; i < n; ++i) {
    const int j = (i + 1) % n;
    f.emplace_back(i, j, n + j);
    f.emplace_back(i, n + j, n + i);
  }
  m.F.resize(static_cast<Eigen::Index>(f.size()), 3);
  for (size_t k = 0; k < f.size(); ++k) m.F.row(static_cast<Eigen::Index>(k)) = f[k].transpose();
  return m;
}

Mesh quad_mesh(const Vec3& a, const Vec3& b, const Vec3& c, const Vec3& d) {
  Mesh m;
  m.V.resize(4, 3);
  m.V << a.transpose(), b.transpose(), c.transpose(), d.transpose();
  m.F.resize(2, 3);
  m.F << 0, 1, 2, 0, 2, 3;
  return m;
}

Mesh revolve_mesh(const std::vector<std::pair<double, double>>& prof, int S) {
  const int P = static_cast<int>(prof.size());
  SIMU_CHECK(P >= 2 && S >= 3, "revolve_mesh: need >= 2 profile points and >= 3 segments (got {}, {})", P, S);
  for (int k = 0; k < P; ++k) {
    SIMU_CHECK(std::isfinite(prof[k].first) && std::isfinite(prof[k].second) && prof[k].second >= 0,
               "revolve_mesh: profile point {} is ({}, {}): need finite values and radius >= 0", k, prof[k].first,
               prof[k].second);
    SIMU_CHECK(k == 0 || k == P - 1 || prof[k].second > 0, "revolve_mesh: interior profile point {} has radius 0", k);
  }
  // Ends of radius 0 are poles (no ring); the other profile points each get a ring.
  const int k0 = prof.front().second > 0 ? 0 : 1, k1 = prof.back().second > 0 ? P - 1 : P - 2;
  const int K = k1 - k0 + 1;
  SIMU_CHECK(K >= 1, "revolve_mesh: a profile of two poles has no surface");
  constexpr double kTwoPi = 6.283185307179586476925;
  Mesh m;
  m.V.resize(2 + K * S, 3);
  m.V.row(0) << 0, prof.front().first, 0;  // top centre or pole
  for (int k = 0; k < K; ++k)
    for (int i = 0; i < S; ++i) {
      const double th = kTwoPi * i / S, r = prof[k0 + k].second;
      m.V.row(1 + k * S + i) << r * std::cos(th), prof[k0 + k].first, r * std::sin(th);
    }
  const int bottom = 1 + K * S;
  m.V.row(bottom) << 0, prof.back().first, 0;
  std::vector<Eigen::Vector3i> f;
  auto ring = [&](int k, int i) { return 1 + k * S + (i % S); };
  // Top and bottom fans (caps or pole fans), then the side quads between consecutive rings.
  for (int i = 0; i < S; ++i) {
    f.emplace_back(0, ring(0, i), ring(0, i + 1));
    f.emplace_back(bottom, ring(K - 1, i + 1), ring(K - 1, i));
    for (int k = 0; k + 1 < K; ++k) {
      f.emplace_back(ring(k, i), ring(k + 1, i), ring(k + 1, i + 1));
      f.emplace_back(ring(k, i), ring(k + 1, i + 1), ring(k, i + 1));
    }
  }
  m.F.resize(static_cast<Eigen::Index>(f.size()), 3);
  for (size_t k = 0; k < f.size(); ++k) m.F.row(static_cast<Eigen::Index>(k)) = f[k].transpose();
  return m;
}

uint64_t fnv1a64(const void* data, size_t n, uint64_t seed) {
  uint64_t h = seed;
  const auto* p = static_cast<const unsigned char*>(data);
  for (size_t i = 0; i < n; ++i) {
    h ^= p[i];
    h *= 1099511628211ULL;
  }
  return h;
}

uint64_t mesh_hash(const Mesh& mesh) {
  uint64_t h = fnv1a64(mesh.V.data(), sizeof(double) * static_cast<size_t>(mesh.V.size()));
  return fnv1a64(mesh.F.data(), sizeof(int) * static_cast<size_t>(mesh.F.size()), h);
}

}  // namespace simu::physics
