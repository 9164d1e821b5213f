#include "bindings/common.h"

namespace kinema::bind {

void bind_poisson(py::module_& m) { (void)m; }

}  // namespace kinema::bind
