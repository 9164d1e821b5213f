// MLS-MPM step on a sparse block grid; see solver.h for the algorithm and kernels.h for the
// per-particle math.
#include "mpm/solver.h"

#include <omp.h>
#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/simd.h"
#include "core/timer.h"
#include "mpm/adjoint_kernels.h"
#include "mpm/kernels.h"

namespace kinema::mpm {

class Solver::Impl {
 public:
  virtual ~Impl() = default;
  virtual StepStats step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* forces) = 0;
  virtual void step_adjoint(const State& before, const State& after, Scalar dt, const Scalar* forces,
                            State& adjoint, ParamsAdjoint& adjoint_params, Scalar* adjoint_forces,
                            Interrupt& interrupt) = 0;
  virtual void sort_rows(State& state) = 0;
  // v_max + c_max of `state` (Solver::signal_speed) from what the last step measured, when
  // `state` is the unchanged State it left (State::binning) and c_max is known: true and
  // `speed` set; false otherwise (the caller then passes over the particles).
  virtual bool measured_speed(const State& state, Scalar& speed) const = 0;
  // The materials' largest squared wave speeds found by such a pass over `state`, kept for
  // later steps when `state` is the unchanged State the last step left.
  virtual void remember_wave_speeds(const State& state, Scalar c2_elastic, Scalar c2_snow) = 0;
};

namespace {

// Row q of every particle array becomes row from(q) (a permutation of the stored rows), one
// array at a time through a spare buffer.
template <class From>
void permute_rows(State& state, From&& from, std::vector<Scalar>& spare) {
  const Index n = state.n;
  const Index d = state.dim;
  auto permute = [&](std::vector<Scalar>& a, Index width) {
    spare.resize(a.size());
    parallel_for(n, [&](Index q) {
      const Scalar* src = &a[static_cast<size_t>(from(q) * width)];
      Scalar* dst = &spare[static_cast<size_t>(q * width)];
      for (Index k = 0; k < width; ++k) dst[k] = src[k];
    });
    a.swap(spare);
  };
  permute(state.x, d);
  permute(state.v, d);
  permute(state.F, d * d);
  permute(state.C, d * d);
  permute(state.mass, 1);
  permute(state.volume, 1);
  permute(state.Jp, 1);
  permute(state.youngs_modulus, 1);
  permute(state.poisson_ratio, 1);
  std::vector<Index> material(static_cast<size_t>(n));
  parallel_for(n, [&](Index q) { material[static_cast<size_t>(q)] = state.material[static_cast<size_t>(from(q))]; });
  state.material.swap(material);
}

constexpr int ipow(int b, int e) { return e == 0 ? 1 : b * ipow(b, e - 1); }

// Fewer particles than this run the transfers on one thread: a step is three parallel loops
// (P2G, grid, G2P), and below about a thousand particles (~50 us of work) waking the team for
// them costs more than it saves.
constexpr Index kParallelParticles = 1024;

// Row chunks of the parallel counting sort (a constant, so the order is the same for any
// thread count).
constexpr Index kSortChunks = 16;

// Interleaves the low 21 bits of each coordinate (z fastest), the order blocks are stored in.
std::uint64_t morton(const std::array<Index, 3>& c) {
  std::uint64_t code = 0;
  for (int bit = 20; bit >= 0; --bit)
    for (int a = 0; a < 3; ++a) code = (code << 1) | ((static_cast<std::uint64_t>(c[a]) >> bit) & 1u);
  return code;
}

// Applies a wall or collider condition with outward normal n (into the material) to v.
template <int D>
void apply_boundary(Vec<D>& v, const Vec<D>& n, Boundary boundary, Scalar friction) {
  if (boundary == Boundary::Sticky) {
    v.setZero();
    return;
  }
  const Scalar vn = v.dot(n);
  if (boundary == Boundary::Separate && vn >= 0) return;
  Vec<D> vt = v - vn * n;
  if (vn < 0 && friction > 0) {  // Coulomb: the tangential speed drops by friction |vn|
    const Scalar t = vt.norm();
    vt = t <= -friction * vn ? Vec<D>::Zero() : Vec<D>(vt * (1 + friction * vn / t));
  }
  v = vt;
}

// The transpose of apply_boundary's Jacobian at v (the branch v takes), applied to v_bar.
template <int D>
Vec<D> apply_boundary_vjp(const Vec<D>& v, const Vec<D>& n, Boundary boundary, Scalar friction, const Vec<D>& v_bar) {
  if (boundary == Boundary::Sticky) return Vec<D>::Zero();
  const Scalar vn = v.dot(n);
  if (boundary == Boundary::Separate && vn >= 0) return v_bar;
  Vec<D> vt_bar = v_bar;
  Scalar vn_bar = 0;
  if (vn < 0 && friction > 0) {
    const Vec<D> vt = v - vn * n;
    const Scalar t = vt.norm();
    if (t <= -friction * vn) return Vec<D>::Zero();
    // out = vt + friction vn vt / t
    const Vec<D> e = vt / t;
    vt_bar += (friction * vn / t) * (v_bar - e * e.dot(v_bar));
    vn_bar = friction * e.dot(v_bar);
  }
  return vt_bar - n * n.dot(vt_bar) + n * vn_bar;
}

// |v|^2 summed in the order Solver::signal_speed sums it (so that G2P's largest is its, bitwise).
template <int D>
Scalar squared_speed(const Vec<D>& v) {
  Scalar v2 = 0;
  for (int a = 0; a < D; ++a) v2 += v(a) * v(a);
  return v2;
}

// Snow's hardening factor exp(hardening (1 - Jp)) (Stomakhin et al. 2013; model.h); exactly 1
// without the exp() call for a particle that has not yielded yet (Jp = 1: exp(0) = 1).
inline Scalar snow_hardening(const Material& m, Scalar Jp) { return Jp == 1 ? 1.0 : std::exp(m.hardening * (1 - Jp)); }

// Lame parameters of particle p from its own moduli (water: mu = lambda = 0).
inline void particle_lame(const State& state, const Material& m, Index p, Scalar& mu, Scalar& lambda) {
  if (m.kind == MaterialKind::Water) {
    mu = lambda = 0;
    return;
  }
  const Scalar E = state.youngs_modulus[static_cast<size_t>(p)], nu = state.poisson_ratio[static_cast<size_t>(p)];
  if (E == m.youngs_modulus && nu == m.poisson_ratio) {  // the material's own: the same bits, no divisions
    mu = m.mu;
    lambda = m.lambda;
    return;
  }
  lame_parameters(E, nu, mu, lambda);
}

template <int D>
class SolverD final : public Solver::Impl {
 public:
  static constexpr int B = D == 2 ? 8 : 4;      // block side in nodes
  static constexpr int T = B + 2;               // tile side: a block plus the stencil's reach
  static constexpr int BN = ipow(B, D);         // nodes per block
  static constexpr int TN = ipow(T, D);         // nodes per tile
  static constexpr int S = D + 1;               // values per node: mass, momentum / velocity
  static constexpr int NEIGHBORS = 1 << D;      // blocks a tile overlaps

  SolverD(const Model& model, const Config& config) : model_(model), config_(config) {
    // Node index I = i + 1 (the ghost layer at i = -1 becomes 0); nodes I = 0 .. shape + 2.
    block_count_ = 1;
    for (int a = 0; a < 3; ++a) {
      // One spare block per axis, so that every particle block has its +1 neighbours.
      blocks_[a] = a < D ? (model.shape[a] + 3 + B - 1) / B + 1 : 1;
      block_count_ *= blocks_[a];
    }
    table_.assign(static_cast<size_t>(block_count_), -1);
    seen_.assign(static_cast<size_t>(block_count_), 0);
  }

  StepStats step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* forces) override {
    check_dt(dt);
    interrupt.check();
    Stopwatch total;
    StepStats stats;
    stats.dt = dt;
    // One parallel region for the whole step: the phases meet at barriers, where the team's
    // threads are still spinning, instead of each phase waking the sleeping team again (for a
    // 2D step of 8,192 particles, about 0.4 ms of work, the six region starts of a step cost
    // more than a second thread saves). Thread 0 takes the stage times as it leaves each phase.
    double mark[3] = {0, 0, 0};
    Scalar vmax2 = 0;
    bool finite = true;
    snow_exponent_ = 0;
    // This solver's last step left this State unchanged (State::binning): its binning stays,
    // updated for the particles that left their block, and so do the wave speeds it knows.
    const bool unchanged = unchanged_since_step(state);
    const bool kept = unchanged && binning_kept_;
    if (!unchanged) wave_speeds_known_ = false;
    mark_ = 0;  // until this step succeeds
    prepare_sort(state, kept);
    const bool parallel = state.n > kParallelParticles;
    const int team = parallel ? choose_team(state.n) : 1;
#pragma omp parallel num_threads(team) if (parallel)
    {
      const bool master = omp_get_thread_num() == 0;
      // 1. Bin the particles into blocks, activate the blocks their stencils reach.
      if (sort_phase(state)) {
        if (master) mark[0] = total.seconds();
        // 2. P2G (Hu et al. 2018, eq. 16-17) into one tile per particle block.
        p2g_phase(state, dt, forces);
        if (master) mark[1] = total.seconds();
        // 3. Each node's mass and momentum summed from the tiles over it, then its velocity,
        //    gravity, walls and colliders.
        grid_phase(dt, nullptr);
        if (master) mark[2] = total.seconds();
        // 4. G2P, advection, deformation update and plasticity.
        g2p_phase(state, dt, vmax2, finite);
      }
    }
    if (bad_ >= 0) throw_bad_particle(state);
    stats.max_speed = check_g2p(state, dt, vmax2, finite);
    measured_v2_ = vmax2;
    measured_snow_exponent_ = snow_exponent_;
    stats.particle_blocks = particle_blocks_;
    stats.active_blocks = static_cast<Index>(slot_key_.size());
    stats.rebinned = rebinned_;
    leave_mark(state);
    stats.seconds = total.seconds();
    stats.threads = team;
    record_team(team, stats.seconds);
    stats.sort_seconds = mark[0];
    stats.p2g_seconds = mark[1] - mark[0];
    stats.grid_seconds = mark[2] - mark[1];
    stats.g2p_seconds = stats.seconds - mark[2];
    state.time += dt;
    ++state.steps;
    stats.time = state.time;
    return stats;
  }

  void step_adjoint(const State& before, const State& after, Scalar dt, const Scalar* forces, State& adjoint,
                    ParamsAdjoint& adjoint_params, Scalar* adjoint_forces, Interrupt& interrupt) override;

  // The team size of a step (no result depends on it). Steps of up to kAdaptParticles
  // particles (a 2D step of 8,192 takes about 0.3-0.6 ms) can run slower on two threads than on
  // one when the two cores are contended (both threads meet at eight barriers a step); with
  // config.adapt_threads each cycle of kAdaptCycle steps times kProbe steps on one thread and
  // kProbe on the full team, and runs the rest on one thread only when its best probe was
  // clearly (by kAdaptMargin) faster: OpenMP's dynamic adjustment of the team, by measurement.
  static constexpr Index kAdaptParticles = 65536, kAdaptCycle = 256, kProbe = 3;
  static constexpr double kAdaptMargin = 0.9;
  int choose_team(Index n) {
    const int most = omp_get_max_threads();
    adapting_ = config_.adapt_threads && most > 1 && n <= kAdaptParticles;
    if (!adapting_) return most;
    const Index c = cycle_step_ % kAdaptCycle;
    if (c == 0) probe_best_[0] = probe_best_[1] = std::numeric_limits<double>::infinity();
    if (c < kProbe) return 1;
    if (c < 2 * kProbe) return most;
    return probe_best_[0] < kAdaptMargin * probe_best_[1] ? 1 : most;
  }
  void record_team(int team, double seconds) {
    if (!adapting_) return;
    if (cycle_step_ % kAdaptCycle < 2 * kProbe) {
      double& best = probe_best_[team == 1 ? 0 : 1];
      best = std::min(best, seconds);
    }
    ++cycle_step_;
  }

  // Stores the rows in the order order_ visits them (the last step's block order).
  void sort_rows(State& state) override {
    if (static_cast<Index>(order_.size()) != state.n || particle_count_ != state.n)
      throw InvalidArgument("state: sort_rows needs the State of the step just taken");
    std::vector<Index>& from = order_;
    std::vector<Index> user(static_cast<size_t>(state.n));
    parallel_for(state.n, [&](Index q) { user[static_cast<size_t>(q)] = state.user_of(from[static_cast<size_t>(q)]); });
    permute_rows(state, [&](Index q) { return from[static_cast<size_t>(q)]; }, spare_);
    state.row.resize(static_cast<size_t>(state.n));
    parallel_for(state.n, [&](Index q) { state.row[static_cast<size_t>(user[static_cast<size_t>(q)])] = q; });
    state.user = std::move(user);
    // The rows are now where order_ visits them: a second call changes nothing.
    parallel_for(state.n, [&](Index q) { order_[static_cast<size_t>(q)] = q; });
  }

 private:
  using RowMap = Eigen::Map<Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>>;
  using ConstRowMap = Eigen::Map<const Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>>;

  static void check_dt(Scalar dt) {
    if (!(std::isfinite(dt) && dt > 0))
      throw InvalidArgument("dt: expected a finite time step > 0 [s], got " + format_real(dt));
  }

