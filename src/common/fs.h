// File helpers: atomic writes (temporary file, fsync, rename) so a crash never leaves a half file.
#pragma once

#include <string>
#include <string_view>

namespace simu::fs {

// Writes bytes to path atomically: path.tmp-<pid> is written, fsynced, renamed over path, and the
// directory fsynced. Creates parent directories. Throws simu::Error naming the path on failure.
void atomic_write(const std::string& path, std::string_view bytes);
// Reads a whole file; throws simu::Error naming the path if it cannot.
std::string read_file(const std::string& path);
// Fsyncs a directory (after renames inside it).
void fsync_dir(const std::string& dir);
// Renames src to dst atomically and fsyncs dst's directory.
void atomic_rename(const std::string& src, const std::string& dst);
// Swaps two existing paths of one filesystem in one atomic step (renameat2 RENAME_EXCHANGE) and
// fsyncs their directory. Returns false, changing nothing, where the kernel or the filesystem cannot
// (EINVAL, ENOSYS, ENOTSUP); other failures throw simu::Error naming both paths.
bool atomic_exchange(const std::string& a, const std::string& b);
// Removes a file or a directory tree, not following symbolic links; a missing path is no error.
// Throws simu::Error naming the first entry that cannot be removed. Use this instead of
// std::filesystem::remove_all: libtorch.so exports its own copy of that function, which crashes on
// non-empty directories when the dynamic linker binds to it.
void remove_tree(const std::string& path);

}  // namespace simu::fs
