// km.sparse kernels: CSR spmv on the 2D 5-point / 3D 7-point Laplacian (memory bound: bytes
// processed counts the matrix arrays, x once and y once, so the GB/s column is an effective
// bandwidth) and CHOLMOD's supernodal factorisation and solve of the 2D Laplacian. Each
// benchmark checks its result before timing. Run with --benchmark_min_time=0.2s for a quick look.
#include <benchmark/benchmark.h>

#include <cmath>
#include <string>
#include <vector>

#include "core/parallel.h"
#include "linalg/cholmod_factor.h"
#include "linalg/csr.h"

namespace kinema {
namespace {

struct Csr {
  Index n = 0;
  std::vector<Index> ptr{0}, idx;
  std::vector<Scalar> val;
  CsrView view() const { return {n, n, ptr.data(), idx.data(), val.data()}; }
  CscView csc() const { return {n, n, ptr.data(), idx.data(), val.data()}; }  // symmetric
  size_t bytes_per_product() const {
    return idx.size() * (sizeof(Index) + sizeof(Scalar)) + ptr.size() * sizeof(Index) +
           2 * static_cast<size_t>(n) * sizeof(Scalar);
  }
};

// -lap on an m^d grid (d = 2: 5-point, d = 3: 7-point), Dirichlet, h = 1, x fastest.
Csr laplacian(Index m, int d) {
  Csr a;
  a.n = d == 2 ? m * m : m * m * m;
  const Index stride[3] = {1, m, m * m};
  a.idx.reserve(static_cast<size_t>(a.n) * (2 * d + 1));
  a.val.reserve(a.idx.capacity());
  for (Index r = 0; r < a.n; ++r) {
    Index coord[3] = {r % m, (r / m) % m, r / (m * m)};
    for (int axis = d - 1; axis >= 0; --axis)  // lower neighbours, farthest first: sorted
      if (coord[axis] > 0) {
        a.idx.push_back(r - stride[axis]);
        a.val.push_back(-1);
      }
    a.idx.push_back(r);
    a.val.push_back(2.0 * d);
    for (int axis = 0; axis < d; ++axis)
      if (coord[axis] + 1 < m) {
        a.idx.push_back(r + stride[axis]);
        a.val.push_back(-1);
      }
    a.ptr.push_back(static_cast<Index>(a.idx.size()));
  }
  return a;
}

// A 1 = number of missing neighbours per cell, summing to 2 d m^(d-1) (exact in floating point).
bool spmv_is_right(const Csr& a, Index m, int d) {
  std::vector<Scalar> x(a.n, 1.0), y(a.n);
  spmv(a.view(), x.data(), y.data());
  Scalar sum = 0;
  for (Scalar v : y) sum += v;
  return sum == 2.0 * d * std::pow(static_cast<Scalar>(m), d - 1);
}

void BM_Spmv(benchmark::State& state, int d) {
  const Index m = state.range(0);
  const Csr a = laplacian(m, d);
  if (!spmv_is_right(a, m, d)) {
    state.SkipWithError("spmv gives a wrong A*1");
    return;
  }
  std::vector<Scalar> x(a.n), y(a.n);
  for (Index i = 0; i < a.n; ++i) x[i] = 1.0 + 1e-3 * (i % 97);
  for (auto _ : state) {
    spmv(a.view(), x.data(), y.data());
    benchmark::DoNotOptimize(y.data());
    benchmark::ClobberMemory();
  }
  state.SetBytesProcessed(static_cast<int64_t>(state.iterations() * a.bytes_per_product()));
  state.counters["n"] = static_cast<double>(a.n);
  state.counters["nnz"] = static_cast<double>(a.idx.size());
  state.counters["threads"] = num_threads();
}

Scalar relative_residual(const Csr& a, const std::vector<Scalar>& x,
                         const std::vector<Scalar>& b) {
  std::vector<Scalar> ax(a.n);
  spmv(a.view(), x.data(), ax.data());
  Scalar r = 0, bb = 0;
  for (Index i = 0; i < a.n; ++i) {
    r += (b[i] - ax[i]) * (b[i] - ax[i]);
    bb += b[i] * b[i];
  }
  return std::sqrt(r / bb);
}

// Analysis + numeric factorisation + one solve, as a user's first cholesky(A).solve(b).
void BM_CholmodFactorSolve(benchmark::State& state) {
  const Index m = state.range(0);
  const Csr a = laplacian(m, 2);
  std::vector<Scalar> b(a.n, 1.0), x(a.n);
  {
    CholmodFactor f(a.csc());
    f.solve(b.data(), x.data());
    if (!f.is_supernodal() || relative_residual(a, x, b) > 1e-10) {
      state.SkipWithError("CHOLMOD: not supernodal or wrong solution");
      return;
    }
    state.counters["nnz_L"] = static_cast<double>(f.factor_nonzeros());
  }
  for (auto _ : state) {
    CholmodFactor f(a.csc());
    f.solve(b.data(), x.data());
    benchmark::DoNotOptimize(x.data());
  }
  state.counters["n"] = static_cast<double>(a.n);
}

// Numeric factorisation only (refactor reuses the analysis), and one solve alone.
void BM_CholmodRefactor(benchmark::State& state) {
  const Csr a = laplacian(state.range(0), 2);
  CholmodFactor f(a.csc());
  for (auto _ : state) f.refactor(a.csc());
  state.counters["n"] = static_cast<double>(a.n);
}

void BM_CholmodSolve(benchmark::State& state) {
  const Csr a = laplacian(state.range(0), 2);
  CholmodFactor f(a.csc());
  std::vector<Scalar> b(a.n, 1.0), x(a.n);
  for (auto _ : state) {
    f.solve(b.data(), x.data());
    benchmark::DoNotOptimize(x.data());
  }
  state.counters["n"] = static_cast<double>(a.n);
}

BENCHMARK_CAPTURE(BM_Spmv, laplacian_2d, 2)->Arg(1024)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Spmv, laplacian_3d, 3)->Arg(128)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_CholmodFactorSolve)->Arg(512)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_CholmodRefactor)->Arg(512)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_CholmodSolve)->Arg(512)->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace
}  // namespace kinema