  // Grid coordinates of x (in cells, ghost-shifted so that node I sits at I - 1).
  Vec<D> grid_coords(const Scalar* x) const {
    Vec<D> g;
    for (int a = 0; a < D; ++a) g(a) = (x[a] - model_.origin[a]) * inv_h_ + 1;
    return g;
  }

  // floor(g - 0.5) for a particle inside the domain (g >= 1), where truncation is the floor
  // (std::floor is a library call without SSE4.1).
  static Index base_node(Scalar g) { return static_cast<Index>(g - 0.5); }

  Index key_of(const std::array<Index, 3>& b) const { return (b[0] * blocks_[1] + b[1]) * blocks_[2] + b[2]; }

  // The sort, in three parts: prepare_sort before the step's parallel region, sort_phase
  // inside it (every thread calls it; false when a particle is bad, for every thread), and
  // build_blocks, run by one thread in the middle. With `kept` (the last step's binning of this
  // State) prepare_sort does it all: rebin() moves the particles the last G2P listed.
  void prepare_sort(const State& state, bool kept) {
    const Index n = state.n;
    particle_count_ = n;
    backup_.resize(static_cast<size_t>(n * kRow));
    bad_ = -1;
    kept_ = kept;
    // (never shrunk: a smaller team this step must not drop the moves of the last)
    const size_t threads = static_cast<size_t>(std::max(1, omp_get_max_threads()));
    if (moves_by_thread_.size() < threads) moves_by_thread_.resize(threads);
    if (kept) rebin(state);
    for (Moves& m : moves_by_thread_) {  // this step's G2P lists its own
      m.list.clear();
      m.outside = false;
    }
    if (kept) return;
    rebinned_ = n;
    // The block table stays from the last step: build_blocks rebuilds it only when the set of
    // particle blocks changed (most steps it does not). seen_ marks the blocks found this step.
    if (++epoch_ == std::numeric_limits<std::int32_t>::max()) {
      std::fill(seen_.begin(), seen_.end(), 0);
      epoch_ = 1;
    }
    particle_key_.resize(static_cast<size_t>(n));
    order_.resize(static_cast<size_t>(n));
    found_.clear();
    sort_chunks_ = n > kParallelParticles ? kSortChunks : 1;
  }

  bool sort_phase(const State& state) {
    if (kept_) return true;
    const Index n = state.n;
    // Keys of the block holding each particle's first stencil node; positions are checked
    // here because a user may write anything into the x view. In the same pass, the distinct
    // particle blocks: each thread lists the keys it finds unmarked; a key two threads both
    // found is listed twice and dropped after the sort, so the list does not depend on the
    // thread count. They take the first slots, in Morton order.
    {
      std::vector<std::pair<std::uint64_t, Index>> mine;
#pragma omp for schedule(static) nowait
      for (Index p = 0; p < n; ++p) {
        const Scalar* x = &state.x[static_cast<size_t>(p * D)];
        const Vec<D> g = grid_coords(x);
        std::array<Index, 3> b{0, 0, 0};
        bool inside = true;
        for (int a = 0; a < D; ++a) {
          inside = inside && g(a) >= 1 && g(a) <= static_cast<Scalar>(model_.shape[a] + 1);
          if (inside) b[a] = base_node(g(a)) / B;
        }
        const Index code = state.material[static_cast<size_t>(p)];
        inside = inside && code >= 0 && code < static_cast<Index>(model_.materials.size());
        const Scalar E = state.youngs_modulus[static_cast<size_t>(p)], nu = state.poisson_ratio[static_cast<size_t>(p)];
        inside = inside && std::isfinite(E) && E > 0 && std::isfinite(nu) && nu > -1 && nu < 0.5;
        const Scalar mp = state.mass[static_cast<size_t>(p)], vp = state.volume[static_cast<size_t>(p)];
        inside = inside && mp > 0 && std::isfinite(mp) && vp > 0 && std::isfinite(vp);
        if (!inside) {
          const Index u = state.user_of(p);
#pragma omp critical(mpm_bad_particle)
          bad_ = bad_ < 0 ? u : std::min(bad_, u);
          continue;
        }
        const Index key = key_of(b);
        particle_key_[static_cast<size_t>(p)] = key;
        std::int32_t& mark = seen_[static_cast<size_t>(key)];
        std::int32_t seen;
#pragma omp atomic read
        seen = mark;
        if (seen != epoch_) {
#pragma omp atomic write
          mark = epoch_;
          mine.emplace_back(morton(coords_of(key)), key);
        }
      }
#pragma omp critical(mpm_found_blocks)
      found_.insert(found_.end(), mine.begin(), mine.end());
    }
#pragma omp barrier
#pragma omp single
    build_blocks();
    if (bad_ >= 0) return false;
    // Counting sort of the particles by block slot, stable (by user row within a block): the
    // user rows are cut into a fixed number of chunks (not one per thread, so that the order
    // does not depend on the thread count), counted per chunk, and each chunk fills its own
    // ranges. order_ holds stored rows (state.row maps user rows to them).
    const Index chunks = sort_chunks_, pb = particle_blocks_;
    const Index* row = state.row.empty() ? nullptr : state.row.data();
    auto stored = [row](Index u) { return row ? row[u] : u; };
    auto chunk_rows = [&](Index c) { return std::make_pair(n * c / chunks, n * (c + 1) / chunks); };
#pragma omp for schedule(static)
    for (Index c = 0; c < chunks; ++c) {
      const auto [first, last] = chunk_rows(c);
      Index* count = &fill_[static_cast<size_t>(c * pb)];
      for (Index u = first; u < last; ++u)
        ++count[table_[static_cast<size_t>(particle_key_[static_cast<size_t>(stored(u))])]];
    }
#pragma omp single
    {
      Index running = 0;
      for (Index s = 0; s < pb; ++s) {
        block_start_[static_cast<size_t>(s)] = running;
        for (Index c = 0; c < chunks; ++c) {
          Index& at = fill_[static_cast<size_t>(c * pb + s)];
          const Index count = at;
          at = running;
          running += count;
        }
      }
      block_start_[static_cast<size_t>(pb)] = running;
    }
#pragma omp for schedule(static)
    for (Index c = 0; c < chunks; ++c) {
      const auto [first, last] = chunk_rows(c);
      Index* at = &fill_[static_cast<size_t>(c * pb)];
      for (Index u = first; u < last; ++u) {
        const Index p = stored(u);
        order_[static_cast<size_t>(at[table_[static_cast<size_t>(particle_key_[static_cast<size_t>(p)])]]++)] = p;
      }
    }
    return true;
  }

  // One thread: the block table from the particle blocks found (nothing after a bad particle:
  // the last step's table stays).
  void build_blocks() {
    if (bad_ >= 0) return;
    std::sort(found_.begin(), found_.end());
    found_.erase(std::unique(found_.begin(), found_.end()), found_.end());
    // The same particle blocks as the last step (in Morton order, as slot_key_ lists them):
    // the table, the slots and their neighbour lists are the ones already built.
    bool same = static_cast<Index>(found_.size()) == particle_blocks_;
    for (size_t i = 0; same && i < found_.size(); ++i) same = found_[i].second == slot_key_[i];
    if (!same) rebuild_table();
    fill_.assign(static_cast<size_t>(sort_chunks_ * particle_blocks_), 0);
    block_start_.resize(static_cast<size_t>(particle_blocks_ + 1));
  }
  // The slots of the particle blocks found_ lists (in its order) and of their +1 neighbours,
  // their neighbour and source lists, and the grid and tiles sized for them.
  void rebuild_table() {
    for (Index key : slot_key_) table_[static_cast<size_t>(key)] = -1;
    slot_key_.clear();
    slot_code_.clear();
    particle_blocks_ = static_cast<Index>(found_.size());
    for (const auto& f : found_) {
      table_[static_cast<size_t>(f.second)] = static_cast<std::int32_t>(slot_key_.size());
      slot_key_.push_back(f.second);
      slot_code_.push_back(f.first);
    }
    // Their +1 neighbours receive the tiles' overflow.
    for (Index s = 0; s < particle_blocks_; ++s) {
      const auto c = coords_of(slot_key_[static_cast<size_t>(s)]);
      for (int o = 1; o < NEIGHBORS; ++o) {
        std::array<Index, 3> nc = c;
        for (int a = 0; a < D; ++a) nc[a] += (o >> a) & 1;
        const Index key = key_of(nc);
        if (table_[static_cast<size_t>(key)] < 0) {
          table_[static_cast<size_t>(key)] = static_cast<std::int32_t>(slot_key_.size());
          slot_key_.push_back(key);
        }
      }
    }
    const Index slots = static_cast<Index>(slot_key_.size());
    neighbor_slot_.resize(static_cast<size_t>(particle_blocks_ * NEIGHBORS));
    for (Index s = 0; s < particle_blocks_; ++s) {
      const auto c = coords_of(slot_key_[static_cast<size_t>(s)]);
      for (int o = 0; o < NEIGHBORS; ++o) {
        std::array<Index, 3> nc = c;
        for (int a = 0; a < D; ++a) nc[a] += (o >> a) & 1;
        neighbor_slot_[static_cast<size_t>(s * NEIGHBORS + o)] = table_[static_cast<size_t>(key_of(nc))];
      }
    }
    // For every slot, the particle blocks whose tiles reach it: the block itself and its -1
    // neighbours (offset o of source_slot_ is the block at c - o), -1 where there is none.
    source_slot_.resize(static_cast<size_t>(slots * NEIGHBORS));
    for (Index s = 0; s < slots; ++s) {
      const auto c = coords_of(slot_key_[static_cast<size_t>(s)]);
      for (int o = 0; o < NEIGHBORS; ++o) {
        std::array<Index, 3> nc = c;
        bool valid = true;
        for (int a = 0; a < D; ++a) {
          nc[a] -= (o >> a) & 1;
          valid = valid && nc[a] >= 0;
        }
        const std::int32_t slot = valid ? table_[static_cast<size_t>(key_of(nc))] : -1;
        source_slot_[static_cast<size_t>(s * NEIGHBORS + o)] = slot < particle_blocks_ ? slot : -1;
      }
    }
    grid_.resize(static_cast<size_t>(slots * BN * S));
    tiles_.resize(static_cast<size_t>(particle_blocks_ * TN * S));
  }

  // ---- the binning kept from step to step -------------------------------------------------
  // G2P lists the particles that leave their block (track); the next step, when it steps the
  // same State unchanged (State::binning), moves only them (rebin) instead of sorting all.

  // A particle that left its block: its position q in order_ (block `from`), user row, and the
  // key and Morton code of the block it entered.
  struct Move {
    std::uint64_t code;
    Index user, q, key;
    std::int32_t from;
  };
  // One thread's moves of a G2P, and whether a particle ended where the sort would reject it
  // (then the next step sorts in full and reports it). Padded: each thread writes its own.
  struct alignas(64) Moves {
    std::vector<Move> list;
    bool outside = false;
  };

  // After G2P moved particle p (position q of block s, whose lower node is o): lists it when the
  // next sort would put it in another block.
  void track(Index s, const std::array<Index, 3>& o, Index q, Index p, const State& state, Moves& moves) const {
    const Vec<D> g = grid_coords(&state.x[static_cast<size_t>(p * D)]);
    std::array<Index, 3> b{0, 0, 0};
    bool left = false;
    for (int a = 0; a < D; ++a) {
      // sort_phase's test (G2P clamps x to the domain, but (x - origin) / h may round past it)
      if (!(g(a) >= 1 && g(a) <= static_cast<Scalar>(model_.shape[a] + 1))) {
        moves.outside = true;
        return;
      }
      const Index node = base_node(g(a));
      left = left || node < o[a] || node >= o[a] + B;
      b[a] = node / B;
    }
    if (left) moves.list.push_back({morton(b), state.user_of(p), q, key_of(b), static_cast<std::int32_t>(s)});
  }

  // Positions strictly inside (lo, hi) on every axis certainly stay in the block whose lower
  // node is o, inside the domain: the positions whose base node floor(g - 1/2) lies in the
  // block (g = (x - origin) / h + 1, grid_coords), origin + (o - 1/2 .. o + B - 1/2) h,
  // clipped to the domain, narrowed by a margin far above the rounding of grid_coords (so
  // that G2P can skip track() for them).
  struct StayBox {
    Scalar lo[D], hi[D];
  };
  StayBox stay_box(const std::array<Index, 3>& o) const {
    StayBox box;
    const Scalar h = model_.h;
    for (int a = 0; a < D; ++a) {
      const Scalar origin = model_.origin[a], upper = model_.upper(a);
      const Scalar margin = 1e-6 * h + 64 * std::numeric_limits<Scalar>::epsilon() * (std::abs(origin) + std::abs(upper));
      box.lo[a] = std::max(origin + (static_cast<Scalar>(o[a]) - 0.5) * h, origin) + margin;
      box.hi[a] = std::min(origin + (static_cast<Scalar>(o[a] + B) - 0.5) * h, upper) - margin;
    }
    return box;
  }

  // After a step that succeeded: the mark that tells the next step (and signal_speed) that the
  // State is still the one this step left. The binning is kept only when no particle ended
  // where the next sort must look at it.
  void leave_mark(State& state) {
    binning_kept_ = true;
    for (const Moves& m : moves_by_thread_)
      binning_kept_ = binning_kept_ && !m.outside;
    // Unique to this solver and step (a State another solver marked must not match).
    mark_ = mix64(id_ + static_cast<std::uint64_t>(++marks_)) | 1u;
    state.binning = mark_;
    marked_ = &state;
  }
  bool unchanged_since_step(const State& state) const {
    return mark_ != 0 && state.binning == mark_ && marked_ == &state && state.n == particle_count_;
  }

