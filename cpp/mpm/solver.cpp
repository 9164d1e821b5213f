// MLS-MPM step on a sparse block grid; see solver.h for the algorithm and kernels.h for the
// per-particle math.
#include "mpm/solver.h"

#include <omp.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"
#include "mpm/kernels.h"

namespace kinema::mpm {

class Solver::Impl {
 public:
  virtual ~Impl() = default;
  virtual StepStats step(State& state, Scalar dt, Interrupt& interrupt) = 0;
};

namespace {

constexpr int ipow(int b, int e) { return e == 0 ? 1 : b * ipow(b, e - 1); }

// Fewer particles than this run the transfers on one thread: waking the team for P2G's 2^d
// colour phases costs more than the work (a step is ~0.2 us per particle and thread).
constexpr Index kParallelParticles = 8192;

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
  }

  StepStats step(State& state, Scalar dt, Interrupt& interrupt) override {
    if (!(std::isfinite(dt) && dt > 0))
      throw InvalidArgument("dt: expected a finite time step > 0 [s], got " + format_real(dt));
    Stopwatch total, watch;
    StepStats stats;
    stats.dt = dt;
    // 1. Bin the particles into blocks, activate the blocks their stencils reach.
    sort(state);
    stats.particle_blocks = particle_blocks_;
    stats.active_blocks = static_cast<Index>(slot_key_.size());
    stats.sort_seconds = watch.seconds();
    interrupt.check();
    // 2. P2G (Hu et al. 2018, eq. 16-17).
    watch.restart();
    p2g(state, dt);
    stats.p2g_seconds = watch.seconds();
    // 3. Grid velocities, gravity, walls and colliders.
    watch.restart();
    grid_update(dt);
    stats.grid_seconds = watch.seconds();
    // 4. G2P, advection, deformation update and plasticity.
    watch.restart();
    stats.max_speed = g2p(state, dt);
    stats.g2p_seconds = watch.seconds();
    state.time += dt;
    ++state.steps;
    stats.seconds = total.seconds();
    return stats;
  }

 private:
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

  void sort(const State& state) {
    const Index n = state.n;
    for (Index key : slot_key_) table_[static_cast<size_t>(key)] = -1;
    slot_key_.clear();
    particle_key_.resize(static_cast<size_t>(n));
    // Keys of the block holding each particle's first stencil node; positions are checked
    // here because a user may write anything into the x view.
    Index bad = -1;
#pragma omp parallel for schedule(static) if (n > kParallelParticles)
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
      if (!inside) {
#pragma omp critical(mpm_bad_particle)
        bad = bad < 0 ? p : std::min(bad, p);
        continue;
      }
      particle_key_[static_cast<size_t>(p)] = key_of(b);
    }
    if (bad >= 0) {
      std::string where = "(";
      for (int a = 0; a < D; ++a) where += (a ? ", " : "") + format_real(state.x[static_cast<size_t>(bad * D + a)]);
      throw InvalidArgument("x: particle " + std::to_string(bad) + " at " + where +
                            ") is outside the domain or not finite (or its material code is not one of the " +
                            std::to_string(model_.materials.size()) + " materials)");
    }
    // The distinct particle blocks, in Morton order, take the first slots.
    std::vector<std::pair<std::uint64_t, Index>> found;
    for (Index p = 0; p < n; ++p) {
      const Index key = particle_key_[static_cast<size_t>(p)];
      if (table_[static_cast<size_t>(key)] < 0) {
        table_[static_cast<size_t>(key)] = 0;
        found.emplace_back(morton(coords_of(key)), key);
      }
    }
    std::sort(found.begin(), found.end());
    particle_blocks_ = static_cast<Index>(found.size());
    for (const auto& f : found) {
      table_[static_cast<size_t>(f.second)] = static_cast<std::int32_t>(slot_key_.size());
      slot_key_.push_back(f.second);
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
    // Counting sort of the particles by block slot (stable: by row within a block).
    block_start_.assign(static_cast<size_t>(particle_blocks_ + 1), 0);
    for (Index p = 0; p < n; ++p) ++block_start_[static_cast<size_t>(table_[particle_key_[p]] + 1)];
    for (Index s = 0; s < particle_blocks_; ++s) block_start_[s + 1] += block_start_[s];
    order_.resize(static_cast<size_t>(n));
    fill_.assign(block_start_.begin(), block_start_.end() - 1);
    for (Index p = 0; p < n; ++p) order_[static_cast<size_t>(fill_[table_[particle_key_[p]]]++)] = p;
    // Colour phases: blocks whose coordinates have the same parities.
    colour_start_.assign(NEIGHBORS + 1, 0);
    colour_blocks_.resize(static_cast<size_t>(particle_blocks_));
    for (Index s = 0; s < particle_blocks_; ++s) ++colour_start_[colour_of(s) + 1];
    for (int c = 0; c < NEIGHBORS; ++c) colour_start_[c + 1] += colour_start_[c];
    std::vector<Index> next(colour_start_.begin(), colour_start_.end() - 1);
    for (Index s = 0; s < particle_blocks_; ++s) colour_blocks_[static_cast<size_t>(next[colour_of(s)]++)] = s;
    grid_.resize(static_cast<size_t>(slots * BN * S));
    parallel_for(slots, [&](Index s) { std::fill_n(&grid_[static_cast<size_t>(s * BN * S)], BN * S, 0.0); });
  }

