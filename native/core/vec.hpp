// Small 3-vector shared by the CPU and CUDA backends.
#pragma once
#include <cmath>

#if defined(__CUDACC__)
#define CB_HD __host__ __device__ __forceinline__
#elif defined(__GNUC__)
// Forced: the per-node functions must inline into the CPU loops for them to vectorise.
#define CB_HD inline __attribute__((always_inline))
#else
#define CB_HD inline
#endif
// The same for a lambda (after its parameters): GCC otherwise keeps the small lambdas of
// node_force's border path out of line, and its loops do not vectorise.
#if defined(__GNUC__) && !defined(__CUDACC__)
#define CB_HD_LAMBDA __attribute__((always_inline))
#else
#define CB_HD_LAMBDA
#endif

namespace cb {

template <class R>
struct V3 {
  R x, y, z;
};

template <class R> CB_HD V3<R> operator+(V3<R> a, V3<R> b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
template <class R> CB_HD V3<R> operator-(V3<R> a, V3<R> b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
template <class R> CB_HD V3<R> operator*(V3<R> a, R s) { return {a.x * s, a.y * s, a.z * s}; }
template <class R> CB_HD V3<R>& operator+=(V3<R>& a, V3<R> b) { a.x += b.x; a.y += b.y; a.z += b.z; return a; }
template <class R> CB_HD V3<R>& operator-=(V3<R>& a, V3<R> b) { a.x -= b.x; a.y -= b.y; a.z -= b.z; return a; }
template <class R> CB_HD R dot(V3<R> a, V3<R> b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
template <class R> CB_HD V3<R> cross(V3<R> a, V3<R> b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
template <class R> CB_HD R length(V3<R> a) { return sqrt(dot(a, a)); }

// Structure-of-arrays view of one buffer of 3-vectors: x, y and z planes of N values each.
// SoA keeps every access coalesced on the GPU and vectorisable on the CPU.
template <class R>
struct Planes {
  R* x;
  R* y;
  R* z;
  CB_HD V3<R> get(int q) const { return {x[q], y[q], z[q]}; }
  CB_HD void set(int q, V3<R> v) const { x[q] = v.x; y[q] = v.y; z[q] = v.z; }
};

// The CPU's view of the grid in its loops over the border nodes: the grid's planes, readable
// two rows beyond either end (CpuCloth pads its buffers). There node_force computes the
// terms of the absent neighbours too and selects them out (add_if in forces.hpp) instead of
// branching over them, and takes the hands' grips from a table rather than grip_node's
// branches, so that those loops vectorise. The GPU never uses it.
template <class R>
struct PaddedPlanes : Planes<R> {
  // Per node of the grid: grip_node's stiffness k (0 where no hand holds the node) and rest
  // offset, and the holding hand's hip.
  const R* grip_k;
  Planes<R> grip_offset, grip_hip;
};
template <class G>
constexpr bool kSelectsAbsent = false;
template <class R>
constexpr bool kSelectsAbsent<PaddedPlanes<R>> = true;

// A window of the n x n grid, as Planes: row `stride` apart, its element 0 the grid's node
// (i0, j0). The CUDA tiled frame (cuda/tiled.cu) keeps a tile and its halo so, on chip.
template <class R>
struct TilePlanes : Planes<R> {
  int stride, i0, j0;
};

// Where node (i, j) of the n x n grid is in a view, and the step from a node to the one a
// row below it: the per-node physics (forces.hpp) indexes its neighbours through these, so
// it runs alike on the whole grid (Planes) and on a window of it (TilePlanes).
template <class R>
CB_HD int node_at(const Planes<R>&, int n, int i, int j) { return i * n + j; }
template <class R>
CB_HD int row_step(const Planes<R>&, int n) { return n; }
template <class R>
CB_HD int node_at(const TilePlanes<R>& t, int, int i, int j) {
  return (i - t.i0) * t.stride + (j - t.j0);
}
template <class R>
CB_HD int row_step(const TilePlanes<R>& t, int) { return t.stride; }

}  // namespace cb
