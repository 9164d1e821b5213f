// What this build of kinema is: compiler, flags, OpenMP, Eigen, CHOLMOD and the BLAS that
// CHOLMOD actually runs on (found at run time, since Debian switches libblas.so.3 by alternatives).
#pragma once

#include <map>
#include <string>

namespace kinema {

std::map<std::string, std::string> build_info();

}  // namespace kinema
