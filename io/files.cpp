#include "io/files.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <vector>

#include "core/errors.hpp"

namespace amalgam {

namespace {
std::string errno_text(int e) {
  return std::strerror(e);
}
}  // namespace

std::uint64_t input_file_size(const std::string& path, const char* what) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0)
    throw InputError(path + ": cannot open " + what + ": " + errno_text(errno));
  if (S_ISDIR(st.st_mode)) throw InputError(path + ": " + what + " is a directory, not a file");
  if (!S_ISREG(st.st_mode))
    throw InputError(path + ": " + what + " is not a regular file (a device, FIFO or socket)");
  return std::uint64_t(st.st_size);
}

std::string read_input_file(const std::string& path, const char* what, std::uint64_t max_bytes) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) throw InputError(path + ": cannot open " + what + ": " + errno_text(errno));
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    const bool dir = S_ISDIR(st.st_mode);
    ::close(fd);
    throw InputError(path + ": " + what +
                     (dir ? " is a directory, not a file"
                          : " is not a regular file (a device, FIFO or socket)"));
  }
  const std::uint64_t size = std::uint64_t(st.st_size);
  if (size > max_bytes) {
    ::close(fd);
    throw InputError(path + ": " + what + " is " + std::to_string(size) +
                     " bytes, more than the limit of " + std::to_string(max_bytes));
  }
  std::string data(size, '\0');
  std::size_t got = 0;
  while (got < size) {
    const ssize_t r = ::read(fd, data.data() + got, size - got);
    if (r < 0 && errno == EINTR) continue;
    if (r <= 0) {
      const int e = errno;
      ::close(fd);
      throw InputError(path + ": cannot read " + what + ": " +
                       (r == 0 ? std::string("it shrank while being read") : errno_text(e)));
    }
    got += std::size_t(r);
  }
  ::close(fd);
  return data;
}

std::uint64_t available_memory_bytes() {
  std::ifstream in("/proc/meminfo");
  std::string key;
  std::uint64_t kb = 0;
  std::string unit;
  while (in >> key >> kb >> unit)
    if (key == "MemAvailable:") return kb * 1024;
  return 0;
}

TempFile::TempFile(const std::string& target) : target_(target) {
  std::vector<char> name(target.begin(), target.end());
  const char suffix[] = ".XXXXXX.tmp";
  name.insert(name.end(), suffix, suffix + sizeof suffix);  // with the terminating NUL
  fd_ = ::mkstemps(name.data(), 4);                         // O_CREAT | O_EXCL, mode 0600
  if (fd_ < 0) throw InputError(target + ": cannot create a file here: " + errno_text(errno));
  tmp_ = name.data();
  // mkstemps creates 0600; frames are ordinary output, readable as the umask allows.
  const mode_t mask = ::umask(0);
  ::umask(mask);
  ::fchmod(fd_, 0666 & ~mask);
}

TempFile::~TempFile() {
  if (fd_ >= 0) ::close(fd_);
  if (!committed_) ::unlink(tmp_.c_str());
}

void TempFile::write(const char* data, std::size_t n) {
  while (n > 0) {
    const ssize_t w = ::write(fd_, data, n);
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) throw InputError(target_ + ": write failed: " + errno_text(w < 0 ? errno : ENOSPC));
    data += w;
    n -= std::size_t(w);
  }
}

std::string TempFile::open_name() const {
  const std::string proc = "/proc/self/fd/" + std::to_string(fd_);
  struct stat a {
  }, b{};
  // Without /proc the library opens the temporary name itself (created by us a moment ago).
  if (::stat(proc.c_str(), &a) == 0 && ::fstat(fd_, &b) == 0 && a.st_ino == b.st_ino &&
      a.st_dev == b.st_dev)
    return proc;
  return tmp_;
}

void TempFile::commit() {
  if (::close(fd_) != 0) {
    fd_ = -1;
    throw InputError(target_ + ": write failed: " + errno_text(errno));
  }
  fd_ = -1;
  if (::rename(tmp_.c_str(), target_.c_str()) != 0)
    throw InputError(target_ +
                     ": cannot rename the temporary file into place: " + errno_text(errno));
  committed_ = true;
}

void append_to_file(const std::string& path, const std::string& data) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_APPEND | O_CREAT | O_NOFOLLOW | O_CLOEXEC, 0666);
  if (fd < 0)
    throw InputError(path + ": cannot append: " + errno_text(errno) +
                     (errno == ELOOP ? " (it is a symbolic link)" : ""));
  std::size_t done = 0;
  while (done < data.size()) {
    const ssize_t w = ::write(fd, data.data() + done, data.size() - done);
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) {
      const int e = w < 0 ? errno : ENOSPC;
      ::close(fd);
      throw InputError(path + ": cannot append: " + errno_text(e));
    }
    done += std::size_t(w);
  }
  if (::close(fd) != 0) throw InputError(path + ": cannot append: " + errno_text(errno));
}

}  // namespace amalgam
