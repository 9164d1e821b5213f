// Google Benchmark of km.grid's advection stage as a 3D smoke step runs it: MacCormack with RK2
// back-traces of two cell-centred scalars (density and temperature, one shared trace) and of the
// three MAC velocity components, on n^3 cells of a closed free-slip box, by each implementation
// of grid/kernels.h (node-wise, rows, rows with AVX2; they give the same bits). The velocity is
// a smooth field of up to 1.5 cells per step, so departure points reach across cells and walls.
#include <benchmark/benchmark.h>

#include <array>
#include <cmath>
#include <vector>

#include "core/parallel.h"
#include "core/simd.h"
#include "grid/advect_rows.h"
#include "grid/kernels.h"

namespace kinema::grid {
namespace {

void BM_AdvectStage(benchmark::State& state) {
  const auto kernel = static_cast<AdvectionKernel>(state.range(0));
  if (kernel == AdvectionKernel::RowsAvx2 && !cpu_has_avx2()) {
    state.SkipWithError("this CPU has no AVX2");
    return;
  }
  const Index n = state.range(1);
  const GridShape shape(std::vector<Index>{n, n, n});
  MacVelocity vel;
  std::array<std::vector<Scalar>, 3> u, u_new;
  for (int a = 0; a < 3; ++a) {
    vel.layout[a] = face_layout(shape, a, false);
    u[a].resize(vel.layout[a].size());
    u_new[a].resize(vel.layout[a].size());
    for_each_node(vel.layout[a], [&](Index i, Index j, Index k, Index f) {
      u[a][f] = 1.5 * std::sin(0.05 * static_cast<Scalar>(i + 2 * j + 3 * k + a));
    });
    vel.comp[a] = u[a].data();
  }
  const FieldLayout C = cell_layout(shape, false);
  std::vector<Scalar> rho(C.size()), temp(C.size()), rho_new(C.size()), temp_new(C.size());
  for_each_node(C, [&](Index i, Index j, Index k, Index c) {
    rho[c] = std::exp(-0.01 * static_cast<Scalar>((i - n / 2) * (i - n / 2) + (j - n / 4) * (j - n / 4) + k));
    temp[c] = 0.5 * rho[c];
  });
  const Scalar* scalars[2] = {rho.data(), temp.data()};
  Scalar* scalars_new[2] = {rho_new.data(), temp_new.data()};
  AdvectionScratch scratch;
  scratch.reserve(vel.layout[0].size(), AdvectionScheme::MacCormack, 2);
  for (auto _ : state) {
    advect_fields(AdvectionScheme::MacCormack, vel, C, 2, scalars, scalars_new, 1.0, 2, scratch, -1, kernel);
    for (int a = 0; a < 3; ++a) {
      const Scalar* q = u[a].data();
      Scalar* out = u_new[a].data();
      advect_fields(AdvectionScheme::MacCormack, vel, vel.layout[a], 1, &q, &out, 1.0, 2, scratch, a, kernel);
    }
    benchmark::DoNotOptimize(u_new[2].data());
  }
  // nodes traced per stage: cells once (both scalars share the trace) plus every face
  state.SetItemsProcessed(state.iterations() *
                          (C.size() + vel.layout[0].size() + vel.layout[1].size() + vel.layout[2].size()));
  state.counters["threads"] = num_threads();
}

// kernel: 1 = node-wise, 2 = rows (baseline ISA), 3 = rows with AVX2 (AdvectionKernel)
BENCHMARK(BM_AdvectStage)
    ->ArgNames({"kernel", "n"})
    ->Args({1, 96})->Args({2, 96})->Args({3, 96})
    ->Args({1, 128})->Args({2, 128})->Args({3, 128})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

}  // namespace
}  // namespace kinema::grid
