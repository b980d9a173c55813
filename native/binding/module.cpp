// The pybind11 module clothball._native: declarations only. Validation lives in the Python
// facade (clothball.game.sim.cloth); stepping releases the GIL.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include "binding/arrays.hpp"
#include "binding/falcon.hpp"
#include "core/backend.hpp"
#include "core/tiled_plan.hpp"

namespace py = pybind11;
void bind_batch(py::module_& m);  // binding/batch.cpp
void bind_loop(py::module_& m);   // binding/loop.cpp
void bind_pump(py::module_& m);   // binding/pump.cpp
void bind_follow(py::module_& m); // binding/pump.cpp
void bind_load_clients(py::module_& m);  // binding/load_clients.cpp
using cbind::Array;

namespace {

class Engine {
 public:
  Engine(const std::string& backend, bool dbl, const cb::Config& c)
      : n_(c.n), impl_(cbind::backend_factory(backend, dbl)(c)) {}
  void configure(const cb::Config& c) { impl_->configure(cb::per_node(c)); }
  void set_hips(Array h) { io().set_hips(h); }
  void set_wind(Array w) { io().set_wind(w); }
  bool state_finite() { return impl_->state_finite(); }
  bool ball_contact_on() { return impl_->ball_contact_on(); }
  unsigned compiled_effects() const { return impl_->compiled_effects(); }
  std::string path() const { return impl_->path(); }
  void set_state(Array p, Array v) { io().set_state(p, v); }
  Array positions() { return io().positions(); }
  Array velocities() { return io().velocities(); }
  Array normals() { return io().normals(); }
  void set_ball(Array pv) { io().set_ball(pv); }
  Array ball() { return io().ball(); }
  Array corners() { return io().corners(); }
  void step(int frames, int substeps, double dt) {
    py::gil_scoped_release release;
    impl_->step(frames, substeps, dt);
  }

 private:
  cbind::Arrays io() { return {*impl_, n_}; }
  int n_;
  std::unique_ptr<cb::Backend> impl_;
};

}  // namespace

