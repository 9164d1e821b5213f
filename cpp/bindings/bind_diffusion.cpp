#include "bindings/common.h"

namespace kinema::bind {

void bind_diffusion(py::module_& m) { (void)m; }

}  // namespace kinema::bind
