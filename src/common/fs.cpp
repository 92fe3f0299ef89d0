#include "common/fs.h"

#include <fcntl.h>
#include <stdio.h>  // renameat2, RENAME_EXCHANGE (glibc >= 2.28)
#include <ftw.h>
#include <signal.h>
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

namespace {
// A process that exists and is not a zombie. A killed writer whose parent died first stays a zombie
// until init reaps it (which a container's init may never do): its temporary files are stale.
bool process_alive(pid_t pid) {
  if (::kill(pid, 0) != 0) return errno != ESRCH;  // EPERM: someone else's live process
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string text((std::istreambuf_iterator<char>(stat)), std::istreambuf_iterator<char>());
  const auto close = text.rfind(')');
  return close == std::string::npos || close + 2 >= text.size() || text[close + 2] != 'Z';
}
}  // namespace

int remove_stale_temps(const std::string& path) {
  const std::filesystem::path p(path);
  const std::string name = p.filename().string();
  if (name.empty()) return 0;
  const std::filesystem::path dir = p.has_parent_path() ? p.parent_path() : std::filesystem::path(".");
  std::error_code ec;
  std::filesystem::directory_iterator it(dir, ec), end;
  if (ec) return 0;
  int removed = 0;
  for (; it != end; it.increment(ec)) {
    if (ec) break;
    const std::string n = it->path().filename().string();
    for (const char* tag : {".tmp-", ".old-"}) {
      const std::string prefix = name + tag;
      if (n.size() <= prefix.size() || n.compare(0, prefix.size(), prefix) != 0) continue;
      const std::string digits = n.substr(prefix.size());
      if (digits.size() > 9 || digits.find_first_not_of("0123456789") != std::string::npos) continue;
      const pid_t pid = static_cast<pid_t>(std::stol(digits));
      if (pid <= 0 || pid == ::getpid() || process_alive(pid)) continue;
      remove_tree(it->path().string());
      ++removed;
    }
  }
  return removed;
}

void replace_dir(const std::string& tmp, const std::string& target) {
  fsync_dir(tmp);
  struct stat st {};
  if (::lstat(target.c_str(), &st) != 0) {
    atomic_rename(tmp, target);
    return;
  }
  if (atomic_exchange(tmp, target)) {
    remove_tree(tmp);  // now the old content
    return;
  }
  const std::string old = target + ".old-" + std::to_string(::getpid());
  atomic_rename(target, old);
  try {
    atomic_rename(tmp, target);
  } catch (...) {
    atomic_rename(old, target);
    throw;
  }
  remove_tree(old);
}

void check_overwrite(const std::string& path, bool overwrite, const std::string& what) {
  struct stat st {};
  if (overwrite || ::lstat(path.c_str(), &st) != 0) return;
  fail_hint("pass --overwrite to replace it, or choose another path", "{} '{}' already exists", what, path);
}

std::string read_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) fail("cannot open '{}' for reading", path);
  std::ostringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

}  // namespace simu::fs
