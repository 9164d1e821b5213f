# Finds CHOLMOD from SuiteSparse. Debian 12 ships SuiteSparse 5.12 without CMake config files,
# so look for the header and library by hand when no config package is installed.
# Defines the imported target SuiteSparse::CHOLMOD and CHOLMOD_VERSION.

find_path(CHOLMOD_INCLUDE_DIR cholmod.h
  PATH_SUFFIXES suitesparse
  HINTS ENV SUITESPARSE_ROOT ENV CONDA_PREFIX)
find_library(CHOLMOD_LIBRARY cholmod HINTS ENV SUITESPARSE_ROOT ENV CONDA_PREFIX)
find_library(SUITESPARSECONFIG_LIBRARY suitesparseconfig HINTS ENV SUITESPARSE_ROOT ENV CONDA_PREFIX)

set(_cholmod_version_header "${CHOLMOD_INCLUDE_DIR}/cholmod.h")
if(EXISTS "${CHOLMOD_INCLUDE_DIR}/cholmod_core.h")  # SuiteSparse 5.x keeps the version there
  set(_cholmod_version_header "${CHOLMOD_INCLUDE_DIR}/cholmod_core.h")
endif()
if(CHOLMOD_INCLUDE_DIR AND EXISTS "${_cholmod_version_header}")
  file(STRINGS "${_cholmod_version_header}" _cholmod_version_lines
       REGEX "^#define CHOLMOD_(MAIN|SUB)_VERSION[ \t]+[0-9]+")
  string(REGEX REPLACE ".*CHOLMOD_MAIN_VERSION[ \t]+([0-9]+).*" "\\1" _major "${_cholmod_version_lines}")
  string(REGEX REPLACE ".*CHOLMOD_SUB_VERSION[ \t]+([0-9]+).*" "\\1" _minor "${_cholmod_version_lines}")
  set(CHOLMOD_VERSION "${_major}.${_minor}")
endif()

include(FindPackageHandleStandardArgs)
find_package_handle_standard_args(CHOLMOD
  REQUIRED_VARS CHOLMOD_LIBRARY CHOLMOD_INCLUDE_DIR SUITESPARSECONFIG_LIBRARY
  VERSION_VAR CHOLMOD_VERSION
  REASON_FAILURE_MESSAGE "CHOLMOD (SuiteSparse) was not found. On Debian/Ubuntu install it with: apt-get install libsuitesparse-dev (and libopenblas-dev for a fast BLAS).")

if(CHOLMOD_FOUND AND NOT TARGET SuiteSparse::CHOLMOD)
  add_library(SuiteSparse::CHOLMOD UNKNOWN IMPORTED)
  set_target_properties(SuiteSparse::CHOLMOD PROPERTIES
    IMPORTED_LOCATION "${CHOLMOD_LIBRARY}"
    INTERFACE_INCLUDE_DIRECTORIES "${CHOLMOD_INCLUDE_DIR}"
    INTERFACE_LINK_LIBRARIES "${SUITESPARSECONFIG_LIBRARY}")
endif()
mark_as_advanced(CHOLMOD_INCLUDE_DIR CHOLMOD_LIBRARY SUITESPARSECONFIG_LIBRARY)
