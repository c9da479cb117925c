// The library's one Embree device and its per-thread error message, shared by tracer.cpp and queries.cpp.
#pragma once

#include <embree3/rtcore.h>

#include <cstdint>
#include <string>
#include <system_error>
#include <thread>
#include <vector>

namespace visfly {

// The process-wide device (created on first use), or null with the error set.
RTCDevice shared_device();

// Set the message vf_last_error() returns on this thread.
void set_error(const std::string& message);

// Run ``work`` on this thread and on up to ``helpers`` more, and wait for all of them. ``work``
// takes its items from a shared counter, so fewer threads than asked (none could start) still
// finish everything.
template <class Work>
void run_on_threads(int64_t helpers, Work& work) {
  std::vector<std::thread> pool;
  pool.reserve(static_cast<size_t>(helpers > 0 ? helpers : 0));
  for (int64_t t = 0; t < helpers; ++t) {
    try {
      pool.emplace_back(work);
    } catch (const std::system_error&) {
      break;
    }
  }
  work();
  for (auto& t : pool) t.join();
}

}  // namespace visfly
