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

// Temporaries of dead writers: removes every sibling of path named "<name>.tmp-<pid>" or
// "<name>.old-<pid>" whose process no longer exists (what a killed run of atomic_write,
// replace_dir or the pair cache writer leaves behind). Returns how many it removed.
int remove_stale_temps(const std::string& path);
// Puts the finished directory tmp in place of target: renamed when target does not exist, else
// swapped in one atomic step (or, where the filesystem cannot, target moved to
// "<target>.old-<pid>" first) and the old content removed. A failure leaves target as it was.
void replace_dir(const std::string& tmp, const std::string& target);
// Refuses (simu::Error naming path, with a hint about --overwrite) when path exists and overwrite
// is false; what names the output ("output directory", "--out").
void check_overwrite(const std::string& path, bool overwrite, const std::string& what);

}  // namespace simu::fs
