// Stand-in linked when the module is built without the CUDA backend.
#include <stdexcept>

#include "core/backend.hpp"
#include "core/batch_stepper.hpp"
#include "cuda_skipped.hpp"  // CLOTHBALL_CUDA_SKIPPED, written by CMake

namespace cb {

std::string cuda_unavailable_reason() {
  return "this build of clothball has no CUDA backend: " CLOTHBALL_CUDA_SKIPPED;
}

double cuda_copy_bandwidth_gbs(size_t, int) {
  throw std::runtime_error("CUDA unavailable: " + cuda_unavailable_reason());
}

template <>
std::unique_ptr<Backend> make_cuda_backend_t<float>(const Config&) {
  throw std::runtime_error("CUDA backend unavailable: " + cuda_unavailable_reason());
}
template <>
std::unique_ptr<Backend> make_cuda_backend_t<double>(const Config&) {
  throw std::runtime_error("CUDA backend unavailable: " + cuda_unavailable_reason());
}

// Never reached: no CUDA backend is made without CUDA.
template <>
std::unique_ptr<BatchStepper> make_cuda_batch_stepper_t<float>(Backend&, int) {
  return nullptr;
}
template <>
std::unique_ptr<BatchStepper> make_cuda_batch_stepper_t<double>(Backend&, int) {
  return nullptr;
}

}  // namespace cb