  std::array<Index, 3> coords_of(Index key) const {
    return {key / (blocks_[1] * blocks_[2]), (key / blocks_[2]) % blocks_[1], key % blocks_[2]};
  }

  int colour_of(Index slot) const {
    const auto c = coords_of(slot_key_[static_cast<size_t>(slot)]);
    int colour = 0;
    for (int a = 0; a < D; ++a) colour |= static_cast<int>(c[a] & 1) << a;
    return colour;
  }

  // Lower node (ghost-shifted) of a block.
  std::array<Index, 3> block_origin(Index slot) const {
    auto c = coords_of(slot_key_[static_cast<size_t>(slot)]);
    for (int a = 0; a < D; ++a) c[a] *= B;
    return c;
  }

  // The tile node t's (slot-relative) address in the grid: which of the 2^d blocks, and where.
  static void tile_to_block(int t, int& neighbor, int& local) {
    int tc[3] = {0, 0, 0};
    for (int a = D - 1; a >= 0; --a) {
      tc[a] = t % T;
      t /= T;
    }
    neighbor = 0;
    local = 0;
    for (int a = 0; a < D; ++a) {
      const int over = tc[a] >= B;
      neighbor |= over << a;
      local = local * B + (tc[a] - over * B);
    }
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

  // Kirchhoff stress of particle p (kernels.h).
  Mat<D> tau(const State& state, Index p, const Mat<D>& F) const {
    const Material& m = model_.materials[static_cast<size_t>(state.material[static_cast<size_t>(p)])];
    switch (m.kind) {
      case MaterialKind::Elastic:
        return corotated_tau<D>(F, svd(F), m.mu, m.lambda);
      case MaterialKind::NeoHookean:
        return neohookean_tau<D>(F, m.mu, m.lambda);
      case MaterialKind::Snow: {
        const Scalar harden = std::exp(m.hardening * (1 - state.Jp[static_cast<size_t>(p)]));
        return corotated_tau<D>(F, svd(F), m.mu * harden, m.lambda * harden);
      }
      case MaterialKind::Sand:
        return hencky_tau<D>(svd(F), m.mu, m.lambda);
      case MaterialKind::Water:
        return water_tau<D>(F.determinant(), m.youngs_modulus, m.gamma);
    }
    return Mat<D>::Zero();
  }

  void p2g(const State& state, Scalar dt) {
    const Scalar h = model_.h, stress_scale = 4 * dt / (h * h);
    const bool parallel = state.n > kParallelParticles;
    for (int colour = 0; colour < NEIGHBORS; ++colour) {
      const Index begin = colour_start_[colour], end = colour_start_[colour + 1];
#pragma omp parallel for schedule(dynamic, 1) if (parallel)
      for (Index k = begin; k < end; ++k) {
        const Index s = colour_blocks_[static_cast<size_t>(k)];
        const auto o = block_origin(s);
        alignas(64) Scalar tile[TN * S];
        std::fill_n(tile, TN * S, 0.0);
        for (Index q = block_start_[s]; q < block_start_[s + 1]; ++q) {
          const Index p = order_[static_cast<size_t>(q)];
          const size_t pd = static_cast<size_t>(p * D);
          const Stencil st = stencil(&state.x[pd], o);
          const Scalar m = state.mass[static_cast<size_t>(p)];
          const Eigen::Map<const Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>> F(&state.F[pd * D]);
          const Eigen::Map<const Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>> C(&state.C[pd * D]);
          const Eigen::Map<const Vec<D>> v(&state.v[pd]);
          // Affine momentum per unit offset, in cells: (m C - 4 dt V / h^2 tau) h.
          const Mat<D> A = (m * C - (stress_scale * state.volume[static_cast<size_t>(p)]) * tau(state, p, F)) * h;
          const Vec<D> q0 = m * v - A * st.fx;  // momentum at offset 0 (the base node)
          scatter(tile, st, m, q0, A);
        }
        flush(tile, s);
      }
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

  void flush(const Scalar* tile, Index s) {
    const std::int32_t* nb = &neighbor_slot_[static_cast<size_t>(s * NEIGHBORS)];
    for (int t = 0; t < TN; ++t) {
      if (tile[t * S] == 0) continue;
      int neighbor, local;
      tile_to_block(t, neighbor, local);
      Scalar* node = &grid_[static_cast<size_t>((static_cast<Index>(nb[neighbor]) * BN + local) * S)];
      for (int c = 0; c < S; ++c) node[c] += tile[t * S + c];
    }
  }

  void grid_update(Scalar dt) {
    const Index slots = static_cast<Index>(slot_key_.size());
    Vec<D> g;
    for (int a = 0; a < D; ++a) g(a) = config_.gravity[a];
#pragma omp parallel for schedule(static) if (slots * BN > kParallelGrain * 4)
    for (Index s = 0; s < slots; ++s) {
      const auto o = block_origin(s);
      for (int l = 0; l < BN; ++l) {
        Scalar* node = &grid_[static_cast<size_t>((s * BN + l) * S)];
        if (node[0] <= 0) continue;
        Vec<D> v;
        for (int a = 0; a < D; ++a) v(a) = node[a + 1] / node[0] + dt * g(a);
        // Node index i (unshifted) per axis.
        Index i[3] = {0, 0, 0};
        int rest = l;
        for (int a = D - 1; a >= 0; --a) {
          i[a] = o[a] + rest % B - 1;
          rest /= B;
        }
        boundary(v, i);
        for (int a = 0; a < D; ++a) node[a + 1] = v(a);
      }
    }
  }

  // Walls at i <= 0 and i >= shape, then the colliders, on the node with index i.
  void boundary(Vec<D>& v, const Index* i) const {
    for (int a = 0; a < D; ++a) {
      if (i[a] <= 0 || i[a] >= model_.shape[a]) {
        Vec<D> n = Vec<D>::Zero();
        n(a) = i[a] <= 0 ? 1 : -1;
        apply_boundary<D>(v, n, model_.boundary, model_.wall_friction);
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
      apply_boundary<D>(v, n, c.boundary, c.friction);
    }
  }

  Scalar g2p(State& state, Scalar dt) {
    const Scalar h = model_.h;
    Scalar vmax = 0;
    bool finite = true;
#pragma omp parallel for schedule(dynamic, 1) reduction(max : vmax) reduction(&& : finite) if (state.n > kParallelParticles)
    for (Index s = 0; s < particle_blocks_; ++s) {
      const auto o = block_origin(s);
      alignas(64) Scalar tile[TN * S];
      gather(tile, s);
      for (Index q = block_start_[s]; q < block_start_[s + 1]; ++q) {
        const Index p = order_[static_cast<size_t>(q)];
        const size_t pd = static_cast<size_t>(p * D);
        const Stencil st = stencil(&state.x[pd], o);
        Vec<D> v = Vec<D>::Zero();
        Mat<D> Bm = Mat<D>::Zero();  // sum w v_i (node offset in cells)^T
        gather_sums(tile, st, v, Bm);
        const Mat<D> C = (4 / h) * (Bm - v * st.fx.transpose());
        Eigen::Map<Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>> F(&state.F[pd * D]);
        Eigen::Map<Eigen::Matrix<Scalar, D, D, Eigen::RowMajor>>(&state.C[pd * D]) = C;
        Mat<D> Fn = (Mat<D>::Identity() + dt * C) * F;
        plasticity(state, p, Fn);
        F = Fn;
        for (int a = 0; a < D; ++a) {
          Scalar& x = state.x[pd + a];
          x = std::clamp(x + dt * v(a), model_.origin[a], model_.upper(a));
          state.v[pd + a] = v(a);
        }
        finite = finite && v.allFinite() && Fn.allFinite();
        vmax = std::max(vmax, v.norm());
      }
    }
    if (!finite || !(vmax * dt <= config_.max_cells_per_step * h))
      throw DivergenceError(
          "mpm: " + std::string(finite ? "particles moved " + format_real(vmax * dt / h) + " cells in one step"
                                       : "a velocity or deformation gradient became non-finite") +
          " at step " + std::to_string(state.steps) + " (t = " + format_real(state.time) + " s, dt = " +
          format_real(dt) + " s); use a dt below stable_dt() (CFL on speed and elastic wave speed)");
    return vmax;
  }

  void gather(Scalar* tile, Index s) const {
    const std::int32_t* nb = &neighbor_slot_[static_cast<size_t>(s * NEIGHBORS)];
    for (int t = 0; t < TN; ++t) {
      int neighbor, local;
      tile_to_block(t, neighbor, local);
      const Scalar* node = &grid_[static_cast<size_t>((static_cast<Index>(nb[neighbor]) * BN + local) * S)];
      for (int c = 1; c < S; ++c) tile[t * S + c] = node[c];
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

  void plasticity(State& state, Index p, Mat<D>& F) const {
    const Material& m = model_.materials[static_cast<size_t>(state.material[static_cast<size_t>(p)])];
    Scalar& Jp = state.Jp[static_cast<size_t>(p)];
    Svd<D> s;
    switch (m.kind) {
      case MaterialKind::Snow:
        F = snow_project<D>(F, m, Jp, s);
        break;
      case MaterialKind::Sand:
        F = sand_project<D>(F, m, Jp, s);
        break;
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
  }

  Model model_;
  Config config_;
  Scalar inv_h_ = 1 / model_.h;
  std::array<Index, 3> blocks_{};
  Index block_count_ = 0;
  std::vector<std::int32_t> table_;          // dense block key -> slot (or -1)
  std::vector<Index> slot_key_;              // slot -> block key; particle blocks first
  Index particle_blocks_ = 0;
  std::vector<std::int32_t> neighbor_slot_;  // (particle block, 2^d) -> slot of the +{0,1}^d block
  std::vector<Index> particle_key_;          // (n,) block key of each particle
  std::vector<Index> block_start_;           // CSR of order_ by particle block
  std::vector<Index> fill_;
  std::vector<Index> order_;                 // particle rows sorted by block
  std::vector<Index> colour_start_, colour_blocks_;
  std::vector<Scalar> grid_;                 // (slots, B^d, d + 1): mass, momentum -> velocity
};

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

StepStats Solver::step(State& state, Scalar dt, Interrupt& interrupt) {
  if (state.dim != model_.dim) throw InvalidArgument("state: dimension differs from the model's");
  return impl_->step(state, dt, interrupt);
}

Scalar Solver::stable_dt(const State& state, Scalar cfl) const {
  if (!(std::isfinite(cfl) && cfl > 0)) throw InvalidArgument("cfl: expected a number > 0, got " + format_real(cfl));
  const int d = state.dim;
  Scalar vmax = 0, harden = 1;
#pragma omp parallel for schedule(static) reduction(max : vmax, harden) if (state.n > kParallelParticles)
  for (Index p = 0; p < state.n; ++p) {
    Scalar v2 = 0;
    for (int a = 0; a < d; ++a) v2 += state.v[static_cast<size_t>(p * d + a)] * state.v[static_cast<size_t>(p * d + a)];
    vmax = std::max(vmax, std::sqrt(v2));
    const Material& m = model_.materials[static_cast<size_t>(state.material[static_cast<size_t>(p)])];
    if (m.kind == MaterialKind::Snow)
      harden = std::max(harden, std::exp(m.hardening * (1 - state.Jp[static_cast<size_t>(p)])));
  }
  Scalar c = 0;
  for (const Material& m : model_.materials)
    c = std::max(c, m.wave_speed * (m.kind == MaterialKind::Snow ? std::sqrt(harden) : 1.0));
  Scalar dt = config_.max_dt;
  if (vmax + c > 0) dt = std::min(dt, cfl * model_.h / (vmax + c));
  Scalar g = 0;
  for (int a = 0; a < d; ++a) g += config_.gravity[a] * config_.gravity[a];
  if (g > 0) dt = std::min(dt, std::sqrt(cfl * model_.h / std::sqrt(g)));
  return dt;
}

Scalar Solver::kinetic_energy(const State& state) const {
  const int d = state.dim;
  return parallel_sum(state.n, [&](Index p) {
    Scalar v2 = 0;
    for (int a = 0; a < d; ++a) v2 += state.v[static_cast<size_t>(p * d + a)] * state.v[static_cast<size_t>(p * d + a)];
    return 0.5 * state.mass[static_cast<size_t>(p)] * v2;
  });
}

std::vector<Scalar> Solver::momentum(const State& state) const {
  const int d = state.dim;
  std::vector<Scalar> out(static_cast<size_t>(d));
  for (int a = 0; a < d; ++a)
    out[a] = parallel_sum(state.n, [&](Index p) {
      return state.mass[static_cast<size_t>(p)] * state.v[static_cast<size_t>(p * d + a)];
    });
  return out;
}

std::vector<Scalar> Solver::angular_momentum(const State& state) const {
  const int d = state.dim;
  const Scalar inertia = model_.h * model_.h / 4;  // sum w (x_i - x_p)(x_i - x_p)^T = h^2/4 I
  // Component c of x x v + (h^2/4) eps_abc C_ba, for (a, b, c) cyclic.
  auto component = [&](int a, int b) {
    return parallel_sum(state.n, [&](Index p) {
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
