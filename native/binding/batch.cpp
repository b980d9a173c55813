// pybind11 declarations of the batch engine (native/core/batch.hpp): arrays in and out for
// every slot at once; stepping releases the GIL. Validation lives in the Python facade
// (clothball.game.sim.batch).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <string>

#include "binding/batch_engine.hpp"

namespace py = pybind11;
using cbind::BatchEngine;

void bind_batch(py::module_& m) {
  py::class_<BatchEngine>(m, "BatchEngine")
      .def(py::init<const std::string&, bool, cb::Config, int, int>(), py::arg("backend"),
           py::arg("double_precision"), py::arg("config"), py::arg("capacity"),
           py::arg("threads") = 0)
      .def("capacity", &BatchEngine::capacity)
      .def("open", &BatchEngine::open)
      .def("close", &BatchEngine::close)
      .def("set_active", &BatchEngine::set_active, py::arg("slot"), py::arg("active"))
      .def("set_hips_all", &BatchEngine::set_hips_all)
      .def("set_wind_all", &BatchEngine::set_wind_all)
      .def("corners_all", &BatchEngine::corners_all)
      .def("step", &BatchEngine::step, py::arg("frames"), py::arg("substeps"), py::arg("dt"))
      .def("set_hips", &BatchEngine::set_hips)
      .def("set_wind", &BatchEngine::set_wind)
      .def("set_state", &BatchEngine::set_state)
      .def("set_ball", &BatchEngine::set_ball)
      .def("ball", &BatchEngine::ball)
      .def("corners", &BatchEngine::corners)
      .def("positions", &BatchEngine::positions)
      .def("gather_positions", &BatchEngine::gather_positions)
      .def("velocities", &BatchEngine::velocities)
      .def("normals", &BatchEngine::normals)
      .def("ball_contact_on", &BatchEngine::ball_contact_on)
      .def("compiled_effects", &BatchEngine::compiled_effects);
}
