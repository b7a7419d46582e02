#include "core/exec/background.hpp"

#include <utility>

namespace amalgam::exec {

BackgroundWorker::BackgroundWorker(bool threaded) : threaded_(threaded) {
  if (threaded_) thread_ = std::thread([this] { loop(); });
}

BackgroundWorker::~BackgroundWorker() {
  if (!threaded_) return;
  {
    std::unique_lock<std::mutex> lock(m_);
    cv_.wait(lock, [this] { return !busy_; });
    stop_ = true;
  }
  cv_.notify_all();
  thread_.join();
}

void BackgroundWorker::loop() {
  std::unique_lock<std::mutex> lock(m_);
  for (;;) {
    cv_.wait(lock, [this] { return stop_ || busy_; });
    if (!busy_) return;  // stop_ with nothing in flight
    std::function<void()> job = std::move(job_);
    lock.unlock();
    std::exception_ptr error;
    try {
      job();
    } catch (...) {
      error = std::current_exception();
    }
    job = nullptr;  // the snapshot it captured is freed before the slot is free again
    lock.lock();
    error_ = error;
    busy_ = false;
    cv_.notify_all();
  }
}

void BackgroundWorker::wait() {
  if (!threaded_) return;
  std::exception_ptr error;
  {
    std::unique_lock<std::mutex> lock(m_);
    cv_.wait(lock, [this] { return !busy_; });
    std::swap(error, error_);
  }
  if (error) std::rethrow_exception(error);
}

void BackgroundWorker::submit(std::function<void()> job) {
  if (!threaded_) {
    job();
    return;
  }
  wait();
  {
    std::lock_guard<std::mutex> lock(m_);
    job_ = std::move(job);
    busy_ = true;
  }
  cv_.notify_all();
}

}  // namespace amalgam::exec
