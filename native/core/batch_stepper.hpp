// What steps a cb::Batch's slots together where a backend does better than stepping each
// alone: the CUDA backend's stepper runs one graph a frame for all slots (cuda/cloth.cu,
// CudaBatch). Plain C++, apart from backend.hpp so that adding it rebuilt no backend.
#pragma once
#include <memory>

#include "backend.hpp"

namespace cb {

class BatchStepper {
 public:
  virtual ~BatchStepper() = default;
  // Slot s was opened with backend b (made by the batch's factory): from now on it is
  // stepped here. Per-slot calls on b (state, ball, hands, read-back) keep working.
  virtual void attach(int s, Backend& b) = 0;
  // Slot s's backend is about to be freed.
  virtual void detach(int s) = 0;
  // Every slot of slots[0..m) (attached, ascending) advances `frames` frames, as each
  // backend's own step would have it.
  virtual void step(const int* slots, int m, int frames, int substeps, double dt) = 0;
  // The node positions of slots[0..m) into out (m x nodes x 3, float64) in one transfer;
  // false where the stepper has no such copy (the batch then reads slot by slot).
  virtual bool gather_positions(const int* /*slots*/, int /*m*/, double* /*out*/) {
    return false;
  }
};

// For a batch of up to `capacity` CUDA backends of `first`'s configuration (and real type):
// a stepper, or null where the backend steps each slot alone (configurations the batched
// kernels do not cover; see cuda/cloth.cu). Never called for CPU backends.
template <class R>
std::unique_ptr<BatchStepper> make_cuda_batch_stepper_t(Backend& first, int capacity);
template <>
std::unique_ptr<BatchStepper> make_cuda_batch_stepper_t<float>(Backend& first, int capacity);
template <>
std::unique_ptr<BatchStepper> make_cuda_batch_stepper_t<double>(Backend& first, int capacity);

inline std::unique_ptr<BatchStepper> make_cuda_batch_stepper(Backend& first, int capacity,
                                                             bool dbl) {
  return dbl ? make_cuda_batch_stepper_t<double>(first, capacity)
             : make_cuda_batch_stepper_t<float>(first, capacity);
}

}  // namespace cb
