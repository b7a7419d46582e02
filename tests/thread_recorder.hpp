// Records the TBB worker threads that join any task arena while it lives (a global
// tbb::task_scheduler_observer): how the tests see how many threads library code used.
#pragma once

#include <tbb/task_scheduler_observer.h>

#include <mutex>
#include <set>
#include <thread>

namespace amalgam::test {

class WorkerRecorder : public tbb::task_scheduler_observer {
 public:
  WorkerRecorder() { observe(true); }
  ~WorkerRecorder() override { observe(false); }
  void on_scheduler_entry(bool is_worker) override {
    if (!is_worker) return;
    std::lock_guard<std::mutex> lock(m_);
    workers_.insert(std::this_thread::get_id());
  }
  std::size_t workers() {
    std::lock_guard<std::mutex> lock(m_);
    return workers_.size();
  }

 private:
  std::mutex m_;
  std::set<std::thread::id> workers_;
};

}  // namespace amalgam::test
