// The library's C boundary, inside: a kernel's C++ exceptions become a return code and this thread's
// last-error message (mlx3d_last_error), and its arguments are checked with messages that name them.
#pragma once

#include <exception>
#include <stdexcept>
#include <string>

namespace mlx3d {

void set_last_error(const std::string& message);

// Runs body(); 0 when it returned, 2 when an argument was invalid (std::invalid_argument, as require throws) and
// 1 when it failed otherwise, with "name: what went wrong" as the last error.
template <class Body>
int guarded(const char* name, Body&& body) noexcept {
  try {
    body();
    set_last_error("");
    return 0;
  } catch (const std::invalid_argument& e) {
    set_last_error(std::string(name) + ": " + e.what());
    return 2;
  } catch (const std::exception& e) {
    set_last_error(std::string(name) + ": " + e.what());
  } catch (...) {
    set_last_error(std::string(name) + ": unknown error");
  }
  return 1;
}

inline void require(bool ok, const std::string& message) {
  if (!ok) throw std::invalid_argument(message);
}

}  // namespace mlx3d
