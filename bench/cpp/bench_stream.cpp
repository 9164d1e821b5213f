// STREAM triad a[i] = b[i] + s * c[i]: this machine's sustainable memory bandwidth, the
// ceiling against which kinema's bandwidth-bound kernels (stencil apply, smoother, SpMV) are
// judged. Method after McCalpin, "Memory bandwidth and machine balance in current high
// performance computers", IEEE TCCA Newsletter 1995 (the STREAM benchmark): arrays far larger
// than the last-level cache, first-touch initialisation by the same static OpenMP schedule as
// the timed loop, and bytes counted as 3 arrays x 8 bytes per element. Written from that
// description; no STREAM source is used.
//
// Counters (rates, per second of wall time):
//   bytes_per_second   STREAM convention, 24 bytes per element (read b, read c, write a);
//   GB                 the same in 1e9 bytes (shown as GB=x/s);
//   GB_write_alloc     32 bytes per element: a cached store first reads the line of a it
//                      writes (write-allocate), so the bus really moves 4 arrays (24 bytes
//                      for the non-temporal triad, which has no write-allocate).
// BM_StreamTriadNT writes a by non-temporal stores (SSE2 movntpd), which skip the
// write-allocate read: the bus moves the 24 counted bytes only. It is the fair ceiling for a
// kernel that streams its own output the same way (the 3D stencil apply on large grids).
// Run: build/bench/kinema_bench --benchmark_filter=StreamTriad
#include <benchmark/benchmark.h>
#include <emmintrin.h>
#include <omp.h>
#include <sys/mman.h>

#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <new>

namespace {

// 10 Mi doubles = 80 MiB per array, 240 MiB in all: far beyond any L3 cache on a 2-core machine.
constexpr std::int64_t kTriadLength = std::int64_t{10} << 20;
constexpr double kTriadScalar = 3.0;

// 2 MiB aligned storage for one array (huge-page aligned), deliberately left uninitialised so that the first
// touch (and with it page placement) happens in the parallel loop below.
struct AlignedArray {
  explicit AlignedArray(std::int64_t n)
      : data(static_cast<double*>(std::aligned_alloc(std::size_t{2} << 20, static_cast<std::size_t>(n) * sizeof(double)))) {
    if (data == nullptr) throw std::bad_alloc();
#ifdef MADV_HUGEPAGE
    // Transparent huge pages, as numpy asks for its large arrays and as the stencil
    // benchmarks (bench_grid.cpp) get them: the ceiling on the same pages as the kernels.
    madvise(data, static_cast<std::size_t>(n) * sizeof(double), MADV_HUGEPAGE);
#endif
  }
  ~AlignedArray() { std::free(data); }
  AlignedArray(const AlignedArray&) = delete;
  AlignedArray& operator=(const AlignedArray&) = delete;
  double* data;
};

void triad_benchmark(benchmark::State& state, bool nontemporal) {
  const int threads = static_cast<int>(state.range(0));
  if (threads > omp_get_num_procs()) {
    state.SkipWithError("more threads than processors");
    return;
  }
  const std::int64_t n = kTriadLength;
  AlignedArray a(n), b(n), c(n);
  double* __restrict pa = a.data;
  double* __restrict pb = b.data;
  double* __restrict pc = c.data;

#pragma omp parallel for schedule(static) num_threads(threads)
  for (std::int64_t i = 0; i < n; ++i) {
    pa[i] = 0.0;
    pb[i] = 1.0;
    pc[i] = 2.0;
  }

  for (auto _ : state) {
    if (nontemporal) {
      // Pairs of elements: the arrays are 64-byte aligned and each thread's static chunk of
      // pairs starts on a 16-byte boundary, as movntpd requires.
#pragma omp parallel for schedule(static) num_threads(threads)
      for (std::int64_t i = 0; i < n; i += 2) {
        const __m128d sum = _mm_add_pd(_mm_load_pd(pb + i), _mm_mul_pd(_mm_set1_pd(kTriadScalar), _mm_load_pd(pc + i)));
        _mm_stream_pd(pa + i, sum);
      }
      _mm_sfence();
    } else {
#pragma omp parallel for schedule(static) num_threads(threads)
      for (std::int64_t i = 0; i < n; ++i) pa[i] = pb[i] + kTriadScalar * pc[i];
    }
    benchmark::DoNotOptimize(pa);
    benchmark::ClobberMemory();
  }

  // A triad that did not run (or ran on the wrong data) must not report a bandwidth.
  if (pa[0] != 1.0 + kTriadScalar * 2.0 || pa[n - 1] != pa[0]) {
    state.SkipWithError("triad result is wrong");
    return;
  }

  const double elements = static_cast<double>(state.iterations()) * static_cast<double>(n);
  state.SetBytesProcessed(static_cast<std::int64_t>(elements * 3 * sizeof(double)));
  state.counters["GB"] = benchmark::Counter(elements * 3 * sizeof(double) * 1e-9, benchmark::Counter::kIsRate);
  state.counters["GB_write_alloc"] =
      benchmark::Counter(elements * (nontemporal ? 3 : 4) * sizeof(double) * 1e-9, benchmark::Counter::kIsRate);
  state.counters["threads"] = threads;
}

void BM_StreamTriad(benchmark::State& state) { triad_benchmark(state, false); }
void BM_StreamTriadNT(benchmark::State& state) { triad_benchmark(state, true); }

// Wall time, not the main thread's CPU time: the work is spread over the OpenMP team.
BENCHMARK(BM_StreamTriad)->ArgName("threads")->Arg(1)->Arg(2)->UseRealTime()->Unit(benchmark::kMillisecond);
BENCHMARK(BM_StreamTriadNT)->ArgName("threads")->Arg(1)->Arg(2)->UseRealTime()->Unit(benchmark::kMillisecond);

}  // namespace
