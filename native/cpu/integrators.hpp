// The CPU backend's integrators other than semi-implicit Euler (velocity Verlet, implicit
// Euler). Each lives in its own translation units (cpu/verlet.cpp, cpu/implicit.cpp, built
// once per real type), so their effect-set specialisations compile in parallel with the
// backend's own; cpu/cloth.cpp only hands them its state through CpuView.
#pragma once
#include <memory>
#include <vector>

#include "core/params.hpp"

namespace cb {

// The CPU backend's state as an integrator sees it: two buffers of positions and
// velocities (cur is the live one), the ball, the frame's inputs.
template <class R>
struct CpuView {
  Params<R> p;
  Planes<R> pos[2], vel[2];
  int* cur;
  Ball<R>* ball;
  FrameInputs<R> fin;
  int threads;
  bool* finite;
};

template <class R>
class CpuIntegrator {
 public:
  virtual ~CpuIntegrator() = default;
  // Step `frames` frames of `substeps` substeps of dt, ending in buffer *v.cur.
  virtual void frames(CpuView<R>& v, int frames, int substeps, R dt) = 0;
  // The state or the ball was replaced: anything the integrator keeps must be recomputed.
  virtual void invalidate() {}
};

template <class R>
std::unique_ptr<CpuIntegrator<R>> make_cpu_verlet(const Config& c);
template <class R>
std::unique_ptr<CpuIntegrator<R>> make_cpu_implicit(const Config& c);
template <>
std::unique_ptr<CpuIntegrator<float>> make_cpu_verlet<float>(const Config& c);
template <>
std::unique_ptr<CpuIntegrator<double>> make_cpu_verlet<double>(const Config& c);
template <>
std::unique_ptr<CpuIntegrator<float>> make_cpu_implicit<float>(const Config& c);
template <>
std::unique_ptr<CpuIntegrator<double>> make_cpu_implicit<double>(const Config& c);

// nullptr for semi-implicit Euler (the backend's own loop).
template <class R>
std::unique_ptr<CpuIntegrator<R>> make_cpu_integrator(const Config& c) {
  if (c.integrator == VELOCITY_VERLET) return make_cpu_verlet<R>(c);
  if (c.integrator == IMPLICIT_EULER) return make_cpu_implicit<R>(c);
  return nullptr;
}

// After the frames: the state stays finite only if every thread's check (the sum of its t - t,
// see se_node_update) stayed 0 and the ball is finite.
template <class R>
inline void note_finite(CpuView<R>& v, R check_all) {
  const Ball<R>& b = *v.ball;
  const R all = b.p.x + b.p.y + b.p.z + b.v.x + b.v.y + b.v.z;
  if (check_all != R(0) || all - all != R(0)) *v.finite = false;
}

// Per-thread partial sums of K values, padded against false sharing, and their totals in
// a fixed (thread) order, so every thread gets the same, reproducible values.
template <class R, int K>
class TeamSums {
 public:
  explicit TeamSums(int threads) : parts_(size_t(threads) * kStride) {}
  // Call from every thread of the team after a worksharing loop (its barrier protects the
  // previous totals' readers); returns the totals.
  template <class Out>
  void reduce(int tid, int threads, const R (&mine)[K], Out& total) {
    for (int k = 0; k < K; ++k) parts_[size_t(tid) * kStride + k] = mine[k];
#pragma omp barrier
    for (int k = 0; k < K; ++k) total[k] = R(0);
    for (int t = 0; t < threads; ++t)
      for (int k = 0; k < K; ++k) total[k] += parts_[size_t(t) * kStride + k];
  }

 private:
  static constexpr int kStride = (K + 15) / 16 * 16;
  std::vector<R> parts_;
};

// The nodes of an n x n grid shared among the team by rows (an orphaned `omp for`): those
// within Margin of the border through edge(i, j), the others through inner(i, j), which
// then needs no bounds tests.
template <int Margin, class Edge, class Inner>
inline void grid_rows(int n, Edge&& edge, Inner&& inner) {
#pragma omp for schedule(static)
  for (int i = 0; i < n; ++i) {
    const bool inner_row = i >= Margin && i < n - Margin;
    const int j0 = inner_row ? Margin : n, j1 = inner_row ? n - Margin : n;
    for (int j = 0; j < j0; ++j) edge(i, j);
    for (int j = j0; j < j1; ++j) inner(i, j);
    for (int j = j1 > j0 ? j1 : j0; j < n; ++j) edge(i, j);
  }
}

}  // namespace cb
