#include "bind_falcon.hpp"

namespace clothball_falcon {
void bind(pybind11::module_& m) {
  m.def_submodule("falcon", "Novint Falcon driver");
}
}  // namespace clothball_falcon
