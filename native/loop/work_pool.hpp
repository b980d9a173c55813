// A few threads that share out the items of one call (the service thread's MESH encoding:
// loop/mesh_msg.hpp, one room's message an item of ~0.5 ms of zlib). Idle workers sleep on
// a condition variable, not spinning (an OpenMP team would spin between calls, which come
// every frame or two), and the calling thread works too.
#pragma once
#include <pthread.h>

#include <condition_variable>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

namespace cb::loop {

class WorkPool {
 public:
  // `threads` in all, the caller included (1: run() calls fn on the caller alone).
  explicit WorkPool(int threads) {
    for (int w = 1; w < threads; ++w) workers_.emplace_back([this, w] { work(w); });
  }
  ~WorkPool() {
    {
      std::lock_guard<std::mutex> g(m_);
      stop_ = true;
    }
    more_.notify_all();
    for (auto& t : workers_) t.join();
  }
  WorkPool(const WorkPool&) = delete;
  WorkPool& operator=(const WorkPool&) = delete;

  int threads() const { return int(workers_.size()) + 1; }

  // fn(item, thread) for every item in [0, count), each once, `thread` in [0, threads());
  // returns when all are done. One caller at a time.
  void run(int count, const std::function<void(int, int)>& fn) {
    std::unique_lock<std::mutex> lk(m_);
    job_ = &fn;
    next_ = 0;
    count_ = pending_ = count;
    if (count > 1) more_.notify_all();
    take(lk, 0);
    done_.wait(lk, [this] { return pending_ == 0; });
    job_ = nullptr;
    count_ = 0;
  }

 private:
  // Items of the current job, one at a time, until none is left (called with m_ held).
  void take(std::unique_lock<std::mutex>& lk, int me) {
    while (next_ < count_) {
      const int item = next_++;
      const std::function<void(int, int)>* job = job_;
      lk.unlock();
      (*job)(item, me);
      lk.lock();
      if (--pending_ == 0) done_.notify_all();
    }
  }
  void work(int me) {
    pthread_setname_np(pthread_self(), "cb-mesh-encode");  // for /proc and the load bench
    std::unique_lock<std::mutex> lk(m_);
    for (;;) {
      more_.wait(lk, [this] { return stop_ || next_ < count_; });
      if (stop_) return;
      take(lk, me);
    }
  }

  std::mutex m_;
  std::condition_variable more_, done_;
  const std::function<void(int, int)>* job_ = nullptr;
  int next_ = 0, count_ = 0, pending_ = 0;
  bool stop_ = false;
  std::vector<std::thread> workers_;
};

}  // namespace cb::loop
