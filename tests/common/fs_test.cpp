// File helpers: remove_tree removes nested trees without following links; atomic_write replaces whole files.
#include "common/fs.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>

#include "common/error.h"
#include "test_util.h"

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
