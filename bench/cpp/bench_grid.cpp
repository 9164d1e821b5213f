// Google Benchmark of the grid Poisson kernels: stencil apply, one red-black Gauss-Seidel sweep,
// restriction, prolongation and one V-cycle, on 2D 1024^2 and 3D 128^3 (and 256^3) Dirichlet grids.
// Bytes processed count the compulsory traffic only (each array read or written once per
// pass), so GB/s compares directly with the STREAM triad (bench_stream.cpp).
#include <benchmark/benchmark.h>

#include <sys/mman.h>

#include <algorithm>
#include <cstdlib>
#include <new>
#include <vector>

#include "core/parallel.h"
#include "core/simd.h"
#include "poisson/multigrid.h"

#if KINEMA_HAVE_AVX2_CLONES
#include <immintrin.h>
#endif

namespace kinema {
namespace {

// numpy backs large arrays by transparent huge pages (it madvises them, as Linux's default THP
// mode "madvise" requires), so that is the memory kinema's kernels meet when called from Python.
// The benchmarks give their arrays the same pages: BenchArray, 2 MiB aligned and madvised.
class BenchArray {
 public:
  BenchArray(Index n, Scalar value) : n_(n) {
    void* p = nullptr;
    const std::size_t bytes = static_cast<std::size_t>(n) * sizeof(Scalar);
    if (posix_memalign(&p, std::size_t{2} << 20, bytes) != 0) throw std::bad_alloc();
#ifdef MADV_HUGEPAGE
    madvise(p, bytes, MADV_HUGEPAGE);
#endif
    data_ = static_cast<Scalar*>(p);
    std::fill(data_, data_ + n, value);
  }
  ~BenchArray() { std::free(data_); }
  BenchArray(const BenchArray&) = delete;
  BenchArray& operator=(const BenchArray&) = delete;
  Scalar* data() { return data_; }

