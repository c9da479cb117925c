// The library's one Embree device and its per-thread error message, shared by tracer.cpp and queries.cpp.
#pragma once

#include <embree3/rtcore.h>

#include <string>

namespace visfly {

// The process-wide device (created on first use), or null with the error set.
RTCDevice shared_device();

// Set the message vf_last_error() returns on this thread.
void set_error(const std::string& message);

}  // namespace visfly
