// Google Benchmark of the SPH light passes' row sums (sph/kernels.h: row_dot, row_weighted), the
// baseline and the AVX2 versions, over the neighbour lists (radius h = 2 s) of a jittered 3D
// lattice of about n particles in Morton order, as the solver holds them; one thread, every row
// once per iteration. Items are neighbour entries, so items/s reads as entries per second. The
// lists and gradients (16 B per entry, 66 MB at 150k particles) do not fit in the caches: this
// measures the passes at the memory bandwidth the solver meets. For reference,
// BM_RowStream reads the same bytes (list and gradients) and sums them, with no gather.
#include <benchmark/benchmark.h>

#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "particles/neighbor_grid.h"
#include "particles/neighbor_lists.h"
#include "sph/model.h"
#include "sph/kernels.h"

namespace kinema {
namespace {

struct RowScene {
  Index n = 0;
  NeighborLists lists;
  std::vector<float> grads;  // random, 3 per entry and the padding float
  std::vector<Scalar> v, c;

  explicit RowScene(Index particles) {
    const Scalar s = 0.01;
    const Index side = static_cast<Index>(std::cbrt(static_cast<double>(particles)));
    const Scalar lower[3] = {0, 0, 0}, upper[3] = {side * s, side * s, side * s};
    std::vector<Scalar> x = sph::block(3, lower, upper, s);
    std::mt19937 rng(7);
    std::uniform_real_distribution<Scalar> jitter(-0.1 * s, 0.1 * s);
    for (Scalar& q : x) q += jitter(rng);
    n = static_cast<Index>(x.size()) / 3;
    const std::vector<Index> order = morton_order<3>(x.data(), n, 2 * s);
    std::vector<Scalar> sorted(x.size());
    for (Index k = 0; k < n; ++k)
      for (int a = 0; a < 3; ++a) sorted[k * 3 + a] = x[order[k] * 3 + a];
    NeighborGrid<3> grid;
    grid.build(sorted.data(), n, 2 * s);
    lists.build<3>(grid, sorted.data(), n, 2 * s, true);
    grads.resize(static_cast<size_t>(lists.size()) * 3 + 1);
    for (float& g : grads) g = static_cast<float>(jitter(rng));
    v.resize(static_cast<size_t>(3 * n));
    c.resize(static_cast<size_t>(n));
    for (Scalar& q : v) q = jitter(rng);
    for (Scalar& q : c) q = jitter(rng);
  }
};

const RowScene& scene() {
  static const RowScene rows(150000);
  return rows;
}

void BM_RowDot(benchmark::State& state, bool avx2) {
  const RowScene& r = scene();
  const auto sums = sph::RowSums<3>::choose(avx2);
  if (avx2 && !sums.avx2) state.SkipWithError("this CPU has no AVX2");
  std::vector<Scalar> out(static_cast<size_t>(r.n));
  for (auto _ : state) {
    for (Index i = 0; i < r.n; ++i)
      out[i] = sums.dot(r.lists.list.data(), r.grads.data(), r.lists.start[i], r.lists.start[i + 1], r.v.data());
    benchmark::DoNotOptimize(out.data());
  }
  state.SetItemsProcessed(state.iterations() * r.lists.size());
}

void BM_RowWeighted(benchmark::State& state, bool avx2) {
  const RowScene& r = scene();
  const auto sums = sph::RowSums<3>::choose(avx2);
  if (avx2 && !sums.avx2) state.SkipWithError("this CPU has no AVX2");
  std::vector<Scalar> out(static_cast<size_t>(3 * r.n));
  for (auto _ : state) {
    for (Index i = 0; i < r.n; ++i)
      sums.weighted(r.lists.list.data(), r.grads.data(), r.lists.start[i], r.lists.start[i + 1], r.c[i], r.c.data(),
                    out.data() + 3 * i);
    benchmark::DoNotOptimize(out.data());
  }
  state.SetItemsProcessed(state.iterations() * r.lists.size());
}

void BM_RowStream(benchmark::State& state) {
  const RowScene& r = scene();
  const Index entries = r.lists.size();
  for (auto _ : state) {
    float g = 0;
    std::int64_t j = 0;
    for (Index k = 0; k < entries; ++k) {
      g += r.grads[3 * k] + r.grads[3 * k + 1] + r.grads[3 * k + 2];
      j += r.lists.list[k];
    }
    benchmark::DoNotOptimize(g);
    benchmark::DoNotOptimize(j);
  }
  state.SetItemsProcessed(state.iterations() * entries);
}

BENCHMARK_CAPTURE(BM_RowDot, baseline, false)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_RowDot, avx2, true)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_RowWeighted, baseline, false)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_RowWeighted, avx2, true)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_RowStream)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace kinema