  // The signal speed of the State the last step left, as Solver::signal_speed computes it (the
  // same expressions on the same maxima: bitwise the same), with no pass over the particles:
  // G2P measured the largest squared speed it stored and snow's largest hardening exponent
  // hardening (1 - Jp) (exp is monotone: the largest hardening is exp of it), and the moduli
  // and materials, which no step changes, gave the wave speeds once.
  bool measured_speed(const State& state, Scalar& speed) const override {
    if (!wave_speeds_known_ || !unchanged_since_step(state)) return false;
    const Scalar harden = measured_snow_exponent_ > 0 ? std::exp(measured_snow_exponent_) : 1.0;
    const Scalar c = std::max(std::sqrt(c2_elastic_), std::sqrt(c2_snow_) * std::sqrt(harden));
    speed = std::sqrt(measured_v2_) + c;
    return true;
  }
  void remember_wave_speeds(const State& state, Scalar c2_elastic, Scalar c2_snow) override {
    if (!unchanged_since_step(state)) return;
    c2_elastic_ = c2_elastic;
    c2_snow_ = c2_snow;
    wave_speeds_known_ = true;
  }

  static std::uint64_t mix64(std::uint64_t z) {  // SplitMix64's finaliser
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  }

  // The last step's binning with the particles its G2P listed moved to their new blocks: the
  // order a full sort gives (blocks in Morton order, a block's particles by user row), in one
  // serial pass (the moves are few; the rest of order_ is copied block by block).
  void rebin(const State& state) {
    moves_.clear();
    for (Moves& m : moves_by_thread_) {
      moves_.insert(moves_.end(), m.list.begin(), m.list.end());
      m.list.clear();
    }
    rebinned_ = static_cast<Index>(moves_.size());
    if (moves_.empty()) return;
    std::sort(moves_.begin(), moves_.end(),
              [](const Move& a, const Move& b) { return a.code != b.code ? a.code < b.code : a.user < b.user; });
    const Index old_blocks = particle_blocks_, moved = static_cast<Index>(moves_.size());
    remaining_.resize(static_cast<size_t>(old_blocks));
    for (Index s = 0; s < old_blocks; ++s)
      remaining_[static_cast<size_t>(s)] = block_start_[static_cast<size_t>(s + 1)] - block_start_[static_cast<size_t>(s)];
    leaving_.clear();
    for (const Move& m : moves_) {
      --remaining_[static_cast<size_t>(m.from)];
      leaving_.push_back(m.q);
    }
    std::sort(leaving_.begin(), leaving_.end());
    // The new particle blocks in Morton order: the old ones that keep or gain particles and the
    // ones the moves enter, each with its old slot (-1: none) and its range of moves_.
    next_.clear();
    Index i = 0;
    auto moves_end = [&](Index first) {
      Index j = first;
      while (j < moved && moves_[static_cast<size_t>(j)].code == moves_[static_cast<size_t>(first)].code) ++j;
      return j;
    };
    for (Index s = 0; s <= old_blocks; ++s) {
      const std::uint64_t code = s < old_blocks ? slot_code_[static_cast<size_t>(s)] : ~std::uint64_t{0};
      while (i < moved && moves_[static_cast<size_t>(i)].code < code) {
        const Index j = moves_end(i);
        next_.push_back({moves_[static_cast<size_t>(i)].code, moves_[static_cast<size_t>(i)].key, -1, i, j});
        i = j;
      }
      if (s == old_blocks) break;
      const Index j = i < moved && moves_[static_cast<size_t>(i)].code == code ? moves_end(i) : i;
      if (remaining_[static_cast<size_t>(s)] > 0 || j > i) next_.push_back({code, slot_key_[static_cast<size_t>(s)], s, i, j});
      i = j;
    }
    // Each new block's rows: its old rows (by user row) less the ones that leave (leaving_, by
    // position), with the ones that enter (by user row) inserted where their user row falls.
    start_next_.resize(next_.size() + 1);
    order_next_.resize(static_cast<size_t>(state.n));
    Index out = 0;
    size_t leave = 0;
    auto copy = [&](Index from, Index to) {
      std::copy(order_.begin() + from, order_.begin() + to, order_next_.begin() + out);
      out += to - from;
    };
    for (size_t k = 0; k < next_.size(); ++k) {
      const NextBlock& nb = next_[k];
      start_next_[k] = out;
      const Index first = nb.old >= 0 ? block_start_[static_cast<size_t>(nb.old)] : 0;
      const Index last = nb.old >= 0 ? block_start_[static_cast<size_t>(nb.old + 1)] : 0;
      while (leave < leaving_.size() && leaving_[leave] < first) ++leave;  // blocks left empty
      Index at = first;  // old rows before `at` are placed
      for (Index m = nb.first_move; m <= nb.end_move; ++m) {
        // where move m enters: before the first old row of a higher user row
        Index enter = last;
        if (m < nb.end_move) {  // a binary search of the old rows from `at`
          const Index u = moves_[static_cast<size_t>(m)].user;
          Index lo = at;
          while (lo < enter) {
            const Index mid = lo + (enter - lo) / 2;
            if (state.user_of(order_[static_cast<size_t>(mid)]) < u) lo = mid + 1;
            else enter = mid;
          }
        }
        for (; leave < leaving_.size() && leaving_[leave] < enter; ++leave) {
          copy(at, leaving_[leave]);
          at = leaving_[leave] + 1;
        }
        copy(at, enter);
        at = enter;
        if (m < nb.end_move) order_next_[static_cast<size_t>(out++)] = order_[static_cast<size_t>(moves_[static_cast<size_t>(m)].q)];
      }
    }
    start_next_[next_.size()] = out;
    order_.swap(order_next_);
    block_start_.swap(start_next_);
    bool same = static_cast<Index>(next_.size()) == old_blocks;
    for (size_t k = 0; same && k < next_.size(); ++k) same = next_[k].old == static_cast<Index>(k);
    if (same) return;
    found_.clear();
    for (const NextBlock& nb : next_) found_.emplace_back(nb.code, nb.key);
    rebuild_table();
  }

  // The particle sort_phase found bad (a value written through a view): names what is wrong.
  [[noreturn]] void throw_bad_particle(const State& state) const {
    const Index bad = bad_;
    const size_t p = static_cast<size_t>(state.row_of(bad));
    const std::string which = "particle " + std::to_string(bad);
    const Index code = state.material[p];
    if (code < 0 || code >= static_cast<Index>(model_.materials.size()))
      throw InvalidArgument("material: " + which + " has material code " + std::to_string(code) +
                            ", not one of the " + std::to_string(model_.materials.size()) + " materials");
    const Scalar E = state.youngs_modulus[p], nu = state.poisson_ratio[p];
    if (!(std::isfinite(E) && E > 0))
      throw InvalidArgument("youngs_modulus: " + which + " has " + format_real(E) + ", expected a finite value > 0");
    if (!(nu > -1 && nu < 0.5))
      throw InvalidArgument("poisson_ratio: " + which + " has " + format_real(nu) + ", expected a value in (-1, 0.5)");
    if (!(state.mass[p] > 0 && std::isfinite(state.mass[p])))
      throw InvalidArgument("mass: " + which + " has " + format_real(state.mass[p]) + ", expected a finite value > 0");
    if (!(state.volume[p] > 0 && std::isfinite(state.volume[p])))
      throw InvalidArgument("volume: " + which + " has " + format_real(state.volume[p]) +
                            ", expected a finite value > 0");
    std::string where = "(";
    for (int a = 0; a < D; ++a) where += (a ? ", " : "") + format_real(state.x[p * D + a]);
    throw InvalidArgument("x: " + which + " at " + where + ") is outside the domain or not finite");
  }

  // After a step whose G2P met a non-finite value (the State restored): the first particle
  // whose v, F, C or Jp was already non-finite before the step (written through a view), named
  // as bad input; empty when the input was finite (a blow-up).
  std::string bad_input(const State& state) const {
    const Index n = state.n;
    const struct { const std::vector<Scalar>& a; int width; const char* name; } fields[] = {
        {state.v, D, "v"}, {state.F, D * D, "F"}, {state.C, D * D, "C"}, {state.Jp, 1, "Jp"}};
    for (const auto& f : fields)
      for (Index p = 0; p < n; ++p)
        for (int k = 0; k < f.width; ++k)
          if (!std::isfinite(f.a[static_cast<size_t>(p * f.width + k)]))
            return std::string(f.name) + ": particle " + std::to_string(state.user_of(p)) +
                   " holds a non-finite value (written through the view?)";
    return "";
  }

  std::array<Index, 3> coords_of(Index key) const {
    return {key / (blocks_[1] * blocks_[2]), (key / blocks_[2]) % blocks_[1], key % blocks_[2]};
  }

  // Lower node (ghost-shifted) of a block.
  std::array<Index, 3> block_origin(Index slot) const {
    auto c = coords_of(slot_key_[static_cast<size_t>(slot)]);
    for (int a = 0; a < D; ++a) c[a] *= B;
    return c;
  }

  // Where tile node t lies in the grid: which of the 2^d blocks from the tile's own (bit a set:
  // the +1 neighbour along axis a) and which node of it.
  struct TileNode {
    int neighbor, local;
  };
  static std::array<TileNode, TN> make_tile_nodes() {
    std::array<TileNode, TN> nodes{};
    for (int t = 0; t < TN; ++t) {
      int tc[3] = {0, 0, 0}, rest = t;
      for (int a = D - 1; a >= 0; --a) {
        tc[a] = rest % T;
        rest /= T;
      }
      int neighbor = 0, local = 0;
      for (int a = 0; a < D; ++a) {
        const int over = tc[a] >= B;
        neighbor |= over << a;
        local = local * B + (tc[a] - over * B);
      }
      nodes[static_cast<size_t>(t)] = {neighbor, local};
    }
    return nodes;
  }
  // overlaps[o]: the (block node, tile node) pairs where the tile of the block at c - o covers
  // the block at c, in tile order.
  struct Overlap {
    int node, tile;
  };
  static std::array<std::vector<Overlap>, NEIGHBORS> make_overlaps() {
    std::array<std::vector<Overlap>, NEIGHBORS> overlaps;
    const auto nodes = make_tile_nodes();
    for (int t = 0; t < TN; ++t)
      overlaps[static_cast<size_t>(nodes[static_cast<size_t>(t)].neighbor)].push_back(
          {nodes[static_cast<size_t>(t)].local, t});
    return overlaps;
  }

  // Per-particle weights and tile-relative base of particle p in a block whose lower node is o.
  struct Stencil {
    Scalar w[D][3];
    Vec<D> fx;  // position relative to the base node, in cells
    int base;   // tile index of the base node
  };

  Stencil stencil(const Scalar* x, const std::array<Index, 3>& o) const {
    Stencil st;
    const Vec<D> g = grid_coords(x);
    st.base = 0;
    for (int a = 0; a < D; ++a) {
      const Index b = base_node(g(a));
      st.fx(a) = g(a) - static_cast<Scalar>(b);
      bspline_weights(st.fx(a), st.w[a]);
      st.base = st.base * T + static_cast<int>(b - o[a]);
    }
    return st;
  }

  // Calls fn(tile index, w, dw/dfx, offset x_i/h - x_p/h) for the 3^d nodes of a stencil.
  template <class Fn>
  static void each_node(const Stencil& st, Fn&& fn) {
    Scalar dw[D][3];
    for (int a = 0; a < D; ++a) bspline_derivatives(st.fx(a), dw[a]);
    for (int node = 0; node < ipow(3, D); ++node) {
      int index[D];
      int rest = node, t = 0;
      for (int a = D - 1; a >= 0; --a) {
        index[a] = rest % 3;
        rest /= 3;
      }
      Scalar w = 1;
      Vec<D> grad_w, offset;
      for (int a = 0; a < D; ++a) {
        t = t * T + index[a];
        w *= st.w[a][index[a]];
        offset(a) = index[a] - st.fx(a);
        grad_w(a) = dw[a][index[a]];
        for (int b = 0; b < D; ++b)
          if (b != a) grad_w(a) *= st.w[b][index[b]];
      }
      fn(st.base + t, w, grad_w, offset);
    }
  }

  // Unshifted node index per axis of node l of the block whose lower node is o.
  static void node_index(const std::array<Index, 3>& o, int l, Index* i) {
    int rest = l;
    for (int a = D - 1; a >= 0; --a) {
      i[a] = o[a] + rest % B - 1;
      rest /= B;
    }
  }

