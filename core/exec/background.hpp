// One background thread that runs one job at a time, for work that may overlap the simulation:
// the frame loop's asynchronous output (apps/frame_loop.cpp). A one-slot queue: submit waits for
// the job in flight before handing over the next, so at most one job runs and at most one more
// is being prepared by the caller (the frame loop's bound: one frame's snapshot in flight).
// A job's exception is kept and rethrown on the caller's thread by the next submit or wait.
// The job itself is plain serial code; OpenVDB calls inside it run under
// exec::with_thread_limit of the space the job was given (the frame loop's writer space: one
// thread).
#pragma once

#include <condition_variable>
#include <exception>
#include <functional>
#include <mutex>
#include <thread>

namespace amalgam::exec {

class BackgroundWorker {
 public:
  // threaded = false runs every job inside submit, on the caller's thread (synchronous output),
  // with the same interface.
  explicit BackgroundWorker(bool threaded);
  // Waits for the job in flight (an exception it threw is dropped: the destructor runs while
  // another error leaves the frame loop) and stops the thread.
  ~BackgroundWorker();
  BackgroundWorker(const BackgroundWorker&) = delete;
  BackgroundWorker& operator=(const BackgroundWorker&) = delete;

  // Waits for the job in flight (rethrowing its exception), then starts `job`.
  void submit(std::function<void()> job);
  // Waits until no job is in flight; rethrows the exception of the last job, once.
  void wait();
  bool threaded() const { return threaded_; }

 private:
  void loop();
  const bool threaded_;
  std::mutex m_;
  std::condition_variable cv_;
  std::function<void()> job_;
  bool busy_ = false, stop_ = false;
  std::exception_ptr error_;
  std::thread thread_;
};

}  // namespace amalgam::exec
