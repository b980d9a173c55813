// The CUDA backend's integrators other than semi-implicit Euler (velocity Verlet, implicit
// Euler), each in its own translation units (cuda/verlet.cu, cuda/implicit.cu, built once
// per real type). cuda/cloth.cu hands them its device state through CudaView and captures
// what they enqueue into the frame's CUDA graph. Included by .cu files only.
#pragma once
#include <cuda_runtime.h>

#include <memory>

#include "core/params.hpp"

namespace cb {

template <class R>
struct CudaView {
  Params<R> p;
  int max_blocks;                // resident blocks of 256 threads the device holds
  Planes<R> pos[2], vel[2];      // the two state buffers
  Ball<R>* ball;                 // two: ball[b] goes with buffer b
  const FrameInputs<R>* fin;     // device copy of the frame's inputs
  int* nonfinite;                // sticky flag
};

template <class R>
class CudaIntegrator {
 public:
  virtual ~CudaIntegrator() = default;
  // Enqueue one substep from buffer b into buffer 1 - b (captured into the frame's graph:
  // no host round trips).
  virtual void substep(cudaStream_t s, const CudaView<R>& v, int b, R dt) = 0;
  // Whether prime() must run before the next frame, given the frame's inputs on the host.
  virtual bool needs_prime(const FrameInputs<R>&) { return false; }
  // Recompute what the integrator keeps, from buffer b into buffer 1 - b (state unchanged).
  virtual void prime(cudaStream_t, const CudaView<R>&, int) {}
  // The state or the ball was replaced.
  virtual void invalidate() {}
};

template <class R>
std::unique_ptr<CudaIntegrator<R>> make_cuda_verlet(const Config& c);
template <class R>
std::unique_ptr<CudaIntegrator<R>> make_cuda_implicit(const Config& c);
template <>
std::unique_ptr<CudaIntegrator<float>> make_cuda_verlet<float>(const Config& c);
template <>
std::unique_ptr<CudaIntegrator<double>> make_cuda_verlet<double>(const Config& c);
template <>
std::unique_ptr<CudaIntegrator<float>> make_cuda_implicit<float>(const Config& c);
template <>
std::unique_ptr<CudaIntegrator<double>> make_cuda_implicit<double>(const Config& c);

// nullptr for semi-implicit Euler (the backend's own kernel).
template <class R>
std::unique_ptr<CudaIntegrator<R>> make_cuda_integrator(const Config& c) {
  if (c.integrator == VELOCITY_VERLET) return make_cuda_verlet<R>(c);
  if (c.integrator == IMPLICIT_EULER) return make_cuda_implicit<R>(c);
  return nullptr;
}

}  // namespace cb