  // Kirchhoff stress of particle p (kernels.h) with its own moduli.
  Mat<D> tau(const State& state, Index p, const Mat<D>& F) const {
    const Material& m = model_.materials[static_cast<size_t>(state.material[static_cast<size_t>(p)])];
    Scalar mu, lambda;
    particle_lame(state, m, p, mu, lambda);
    switch (m.kind) {
      case MaterialKind::Elastic:
        if constexpr (D == 2) return corotated_tau(F, mu, lambda);
        else return corotated_tau<D>(F, svd(F), mu, lambda);
      case MaterialKind::NeoHookean:
        return neohookean_tau<D>(F, mu, lambda);
      case MaterialKind::Snow: {
        const Scalar harden = snow_hardening(m, state.Jp[static_cast<size_t>(p)]);
        if constexpr (D == 2) return corotated_tau(F, mu * harden, lambda * harden);
        else return corotated_tau<D>(F, svd(F), mu * harden, lambda * harden);
      }
      case MaterialKind::Sand:
        return hencky_tau<D>(svd(F), mu, lambda);
      case MaterialKind::Water:
        return water_tau<D>(F.determinant(), state.youngs_modulus[static_cast<size_t>(p)], m.gamma);
    }
    return Mat<D>::Zero();
  }

  // The rows of particle order_[q + kAhead] are fetched into cache while particle q is worked
  // on: the transfers visit the rows in block order, which is random in the user's row order
  // (a block-sorted row order runs mpm88 12% faster per core), so the hardware prefetcher
  // cannot see them coming. No effect on the results.
  static constexpr Index kAhead = 12;
  void prefetch_row(const State& state, Index q, Index end) const {
    if (q + kAhead >= end) return;
    const size_t p = static_cast<size_t>(order_[static_cast<size_t>(q + kAhead)]);
    __builtin_prefetch(&state.x[p * D]);
    __builtin_prefetch(&state.v[p * D]);
    __builtin_prefetch(&state.F[p * D * D]);
    __builtin_prefetch(&state.C[p * D * D]);
    __builtin_prefetch(&state.mass[p]);
    __builtin_prefetch(&state.volume[p]);
    __builtin_prefetch(&state.material[p]);
    __builtin_prefetch(&state.Jp[p]);
    __builtin_prefetch(&state.youngs_modulus[p]);
    __builtin_prefetch(&state.poisson_ratio[p]);
  }

  // The transfers' work items are the particle blocks, handed out one at a time (the tiles make
  // the results independent of which thread takes which). With the rows stored in block order
  // (sort_rows) a block's rows are one contiguous range, so the two threads share no cache line
  // of the particle arrays but at the ends of their blocks. (Session 12's 2D lanes, two tiles
  // per block for two fixed halves of the user rows, kept each row on one core while the rows
  // were in random user order; with sorted rows the second tile's gathers and sums cost more:
  // mpm88 on 2 threads 0.39-0.41 against 0.33 ms per substep.)
  template <class Fn>
  void each_block(Fn&& fn) const {
#pragma omp for schedule(dynamic, 1)
    for (Index s = 0; s < particle_blocks_; ++s) fn(s);
  }
  // Calls fn(q, end) for the positions q of order_ in block s, whose rows end at `end`.
  template <class Fn>
  void each_in_block(Index s, Fn&& fn) const {
    const Index end = block_start_[static_cast<size_t>(s + 1)];
    for (Index q = block_start_[static_cast<size_t>(s)]; q < end; ++q) fn(q, end);
  }

  // Each work item scatters into its own tile of tiles_ (no two threads write one value).
  // Called by every thread of a parallel region (a work-shared loop ending in a barrier).
  void p2g_phase(const State& state, Scalar dt, const Scalar* forces) {
#if KINEMA_HAVE_AVX2_CLONES
    if constexpr (D == 2) {
      if (avx2_) {
        p2g_lanes_avx2(state, dt, forces);
        return;
      }
    }
#endif
    const Scalar h = model_.h, stress_scale = 4 * dt / (h * h);
    each_block([&](Index s) {
      const auto o = block_origin(s);
      Scalar* tile = &tiles_[static_cast<size_t>(s * TN * S)];
      std::fill_n(tile, TN * S, 0.0);
      each_in_block(s, [&](Index q, Index end) {
        prefetch_row(state, q, end);
        const Index p = order_[static_cast<size_t>(q)];
        const size_t pd = static_cast<size_t>(p * D);
        const Stencil st = stencil(&state.x[pd], o);
        const Scalar m = state.mass[static_cast<size_t>(p)];
        const Eigen::Map<const Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>> F(&state.F[pd * D]);
        const Eigen::Map<const Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>> C(&state.C[pd * D]);
        const Eigen::Map<const Vec<D>> v(&state.v[pd]);
        // Affine momentum per unit offset, in cells: (m C - 4 dt V / h^2 tau) h.
        const Mat<D> A = (m * C - (stress_scale * state.volume[static_cast<size_t>(p)]) * tau(state, p, F)) * h;
        // Momentum at offset 0 (the base node); an external force adds dt f, as gravity would.
        const Vec<D> q0 = forces ? Vec<D>(m * v + dt * Eigen::Map<const Vec<D>>(forces + state.user_of(p) * D) - A * st.fx)
                                 : Vec<D>(m * v - A * st.fx);
        scatter(tile, st, m, q0, A);
      });
    });
  }

  // For every slot, work-shared among the threads of the enclosing parallel region (ending in
  // a barrier): sums the tiles over its nodes (the sources in the fixed order of source_slot_,
  // so a node's sum does not depend on the thread count) into `sum` (B^d (d + 1)) and calls
  // node_fn(slot, sum).
  template <class Fn>
  void reduce_tiles(const std::vector<Scalar>& tiles, Fn&& node_fn) const {
    const Index slots = static_cast<Index>(slot_key_.size());
#pragma omp for schedule(static)
    for (Index s = 0; s < slots; ++s) {
      alignas(64) Scalar sum[BN * S];
      std::fill_n(sum, BN * S, 0.0);
      for (int o = 0; o < NEIGHBORS; ++o) {
        const std::int32_t src = source_slot_[static_cast<size_t>(s * NEIGHBORS + o)];
        if (src < 0) continue;
        const Scalar* tile = &tiles[static_cast<size_t>(src) * TN * S];
        for (const Overlap& ov : overlaps_[static_cast<size_t>(o)])
          for (int c = 0; c < S; ++c) sum[ov.node * S + c] += tile[ov.tile * S + c];
      }
      node_fn(s, sum);
    }
  }

  void scatter(Scalar* tile, const Stencil& st, Scalar m, const Vec<D>& q0, const Mat<D>& A) const {
    if constexpr (D == 2) {
      for (int i = 0; i < 3; ++i) {
        const Vec<D> qi = q0 + A.col(0) * i;
        for (int j = 0; j < 3; ++j) {
          const Scalar w = st.w[0][i] * st.w[1][j];
          const Vec<D> q = qi + A.col(1) * j;
          Scalar* node = tile + (st.base + i * T + j) * S;
          node[0] += w * m;
          node[1] += w * q(0);
          node[2] += w * q(1);
        }
      }
    } else {
      for (int i = 0; i < 3; ++i) {
        const Vec<D> qi = q0 + A.col(0) * i;
        for (int j = 0; j < 3; ++j) {
          const Scalar wij = st.w[0][i] * st.w[1][j];
          const Vec<D> qij = qi + A.col(1) * j;
          Scalar* row = tile + (st.base + (i * T + j) * T) * S;
          for (int k = 0; k < 3; ++k) {
            const Scalar w = wij * st.w[2][k];
            const Vec<D> q = qij + A.col(2) * k;
            Scalar* node = row + k * S;
            node[0] += w * m;
            node[1] += w * q(0);
            node[2] += w * q(1);
            node[3] += w * q(2);
          }
        }
      }
    }
  }

  // The grid pass: each node's mass and momentum summed from the tiles, then
  // v = (m v) / m + dt g and the wall and collider conditions. `pre` (slots B^d d, or null)
  // receives each node's velocity before the conditions, which their adjoint needs.
  void grid_phase(Scalar dt, Scalar* pre) {
    Vec<D> g;
    for (int a = 0; a < D; ++a) g(a) = config_.gravity[a];
    reduce_tiles(tiles_, [&](Index s, const Scalar* sum) {
      const auto o = block_origin(s);
      Scalar* out = &grid_[static_cast<size_t>(s * BN * S)];
      for (int l = 0; l < BN; ++l) {
        const Scalar* in = sum + l * S;
        Scalar* node = out + l * S;
        node[0] = in[0];
        if (in[0] <= 0) {
          for (int a = 0; a < D; ++a) node[a + 1] = 0;
          continue;
        }
        Vec<D> v;
        for (int a = 0; a < D; ++a) v(a) = in[a + 1] / in[0] + dt * g(a);
        if (pre) Eigen::Map<Vec<D>>(pre + (s * BN + l) * D) = v;
        Index i[3] = {0, 0, 0};
        node_index(o, l, i);
        boundary(v, i);
        for (int a = 0; a < D; ++a) node[a + 1] = v(a);
      }
    });
  }

  void boundary(Vec<D>& v, const Index* i) const {
    conditions(i, [&](const Vec<D>& n, Boundary b, Scalar friction) { apply_boundary<D>(v, n, b, friction); });
  }

  // The transpose of boundary()'s Jacobian at v, applied to v_bar: the conditions in reverse,
  // each at the velocity it saw.
  Vec<D> boundary_vjp(Vec<D> v, const Index* i, Vec<D> v_bar) const {
    struct Applied {
      Vec<D> n, v;
      Boundary boundary;
      Scalar friction;
    };
    // At most d walls and every collider apply; a node meets few, so the record lives on the
    // stack (this runs for every node with mass).
    constexpr size_t kInline = 8;
    Applied on_stack[kInline];
    std::vector<Applied> on_heap;
    Applied* applied = on_stack;
    if (D + model_.colliders.size() > kInline) {
      on_heap.resize(D + model_.colliders.size());
      applied = on_heap.data();
    }
    int count = 0;
    conditions(i, [&](const Vec<D>& n, Boundary b, Scalar friction) {
      applied[count++] = {n, v, b, friction};
      apply_boundary<D>(v, n, b, friction);
    });
    for (int c = count - 1; c >= 0; --c)
      v_bar = apply_boundary_vjp<D>(applied[c].v, applied[c].n, applied[c].boundary, applied[c].friction, v_bar);
    return v_bar;
  }

  // Calls fn(normal, boundary, friction) for each condition on the node with index i, in the
  // order they apply: walls at i <= 0 and i >= shape, then the colliders.
  template <class Fn>
  void conditions(const Index* i, Fn&& fn) const {
    for (int a = 0; a < D; ++a) {
      if (i[a] <= 0 || i[a] >= model_.shape[a]) {
        Vec<D> n = Vec<D>::Zero();
        n(a) = i[a] <= 0 ? 1 : -1;
        fn(n, model_.boundary, model_.wall_friction);
      }
    }
    if (model_.colliders.empty()) return;
    Vec<D> x;
    for (int a = 0; a < D; ++a) x(a) = model_.origin[a] + static_cast<Scalar>(i[a]) * model_.h;
    for (const Collider& c : model_.colliders) {
      Vec<D> n;
      if (c.shape == Collider::Shape::Sphere) {
        Vec<D> r;
        for (int a = 0; a < D; ++a) r(a) = x(a) - c.center[a];
        const Scalar dist = r.norm();
        if (dist >= c.radius) continue;
        n = dist > 0 ? Vec<D>(r / dist) : Vec<D>::UnitY();
      } else {
        bool inside = true;
        Scalar nearest = std::numeric_limits<Scalar>::infinity();
        int face = 0;
        for (int a = 0; a < D && inside; ++a) {
          inside = x(a) > c.lower[a] && x(a) < c.upper[a];
          const Scalar lo = x(a) - c.lower[a], hi = c.upper[a] - x(a);
          if (lo < nearest) nearest = lo, face = -(a + 1);
          if (hi < nearest) nearest = hi, face = a + 1;
        }
        if (!inside) continue;
        n.setZero();
        n(std::abs(face) - 1) = face > 0 ? 1 : -1;
      }
      fn(n, c.boundary, c.friction);
    }
  }

  // Work-shared among the threads of the enclosing parallel region; each thread's largest
  // squared speed and finiteness are merged into the shared vmax2_all and finite_all (a max
  // and an and: the same whatever the thread count).
  void g2p_phase(State& state, Scalar dt, Scalar& vmax2_all, bool& finite_all) {
    const Scalar h = model_.h;
    Scalar vmax2 = 0, snow_exponent = 0;
    bool finite = true;
    Moves& moves = moves_by_thread_[static_cast<size_t>(omp_get_thread_num())];
#if KINEMA_HAVE_AVX2_CLONES
    if constexpr (D == 2) {
      if (avx2_) g2p_lanes_avx2(state, dt, vmax2, snow_exponent, finite, moves);
    }
    if (!(D == 2 && avx2_))
#endif
    each_block([&](Index s) {
      const auto o = block_origin(s);
      const StayBox box = stay_box(o);
      alignas(64) Scalar tile[TN * S];
      gather<1>(tile, s, grid_);
      each_in_block(s, [&](Index q, Index end) {
        prefetch_row(state, q, end);
        const Index p = order_[static_cast<size_t>(q)];
        const size_t pd = static_cast<size_t>(p * D);
        save_row(state, p, q);
        const Stencil st = stencil(&state.x[pd], o);
        Vec<D> v = Vec<D>::Zero();
        Mat<D> Bm = Mat<D>::Zero();  // sum w v_i (node offset in cells)^T
        gather_sums(tile, st, v, Bm);
        const Mat<D> C = (4 / h) * (Bm - v * st.fx.transpose());
        Eigen::Map<Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>> F(&state.F[pd * D]);
        Eigen::Map<Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>>(&state.C[pd * D]) = C;
        Mat<D> Fn = (Mat<D>::Identity() + dt * C) * F;
        snow_exponent = std::max(snow_exponent, plasticity(state, p, Fn, dt));
        F = Fn;
        for (int a = 0; a < D; ++a) {
          Scalar& x = state.x[pd + a];
          x = std::clamp(x + dt * v(a), model_.origin[a], model_.upper(a));
          state.v[pd + a] = v(a);
        }
        bool stays = true;  // (without branches: nearly every particle stays)
        for (int a = 0; a < D; ++a) stays &= (state.x[pd + a] > box.lo[a]) & (state.x[pd + a] < box.hi[a]);
        if (!stays) track(s, o, q, p, state, moves);
        finite = finite && v.allFinite() && Fn.allFinite();
        vmax2 = std::max(vmax2, squared_speed(v));
      });
    });
#pragma omp critical(mpm_g2p_reduce)
    {
      vmax2_all = std::max(vmax2_all, vmax2);
      snow_exponent_ = std::max(snow_exponent_, snow_exponent);
      finite_all = finite_all && finite;
    }
  }

