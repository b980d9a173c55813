#include <omp.h>

#include "core/backend.hpp"

namespace cb {
int cpu_threads() { return omp_get_max_threads(); }
}  // namespace cb
