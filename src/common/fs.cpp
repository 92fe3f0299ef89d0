#include "common/fs.h"

#include <fcntl.h>
#include <stdio.h>  // renameat2, RENAME_EXCHANGE (glibc >= 2.28)
#include <ftw.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "common/error.h"

namespace simu::fs {

void fsync_dir(const std::string& dir) {
  const int fd = ::open(dir.empty() ? "." : dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (fd < 0) return;
  ::fsync(fd);
  ::close(fd);
}

void remove_tree(const std::string& path) {
  struct stat st {};
  if (::lstat(path.c_str(), &st) != 0 && errno == ENOENT) return;
  // Depth-first, not following links: files and links unlinked, directories removed after their contents.
  static thread_local std::string failed;
  static thread_local int failed_errno;
  failed.clear();
  failed_errno = 0;
  ::nftw(path.c_str(), [](const char* p, const struct stat*, int type, struct FTW*) -> int {
    const int rc = type == FTW_DP ? ::rmdir(p) : ::unlink(p);
    if (rc != 0 && errno != ENOENT && failed.empty()) {
      failed = p;
      failed_errno = errno;
    }
    return 0;
  }, 16, FTW_DEPTH | FTW_PHYS);
  if (!failed.empty()) fail("cannot remove '{}' (removing '{}'): {}", failed, path, std::strerror(failed_errno));
}

void atomic_rename(const std::string& src, const std::string& dst) {
  if (::rename(src.c_str(), dst.c_str()) != 0) fail("cannot rename '{}' to '{}': {}", src, dst, std::strerror(errno));
  fsync_dir(std::filesystem::path(dst).parent_path().string());
}

bool atomic_exchange(const std::string& a, const std::string& b) {
  if (::renameat2(AT_FDCWD, a.c_str(), AT_FDCWD, b.c_str(), RENAME_EXCHANGE) != 0) {
    if (errno == EINVAL || errno == ENOSYS || errno == ENOTSUP) return false;
    fail("cannot exchange '{}' and '{}': {}", a, b, std::strerror(errno));
  }
  fsync_dir(std::filesystem::path(b).parent_path().string());
  return true;
}

void atomic_write(const std::string& path, std::string_view bytes) {
  const std::filesystem::path p(path);
  if (p.has_parent_path()) std::filesystem::create_directories(p.parent_path());
  const std::string tmp = path + ".tmp-" + std::to_string(::getpid());
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  if (fd < 0) fail("cannot create '{}': {}", tmp, std::strerror(errno));
  size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (n < 0) {
      if (errno == EINTR) continue;
      const std::string why = std::strerror(errno);
      ::close(fd);
      ::unlink(tmp.c_str());
      fail("cannot write '{}': {}", tmp, why);
    }
    done += static_cast<size_t>(n);
  }
  if (::fsync(fd) != 0 || ::close(fd) != 0) {
    ::unlink(tmp.c_str());
    fail("cannot flush '{}': {}", tmp, std::strerror(errno));
  }
  atomic_rename(tmp, path);
}

std::string read_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) fail("cannot open '{}' for reading", path);
  std::ostringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

}  // namespace simu::fs
