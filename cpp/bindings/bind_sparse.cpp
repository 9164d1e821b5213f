#include "bindings/common.h"

namespace kinema::bind {

void bind_sparse(py::module_& m) { (void)m; }

}  // namespace kinema::bind
