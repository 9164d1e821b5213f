#include "core/build_info.h"

#include <cholmod.h>
#include <dlfcn.h>
#include <omp.h>

#include <Eigen/Core>
#include <filesystem>
#include <system_error>

extern "C" {
// Fortran BLAS entry point, resolved through CHOLMOD's own link to libblas.so.3.
void dgemm_(const char*, const char*, const int*, const int*, const int*, const double*,
            const double*, const int*, const double*, const int*, const double*, double*,
            const int*);
}

namespace kinema {

namespace {

std::string blas_library() {
  Dl_info info{};
  if (dladdr(reinterpret_cast<void*>(&dgemm_), &info) && info.dli_fname) {
    // Debian's libblas.so.3 is an alternatives symlink: report the library it resolves to.
    std::error_code ec;
    const auto real = std::filesystem::canonical(info.dli_fname, ec);
    return ec ? std::string(info.dli_fname) : real.string();
  }
  return "unknown";
}

// OpenBLAS identifies itself through openblas_get_config(); other BLAS libraries lack it.
std::string blas_config() {
  using ConfigFn = char* (*)();
  auto fn = reinterpret_cast<ConfigFn>(dlsym(RTLD_DEFAULT, "openblas_get_config"));
  return fn ? std::string(fn()) : std::string("not OpenBLAS (reference or other BLAS)");
}

}  // namespace

std::map<std::string, std::string> build_info() {
  int v[3] = {0, 0, 0};
  cholmod_version(v);
  return {
      {"version", KINEMA_VERSION},
      {"compiler", KINEMA_CXX_COMPILER},
      {"flags", KINEMA_CXX_FLAGS},
      {"build_type", KINEMA_BUILD_TYPE},
      {"openmp", std::to_string(_OPENMP)},
      {"eigen", std::to_string(EIGEN_WORLD_VERSION) + "." + std::to_string(EIGEN_MAJOR_VERSION) +
                    "." + std::to_string(EIGEN_MINOR_VERSION)},
      {"cholmod", std::to_string(v[0]) + "." + std::to_string(v[1]) +
                      "." + std::to_string(v[2])},
      {"blas", blas_library()},
      {"blas_config", blas_config()},
  };
}

}  // namespace kinema
