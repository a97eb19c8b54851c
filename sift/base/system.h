// Small helpers over the C and C++ runtime shared by the modules: errno's text and elapsed seconds.
#pragma once

#include <cerrno>
#include <chrono>
#include <cstring>
#include <string>

namespace oxbow {

// The text of the current errno (read it before any call that may change errno).
inline std::string ErrnoText() { return std::strerror(errno); }

// Seconds elapsed on the steady clock since t.
inline double SecondsSince(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}

}  // namespace oxbow
