// config::check_in: the domain check of a number read from a config key (closed and open lower
// bounds, the inclusive upper bound, non-finite values) and its message naming file, key path and domain.
#include "common/config_check.h"

#include <cmath>
#include <limits>

#include "test_files.h"

using simu::testing::error_of;

namespace {

// A reader of the mapping under "optim" of an in-memory file named "run.yaml".
simu::config::Reader optim_reader() {
  simu::config::Reader root(simu::config::load_text("optim: {lr: 1}\n", "run.yaml"), "run.yaml");
  return root.child("optim");
}

}  // namespace

// Values inside the domain pass; the bounds are inclusive unless the lower one is open.
TEST(ConfigCheck, AcceptsTheDomainWithItsBounds) {
  const auto r = optim_reader();
  EXPECT_NO_THROW(simu::config::check_in(r, "lr", 0.5, 0, 1, true, "(0, 1]"));
  EXPECT_NO_THROW(simu::config::check_in(r, "lr", 1.0, 0, 1, true, "(0, 1]"));
  EXPECT_NO_THROW(simu::config::check_in(r, "lr", 0.0, 0, 1, false, "[0, 1]"));
  EXPECT_NO_THROW(simu::config::check_in(r, "lr", -100.0, -100, 100, false, "[-100, 100]"));
}

// Outside the domain (an open lower bound itself, above the upper bound, NaN, infinity): an error
// naming the file, the key's full path, the domain and the value.
TEST(ConfigCheck, RejectsOutsideValuesNamingFileKeyAndDomain) {
  const auto r = optim_reader();
  const double inf = std::numeric_limits<double>::infinity();
  for (double v : {0.0, -1.0, 1.5, std::nan(""), inf, -inf}) {
    const std::string m = error_of([&] { simu::config::check_in(r, "lr", v, 0, 1, true, "(0, 1]"); });
    EXPECT_NE(m.find("run.yaml: key 'optim.lr': expected a finite number in (0, 1], got "), std::string::npos)
        << v << ": " << m;
  }
  const std::string m = error_of([&] { simu::config::check_in(r, "lr", -0.5, 0, 1, false, "[0, 1]"); });
  EXPECT_NE(m.find("in [0, 1], got -0.5"), std::string::npos) << m;
}

// int_field and choice_field (shared by the training configs): a present key is read and checked, an
// absent one keeps the default; out-of-range integers and unknown choices name file, key and value.
TEST(ConfigCheck, IntAndChoiceFields) {
  simu::config::Reader root(simu::config::load_text("data: {batch: 0, steps: 5, kind: cosine, mode: fast}\n", "run.yaml"),
                            "run.yaml");
  auto r = root.child("data");
  int64_t steps = 1, absent = 7;
  simu::config::int_field(r, "steps", steps, 1, 10);
  simu::config::int_field(r, "absent", absent, 1);
  EXPECT_EQ(steps, 5);
  EXPECT_EQ(absent, 7);
  int64_t batch = 1;
  EXPECT_NE(error_of([&] { simu::config::int_field(r, "batch", batch, 1); })
                .find("run.yaml: key 'data.batch': expected an integer >= 1, got 0"),
            std::string::npos);
  EXPECT_NE(error_of([&] { simu::config::int_field(r, "steps", steps, 6, 9); }).find("expected an integer in 6..9, got 5"),
            std::string::npos);
  std::string kind = "constant", mode = "slow";
  simu::config::choice_field(r, "kind", kind, {"constant", "cosine"});
  EXPECT_EQ(kind, "cosine");
  EXPECT_NE(error_of([&] { simu::config::choice_field(r, "mode", mode, {"slow", "exact"}); })
                .find("run.yaml: key 'data.mode': expected 'slow' or 'exact', got 'fast'"),
            std::string::npos);
}
