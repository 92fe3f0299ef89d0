// libFuzzer target: a build_pairs manifest (src/pipeline/resample/pair_manifest.cpp parse_manifest: JSON lines,
// comments, blank lines, keys per kind, weights, duplicate ids, paths resolved against the manifest's
// folder). Input: the manifest text. Checks beyond "no crash": every good record and every issue
// carries a line number inside the text, ids are unique, and each issue has a message.
#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <set>
#include <string>

#include "common/error.h"
#include "pipeline/resample/pair_builder.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  const auto m = simu::resample::parse_manifest(text, "/data/pairs");
  const int64_t lines = 1 + static_cast<int64_t>(std::count(text.begin(), text.end(), '\n'));
  std::set<std::string> ids;
  for (const auto& r : m.pairs) {
    if (r.line < 1 || r.line > lines || r.id.empty() || !ids.insert(r.id).second || r.image.empty() || r.mask.empty())
      std::abort();
  }
  for (const auto& i : m.issues)
    if (i.line < 1 || i.line > lines || i.message.empty()) std::abort();
  if (static_cast<int64_t>(m.pairs.size() + m.issues.size()) != m.records) std::abort();
  return 0;
}