  // After G2P: a blow-up restores the State and throws; otherwise the largest speed.
  Scalar check_g2p(State& state, Scalar dt, Scalar vmax2, bool finite) {
    const Scalar h = model_.h;
    const Scalar vmax = std::sqrt(vmax2);
    if (!finite || !(vmax * dt <= config_.max_cells_per_step * h)) {
      parallel_for(state.n, [&](Index q) { restore_row(state, order_[static_cast<size_t>(q)], q); });
      if (!finite) {
        const std::string input = bad_input(state);
        if (!input.empty()) throw InvalidArgument(input);
      }
      throw DivergenceError(
          "mpm: " + std::string(finite ? "particles moved " + format_real(vmax * dt / h) + " cells in one step"
                                       : "a velocity or deformation gradient became non-finite") +
          " at step " + std::to_string(state.steps) + " (t = " + format_real(state.time) + " s, dt = " +
          format_real(dt) + " s); use a dt below stable_dt() (CFL on speed and elastic wave speed)");
    }
    return vmax;
  }

  // G2P is the only phase that writes the State, and it can fail (a blow-up): it saves the
  // values it overwrites, particle by particle while they are in cache, so that a step that
  // throws leaves the State as it was without a copy of the whole State before every step.
  // The backup holds one array per field (x, v, F, C, Jp, each of n rows); row q of each is the
  // particle at position q of the block order (sequential writes), so `rows` consecutive
  // stored rows at consecutive positions (rows sorted into blocks) are one copy per field.
  static constexpr int kRow = 2 * D + 2 * D * D + 1;  // x, v, F, C, Jp
  Scalar* backup_field(int field) {
    static constexpr int kOffset[5] = {0, D, 2 * D, 2 * D + D * D, 2 * D + 2 * D * D};
    return backup_.data() + static_cast<size_t>(particle_count_ * kOffset[field]);
  }
  template <int Rows = 1>
  void save_row(const State& state, Index p, Index q) {
    // Element by element with constant counts: std::copy_n of these short rows became memmove calls.
    const size_t pd = static_cast<size_t>(p * D), qd = static_cast<size_t>(q * D);
    Scalar *x = backup_field(0) + qd, *v = backup_field(1) + qd;
    Scalar *F = backup_field(2) + qd * D, *C = backup_field(3) + qd * D, *Jp = backup_field(4) + q;
    for (int k = 0; k < Rows * D; ++k) x[k] = state.x[pd + k];
    for (int k = 0; k < Rows * D; ++k) v[k] = state.v[pd + k];
    for (int k = 0; k < Rows * D * D; ++k) F[k] = state.F[pd * D + k];
    for (int k = 0; k < Rows * D * D; ++k) C[k] = state.C[pd * D + k];
    for (int k = 0; k < Rows; ++k) Jp[k] = state.Jp[static_cast<size_t>(p) + k];
  }
  void restore_row(State& state, Index p, Index q) {
    const size_t pd = static_cast<size_t>(p * D), qd = static_cast<size_t>(q * D);
    std::copy_n(backup_field(0) + qd, D, &state.x[pd]);
    std::copy_n(backup_field(1) + qd, D, &state.v[pd]);
    std::copy_n(backup_field(2) + qd * D, D * D, &state.F[pd * D]);
    std::copy_n(backup_field(3) + qd * D, D * D, &state.C[pd * D]);
    state.Jp[static_cast<size_t>(p)] = backup_field(4)[q];
  }

  // Copies components First..S-1 of the nodes a block's tile covers from `source` (First is a
  // constant: a copy of a run-time length became a memmove call per node).
  template <int First>
  void gather(Scalar* tile, Index s, const std::vector<Scalar>& source) const {
    const std::int32_t* nb = &neighbor_slot_[static_cast<size_t>(s * NEIGHBORS)];
    for (int t = 0; t < TN; ++t) {
      const TileNode& tn = tile_nodes_[static_cast<size_t>(t)];
      const Scalar* node = &source[static_cast<size_t>((static_cast<Index>(nb[tn.neighbor]) * BN + tn.local) * S)];
      for (int c = First; c < S; ++c) tile[t * S + c] = node[c];
    }
  }

  void gather_sums(const Scalar* tile, const Stencil& st, Vec<D>& v, Mat<D>& Bm) const {
    if constexpr (D == 2) {
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          const Scalar w = st.w[0][i] * st.w[1][j];
          const Scalar* node = tile + (st.base + i * T + j) * S;
          const Vec<D> wv(w * node[1], w * node[2]);
          v += wv;
          Bm.col(0) += wv * i;
          Bm.col(1) += wv * j;
        }
    } else {
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          const Scalar wij = st.w[0][i] * st.w[1][j];
          const Scalar* row = tile + (st.base + (i * T + j) * T) * S;
          Vec<D> sum = Vec<D>::Zero(), sum_k = Vec<D>::Zero();
          for (int k = 0; k < 3; ++k) {
            const Scalar w = wij * st.w[2][k];
            const Scalar* node = row + k * S;
            const Vec<D> wv(w * node[1], w * node[2], w * node[3]);
            sum += wv;
            sum_k += wv * k;
          }
          v += sum;
          Bm.col(0) += sum * i;
          Bm.col(1) += sum * j;
          Bm.col(2) += sum_k;
        }
    }
  }

  // Returns snow's hardening exponent hardening (1 - Jp) after the projection (0 for the other
  // materials): what signal_speed's hardening is the exp of.
  Scalar plasticity(State& state, Index p, Mat<D>& F, Scalar dt) const {
    const Material& m = model_.materials[static_cast<size_t>(state.material[static_cast<size_t>(p)])];
    Scalar& Jp = state.Jp[static_cast<size_t>(p)];
    Svd<D> s;
    switch (m.kind) {
      case MaterialKind::Snow:
        if constexpr (D == 2) F = snow_project(F, m, Jp);
        else F = snow_project<D>(F, m, Jp, s);
        return m.hardening * (1 - Jp);
      case MaterialKind::Sand: {
        Material own = m;  // the yield surface with this particle's moduli
        particle_lame(state, m, p, own.mu, own.lambda);
        F = sand_project<D>(F, own, Jp, s, dt);
        break;
      }
      case MaterialKind::Water: {
        // A fluid has no shear memory: keep only the volume ratio, F = J^(1/d) I.
        const Scalar J = F.determinant();
        const Scalar Jc = std::max(J, 1e-6);
        F = Mat<D>::Identity() * (D == 2 ? std::sqrt(Jc) : std::cbrt(Jc));
        break;
      }
      default:
        break;
    }
    return 0;
  }

