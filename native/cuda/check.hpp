// Error checking for CUDA runtime calls: a failure becomes an exception naming the call.
#pragma once
#include <cuda_runtime.h>

#include <stdexcept>
#include <string>

#define CB_CUDA(call)                                                                  \
  do {                                                                                 \
    cudaError_t err_ = (call);                                                         \
    if (err_ != cudaSuccess)                                                           \
      throw std::runtime_error(std::string("CUDA error in ") + #call + ": " +          \
                               cudaGetErrorString(err_));                              \
  } while (0)
