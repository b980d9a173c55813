// CUDA device queries shared by both precisions of the CUDA backend.
#include <cuda_runtime.h>

#include <algorithm>
#include <stdexcept>
#include <string>
#include <vector>

#include "core/backend.hpp"
#include "cuda/check.hpp"

namespace cb {


std::string cuda_unavailable_reason() {
  int count = 0;
  cudaError_t err = cudaGetDeviceCount(&count);
  if (err != cudaSuccess) {
    cudaGetLastError();
    return std::string("no usable CUDA device (") + cudaGetErrorString(err) + ")";
  }
  if (count == 0) return "no CUDA device found";
  return "";
}

double cuda_copy_bandwidth_gbs(size_t bytes, int reps) {
  std::string why = cuda_unavailable_reason();
  if (!why.empty()) throw std::runtime_error("CUDA unavailable: " + why);
  char *a = nullptr, *b = nullptr;
  CB_CUDA(cudaMalloc(&a, bytes));
  CB_CUDA(cudaMalloc(&b, bytes));
  CB_CUDA(cudaMemset(a, 1, bytes));
  cudaEvent_t t0, t1;
  CB_CUDA(cudaEventCreate(&t0));
  CB_CUDA(cudaEventCreate(&t1));
  std::vector<float> ms;
  for (int r = 0; r < reps + 2; ++r) {  // two warm-up copies
    CB_CUDA(cudaEventRecord(t0));
    CB_CUDA(cudaMemcpy(b, a, bytes, cudaMemcpyDeviceToDevice));
    CB_CUDA(cudaEventRecord(t1));
    CB_CUDA(cudaEventSynchronize(t1));
    float m = 0;
    CB_CUDA(cudaEventElapsedTime(&m, t0, t1));
    if (r >= 2) ms.push_back(m);
  }
  cudaEventDestroy(t0); cudaEventDestroy(t1); cudaFree(a); cudaFree(b);
  std::sort(ms.begin(), ms.end());
  // Bytes read plus bytes written, over the median time.
  return 2.0 * double(bytes) / (double(ms[ms.size() / 2]) * 1e-3) / 1e9;
}

}  // namespace cb