#if KINEMA_HAVE_AVX2_CLONES
  // ---- 2D transfers four particles wide (AVX2) ----------------------------------------------
  // The stencil weights, the affine momentum and the weighted sums of four particles of a block
  // in one vector operation each (GCC vector extension, compiled for AVX2 only; the baseline
  // build takes the scalar code above). Every value is computed with the scalar code's
  // operations in the scalar code's order and without FMA, so the results are bitwise those of
  // the scalar path; P2G's contributions are then added into the tile particle by particle in
  // block order, so each node's sum keeps its order. The materials' stresses and return
  // mappings stay per particle (tau, plasticity), as does the backup of the rows.
  typedef Scalar Lanes __attribute__((vector_size(4 * sizeof(Scalar))));
  typedef std::int32_t LaneInts __attribute__((vector_size(4 * sizeof(std::int32_t))));

  // Component k of rows p[0..3] of an array of W values per row (W = 1, 2, 4): out[k][l] =
  // a[p[l] W + k]. Rows stored in block order (sort_rows) are mostly four consecutive rows: then
  // W vector loads and a transpose instead of 4 W scalar loads.
  static bool consecutive(const Index* p) { return p[1] == p[0] + 1 && p[2] == p[0] + 2 && p[3] == p[0] + 3; }
  template <int W>
  KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE static void load_lanes(const Scalar* a, const Index* p, bool together,
                                                                 Lanes* out) {
    if (together) {
      const Scalar* r = a + p[0] * W;
      if constexpr (W == 1) {
        out[0] = Lanes(_mm256_loadu_pd(r));
      } else if constexpr (W == 2) {
        const __m256d u = _mm256_loadu_pd(r), w = _mm256_loadu_pd(r + 4);
        out[0] = Lanes(_mm256_permute4x64_pd(_mm256_unpacklo_pd(u, w), 0xD8));
        out[1] = Lanes(_mm256_permute4x64_pd(_mm256_unpackhi_pd(u, w), 0xD8));
      } else {
        static_assert(W == 4, "rows of 1, 2 or 4 values");
        transpose4(_mm256_loadu_pd(r), _mm256_loadu_pd(r + 4), _mm256_loadu_pd(r + 8), _mm256_loadu_pd(r + 12), out);
      }
      return;
    }
    for (int k = 0; k < W; ++k)
      out[k] = Lanes{a[p[0] * W + k], a[p[1] * W + k], a[p[2] * W + k], a[p[3] * W + k]};
  }
  // The inverse: rows p[0 .. count - 1] of a take their lanes of in.
  template <int W>
  KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE static void store_lanes(Scalar* a, const Index* p, int count, bool together,
                                                                  const Lanes* in) {
    if (together && count == 4) {
      Scalar* r = a + p[0] * W;
      if constexpr (W == 2) {
        const __m256d lo = _mm256_unpacklo_pd(__m256d(in[0]), __m256d(in[1]));
        const __m256d hi = _mm256_unpackhi_pd(__m256d(in[0]), __m256d(in[1]));
        _mm256_storeu_pd(r, _mm256_permute2f128_pd(lo, hi, 0x20));
        _mm256_storeu_pd(r + 4, _mm256_permute2f128_pd(lo, hi, 0x31));
      } else {
        static_assert(W == 4, "rows of 2 or 4 values");
        Lanes rows[4];
        transpose4(__m256d(in[0]), __m256d(in[1]), __m256d(in[2]), __m256d(in[3]), rows);
        for (int k = 0; k < 4; ++k) _mm256_storeu_pd(r + 4 * k, __m256d(rows[k]));
      }
      return;
    }
    for (int l = 0; l < count; ++l)
      for (int k = 0; k < W; ++k) a[p[l] * W + k] = in[k][l];
  }
  KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE static void transpose4(__m256d r0, __m256d r1, __m256d r2, __m256d r3,
                                                                 Lanes* out) {
    const __m256d t0 = _mm256_unpacklo_pd(r0, r1), t1 = _mm256_unpackhi_pd(r0, r1);
    const __m256d t2 = _mm256_unpacklo_pd(r2, r3), t3 = _mm256_unpackhi_pd(r2, r3);
    out[0] = Lanes(_mm256_permute2f128_pd(t0, t2, 0x20));
    out[1] = Lanes(_mm256_permute2f128_pd(t1, t3, 0x20));
    out[2] = Lanes(_mm256_permute2f128_pd(t0, t2, 0x31));
    out[3] = Lanes(_mm256_permute2f128_pd(t1, t3, 0x31));
  }

  // Weights and bases of the four particles p[0..3] of a block whose lower node is o:
  // w[a][k] and fx[a] per axis, base[l] the tile index of particle l's base node.
  KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void stencil_lanes(const Lanes* xs, const std::array<Index, 3>& o,
                                                               Lanes w[2][3], Lanes fx[2], int base[4]) const {
    LaneInts b[2];
    for (int a = 0; a < 2; ++a) {
      const Lanes x = xs[a];
      const Lanes g = (x - model_.origin[a]) * inv_h_ + 1;
      b[a] = __builtin_convertvector(g - 0.5, LaneInts);  // truncation = floor (g >= 1)
      fx[a] = g - __builtin_convertvector(b[a], Lanes);
      const Lanes ca = 1.5 - fx[a], cb = fx[a] - 1.0, cc = fx[a] - 0.5;
      w[a][0] = 0.5 * ca * ca;
      w[a][1] = 0.75 - cb * cb;
      w[a][2] = 0.5 * cc * cc;
    }
    for (int l = 0; l < 4; ++l)
      base[l] = static_cast<int>((b[0][l] - o[0]) * T + (b[1][l] - o[1]));
  }

  // The rows p of a block's positions q .. q + 3 (the last repeated past `end`), whether they are
  // four consecutive rows, and how many are real.
  int lane_rows(Index q, Index end, Index* p, bool& together) const {
    for (int l = 0; l < 4; ++l) p[l] = order_[static_cast<size_t>(std::min<Index>(q + l, end - 1))];
    together = consecutive(p);
    return static_cast<int>(std::min<Index>(4, end - q));
  }

  // Kirchhoff stress (row-major) of four particles of one material kind, with the operations of
  // kernels.h's 2D corotated_tau, neohookean_tau and water_tau in their order (so bitwise the
  // same); false (nothing written) for a kind that stays per particle (sand).
  KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE bool tau_lanes(MaterialKind kind, Scalar gamma, const Lanes* F,
                                                          Lanes mu, Lanes lambda, Lanes bulk, Lanes* t) const {
    const Lanes J = F[0] * F[3] - F[2] * F[1];
    switch (kind) {
      case MaterialKind::Elastic:
      case MaterialKind::Snow: {
        const Lanes a = F[0] + F[3], b = F[2] - F[1], r2 = a * a + b * b;
        const Lanes r = Lanes(_mm256_sqrt_pd(__m256d(r2)));
        const Lanes one = Lanes{} + 1.0, zero = Lanes{};
        const Lanes c = r > 0 ? a / r : one, s = r > 0 ? b / r : zero;
        const Lanes mu2 = 2 * mu;
        const Lanes X[4] = {mu2 * (F[0] - c), mu2 * (F[1] + s), mu2 * (F[2] - s), mu2 * (F[3] - c)};
        for (int r0 = 0; r0 < 2; ++r0)
          for (int c0 = 0; c0 < 2; ++c0) t[r0 * 2 + c0] = X[r0 * 2] * F[c0 * 2] + X[r0 * 2 + 1] * F[c0 * 2 + 1];
        const Lanes diag = lambda * (J - 1) * J;
        t[0] += diag;
        t[3] += diag;
        return true;
      }
      case MaterialKind::NeoHookean: {
        const Lanes ls = lambda + mu;
        const Lanes X[4] = {mu * F[0], mu * F[1], mu * F[2], mu * F[3]};
        for (int r0 = 0; r0 < 2; ++r0)
          for (int c0 = 0; c0 < 2; ++c0) t[r0 * 2 + c0] = X[r0 * 2] * F[c0 * 2] + X[r0 * 2 + 1] * F[c0 * 2 + 1];
        const Lanes diag = ls * (J - 1) * J - mu * J;
        t[0] += diag;
        t[3] += diag;
        return true;
      }
      case MaterialKind::Water: {
        const Lanes Jc = J < 1e-6 ? Lanes{} + 1e-6 : J;
        const Lanes inv = 1 / Jc;
        Lanes J_gamma;
        if (gamma == 7) {
          J_gamma = (inv * inv * inv) * (inv * inv * inv) * inv;
        } else {
          for (int l = 0; l < 4; ++l) J_gamma[l] = std::pow(inv[l], gamma);
        }
        const Lanes p = bulk / gamma * (J_gamma - 1);
        const Lanes diag = -J * p;
        t[0] = t[3] = 1.0 * diag;
        t[1] = t[2] = 0.0 * diag;
        return true;
      }
      default:
        return false;
    }
  }

  KINEMA_TARGET_AVX2 void p2g_lanes_avx2(const State& state, Scalar dt, const Scalar* forces) {
    const Scalar h = model_.h, stress_scale = 4 * dt / (h * h);
#pragma omp for schedule(dynamic, 1)
    for (Index s = 0; s < particle_blocks_; ++s) {
      const auto o = block_origin(s);
      Scalar* tile = &tiles_[static_cast<size_t>(s * TN * S)];
      std::fill_n(tile, TN * S, 0.0);
      const Index end = block_start_[static_cast<size_t>(s + 1)];
      for (Index q = block_start_[static_cast<size_t>(s)]; q < end; q += 4) {
        prefetch_row(state, q, end);
        Index p[4];
        bool together;
        const int count = lane_rows(q, end, p, together);
        Lanes w[2][3], fx[2], x[2];
        int base[4];
        load_lanes<2>(state.x.data(), p, together, x);
        stencil_lanes(x, o, w, fx, base);
        Lanes m, vol, v[2], C[4], F[4], tau4[4], mu, lambda, bulk;
        load_lanes<1>(state.mass.data(), p, together, &m);
        load_lanes<1>(state.volume.data(), p, together, &vol);
        load_lanes<2>(state.v.data(), p, together, v);
        load_lanes<4>(state.C.data(), p, together, C);
        load_lanes<4>(state.F.data(), p, together, F);
        const Index code = state.material[static_cast<size_t>(p[0])];
        bool one_material = true;
        for (int l = 1; l < 4; ++l) one_material = one_material && state.material[static_cast<size_t>(p[l])] == code;
        const Material& mat = model_.materials[static_cast<size_t>(code)];
        bool done = false;
        if (one_material && mat.kind != MaterialKind::Sand) {
          for (int l = 0; l < 4; ++l) {
            particle_lame(state, mat, p[l], mu[l], lambda[l]);
            bulk[l] = state.youngs_modulus[static_cast<size_t>(p[l])];
            if (mat.kind == MaterialKind::Snow) {
              const Scalar harden = snow_hardening(mat, state.Jp[static_cast<size_t>(p[l])]);
              mu[l] = mu[l] * harden;
              lambda[l] = lambda[l] * harden;
            }
          }
          done = tau_lanes(mat.kind, mat.gamma, F, mu, lambda, bulk, tau4);
        }
        if (!done) {
          for (int l = 0; l < 4; ++l) {
            Mat<2> Fl;
            Fl << F[0][l], F[1][l], F[2][l], F[3][l];
            const Mat<2> t = tau(state, p[l], Fl);
            tau4[0][l] = t(0, 0);
            tau4[1][l] = t(0, 1);
            tau4[2][l] = t(1, 0);
            tau4[3][l] = t(1, 1);
          }
        }
        // A (row-major) = (m C - 4 dt V / h^2 tau) h; q0 = m v [+ dt f] - A fx.
        const Lanes sv = stress_scale * vol;
        Lanes A[4];
        for (int k = 0; k < 4; ++k) A[k] = (m * C[k] - sv * tau4[k]) * h;
        Lanes q0[2];
        for (int r = 0; r < 2; ++r) {
          Lanes mv = m * v[r];
          if (forces) {
            Lanes f;
            for (int l = 0; l < 4; ++l) f[l] = forces[state.user_of(p[l]) * 2 + r];
            mv = mv + dt * f;
          }
          q0[r] = mv - (A[r * 2] * fx[0] + A[r * 2 + 1] * fx[1]);
        }
        // The 9 nodes' contributions (mass, momentum) of the four particles.
        Lanes add[9][3];
        for (int i = 0; i < 3; ++i) {
          const Scalar di = i;
          const Lanes qi0 = q0[0] + A[0] * di, qi1 = q0[1] + A[2] * di;
          for (int j = 0; j < 3; ++j) {
            const Scalar dj = j;
            const Lanes wn = w[0][i] * w[1][j];
            Lanes* out = add[i * 3 + j];
            out[0] = wn * m;
            out[1] = wn * (qi0 + A[1] * dj);
            out[2] = wn * (qi1 + A[3] * dj);
          }
        }
        // Each particle's (momentum x, y) pairs by one shuffle per two particles, added as one
        // 2-wide value per node; the mass alone.
        __m128d pair[9][4];
        for (int k = 0; k < 9; ++k) {
          const __m256d lo = _mm256_unpacklo_pd(__m256d(add[k][1]), __m256d(add[k][2]));
          const __m256d hi = _mm256_unpackhi_pd(__m256d(add[k][1]), __m256d(add[k][2]));
          pair[k][0] = _mm256_castpd256_pd128(lo);
          pair[k][1] = _mm256_castpd256_pd128(hi);
          pair[k][2] = _mm256_extractf128_pd(lo, 1);
          pair[k][3] = _mm256_extractf128_pd(hi, 1);
        }
        for (int l = 0; l < count; ++l)
          for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) {
              Scalar* node = tile + (base[l] + i * T + j) * S;
              node[0] += add[i * 3 + j][0][l];
              _mm_storeu_pd(node + 1, _mm_add_pd(_mm_loadu_pd(node + 1), pair[i * 3 + j][l]));
            }
      }
    }
  }

  // kernels.h's 2D snow_project of four particles, with its operations in its order (bitwise
  // the same): a lane whose singular values do not clamp keeps its F and Jp.
  KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE static void snow_lanes(const Material& m, const Index* p, int count,
                                                                 Scalar* Jp, Lanes* F) {
    const Lanes e = 0.5 * (F[0] + F[3]), f = 0.5 * (F[2] - F[1]);
    const Lanes g = 0.5 * (F[0] - F[3]), k = 0.5 * (F[1] + F[2]);
    const Lanes r1 = Lanes(_mm256_sqrt_pd(__m256d(e * e + f * f))), r2 = Lanes(_mm256_sqrt_pd(__m256d(g * g + k * k)));
    const Lanes s1 = r1 + r2, s2 = r1 - r2;
    const Scalar lo = 1 - m.theta_c, hi = 1 + m.theta_s;
    const Lanes lov = Lanes{} + lo, hiv = Lanes{} + hi;
    // std::clamp(s, lo, hi): s < lo ? lo : (hi < s ? hi : s).
    const Lanes c1 = s1 < lo ? lov : (hi < s1 ? hiv : s1), c2 = s2 < lo ? lov : (hi < s2 ? hiv : s2);
    const auto keep = (c1 == s1) & (c2 == s2);
    bool all_kept = true;
    for (int l = 0; l < 4; ++l) all_kept = all_kept && keep[l];
    if (all_kept) return;
    const Lanes ratio = (s1 * s2) / (c1 * c2);
    for (int l = 0; l < count; ++l)
      if (!keep[l]) Jp[p[l]] *= ratio[l];
    const Lanes n1 = 0.5 * (c1 + c2), n2 = 0.5 * (c1 - c2);
    const Lanes zero = Lanes{};
    const Lanes a1 = r1 > 0 ? n1 / r1 : zero, a2 = r2 > 0 ? n2 / r2 : zero;
    const Lanes E = r1 > 0 ? a1 * e : n1, Fs = a1 * f, G = a2 * g, K = a2 * k;
    const Lanes out[4] = {E + G, K - Fs, Fs + K, E - G};
    for (int c = 0; c < 4; ++c) F[c] = keep ? F[c] : out[c];
  }

  KINEMA_TARGET_AVX2 void g2p_lanes_avx2(State& state, Scalar dt, Scalar& vmax2, Scalar& snow_exponent, bool& finite,
                                         Moves& moves) {
    const Scalar h = model_.h, four_h = 4 / h;
#pragma omp for schedule(dynamic, 1)
    for (Index s = 0; s < particle_blocks_; ++s) {
      const auto o = block_origin(s);
      const StayBox box = stay_box(o);
      alignas(64) Scalar tile[TN * S];
      gather<1>(tile, s, grid_);
      const Index end = block_start_[static_cast<size_t>(s + 1)];
      for (Index q = block_start_[static_cast<size_t>(s)]; q < end; q += 4) {
        prefetch_row(state, q, end);
        Index p[4];
        bool together;
        const int count = lane_rows(q, end, p, together);
        if (together && count == 4) save_row<4>(state, p[0], q);
        else
          for (int l = 0; l < count; ++l) save_row(state, p[l], q + l);
        Lanes w[2][3], fx[2], x[2];
        int base[4];
        load_lanes<2>(state.x.data(), p, together, x);
        stencil_lanes(x, o, w, fx, base);
        // v = sum w v_i, Bm = sum w v_i (node offset)^T (row-major), as gather_sums.
        Lanes v[2] = {Lanes{} + 0.0, Lanes{} + 0.0}, Bm[4] = {Lanes{} + 0.0, Lanes{} + 0.0, Lanes{} + 0.0, Lanes{} + 0.0};
        for (int i = 0; i < 3; ++i) {
          const Scalar di = i;
          for (int j = 0; j < 3; ++j) {
            const Scalar dj = j;
            const Lanes wn = w[0][i] * w[1][j];
            // (v_x, v_y) of particles 0 and 2 in one register, 1 and 3 in another; one shuffle
            // each gives the four v_x and the four v_y.
            const int t = i * T + j;
            const __m256d even = _mm256_insertf128_pd(
                _mm256_castpd128_pd256(_mm_loadu_pd(tile + (base[0] + t) * S + 1)),
                _mm_loadu_pd(tile + (base[2] + t) * S + 1), 1);
            const __m256d odd = _mm256_insertf128_pd(
                _mm256_castpd128_pd256(_mm_loadu_pd(tile + (base[1] + t) * S + 1)),
                _mm_loadu_pd(tile + (base[3] + t) * S + 1), 1);
            const Lanes n1 = Lanes(_mm256_unpacklo_pd(even, odd)), n2 = Lanes(_mm256_unpackhi_pd(even, odd));
            const Lanes wv0 = wn * n1, wv1 = wn * n2;
            v[0] += wv0;
            v[1] += wv1;
            Bm[0] += wv0 * di;
            Bm[2] += wv1 * di;
            Bm[1] += wv0 * dj;
            Bm[3] += wv1 * dj;
          }
        }
        Lanes C[4], F[4], Fn[4];
        for (int r = 0; r < 2; ++r)
          for (int c = 0; c < 2; ++c) C[r * 2 + c] = four_h * (Bm[r * 2 + c] - v[r] * fx[c]);
        load_lanes<4>(state.F.data(), p, together, F);
        // (I + dt C) F
        const Lanes M[4] = {1.0 + dt * C[0], 0.0 + dt * C[1], 0.0 + dt * C[2], 1.0 + dt * C[3]};
        for (int r = 0; r < 2; ++r)
          for (int c = 0; c < 2; ++c) Fn[r * 2 + c] = M[r * 2] * F[c] + M[r * 2 + 1] * F[2 + c];
        for (int a = 0; a < 2; ++a) {
          x[a] = x[a] + dt * v[a];
          x[a] = x[a] < model_.origin[a] ? Lanes{} + model_.origin[a] : x[a];  // std::clamp
          x[a] = model_.upper(a) < x[a] ? Lanes{} + model_.upper(a) : x[a];
        }
        // Lanes whose particle stays in block s where the next sort looks (track, four wide).
        const auto stays = (x[0] > box.lo[0]) & (x[0] < box.hi[0]) & (x[1] > box.lo[1]) & (x[1] < box.hi[1]);
        const Lanes speed2 = v[0] * v[0] + v[1] * v[1];
        // Plasticity four wide where the lanes hold one material without a return mapping
        // (elastic, neo-Hookean) or water (F = sqrt(J) I, as plasticity()); else per particle.
        const Index code = state.material[static_cast<size_t>(p[0])];
        bool one_material = true;
        for (int l = 1; l < 4; ++l) one_material = one_material && state.material[static_cast<size_t>(p[l])] == code;
        const MaterialKind kind = model_.materials[static_cast<size_t>(code)].kind;
        const bool lanes_plastic = one_material && (kind == MaterialKind::Elastic || kind == MaterialKind::NeoHookean ||
                                                    kind == MaterialKind::Water || kind == MaterialKind::Snow);
        if (lanes_plastic && kind == MaterialKind::Snow) {
          const Material& snow = model_.materials[static_cast<size_t>(code)];
          snow_lanes(snow, p, count, state.Jp.data(), Fn);
          for (int l = 0; l < count; ++l)  // as plasticity() returns it
            snow_exponent = std::max(snow_exponent, snow.hardening * (1 - state.Jp[static_cast<size_t>(p[l])]));
        }
        if (lanes_plastic && kind == MaterialKind::Water) {
          const Lanes J = Fn[0] * Fn[3] - Fn[2] * Fn[1];
          const Lanes Jc = J < 1e-6 ? Lanes{} + 1e-6 : J;
          const Lanes r = Lanes(_mm256_sqrt_pd(__m256d(Jc)));
          Fn[0] = Fn[3] = 1.0 * r;
          Fn[1] = Fn[2] = 0.0 * r;
        }
        if (!lanes_plastic) {
          for (int l = 0; l < count; ++l) {
            Mat<2> Fl;
            Fl << Fn[0][l], Fn[1][l], Fn[2][l], Fn[3][l];
            snow_exponent = std::max(snow_exponent, plasticity(state, p[l], Fl, dt));
            for (int k = 0; k < 4; ++k) Fn[k][l] = Fl(k / 2, k % 2);
          }
        }
        store_lanes<4>(state.C.data(), p, count, together, C);
        store_lanes<4>(state.F.data(), p, count, together, Fn);
        store_lanes<2>(state.x.data(), p, count, together, x);
        store_lanes<2>(state.v.data(), p, count, together, v);
        const int left = ~_mm256_movemask_pd(__m256d(stays)) & ((1 << count) - 1);
        if (left)
          for (int l = 0; l < count; ++l)
            if ((left >> l) & 1) track(s, o, q + l, p[l], state, moves);
        // 0 in every lane whose v and F are finite (NaN otherwise).
        const Lanes bad = (v[0] - v[0]) + (v[1] - v[1]) + (Fn[0] - Fn[0]) + (Fn[1] - Fn[1]) + (Fn[2] - Fn[2]) +
                          (Fn[3] - Fn[3]);
        for (int l = 0; l < count; ++l) {
          finite = finite && bad[l] == 0;
          vmax2 = std::max(vmax2, speed2[l]);
        }
      }
    }
  }