 private:
  Index n_;
  Scalar* data_ = nullptr;
};

#if KINEMA_HAVE_AVX2_CLONES
KINEMA_TARGET_AVX2 void hand_loop_apply(const Scalar* x, Scalar* y, Index n, Index s0, Index s1, Scalar d,
                                        Scalar ih2) {
  const __m256d vd = _mm256_set1_pd(d), vih2 = _mm256_set1_pd(ih2);
#pragma omp parallel for schedule(static)
  for (Index row = n; row < n * n - n; ++row) {  // planes 1 .. n-2: every load in range
    for (Index c = row * n; c < (row + 1) * n; c += 4) {
      if ((c & 7) < 4) __builtin_prefetch(x + c + s0 + 64, 0, 3);
      __m256d nb = _mm256_add_pd(_mm256_add_pd(_mm256_add_pd(_mm256_loadu_pd(x + c - s1), _mm256_loadu_pd(x + c + s1)),
                                               _mm256_loadu_pd(x + c - 1)),
                                 _mm256_loadu_pd(x + c + 1));
      nb = _mm256_add_pd(nb, _mm256_add_pd(_mm256_loadu_pd(x + c - s0), _mm256_loadu_pd(x + c + s0)));
      _mm256_stream_pd(y + c, _mm256_sub_pd(_mm256_mul_pd(vd, _mm256_loadu_pd(x + c)), _mm256_mul_pd(vih2, nb)));
    }
  }
  _mm_sfence();
}
#else
void hand_loop_apply(const Scalar* x, Scalar* y, Index n, Index s0, Index s1, Scalar d, Scalar ih2) {
#pragma omp parallel for schedule(static)
  for (Index c = s0; c < n * n * n - s0; ++c)
    y[c] = d * x[c] - ih2 * (x[c - s1] + x[c + s1] + x[c - 1] + x[c + 1] + x[c - s0] + x[c + s0]);
}
#endif

GridShape shape_of(int64_t dim, int64_t n) {
  return dim == 2 ? GridShape({n, n}) : GridShape({n, n, n});
}

void apply_benchmark(benchmark::State& state, bool baseline) {
  const GridShape shape = shape_of(state.range(0), state.range(1));
  // The operator picks its instruction set when it is built (core/simd.h).
  if (baseline) setenv("KINEMA_SIMD", "baseline", 1);
  const PoissonOperator op(shape, 1.0 / state.range(1), Boundary::Dirichlet, nullptr);
  if (baseline) unsetenv("KINEMA_SIMD");
  BenchArray x(shape.size(), 1.0), y(shape.size(), 0.0);
  for (auto _ : state) {
    op.apply(x.data(), y.data());
    benchmark::DoNotOptimize(y.data());
  }
  state.SetBytesProcessed(state.iterations() * shape.size() * 16);  // read x, write y
  state.counters["threads"] = num_threads();
  state.counters["avx2"] = op.avx2();
}

// The stencil apply as it runs (AVX2 rows where the CPU has AVX2), and forced to SSE2.
void BM_PoissonApply(benchmark::State& state) { apply_benchmark(state, false); }
void BM_PoissonApplyBaseline(benchmark::State& state) { apply_benchmark(state, true); }

// The 3D apply with the result written through the cache (0) or by non-temporal stores (1), on
// 128^3 (16 MiB per array) and 256^3 (128 MiB): the measurement behind kStreamBytes.
void BM_PoissonApplyStores(benchmark::State& state) {
  const GridShape shape = shape_of(3, state.range(0));
  PoissonOperator op(shape, 1.0 / state.range(0), Boundary::Dirichlet, nullptr);
  op.set_stream_stores(state.range(1) != 0);
  BenchArray x(shape.size(), 1.0), y(shape.size(), 0.0);
  for (auto _ : state) {
    op.apply(x.data(), y.data());
    benchmark::DoNotOptimize(y.data());
  }
  state.SetBytesProcessed(state.iterations() * shape.size() * 16);
  state.counters["threads"] = num_threads();
  state.counters["stream"] = op.stream_stores();
}

// A reference for the 3D apply: the plain 7-point loop with the same operations, written by
// hand with non-temporal stores, on every row (the domain faces read across them, so the result
// is not the operator's; only its time matters). What kinema's apply at 256^3 should come close
// to (the comparison that found the faults recorded in bench/RESULTS.md, appendix A.1).
void BM_ApplyHandLoop(benchmark::State& state) {
  const Index n = state.range(0), s1 = n, s0 = n * n, size = n * n * n;
  BenchArray x(size, 1.0), y(size, 0.0);
  const Scalar d = 6.0 * n * n, ih2 = 1.0 * n * n;
  for (auto _ : state) {
    hand_loop_apply(x.data(), y.data(), n, s0, s1, d, ih2);
    benchmark::DoNotOptimize(y.data());
  }
  state.SetBytesProcessed(state.iterations() * size * 16);
  state.counters["threads"] = num_threads();
}

void BM_RedBlackSweep(benchmark::State& state) {
  const GridShape shape = shape_of(state.range(0), state.range(1));
  const PoissonOperator op(shape, 1.0 / state.range(1), Boundary::Dirichlet, nullptr);
  BenchArray x(shape.size(), 0.0), b(shape.size(), 1.0);
  for (auto _ : state) {
    op.sweep(b.data(), x.data(), 0);
    benchmark::DoNotOptimize(x.data());
  }
  state.SetBytesProcessed(state.iterations() * shape.size() * 24);  // read b, read+write x
  state.counters["threads"] = num_threads();
}

void BM_Restrict(benchmark::State& state) {
  const GridShape shape = shape_of(state.range(0), state.range(1));
  const PoissonOperator op(shape, 1.0 / state.range(1), Boundary::Dirichlet, nullptr);
  Multigrid mg(op);
  std::vector<Scalar> fine(shape.size(), 1.0), coarse(mg.level(1).size());
  for (auto _ : state) {
    mg.restrict_residual(0, fine.data(), coarse.data());
    benchmark::DoNotOptimize(coarse.data());
  }
  state.SetBytesProcessed(state.iterations() * (shape.size() + coarse.size()) * 8);
  state.counters["threads"] = num_threads();
}

void BM_Prolong(benchmark::State& state) {
  const GridShape shape = shape_of(state.range(0), state.range(1));
  const PoissonOperator op(shape, 1.0 / state.range(1), Boundary::Dirichlet, nullptr);
  Multigrid mg(op);
  std::vector<Scalar> fine(shape.size(), 0.0), coarse(mg.level(1).size(), 1.0);
  for (auto _ : state) {
    mg.prolong_add(0, coarse.data(), fine.data());
    benchmark::DoNotOptimize(fine.data());
  }
  state.SetBytesProcessed(state.iterations() * (2 * shape.size() + coarse.size()) * 8);
  state.counters["threads"] = num_threads();
}

void BM_VCycle(benchmark::State& state) {
  const GridShape shape = shape_of(state.range(0), state.range(1));
  const PoissonOperator op(shape, 1.0 / state.range(1), Boundary::Dirichlet, nullptr);
  Multigrid mg(op);
  std::vector<Scalar> b(shape.size(), 1.0), x(shape.size());
  for (auto _ : state) {
    mg.vcycle(b.data(), x.data());
    benchmark::DoNotOptimize(x.data());
  }
  state.counters["levels"] = mg.levels();
  state.counters["threads"] = num_threads();
}

#define GRID_ARGS Args({2, 1024})->Args({3, 128})->Unit(benchmark::kMillisecond)->UseRealTime()
// 256^3 (128 MiB per array) is far beyond the last-level cache: the memory-bound case.
BENCHMARK(BM_PoissonApply)->GRID_ARGS->Args({3, 256});
BENCHMARK(BM_PoissonApplyBaseline)->GRID_ARGS->Args({3, 256});
BENCHMARK(BM_RedBlackSweep)->GRID_ARGS->Args({3, 256});
BENCHMARK(BM_ApplyHandLoop)->Arg(256)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_PoissonApplyStores)->ArgsProduct({{128, 256}, {0, 1}})->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_Restrict)->GRID_ARGS;
BENCHMARK(BM_Prolong)->GRID_ARGS;
BENCHMARK(BM_VCycle)->GRID_ARGS;

}  // namespace
}  // namespace kinema
