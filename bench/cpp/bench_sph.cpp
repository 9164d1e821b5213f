// Google Benchmark of the SPH kernels on a jittered 3D lattice (spacing s, support h = 2 s,
// about 33 neighbours per particle): the cell-grid neighbour build (counting sort + lists, per
// cell subdivision and SIMD path),
// the Verlet-list filter that replaces it between rebuilds, and the density pass of the solver
// (Solver::density_error at unchanged positions: lists filter, density sum, mean compression).
// Items processed are neighbour entries (2 per pair), so items/s reads as entries per second.
// The grid search of a DFSPH step on the dam break's column (fluid and boundary lists).
// Whole time steps (WCSPH, DFSPH) on the 3D dam break of bench/sph/sph_bench.py: a column
// a x 2a x a (a = 0.5 m) in the box 4a x 3a x a, timed after 0.02 s of simulated start-up.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include "core/interrupt.h"
#include "core/parallel.h"
#include "core/simd.h"
#include "particles/neighbor_grid.h"
#include "particles/neighbor_lists.h"
#include "sph/fluid.h"

namespace kinema {
namespace {

constexpr Scalar kSpacing = 0.01;

// A cube of about n particles on the lattice, each moved by up to 0.1 spacing per axis, in
// Morton order.
std::vector<Scalar> jittered_cube(Index n) {
  const Index side = static_cast<Index>(std::cbrt(static_cast<double>(n)));
  const Scalar lower[3] = {0, 0, 0};
  const Scalar upper[3] = {side * kSpacing, side * kSpacing, side * kSpacing};
  std::vector<Scalar> x = sph::block(3, lower, upper, kSpacing);
  std::mt19937 rng(7);
  std::uniform_real_distribution<Scalar> jitter(-0.1 * kSpacing, 0.1 * kSpacing);
  for (Scalar& c : x) c += jitter(rng);
  // In Morton order of cells of edge h, as the solver keeps its particles.
  const Index n_points = static_cast<Index>(x.size()) / 3;
  const std::vector<Index> order = morton_order<3>(x.data(), n_points, 2 * kSpacing);
  std::vector<Scalar> sorted(x.size());
  for (Index k = 0; k < n_points; ++k)
    for (int a = 0; a < 3; ++a) sorted[k * 3 + a] = x[order[k] * 3 + a];
  return sorted;
}

// Arguments: particles, cell subdivision (cells of edge h / subdivision), 1 for the AVX2 path
// (where the CPU has it) or 0 for the baseline.
void BM_NeighborBuild(benchmark::State& state) {
  const std::vector<Scalar> x = jittered_cube(state.range(0));
  const Index n = static_cast<Index>(x.size()) / 3;
  const Scalar h = 2 * kSpacing;
  const int subdivision = static_cast<int>(state.range(1));
  const bool avx2 = state.range(2) != 0 && use_avx2();
  NeighborGrid<3> grid;
  NeighborLists lists;
  for (auto _ : state) {
    grid.build(x.data(), n, h, subdivision);
    lists.build<3>(grid, x.data(), n, h, true, avx2);
    benchmark::DoNotOptimize(lists.list.data());
  }
  state.SetItemsProcessed(state.iterations() * lists.size());
  state.counters["particles"] = static_cast<double>(n);
  state.counters["threads"] = num_threads();
  state.counters["avx2"] = avx2;
}

void BM_VerletFilter(benchmark::State& state) {
  const std::vector<Scalar> x = jittered_cube(state.range(0));
  const Index n = static_cast<Index>(x.size()) / 3;
  const Scalar h = 2 * kSpacing;
  NeighborGrid<3> grid;
  NeighborLists wide, exact;
  grid.build(x.data(), n, 1.2 * h);  // skin 0.2 h, the solver's default
  wide.build<3>(grid, x.data(), n, 1.2 * h, true);
  for (auto _ : state) {
    exact.filter<3>(wide, x.data(), x.data(), n, h);
    benchmark::DoNotOptimize(exact.list.data());
  }
  state.SetItemsProcessed(state.iterations() * exact.size());
  state.counters["particles"] = static_cast<double>(n);
  state.counters["threads"] = num_threads();
}

void BM_DensityPass(benchmark::State& state) {
  const std::vector<Scalar> x = jittered_cube(state.range(0));
  sph::State s(3, static_cast<Index>(x.size()) / 3);
  s.x = x;
  const sph::Model model = sph::make_model(3, kSpacing, 1000, {}, nullptr, nullptr);
  sph::Config config;
  config.method = sph::Method::WCSPH;
  config.gravity = {0, 0, 0};
  config.speed_of_sound = 20;
  const auto solver = sph::Solver::create(model, config, s);
  solver->density_error(s);  // builds the lists once
  for (auto _ : state) benchmark::DoNotOptimize(solver->density_error(s));
  state.counters["particles"] = static_cast<double>(s.n);
  state.counters["threads"] = num_threads();
}

// The grid search of one DFSPH step without a skin on the dam break's column of about n
// particles (jittered by 0.1 spacing, Morton order): fluid grid build, fluid lists (radius h)
// and boundary lists against the static grid of the box's wall samples. Arguments: particles,
// 1 for the AVX2 path (where the CPU has it) or 0 for the baseline.
void BM_DamBreakSearch(benchmark::State& state) {
  const Scalar a = 0.5;
  const Scalar spacing = a * std::cbrt(2.0 / static_cast<double>(state.range(0)));
  const Scalar lower[3] = {0, 0, 0}, column[3] = {a, 2 * a, a}, box[3] = {4 * a, 3 * a, a};
  std::vector<Scalar> x = sph::block(3, lower, column, spacing);
  std::mt19937 rng(7);
  std::uniform_real_distribution<Scalar> jitter(-0.1 * spacing, 0.1 * spacing);
  for (Scalar& c : x) c += jitter(rng);
  const Index n = static_cast<Index>(x.size()) / 3;
  const sph::Model model = sph::make_model(3, spacing, 1000, {}, lower, box);
  const std::vector<Index> order = morton_order<3>(x.data(), n, model.h);
  std::vector<Scalar> xs(x.size());
  for (Index k = 0; k < n; ++k)
    for (int c = 0; c < 3; ++c) xs[k * 3 + c] = x[order[k] * 3 + c];
  const bool avx2 = state.range(1) != 0 && use_avx2();
  NeighborGrid<3> fluid_grid, boundary_grid;
  NeighborLists fluid, boundary;
  boundary_grid.build(model.boundary_x.data(), model.boundary_count(), model.h);
  for (auto _ : state) {
    fluid_grid.build(xs.data(), n, model.h);
    fluid.build<3>(fluid_grid, xs.data(), n, model.h, true, avx2);
    boundary.build<3>(boundary_grid, xs.data(), n, model.h, false, avx2);
    benchmark::DoNotOptimize(boundary.list.data());
  }
  state.SetItemsProcessed(state.iterations() * (fluid.size() + boundary.size()));
  state.counters["particles"] = static_cast<double>(n);
  state.counters["boundary_entries"] = static_cast<double>(boundary.size());
  state.counters["threads"] = num_threads();
  state.counters["avx2"] = avx2;
}

// The dam break of bench/sph/sph_bench.py with about n particles, advanced through the start-up in
// CFL steps (cfl 0.4) as Fluid.advance does, then timed step by step at the Python benchmark's
// dt (DFSPH: the CFL step at the surge-front speed sqrt(2 g 2a); WCSPH: the acoustic CFL step).
// Counters: the DFSPH solvers' iterations per step.
void BM_DamBreakStep(benchmark::State& state, sph::Method method) {
  const Scalar a = 0.5;
  const Scalar spacing = a * std::cbrt(2.0 / static_cast<double>(state.range(0)));
  const Scalar lower[3] = {0, 0, 0}, column[3] = {a, 2 * a, a}, box[3] = {4 * a, 3 * a, a};
  const std::vector<Scalar> x = sph::block(3, lower, column, spacing);
  sph::State s(3, static_cast<Index>(x.size()) / 3);
  s.x = x;
  const sph::Model model = sph::make_model(3, spacing, 1000, {}, lower, box);
  sph::Config config;
  config.method = method;
  const auto solver = sph::Solver::create(model, config, s);
  Interrupt interrupt;
  const Scalar start = 0.02;
  while (s.time < start) {
    Scalar dt = solver->stable_dt(s, 0.4);
    if (dt >= start - s.time || start - s.time - dt < 0.1 * dt) dt = start - s.time;
    solver->step(s, dt, interrupt);
  }
  Scalar dt = solver->stable_dt(s, 0.4);
  if (method == sph::Method::DFSPH) dt = std::min(dt, 0.4 * spacing / std::sqrt(2 * 9.81 * 2 * a));
  // Past the DFSPH solvers' first steps at the smaller dt (the Python benchmark's first call).
  for (int k = 0; k < 5; ++k) solver->step(s, dt, interrupt);
  double iterations = 0;
  for (auto _ : state) {
    const sph::StepStats stats = solver->step(s, dt, interrupt);
    iterations += stats.iterations + stats.divergence_iterations;
  }
  state.counters["particles"] = static_cast<double>(s.n);
  state.counters["threads"] = num_threads();
  state.counters["iterations"] = benchmark::Counter(iterations, benchmark::Counter::kAvgIterations);
}

BENCHMARK(BM_NeighborBuild)
    ->ArgsProduct({{20000, 150000}, {1, 2}, {0, 1}})
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_DamBreakSearch)->ArgsProduct({{150000}, {0, 1}})->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_VerletFilter)->Arg(20000)->Arg(150000)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_DensityPass)->Arg(20000)->Arg(150000)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_DamBreakStep, dfsph, sph::Method::DFSPH)->Arg(150000)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_DamBreakStep, wcsph, sph::Method::WCSPH)->Arg(150000)->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace
}  // namespace kinema