PYBIND11_MODULE(_native, m) {
  m.doc() = "clothball native core: mass-spring cloth (CPU and CUDA) and the Falcon driver";
  py::class_<cb::Config>(m, "Config")
      .def(py::init<>())
      .def_readwrite("n", &cb::Config::n)
      .def_readwrite("rest_len", &cb::Config::rest_len)
      .def_readwrite("node_mass", &cb::Config::node_mass)
      .def_readwrite("k_struct", &cb::Config::k_struct)
      .def_readwrite("k_shear", &cb::Config::k_shear)
      .def_readwrite("k_bend", &cb::Config::k_bend)
      .def_readwrite("k_plate", &cb::Config::k_plate)
      .def_readwrite("struct_compress", &cb::Config::struct_compress)
      .def_property(
          "gravity", [](const cb::Config& c) { return std::array<double, 3>{c.gravity[0], c.gravity[1], c.gravity[2]}; },
          [](cb::Config& c, std::array<double, 3> g) { for (int k = 0; k < 3; ++k) c.gravity[k] = g[k]; })
      .def_readwrite("damping", &cb::Config::damping)
      .def_readwrite("ball_radius", &cb::Config::ball_radius)
      .def_readwrite("ball_mass", &cb::Config::ball_mass)
      .def_readwrite("ball_k", &cb::Config::ball_k)
      .def_readwrite("ball_damping", &cb::Config::ball_damping)
      .def_readwrite("ball_edges", &cb::Config::ball_edges)
      .def_readwrite("damping_rate", &cb::Config::damping_rate)
      .def_readwrite("ball_k_area", &cb::Config::ball_k_area)
      .def_readwrite("bending_stiffness", &cb::Config::bending_stiffness)
      .def_readwrite("coupling_k", &cb::Config::coupling_k)
      .def_readwrite("grip_radius", &cb::Config::grip_radius)
      .def_readwrite("air_density", &cb::Config::air_density)
      .def_readwrite("drag", &cb::Config::drag)
      .def_readwrite("lift", &cb::Config::lift)
      .def_readwrite("max_strain", &cb::Config::max_strain)
      .def_readwrite("strain_iterations", &cb::Config::strain_iterations)
      .def_readwrite("threads", &cb::Config::threads)
      .def_readwrite("integrator", &cb::Config::integrator)
      .def_readwrite("cg_max_iterations", &cb::Config::cg_max_iterations)
      .def_readwrite("cg_tolerance", &cb::Config::cg_tolerance)
      .def_readwrite("effects", &cb::Config::effects);

  py::class_<Engine>(m, "Engine")
      .def(py::init<const std::string&, bool, const cb::Config&>(), py::arg("backend"),
           py::arg("double_precision"), py::arg("config"))
      .def("configure", &Engine::configure)
      .def("set_hips", &Engine::set_hips)
      .def("set_wind", &Engine::set_wind)
      .def("state_finite", &Engine::state_finite)
      .def("ball_contact_on", &Engine::ball_contact_on)
      .def("compiled_effects", &Engine::compiled_effects)
      .def("path", &Engine::path)
      .def("set_state", &Engine::set_state)
      .def("positions", &Engine::positions)
      .def("velocities", &Engine::velocities)
      .def("normals", &Engine::normals)
      .def("set_ball", &Engine::set_ball)
      .def("ball", &Engine::ball)
      .def("corners", &Engine::corners)
      .def("step", &Engine::step, py::arg("frames"), py::arg("substeps"), py::arg("dt"));

  bind_batch(m);
  bind_loop(m);
  bind_pump(m);
  bind_follow(m);
  bind_load_clients(m);

  py::dict effects;
  effects["structural"] = unsigned(cb::STRUCTURAL);
  effects["shear"] = unsigned(cb::SHEAR);
  effects["bend"] = unsigned(cb::BEND);
  effects["gravity"] = unsigned(cb::GRAVITY);
  effects["damping"] = unsigned(cb::DAMPING);
  effects["ball"] = unsigned(cb::BALL);
  effects["coupling"] = unsigned(cb::COUPLING);
  effects["wind"] = unsigned(cb::WIND);
  effects["strain_limit"] = unsigned(cb::STRAIN_LIMIT);
  m.attr("EFFECT_BITS") = effects;
  py::dict integrators;
  integrators["semi_implicit_euler"] = int(cb::SEMI_IMPLICIT_EULER);
  integrators["velocity_verlet"] = int(cb::VELOCITY_VERLET);
  integrators["implicit_euler"] = int(cb::IMPLICIT_EULER);
  m.attr("INTEGRATOR_IDS") = integrators;
  m.def("cuda_unavailable_reason", &cb::cuda_unavailable_reason,
        "Empty string when a CUDA device can be used, else the reason it cannot.");
  m.def("cpu_threads", &cb::cpu_threads);
  m.def(
      "strain_sweeps",
      [](int iterations) {
        cb::Config c;
        c.effects = cb::STRAIN_LIMIT;
        c.strain_iterations = iterations;
        return cb::strain_sweeps(c);
      },
      "Strain-limiting passes (rows, then columns) a substep for strain_limit.iterations.");
  m.def(
      "tiled_plan",
      [](const cb::Config& c, bool dbl, int blocks, size_t shared_max) -> py::object {
        const size_t real = dbl ? sizeof(double) : sizeof(float);
        const cb::TiledPlan t = cb::tiled_plan_for(c, real, blocks, shared_max);
        if (!t.ok()) return py::none();
        py::dict d;
        d["tiles_y"] = t.tiles_y;
        d["tiles_x"] = t.tiles_x;
        d["th"] = t.th;
        d["tw"] = t.tw;
        d["reach"] = t.reach;
        d["shared_bytes"] = t.shared_bytes;
        d["chosen"] = cb::tiled_wanted(t, c.n);
        return d;
      },
      py::arg("config"), py::arg("double_precision"), py::arg("blocks"), py::arg("shared_max"),
      "The CUDA tiled frame's tiles for a configuration on a device of `blocks` "
      "multiprocessors and `shared_max` bytes of shared memory a block (None: it cannot run "
      "tiled there), and whether a cloth would take it (core/tiled_plan.hpp).");
  m.attr("TILED_MIN_N") = cb::kTiledMinN;
  m.attr("TILED_MIN_N_BEND") = cb::kTiledMinNBend;
  m.def("per_node", &cb::per_node, py::arg("config"),
        "The configuration with its material values turned into per-node ones, as the "
        "backends see it (damping from damping_rate, ball_k from ball_k_area, k_plate from "
        "bending_stiffness).");
  m.def("cuda_copy_bandwidth_gbs", &cb::cuda_copy_bandwidth_gbs, py::arg("bytes"),
        py::arg("reps") = 20, py::call_guard<py::gil_scoped_release>());
  clothball_falcon::bind(m);
}