#endif

  Model model_;
  Config config_;
  Scalar inv_h_ = 1 / model_.h;
  bool avx2_ = use_avx2();                   // 2D transfers four particles wide (p2g_lanes_avx2)
  std::vector<Scalar> spare_;                // scratch of permute_rows
  const std::array<TileNode, TN> tile_nodes_ = make_tile_nodes();
  const std::array<std::vector<Overlap>, NEIGHBORS> overlaps_ = make_overlaps();
  std::array<Index, 3> blocks_{};
  Index block_count_ = 0;
  std::vector<std::int32_t> table_;          // dense block key -> slot (or -1)
  std::vector<std::int32_t> seen_;           // dense block key -> last epoch_ it held a particle
  std::int32_t epoch_ = 0;                   // sorts so far (wrapping), the mark of this one
  std::vector<Index> slot_key_;              // slot -> block key; particle blocks first
  Index particle_blocks_ = 0;
  std::vector<std::int32_t> neighbor_slot_;  // (particle block, 2^d) -> slot of the +{0,1}^d block
  std::vector<Index> particle_key_;          // (n,) block key of each particle
  std::vector<Index> block_start_;           // CSR of order_ by particle block
  std::vector<Index> fill_;                  // (sort chunks, particle blocks): counts, then write positions
  std::vector<Index> order_;                 // particle rows sorted by block
  std::vector<std::int32_t> source_slot_;   // (slot, 2^d) -> particle block at c - o (or -1)
  std::vector<Scalar> tiles_;                // (particle blocks, (B + 2)^d, d + 1): P2G's tiles
  Index particle_count_ = 0;                 // n of the last sort
  bool adapting_ = false;                    // choose_team measures this step
  Index cycle_step_ = 0;                     // steps measured by choose_team
  double probe_best_[2] = {0, 0};            // best probe seconds this cycle: one thread, full team
  std::vector<Scalar> grid_;                 // (slots, B^d, d + 1): mass, momentum -> velocity
  std::vector<Scalar> backup_;               // (n, kRow): what G2P overwrote, for a failed step
  std::vector<std::pair<std::uint64_t, Index>> found_;  // (Morton code, key) of the particle blocks
  Index bad_ = -1;                           // lowest row of a particle outside the domain, or -1
  Index sort_chunks_ = 1;                    // row chunks of the counting sort
  std::vector<Scalar> pre_;                  // (slots, B^d, d): velocity before the boundary conditions
  // The binning kept from step to step (rebin).
  struct NextBlock {
    std::uint64_t code;
    Index key, old, first_move, end_move;
  };
  std::vector<std::uint64_t> slot_code_;     // particle slot -> Morton code of its block
  bool kept_ = false;                        // this step kept the last step's binning
  Index rebinned_ = 0;                       // particles binned anew this step
  std::vector<Moves> moves_by_thread_;       // per thread: G2P's particles that left their block
  std::vector<Move> moves_;                  // all of them, by (block code, user row)
  std::vector<Index> remaining_;             // old particle slot -> rows that stay
  std::vector<Index> leaving_;               // positions in order_ of the particles that move, sorted
  std::vector<NextBlock> next_;              // the new particle blocks
  std::vector<Index> order_next_, start_next_;  // the new order_ and block_start_
  std::uint64_t mark_ = 0;                   // State::binning this solver's last step left (0: none)
  const State* marked_ = nullptr;            // the State it left it on
  bool binning_kept_ = false;                // the next step may keep that step's binning
  // What the last step measured of the State it left (measured_speed): the largest squared
  // particle speed and snow hardening exponent after G2P (snow_exponent_: this step's, merged
  // from the threads), and the materials' largest squared wave speeds (wave_speeds_known_).
  Scalar measured_v2_ = 0, measured_snow_exponent_ = 0, snow_exponent_ = 0;
  Scalar c2_elastic_ = 0, c2_snow_ = 0;
  bool wave_speeds_known_ = false;
  Index marks_ = 0;                          // marks left so far
  const std::uint64_t id_ = mix64(reinterpret_cast<std::uintptr_t>(this) ^
                                  static_cast<std::uint64_t>(std::chrono::steady_clock::now().time_since_epoch().count()));
  std::vector<Scalar> adjoint_grid_;         // (slots, B^d, d + 1): dL/d(mass, momentum)
};

