// File helpers: remove_tree removes nested trees without following links; atomic_write replaces whole files;
// no source calls std::filesystem::remove_all (libtorch.so's exported copy crashes on non-empty folders).
#include "common/source_dir.h"
#include "common/fs.h"

#include <sys/wait.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "common/error.h"
#include "test_files.h"

namespace stdfs = std::filesystem;

// A nested tree with files and a link to a directory outside it: the tree goes, the link target stays.
TEST(Fs, RemoveTreeRemovesNestedTreeNotFollowingLinks) {
  const std::string dir = simu::testing::temp_dir("fs_remove");
  const std::string tree = dir + "/tree", keep = dir + "/keep";
  stdfs::create_directories(tree + "/a/b/c");
  stdfs::create_directories(keep);
  std::ofstream(tree + "/a/file.txt") << "x";
  std::ofstream(tree + "/a/b/c/deep.bin") << "yy";
  std::ofstream(keep + "/precious.txt") << "z";
  ASSERT_EQ(::symlink(keep.c_str(), (tree + "/a/link").c_str()), 0);
  simu::fs::remove_tree(tree);
  EXPECT_FALSE(stdfs::exists(tree));
  EXPECT_TRUE(stdfs::exists(keep + "/precious.txt"));
  // A single file, then a missing path (no error).
  simu::fs::remove_tree(keep + "/precious.txt");
  EXPECT_FALSE(stdfs::exists(keep + "/precious.txt"));
  EXPECT_NO_THROW(simu::fs::remove_tree(dir + "/does_not_exist"));
  simu::fs::remove_tree(dir);
  EXPECT_FALSE(stdfs::exists(dir));
}

// An entry that cannot be removed (read-only parent) is an error naming it. Skipped as root, who may
// remove anything.
TEST(Fs, RemoveTreeFailureNamesEntry) {
  if (::geteuid() == 0) GTEST_SKIP() << "running as root: permissions do not stop removal";
  const std::string dir = simu::testing::temp_dir("fs_remove_ro");
  stdfs::create_directories(dir + "/ro");
  std::ofstream(dir + "/ro/f.txt") << "x";
  stdfs::permissions(dir + "/ro", stdfs::perms::owner_read | stdfs::perms::owner_exec);
  try {
    simu::fs::remove_tree(dir);
    ADD_FAILURE() << "no error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("f.txt"), std::string::npos) << e.what();
  }
  stdfs::permissions(dir + "/ro", stdfs::perms::owner_all);
  simu::fs::remove_tree(dir);
}

// Temporaries of a dead writer ("<name>.tmp-<pid>", "<name>.old-<pid>") are removed by the next run;
// those of a live process, of this process and unrelated names stay.
TEST(Fs, StaleTempsOfDeadWritersAreRemoved) {
  const std::string dir = simu::testing::temp_dir("fs_stale");
  // A pid that is surely dead: a child that has exited and been reaped.
  const pid_t dead = ::fork();
  if (dead == 0) ::_exit(0);
  int status = 0;
  ::waitpid(dead, &status, 0);
  const std::string target = dir + "/adapter";
  stdfs::create_directories(target + ".tmp-" + std::to_string(dead) + "/sub");
  std::ofstream(target + ".old-" + std::to_string(dead)) << "x";
  stdfs::create_directories(target + ".tmp-" + std::to_string(::getppid()));  // alive
  stdfs::create_directories(target + ".tmp-" + std::to_string(::getpid()));   // this process
  std::ofstream(target + ".tmp-notapid") << "x";
  std::ofstream(dir + "/other.tmp-" + std::to_string(dead)) << "x";
  EXPECT_EQ(simu::fs::remove_stale_temps(target), 2);
  EXPECT_FALSE(stdfs::exists(target + ".tmp-" + std::to_string(dead)));
  EXPECT_FALSE(stdfs::exists(target + ".old-" + std::to_string(dead)));
  EXPECT_TRUE(stdfs::exists(target + ".tmp-" + std::to_string(::getppid())));
  EXPECT_TRUE(stdfs::exists(target + ".tmp-" + std::to_string(::getpid())));
  EXPECT_TRUE(stdfs::exists(target + ".tmp-notapid"));
  EXPECT_TRUE(stdfs::exists(dir + "/other.tmp-" + std::to_string(dead)));
}

// replace_dir puts a finished directory in place whole; check_overwrite refuses an existing output.
TEST(Fs, ReplaceDirAndOverwriteCheck) {
  const std::string dir = simu::testing::temp_dir("fs_replace");
  const std::string target = dir + "/out", tmp = dir + "/out.tmp-1";
  stdfs::create_directories(tmp);
  std::ofstream(tmp + "/a.txt") << "new";
  simu::fs::replace_dir(tmp, target);  // fresh
  EXPECT_EQ(simu::fs::read_file(target + "/a.txt"), "new");
  stdfs::create_directories(tmp);
  std::ofstream(tmp + "/b.txt") << "newer";
  simu::fs::replace_dir(tmp, target);  // replaces the whole directory
  EXPECT_FALSE(stdfs::exists(target + "/a.txt"));
  EXPECT_EQ(simu::fs::read_file(target + "/b.txt"), "newer");
  EXPECT_FALSE(stdfs::exists(tmp));
  try {
    simu::fs::check_overwrite(target, false, "output directory");
    ADD_FAILURE() << "no error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("output directory '" + target + "' already exists"), std::string::npos);
    EXPECT_NE(e.hint().find("--overwrite"), std::string::npos);
  }
  EXPECT_NO_THROW(simu::fs::check_overwrite(target, true, "output directory"));
  EXPECT_NO_THROW(simu::fs::check_overwrite(dir + "/absent", false, "output directory"));
}

// No source of the tree calls std::filesystem::remove_all: programs link libtorch.so, whose exported copy of it
// is what the dynamic linker binds, and it crashes on a non-empty folder (fs::remove_tree is the replacement).
TEST(Fs, NoSourceCallsStdRemoveAll) {
  namespace sfs = std::filesystem;
  const std::string needle = std::string("remove_") + "all(";  // split so this file does not match itself
  std::vector<std::string> hits;
  for (const char* top : {"src", "apps", "bench", "tests", "fuzz", "python/src"}) {
    const sfs::path root = sfs::path(simu::source_dir()) / top;
    ASSERT_TRUE(sfs::is_directory(root)) << root;
    for (const auto& e : sfs::recursive_directory_iterator(root)) {
      const std::string ext = e.path().extension().string();
      if (!e.is_regular_file() || (ext != ".cpp" && ext != ".h" && ext != ".cu")) continue;
      std::ifstream f(e.path());
      std::string line;
      for (int n = 1; std::getline(f, line); ++n) {
        const size_t code_end = line.find("//");
        if (line.substr(0, code_end).find(needle) != std::string::npos)
          hits.push_back(e.path().string() + ":" + std::to_string(n));
      }
    }
  }
  EXPECT_TRUE(hits.empty()) << "std::filesystem::remove_all called at " << hits.front() << " (and " << hits.size() - 1
                            << " more): use simu::fs::remove_tree";
}
