// Run-time choice of the instruction set for the few hot loops that gain from wider vectors.
// The package is built for the baseline x86-64 (SSE2; no -march=native unless asked for), and
// a kernel that profits from AVX2 is compiled twice: once for the baseline and once with
// KINEMA_TARGET_AVX2, both from one always-inline body. Without FMA the two versions perform
// the same operations in the same order, so their results are bitwise identical; only the
// vector width differs.
#pragma once

#include <cstdlib>
#include <cstring>

namespace kinema {

#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#define KINEMA_HAVE_AVX2_CLONES 1
#define KINEMA_TARGET_AVX2 __attribute__((target("avx2")))
#define KINEMA_ALWAYS_INLINE __attribute__((always_inline)) inline
#else
#define KINEMA_HAVE_AVX2_CLONES 0
#define KINEMA_TARGET_AVX2
#define KINEMA_ALWAYS_INLINE inline
#endif

// True when this CPU runs AVX2 and the AVX2 versions were compiled in.
inline bool cpu_has_avx2() {
#if KINEMA_HAVE_AVX2_CLONES
  return __builtin_cpu_supports("avx2");
#else
  return false;
#endif
}

// The default choice: AVX2 where the CPU has it, unless the environment asks for the baseline
// (KINEMA_SIMD=baseline, for reproducing a figure or a bug on the narrower path).
inline bool use_avx2() {
  const char* choice = std::getenv("KINEMA_SIMD");
  if (choice != nullptr && std::strcmp(choice, "baseline") == 0) return false;
  return cpu_has_avx2();
}

}  // namespace kinema
