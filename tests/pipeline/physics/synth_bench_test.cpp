// Tests physics/synth_bench.h, the synthetic benchmark's evaluation: on generated scenes whose
// injected errors are known, the oracle decision follows the injection (bottom_cut -> resample, any
// other error -> stretch); the table counts what was measured; the thread count changes nothing.
#include <fmt/format.h>
#include <gtest/gtest.h>

#include "pipeline/physics/synth_bench.h"

using namespace simu::physics;

TEST(SynthBench, OracleDecisionsFollowTheInjectedErrors) {
  SynthBenchOptions o;
  o.num_scenes = 3;
  o.seed = 5;
  o.mujoco = false;
  o.synthetic.layout = "mixed";
  const SynthBenchResult r = run_synth_bench(o);
  ASSERT_EQ(r.num_scenes, 3);
  ASSERT_EQ(r.scenes.size(), 3u);
  int n = 0, resample = 0;
  for (int k = 0; k < r.num_scenes; ++k) {
    EXPECT_EQ(r.errors[k], "") << "scene " << k;
    for (const ObjectOutcome& ob : r.scenes[k].objects) {
      ++n;
      const Branch want = ob.error == InjectedError::BottomCut ? Branch::Resample : Branch::Stretch;
      EXPECT_EQ(ob.expected, want) << ob.id;
      EXPECT_TRUE(ob.decided) << ob.id;
      EXPECT_EQ(ob.got, want) << ob.id << " (" << to_string(ob.error) << ")";
      resample += ob.got == Branch::Resample;
    }
  }
  ASSERT_GT(n, 0);
  const std::string table = synth_bench_table(o, r);
  EXPECT_NE(table.find(fmt::format("({} / {} correct)", n, n)), std::string::npos) << table;
  EXPECT_NE(table.find("resample branch stand-in: stretch"), std::string::npos) << table;
  // Same scenes on 3 threads: the same table (results are collected in scene order).
  SynthBenchOptions p = o;
  p.threads = 3;
  EXPECT_EQ(synth_bench_table(p, run_synth_bench(p)), table);
}
