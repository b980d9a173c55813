// Binds the Falcon driver into clothball._native (submodule `falcon`).
#pragma once
#include <pybind11/pybind11.h>

namespace clothball_falcon {
void bind(pybind11::module_& m);
}