template <int D>
void SolverD<D>::step_adjoint(const State& before, const State& after, Scalar dt, const Scalar* forces,
                              State& adjoint, ParamsAdjoint& adjoint_params, Scalar* adjoint_forces,
                              Interrupt& interrupt) {
  check_dt(dt);
  const Index n = before.n;
  for (Index p = 0; p < n; ++p) {
    const Index code = before.material[static_cast<size_t>(p)];
    if (code >= 0 && code < static_cast<Index>(model_.materials.size()) &&
        !differentiable_material(model_.materials[static_cast<size_t>(code)].kind))
      throw InvalidArgument(std::string("material: gradients need elastic, neohookean or water particles, particle ") +
                            std::to_string(p) + " is " +
                            material_name(model_.materials[static_cast<size_t>(code)].kind));
  }
  // 1. The step's grid, rebuilt from `before` as step() built it: masses, momenta, and the
  //    velocities before (pre_) and after (grid_) the boundary conditions. (This replaces the
  //    binning the last step kept.)
  mark_ = 0;
  prepare_sort(before, false);
#pragma omp parallel if (n > kParallelParticles)
  if (sort_phase(before)) {
#pragma omp single
    pre_.resize(slot_key_.size() * BN * D);
    p2g_phase(before, dt, forces);
    grid_phase(dt, pre_.data());
  }
  if (bad_ >= 0) throw_bad_particle(before);
  interrupt.check();
  adjoint_grid_.resize(grid_.size());
  const Scalar h = model_.h, apic = 4 / h, stress_scale = 4 * dt / (h * h);
  const bool parallel = n > kParallelParticles;
  adjoint_params.youngs_modulus.assign(static_cast<size_t>(n), 0.0);
  adjoint_params.poisson_ratio.assign(static_cast<size_t>(n), 0.0);

  // 2. G2P transposed: v' = sum w u_i, C' = 4/h sum w u_i d_i^T, F' = (I + dt C') F,
  //    x' = clamp(x + dt v'). Scatters dL/du_i into each particle block's tile, as P2G.
  {
#pragma omp parallel for schedule(dynamic, 1) if (parallel)
    for (Index s = 0; s < particle_blocks_; ++s) {
      const auto o = block_origin(s);
      alignas(64) Scalar velocity[TN * S];
      Scalar* tile = &tiles_[static_cast<size_t>(s * TN * S)];
      gather<1>(velocity, s, grid_);
      std::fill_n(tile, TN * S, 0.0);
      for (Index q = block_start_[s]; q < block_start_[s + 1]; ++q) {
        const Index p = order_[static_cast<size_t>(q)];
        const size_t pd = static_cast<size_t>(p * D);
        const Stencil st = stencil(&before.x[pd], o);
        const Mat<D> C_after = ConstRowMap(&after.C[pd * D]);
        const Mat<D> F = ConstRowMap(&before.F[pd * D]);
        Mat<D> F_bar = RowMap(&adjoint.F[pd * D]);
        // Water's F' is the projection of the trial (I + dt C') F.
        if (model_.materials[static_cast<size_t>(before.material[static_cast<size_t>(p)])].kind == MaterialKind::Water)
          F_bar = water_projection_vjp<D>(Mat<D>((Mat<D>::Identity() + dt * C_after) * F), F_bar);
        Vec<D> x_bar;
        for (int a = 0; a < D; ++a) {
          const Scalar y = before.x[pd + a] + dt * after.v[pd + a];
          const bool clamped = y < model_.origin[a] || model_.upper(a) < y;
          x_bar(a) = clamped ? 0 : adjoint.x[pd + a];
        }
        const Mat<D> C_bar = Mat<D>(RowMap(&adjoint.C[pd * D])) + dt * F_bar * F.transpose();
        const Vec<D> v_bar = Eigen::Map<const Vec<D>>(&adjoint.v[pd]) + dt * x_bar;
        Vec<D> fx_bar = Vec<D>::Zero();
        const Mat<D> C_bar_t = apic * C_bar.transpose();
        each_node(st, [&](int t, Scalar w, const Vec<D>& grad_w, const Vec<D>& offset) {
          const Eigen::Map<const Vec<D>> u(velocity + t * S + 1);
          const Vec<D> g = v_bar + apic * (C_bar * offset);
          Eigen::Map<Vec<D>>(tile + t * S + 1) += w * g;
          fx_bar += u.dot(g) * grad_w;
        });
        fx_bar -= C_bar_t * Eigen::Map<const Vec<D>>(&after.v[pd]);  // sum over nodes of w C_bar^T u_i: v' = sum w u_i
        // x and F of `before` also reach the step through P2G, which adds to these; v and C
        // only through P2G, which sets theirs.
        Eigen::Map<Vec<D>>(&adjoint.x[pd]) = x_bar + fx_bar / h;
        RowMap(&adjoint.F[pd * D]) = (Mat<D>::Identity() + dt * C_after).transpose() * F_bar;
      }
    }
  }
  interrupt.check();

  // 3. Grid update transposed, node by node (on dL/du_i summed from the tiles):
  //    u = P / M + dt g, then the boundary conditions.
  Vec<D> g;
  for (int a = 0; a < D; ++a) g(a) = config_.gravity[a];
#pragma omp parallel if (parallel)
  reduce_tiles(tiles_, [&](Index s, const Scalar* sum) {
    const auto o = block_origin(s);
    for (int l = 0; l < BN; ++l) {
      const size_t at = static_cast<size_t>((s * BN + l) * S);
      const Scalar M = grid_[at];
      Scalar* node = &adjoint_grid_[at];
      if (M <= 0) {
        std::fill_n(node, S, 0.0);
        continue;
      }
      Index i[3] = {0, 0, 0};
      node_index(o, l, i);
      const Vec<D> u = Eigen::Map<const Vec<D>>(&pre_[static_cast<size_t>((s * BN + l) * D)]);
      const Vec<D> u_bar = boundary_vjp(u, i, Eigen::Map<const Vec<D>>(sum + l * S + 1));
      node[0] = -u_bar.dot(u - dt * g) / M;
      Eigen::Map<Vec<D>>(node + 1) = u_bar / M;
    }
  });
  interrupt.check();

  // 4. P2G transposed, a gather per particle: M_i = sum w m, P_i = sum w (m v + dt f + A d_i),
  //    A = (m C - 4 dt V / h^2 tau(F)) h.
#pragma omp parallel for schedule(dynamic, 1) if (parallel)
  for (Index s = 0; s < particle_blocks_; ++s) {
    const auto o = block_origin(s);
    alignas(64) Scalar tile[TN * S];
    gather<0>(tile, s, adjoint_grid_);
    for (Index q = block_start_[s]; q < block_start_[s + 1]; ++q) {
      const Index p = order_[static_cast<size_t>(q)];
      const size_t pd = static_cast<size_t>(p * D);
      const Stencil st = stencil(&before.x[pd], o);
      const Scalar m = before.mass[static_cast<size_t>(p)], V = before.volume[static_cast<size_t>(p)];
      const Mat<D> F = ConstRowMap(&before.F[pd * D]);
      const Mat<D> C = ConstRowMap(&before.C[pd * D]);
      Vec<D> momentum = m * Eigen::Map<const Vec<D>>(&before.v[pd]);
      if (forces) momentum += dt * Eigen::Map<const Vec<D>>(forces + pd);
      const Material& mat = model_.materials[static_cast<size_t>(before.material[static_cast<size_t>(p)])];
      const bool corotated = mat.kind == MaterialKind::Elastic, water = mat.kind == MaterialKind::Water;
      Scalar mu, lambda;
      particle_lame(before, mat, p, mu, lambda);
      const Scalar E = before.youngs_modulus[static_cast<size_t>(p)];
      // tau as step() computes it (kernels.h), with one SVD for the stress and its adjoint.
      Svd<D> sv;
      if (corotated) sv = svd(F);
      const Mat<D> stress = corotated ? corotated_tau<D>(F, sv, mu, lambda)
                            : water   ? water_tau<D>(F.determinant(), E, mat.gamma)
                                      : neohookean_tau<D>(F, mu, lambda);
      const Mat<D> A = (m * C - (stress_scale * V) * stress) * h;
      Vec<D> P_bar_sum = Vec<D>::Zero(), fx_bar = Vec<D>::Zero();
      Mat<D> A_bar = Mat<D>::Zero();
      each_node(st, [&](int t, Scalar w, const Vec<D>& grad_w, const Vec<D>& offset) {
        const Scalar M_bar = tile[t * S];
        const Eigen::Map<const Vec<D>> P_bar(tile + t * S + 1);
        P_bar_sum += w * P_bar;
        A_bar += (w * P_bar) * offset.transpose();
        fx_bar += (P_bar.dot(momentum + A * offset) + M_bar * m) * grad_w;
      });
      fx_bar -= A.transpose() * P_bar_sum;  // sum over nodes of w A^T P_bar_i
      Eigen::Map<Vec<D>>(&adjoint.v[pd]) = m * P_bar_sum;
      if (adjoint_forces) Eigen::Map<Vec<D>>(adjoint_forces + pd) = dt * P_bar_sum;
      RowMap(&adjoint.C[pd * D]) = (m * h) * A_bar;
      Eigen::Map<Vec<D>>(&adjoint.x[pd]) += fx_bar / h;
      // tau's adjoint, then the moduli's.
      const Mat<D> tau_bar = -(stress_scale * V * h) * A_bar;
      Scalar mu_bar, lambda_bar;
      Mat<D> F_bar = RowMap(&adjoint.F[pd * D]);
      if (water) {
        adjoint_params.youngs_modulus[static_cast<size_t>(p)] = water_tau_vjp<D>(F, E, mat.gamma, tau_bar, F_bar);
        RowMap(&adjoint.F[pd * D]) = F_bar;
        continue;
      }
      if (corotated)
        corotated_tau_vjp<D>(F, sv, mu, lambda, tau_bar, F_bar, mu_bar, lambda_bar);
      else
        neohookean_tau_vjp<D>(F, mu, lambda, tau_bar, F_bar, mu_bar, lambda_bar);
      RowMap(&adjoint.F[pd * D]) = F_bar;
      lame_parameters_vjp(before.youngs_modulus[static_cast<size_t>(p)], before.poisson_ratio[static_cast<size_t>(p)],
                          mu_bar, lambda_bar, adjoint_params.youngs_modulus[static_cast<size_t>(p)],
                          adjoint_params.poisson_ratio[static_cast<size_t>(p)]);
    }
  }
}

}  // namespace

Solver::Solver(const Model& model, const Config& config) : model_(model), config_(config) {
  if (!(std::isfinite(config.max_cells_per_step) && config.max_cells_per_step > 0))
    throw InvalidArgument("max_cells_per_step: expected a number > 0");
  if (!(std::isfinite(config.max_dt) && config.max_dt > 0)) throw InvalidArgument("max_dt: expected a number > 0");
  for (int a = 0; a < 3; ++a)
    if (!std::isfinite(config.gravity[a])) throw InvalidArgument("gravity: expected finite components");
  if (model.dim == 2)
    impl_ = std::make_unique<SolverD<2>>(model_, config_);
  else
    impl_ = std::make_unique<SolverD<3>>(model_, config_);
}

Solver::~Solver() = default;

bool differentiable_material(MaterialKind kind) {
  return kind == MaterialKind::Elastic || kind == MaterialKind::NeoHookean || kind == MaterialKind::Water;
}

StepStats Solver::step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* forces) {
  if (state.dim != model_.dim) throw InvalidArgument("state: dimension differs from the model's");
  return impl_->step(state, dt, interrupt, forces);
}

void Solver::sort_rows(State& state) {
  if (state.dim != model_.dim) throw InvalidArgument("state: dimension differs from the model's");
  impl_->sort_rows(state);
}

void Solver::user_order(State& state) {
  if (state.user_ordered()) return;
  permute_rows(state, [&](Index u) { return state.row[static_cast<size_t>(u)]; }, spare_);
  state.user.clear();
  state.row.clear();
  state.binning = 0;
}

void Solver::step_adjoint(const State& before, const State& after, Scalar dt, const Scalar* forces, State& adjoint,
                          ParamsAdjoint& adjoint_params, Scalar* adjoint_forces, Interrupt& interrupt) {
  if (before.dim != model_.dim || after.dim != model_.dim || adjoint.dim != model_.dim)
    throw InvalidArgument("state: dimension differs from the model's");
  if (!before.user_ordered() || !after.user_ordered() || !adjoint.user_ordered())
    throw InvalidArgument("state: step_adjoint needs its States' rows in user order (Solver::user_order)");
  const size_t n = static_cast<size_t>(before.n), d = static_cast<size_t>(model_.dim);
  if (after.n != before.n || adjoint.x.size() != n * d || adjoint.v.size() != n * d ||
      adjoint.F.size() != n * d * d || adjoint.C.size() != n * d * d)
    throw InvalidArgument("adjoint: expected x, v (n, d) and F, C (n, d, d) for the n = " + std::to_string(n) +
                          " particles of `before` and `after`");
  impl_->step_adjoint(before, after, dt, forces, adjoint, adjoint_params, adjoint_forces, interrupt);
}

Scalar Solver::signal_speed(const State& state) const {
  Scalar measured = 0;
  if (impl_->measured_speed(state, measured)) return measured;  // the State the last step left
  const int d = state.dim;
  // Wave speeds from each particle's own moduli, with the expressions of make_material. The
  // squares are maximised and the root taken once: sqrt is monotone and correctly rounded, so
  // sqrt(max a) is max sqrt(a) bit for bit (a NaN or negative square is passed over either way).
  Scalar v2max = 0, harden = 1, c2_elastic = 0, c2_snow = 0;
  // One thread up to 65,536 particles (about 4 ns each): a team costs more to start than it saves.
#pragma omp parallel for schedule(static) reduction(max : v2max, harden, c2_elastic, c2_snow) if (state.n > 65536)
  for (Index p = 0; p < state.n; ++p) {
    Scalar v2 = 0;
    for (int a = 0; a < d; ++a) v2 += state.v[static_cast<size_t>(p * d + a)] * state.v[static_cast<size_t>(p * d + a)];
    v2max = std::max(v2max, v2);
    const auto kind = state.material[static_cast<size_t>(p)];
    // A material index written out of range through the view is the step's to name, not read here.
    if (kind < 0 || static_cast<size_t>(kind) >= model_.materials.size()) continue;
    const Material& m = model_.materials[static_cast<size_t>(kind)];
    const Scalar E = state.youngs_modulus[static_cast<size_t>(p)];
    Scalar mu, lambda;
    lame_parameters(E, state.poisson_ratio[static_cast<size_t>(p)], mu, lambda);
    const Scalar c2 = m.kind == MaterialKind::Water ? E / m.density : (lambda + 2 * mu) / m.density;
    if (m.kind == MaterialKind::Snow) {
      harden = std::max(harden, snow_hardening(m, state.Jp[static_cast<size_t>(p)]));
      c2_snow = std::max(c2_snow, c2);
    } else {
      c2_elastic = std::max(c2_elastic, c2);
    }
  }
  impl_->remember_wave_speeds(state, c2_elastic, c2_snow);
  const Scalar c = std::max(std::sqrt(c2_elastic), std::sqrt(c2_snow) * std::sqrt(harden));
  return std::sqrt(v2max) + c;
}

bool Solver::speed_measured(const State& state) const {
  Scalar speed = 0;
  return impl_->measured_speed(state, speed);
}

Scalar Solver::cfl_dt(const State& state) const {
  const Scalar speed = signal_speed(state);
  return speed > 0 ? model_.h / speed : std::numeric_limits<Scalar>::infinity();
}

Scalar Solver::stable_dt(const State& state, Scalar cfl) const {
  if (!(std::isfinite(cfl) && cfl > 0)) throw InvalidArgument("cfl: expected a number > 0, got " + format_real(cfl));
  const int d = state.dim;
  const Scalar speed = signal_speed(state);
  Scalar dt = config_.max_dt;
  if (speed > 0) dt = std::min(dt, cfl * model_.h / speed);
  Scalar g = 0;
  for (int a = 0; a < d; ++a) g += config_.gravity[a] * config_.gravity[a];
  if (g > 0) dt = std::min(dt, std::sqrt(cfl * model_.h / std::sqrt(g)));
  return dt;
}

Scalar Solver::kinetic_energy(const State& state) const {
  const int d = state.dim;
  // Summed in user-row order, whatever the stored order (the same bits either way).
  return parallel_sum(state.n, [&](Index u) {
    const Index p = state.row_of(u);
    Scalar v2 = 0;
    for (int a = 0; a < d; ++a) v2 += state.v[static_cast<size_t>(p * d + a)] * state.v[static_cast<size_t>(p * d + a)];
    return 0.5 * state.mass[static_cast<size_t>(p)] * v2;
  });
}

std::vector<Scalar> Solver::momentum(const State& state) const {
  const int d = state.dim;
  std::vector<Scalar> out(static_cast<size_t>(d));
  for (int a = 0; a < d; ++a)
    out[a] = parallel_sum(state.n, [&](Index u) {
      const Index p = state.row_of(u);
      return state.mass[static_cast<size_t>(p)] * state.v[static_cast<size_t>(p * d + a)];
    });
  return out;
}

std::vector<Scalar> Solver::angular_momentum(const State& state) const {
  const int d = state.dim;
  const Scalar inertia = model_.h * model_.h / 4;  // sum w (x_i - x_p)(x_i - x_p)^T = h^2/4 I
  // Component c of x x v + (h^2/4) eps_abc C_ba, for (a, b, c) cyclic.
  auto component = [&](int a, int b) {
    return parallel_sum(state.n, [&](Index u) {
      const Index p = state.row_of(u);
      const size_t pd = static_cast<size_t>(p * d);
      const Scalar* x = &state.x[pd];
      const Scalar* v = &state.v[pd];
      const Scalar* C = &state.C[pd * d];
      return state.mass[static_cast<size_t>(p)] *
             (x[a] * v[b] - x[b] * v[a] + inertia * (C[b * d + a] - C[a * d + b]));
    });
  };
  if (d == 2) return {component(0, 1)};
  return {component(1, 2), component(2, 0), component(0, 1)};
}

}  // namespace kinema::mpm
