// The interface both backends implement. Plain C++ (no CUDA, no pybind11) so the binding
// file and the CUDA file meet only here. Arrays cross it as float64, nodes row-major
// (i * n + j), 3 values a node.
#pragma once
#include <array>
#include <memory>
#include <string>
#include <utility>

#include "params.hpp"

namespace cb {

class Backend {
 public:
  virtual ~Backend() = default;
  virtual void configure(const Config& c) = 0;  // same n; new parameters or effect set
  virtual void set_hips(const double* h) = 0;   // 4 x 3
  virtual void set_wind(const double* w) = 0;   // 3: wind velocity for the next frames
  virtual void set_state(const double* pos, const double* vel) = 0;
  virtual void get_positions(double* out) = 0;
  virtual void get_velocities(double* out) = 0;
  virtual void get_normals(double* out) = 0;
  virtual void set_ball(const double* pv) = 0;  // position then velocity
  virtual void get_ball(double* pv) = 0;
  // Corner positions and velocities (4 x 6) as of the last frame: all that must leave the
  // device every frame.
  virtual void get_corners(double* out) = 0;
  virtual void step(int frames, int substeps, double dt) = 0;
  // False once any node's position or velocity became non-finite (sticky until set_state).
  virtual bool state_finite() = 0;
  // The effects the running kernels simulate (Effect bits + STRAIN_LIMIT): their compiled
  // set and the run-time ones (compiled_effect_set in params.hpp).
  virtual unsigned compiled_effects() const = 0;
  // Whether the next substep computes ball contact: false while no node can touch the
  // ball, when the sweep runs compiled without it (forces.hpp, contact_possible).
  virtual bool ball_contact_on() = 0;
  // How a frame is stepped: "cpu"; on CUDA "tiled" (the whole frame in one launch, the
  // state on chip: core/tiled_plan.hpp), "substeps" (a launch a substep) or
  // "node_a_thread" (the same, one node a thread: the largest cloths).
  virtual std::string path() const = 0;
};

// Each backend is compiled once per real type, in its own translation units (the effect-set
// specialisations make these the long compiles; they build in parallel).
template <class R>
std::unique_ptr<Backend> make_cpu_backend_t(const Config& c);
template <class R>
std::unique_ptr<Backend> make_cuda_backend_t(const Config& c);
template <>
std::unique_ptr<Backend> make_cpu_backend_t<float>(const Config& c);
template <>
std::unique_ptr<Backend> make_cpu_backend_t<double>(const Config& c);
template <>
std::unique_ptr<Backend> make_cuda_backend_t<float>(const Config& c);
template <>
std::unique_ptr<Backend> make_cuda_backend_t<double>(const Config& c);

// Both take the scene's configuration, material values and all (per_node in params.hpp).
inline std::unique_ptr<Backend> make_cpu_backend(const Config& c, bool dbl) {
  const Config p = per_node(c);
  return dbl ? make_cpu_backend_t<double>(p) : make_cpu_backend_t<float>(p);
}
inline std::unique_ptr<Backend> make_cuda_backend(const Config& c, bool dbl) {
  const Config p = per_node(c);
  return dbl ? make_cuda_backend_t<double>(p) : make_cuda_backend_t<float>(p);
}
// Empty when a CUDA device can be used, else why not.
std::string cuda_unavailable_reason();
int cpu_threads();
// Device-to-device copy bandwidth (bytes read + written per second / 1e9), median of reps.
double cuda_copy_bandwidth_gbs(size_t bytes, int reps);

// A table with one entry per compiled effect set: Impl<E>::fn for every E in [0, N).
template <class Fn, template <unsigned> class Impl, unsigned... E>
std::array<Fn, sizeof...(E)> effect_table(std::integer_sequence<unsigned, E...>) {
  return {{Impl<E>::fn...}};
}

// The same over [0, N), built once: a backend's dispatch on its scene's effect set.
template <class Fn, template <unsigned> class Impl, unsigned N = kNumEffectSets>
const std::array<Fn, N>& dispatch_table() {
  static const auto t = effect_table<Fn, Impl>(std::make_integer_sequence<unsigned, N>{});
  return t;
}

}  // namespace cb
