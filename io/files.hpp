// Files from outside and files we write, handled as untrusted: inputs must be regular files of a
// bounded size, read whole; outputs go to a temporary file created exclusively (never through an
// existing name or symbolic link) and renamed into place.
#pragma once

#include <cstdint>
#include <string>

namespace amalgam {

// Size of a regular input file. Throws InputError naming the file and `what` ("scene file",
// "mesh", "checkpoint") when it cannot be opened, is a directory, a device, a FIFO or a socket.
std::uint64_t input_file_size(const std::string& path, const char* what);

// Reads a whole regular file of at most max_bytes (InputError beyond, before reading anything).
std::string read_input_file(const std::string& path, const char* what, std::uint64_t max_bytes);

// Memory the kernel reports as available to a new allocation (MemAvailable), in bytes; 0 if
// unknown.
std::uint64_t available_memory_bytes();

// A temporary file beside `target` (target + ".XXXXXX.tmp", created with O_CREAT | O_EXCL, so
// it is always a new file of ours and never an existing file or link). commit() renames it onto
// the target; rename replaces a symbolic link at the target rather than writing through it. The
// destructor removes an uncommitted file.
class TempFile {
 public:
  explicit TempFile(const std::string& target);
  ~TempFile();
  TempFile(const TempFile&) = delete;
  TempFile& operator=(const TempFile&) = delete;

  // Writes all of data at the current offset; InputError naming the target on failure.
  void write(const char* data, std::size_t n);
  // A name that opens this very file (/proc/self/fd/N), for libraries that write by name.
  std::string open_name() const;
  const std::string& name() const { return tmp_; }
  int fd() const { return fd_; }
  void commit();

 private:
  std::string target_, tmp_;
  int fd_ = -1;
  bool committed_ = false;
};

// Appends to a file that is not a symbolic link (O_APPEND | O_NOFOLLOW); creates it if missing.
void append_to_file(const std::string& path, const std::string& data);

}  // namespace amalgam
