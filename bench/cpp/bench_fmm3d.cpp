// Google Benchmark of the 3D FMM's near field (fmm/p2p3d.h): two adjacent leaves of n points
// each (uniform in two unit cubes sharing a face), potential and gradient both ways, either by
// p2p_fast twice (each target against the other leaf's sources) or by p2p_mutual once (each
// pair's kernel evaluated once for both ends). Items are pair interactions (2 n^2 per
// iteration), so items/s reads as interactions per second; one thread, data in L1/L2.
#include <benchmark/benchmark.h>

#include <random>
#include <vector>

#include "fmm/p2p3d.h"

namespace kinema::fmm3 {
namespace {

struct Leaves {
  std::vector<Scalar> x[2][3], q[2];
  explicit Leaves(Index n) {
    std::mt19937_64 rng(3);
    std::uniform_real_distribution<Scalar> u(0, 1);
    for (int b = 0; b < 2; ++b) {
      for (Index i = 0; i < n; ++i) {
        x[b][0].push_back(u(rng) + b), x[b][1].push_back(u(rng)), x[b][2].push_back(u(rng));
        q[b].push_back(u(rng) - 0.5);
      }
      // Padding to whole vectors for p2p_mutual: zero charges at the first point.
      while (x[b][0].size() % 4)
        for (int d = 0; d < 3; ++d) x[b][d].push_back(x[b][d][0]), q[b].push_back(0);
    }
  }
};

void BM_P2POneWayTwice(benchmark::State& state) {
  const Index n = state.range(0);
  const Leaves l(n);
  std::vector<Scalar> out(4 * 2 * n);
  for (auto _ : state) {
    for (int b = 0; b < 2; ++b)
      for (Index i = 0; i < n; ++i)
        p2p_fast(true, 2, 0.0, l.x[b][0][i], l.x[b][1][i], l.x[b][2][i], l.x[1 - b][0].data(),
                 l.x[1 - b][1].data(), l.x[1 - b][2].data(), l.q[1 - b].data(), n, &out[4 * (b * n + i)]);
    benchmark::DoNotOptimize(out.data());
  }
  state.SetItemsProcessed(state.iterations() * 2 * n * n);
}

void BM_P2PMutual(benchmark::State& state) {
  if (!p2p_mutual_available()) {
    state.SkipWithError("no vectorised mutual kernel on this CPU");
    return;
  }
  const Index n = state.range(0), stride = (n + 3) & ~Index{3};
  const Leaves l(n);
  const Scalar* xa[3] = {l.x[0][0].data(), l.x[0][1].data(), l.x[0][2].data()};
  const Scalar* xb[3] = {l.x[1][0].data(), l.x[1][1].data(), l.x[1][2].data()};
  std::vector<Scalar> out_a(4 * n), out_b(4 * stride);
  for (auto _ : state) {
    p2p_mutual(true, 2, 0.0, xa, l.q[0].data(), n, xb, l.q[1].data(), stride, stride, out_a.data(), out_b.data());
    benchmark::DoNotOptimize(out_a.data());
    benchmark::DoNotOptimize(out_b.data());
  }
  state.SetItemsProcessed(state.iterations() * 2 * n * n);
}

BENCHMARK(BM_P2POneWayTwice)->Arg(64)->Arg(244);
BENCHMARK(BM_P2PMutual)->Arg(64)->Arg(244);

}  // namespace
}  // namespace kinema::fmm3
