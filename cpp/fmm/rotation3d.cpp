// Rotation-based M2L (see rotation3d.h): construction of the Wigner d-matrices and of the
// z-axis translations, and their application to kColumns expansions at a time.
#include "fmm/rotation3d.h"

#include <Eigen/Eigenvalues>
#include <cmath>
#include <complex>
#include <map>

#include "core/simd.h"
#include "fmm/p2p3d.h"

namespace kinema::fmm3 {

namespace {

constexpr int K = RotatedTranslation::kColumns;

// sqrt((l+m)! (l-m)!) in long double: the scale between the solid harmonics R_lm of
// kernels3d.h and the orthonormal ones, R_lm = c_l r^l Y_lm / s_lm.
long double harmonic_scale(int l, int m) {
  long double f = 1;
  for (int k = 2; k <= l + m; ++k) f *= k;
  for (int k = 2; k <= l - m; ++k) f *= k;
  return std::sqrt(f);
}

// Eigenvectors of the Hermitian H = i (J+ - J-)/2 on the degree-l harmonics (row m + l), whose
// eigenvalues are the integers -l..l: d^l(b) = exp(-b (J+ - J-)/2) = V exp(i b Lambda) V^H.
struct Generator {
  Eigen::MatrixXcd vectors;
  Eigen::VectorXd values;
  explicit Generator(int l) {
    const int n = 2 * l + 1;
    Eigen::MatrixXcd h = Eigen::MatrixXcd::Zero(n, n);
    for (int m = -l; m < l; ++m) {
      // <m+1| J+ |m> = sqrt(l(l+1) - m(m+1)) = <m| J- |m+1>
      const double c = std::sqrt(double(l * (l + 1) - m * (m + 1)));
      h(m + 1 + l, m + l) = std::complex<double>(0, 0.5 * c);
      h(m + l, m + 1 + l) = std::complex<double>(0, -0.5 * c);
    }
    Eigen::SelfAdjointEigenSolver<Eigen::MatrixXcd> solver(h);
    vectors = solver.eigenvectors();
    values = solver.eigenvalues();
  }
  // d^l_{m'm}(b) at row m' + l, column m + l.
  Eigen::MatrixXd wigner(double b) const {
    Eigen::VectorXcd phase(values.size());
    for (Eigen::Index k = 0; k < values.size(); ++k)
      phase[k] = std::exp(std::complex<double>(0, b * values[k]));
    return (vectors * phase.asDiagonal() * vectors.adjoint()).real();
  }
};

// dst[r] = sum_j a[r * lda + j] src[j] for r < rows, j < cols, each a row of K values held in
// vectors of W doubles: R rows at a time (then fewer), so that every load of a source row
// feeds R vector multiply-adds and the R x K/W sums stay in registers. Each value is summed
// over j in order whatever W and R are.
template <int W, int R>
KINEMA_ALWAYS_INLINE void rows_product(int rows, int cols, const Scalar* a, int lda,
                                       const Scalar* const* src, Scalar* const* dst, int r = 0) {
  typedef Scalar V __attribute__((vector_size(W * sizeof(Scalar)), aligned(sizeof(Scalar))));
  constexpr int NV = K / W;
  for (; r + R <= rows; r += R) {
    V acc[R][NV];
    for (int i = 0; i < R; ++i)
      for (int v = 0; v < NV; ++v) acc[i][v] = V{};
    const Scalar* row = a + r * lda;
    for (int j = 0; j < cols; ++j) {
      const V* x = reinterpret_cast<const V*>(src[j]);
      V xv[NV];
      for (int v = 0; v < NV; ++v) xv[v] = x[v];
      for (int i = 0; i < R; ++i) {
        const Scalar w = row[i * lda + j];
        for (int v = 0; v < NV; ++v) acc[i][v] += w * xv[v];
      }
    }
    for (int i = 0; i < R; ++i)
      for (int v = 0; v < NV; ++v) reinterpret_cast<V*>(dst[r + i])[v] = acc[i][v];
  }
  if constexpr (R > 1) rows_product<W, R / 2>(rows, cols, a, lda, src, dst, r);
}

// Position of (Re or Im) coefficient (l, m) of the rotated frame, layout grouped by m:
// Re X_{m..pt, m} then (m > 0) Im X_{m..pt, m}.
inline int group_start(int m, int pt) {
  return m == 0 ? 0 : (pt + 1) + 2 * ((m - 1) * (pt + 1) - m * (m - 1) / 2);
}
inline int interleaved(int l, int m, bool imag) { return l * l + (m == 0 ? 0 : 2 * m - 1 + imag); }

// Degree l of `to` = e^{i sign m a} times degree l of `from` (interleaved layout, K columns).
KINEMA_ALWAYS_INLINE void rotate_z(int l, const Scalar* cos_ma, const Scalar* sin_ma, Scalar sign,
                                   const Scalar* from, Scalar* to) {
  for (int c = 0; c < K; ++c) to[(l * l) * K + c] = from[(l * l) * K + c];
  for (int m = 1; m <= l; ++m) {
    const Scalar co = cos_ma[m], si = sign * sin_ma[m];
    const Scalar* re = from + interleaved(l, m, false) * K;
    const Scalar* im = from + interleaved(l, m, true) * K;
    Scalar* tr = to + interleaved(l, m, false) * K;
    Scalar* ti = to + interleaved(l, m, true) * K;
    for (int c = 0; c < K; ++c) {
      tr[c] = co * re[c] - si * im[c];
      ti[c] = si * re[c] + co * im[c];
    }
  }
}

template <int W, int R>
KINEMA_ALWAYS_INLINE void apply_body(int pt, const Scalar* cos_ma, const Scalar* sin_ma, Scalar s_in, Scalar s_out,
                                     const Scalar* rot, const size_t* block_start,
                                     const Scalar* trans, const size_t* trans_start, int p,
                                     const Scalar* in, Scalar* out, Scalar* x, Scalar* y) {
  // 1. About z: X_lm = e^{i s_in m a} M_lm.
  for (int l = 0; l <= pt; ++l) rotate_z(l, cos_ma, sin_ma, s_in, in, x);
  // 2. About y, degree by degree, into the layout grouped by m.
  const Scalar* src[2 * 41 + 2];
  Scalar* dst[2 * 41 + 2];
  for (int l = 0; l <= pt; ++l) {
    const Scalar* fre = rot + block_start[l];
    const Scalar* fim = fre + (l + 1) * (l + 1);
    for (int m = 0; m <= l; ++m) {
      src[m] = x + interleaved(l, m, false) * K;
      dst[m] = y + (group_start(m, pt) + l - m) * K;
    }
    rows_product<W, R>(l + 1, l + 1, fre, l + 1, src, dst);
    for (int m = 1; m <= l; ++m) {
      src[m - 1] = x + interleaved(l, m, true) * K;
      dst[m - 1] = y + (group_start(m, pt) + (pt + 1 - m) + l - m) * K;
    }
    rows_product<W, R>(l, l, fim, l, src, dst);
  }
  // 3. Along z, one matrix per m for both parts (the sign of the M2L's imaginary part is in
  // the backward rotation).
  for (int m = 0; m <= pt; ++m) {
    const Scalar* t = trans + trans_start[m];
    const int stride = p + 1 - m, count = pt + 1 - m;
    for (int part = 0; part < (m == 0 ? 1 : 2); ++part) {
      const int base = group_start(m, pt) + part * (pt + 1 - m);
      for (int j = 0; j < count; ++j) src[j] = y + (base + j) * K, dst[j] = x + (base + j) * K;
      rows_product<W, R>(count, count, t, stride, src, dst);
    }
  }
  // 4. Back about y (into y, interleaved), 5. back about z into out.
  for (int l = 0; l <= pt; ++l) {
    const Scalar* bre = rot + block_start[l] + (l + 1) * (l + 1) + l * l;
    const Scalar* bim = bre + (l + 1) * (l + 1);
    for (int m = 0; m <= l; ++m) {
      src[m] = x + (group_start(m, pt) + l - m) * K;
      dst[m] = y + interleaved(l, m, false) * K;
    }
    rows_product<W, R>(l + 1, l + 1, bre, l + 1, src, dst);
    for (int m = 1; m <= l; ++m) {
      src[m - 1] = x + (group_start(m, pt) + (pt + 1 - m) + l - m) * K;
      dst[m - 1] = y + interleaved(l, m, true) * K;
    }
    rows_product<W, R>(l, l, bim, l, src, dst);
    rotate_z(l, cos_ma, sin_ma, s_out, y, out);
  }
}

void apply_portable(int pt, const Scalar* cos_ma, const Scalar* sin_ma, Scalar s_in, Scalar s_out, const Scalar* rot,
                    const size_t* block_start, const Scalar* trans, const size_t* trans_start,
                    int p, const Scalar* in, Scalar* out, Scalar* x, Scalar* y) {
  apply_body<2, 2>(pt, cos_ma, sin_ma, s_in, s_out, rot, block_start, trans, trans_start, p, in, out, x, y);
}

#if KINEMA_HAVE_AVX2_CLONES
__attribute__((target("avx2,fma"))) void apply_avx2(
    int pt, const Scalar* cos_ma, const Scalar* sin_ma, Scalar s_in, Scalar s_out, const Scalar* rot, const size_t* block_start,
    const Scalar* trans, const size_t* trans_start, int p, const Scalar* in, Scalar* out, Scalar* x,
    Scalar* y) {
  apply_body<4, 2>(pt, cos_ma, sin_ma, s_in, s_out, rot, block_start, trans, trans_start, p, in, out, x, y);
}
__attribute__((target("avx512f,avx2,fma"))) void apply_avx512(
    int pt, const Scalar* cos_ma, const Scalar* sin_ma, Scalar s_in, Scalar s_out, const Scalar* rot, const size_t* block_start,
    const Scalar* trans, const size_t* trans_start, int p, const Scalar* in, Scalar* out, Scalar* x,
    Scalar* y) {
  apply_body<8, 4>(pt, cos_ma, sin_ma, s_in, s_out, rot, block_start, trans, trans_start, p, in, out, x, y);
}
#endif

}  // namespace

RotatedTranslation::RotatedTranslation(int p, Translation kind, const std::vector<int>& canonical)
    : p_(p), kind_(kind), offsets_(64) {
  block_start_.resize(static_cast<size_t>(p + 2));
  block_start_[0] = 0;
  for (int l = 0; l <= p; ++l)
    block_start_[static_cast<size_t>(l + 1)] = block_start_[static_cast<size_t>(l)] + 2 * ((l + 1) * (l + 1) + l * l);
  translation_start_.resize(static_cast<size_t>(p + 2));
  translation_start_[0] = 0;
  for (int m = 0; m <= p; ++m)
    translation_start_[static_cast<size_t>(m + 1)] = translation_start_[static_cast<size_t>(m)] + (p + 1 - m) * (p + 1 - m);

  // Distinct polar angles (by (dx^2 + dy^2, dz)) and distances (by |d|^2).
  std::map<std::pair<int, int>, int> angle_index;
  std::map<int, int> distance_index;
  std::vector<double> angles;
  std::vector<int> squares;
  for (int b : canonical) {
    const int dx = b / 16, dy = (b / 4) % 4, dz = b % 4;
    const int rho2 = dx * dx + dy * dy;
    Offset& o = offsets_[static_cast<size_t>(b)];
    auto a = angle_index.emplace(std::make_pair(rho2, dz), static_cast<int>(angles.size()));
    if (a.second) angles.push_back(std::atan2(std::sqrt(double(rho2)), double(dz)));
    o.angle = a.first->second;
    auto d = distance_index.emplace(rho2 + dz * dz, static_cast<int>(squares.size()));
    if (d.second) squares.push_back(rho2 + dz * dz);
    o.distance = d.first->second;
    const double azimuth = std::atan2(double(dy), double(dx));
    o.cos_ma.resize(static_cast<size_t>(p + 1));
    o.sin_ma.resize(static_cast<size_t>(p + 1));
    for (int m = 0; m <= p; ++m) {
      o.cos_ma[static_cast<size_t>(m)] = std::cos(m * azimuth);
      o.sin_ma[static_cast<size_t>(m)] = std::sin(m * azimuth);
    }
  }

  // Rotations. With Q = Ry(-b) Rz(-a) taking the offset to +z, R(Q y) = D R(y) where
  // D = Dy diag(e^{-i m a}) and, on the orthonormal harmonics, Dn_{mm'} = d^l_{m'm}(b) (real,
  // orthogonal). Multipoles (conj R, scaled as s M) rotate by conj(D): forward
  // X = e^{i m a} M, Y = S^-1 Dn S X; backward S^-1 Dn^T S, then e^{-i m a}. Locals (scaled as
  // L / s) rotate by conj(D)^-T: forward e^{-i m a}, then S Dn S^-1; backward S Dn^T S^-1,
  // then e^{i m a}. With X_{-m} = (-1)^m conj(X_m) each map G splits into a block on the
  // real parts, G(m, 0) and G(m, m') + (-1)^m' G(m, -m'), and one on the imaginary parts,
  // G(m, m') - (-1)^m' G(m, -m').
  const bool multipole_in = kind != Translation::L2L, multipole_out = kind == Translation::M2M;
  rotations_.assign(angles.size(), std::vector<Scalar>(block_start_.back()));
#pragma omp parallel for schedule(dynamic, 1)
  for (int l = p; l >= 0; --l) {
    const Generator generator(l);
    std::vector<long double> s(static_cast<size_t>(l + 1));
    for (int m = 0; m <= l; ++m) s[static_cast<size_t>(m)] = harmonic_scale(l, m);
    for (size_t a = 0; a < angles.size(); ++a) {
      const Eigen::MatrixXd d = generator.wigner(angles[a]);
      auto scale = [&](int m) { return s[static_cast<size_t>(std::abs(m))]; };
      auto dn = [&](int m, int mp) { return static_cast<long double>(d(mp + l, m + l)); };
      auto forward = [&](int m, int mp) {
        return static_cast<Scalar>(multipole_in ? dn(m, mp) * scale(mp) / scale(m) : dn(m, mp) * scale(m) / scale(mp));
      };
      auto backward = [&](int m, int mp) {
        return static_cast<Scalar>(multipole_out ? dn(mp, m) * scale(mp) / scale(m) : dn(mp, m) * scale(m) / scale(mp));
      };
      // The M2L translation gives Im L = -(...) Im Y: its sign is folded into the backward block.
      const Scalar im_sign = kind == Translation::M2L ? -1 : 1;
      Scalar* block = &rotations_[a][block_start_[static_cast<size_t>(l)]];
      for (int pass = 0; pass < 2; ++pass) {
        Scalar* re = block + pass * ((l + 1) * (l + 1) + l * l);
        Scalar* im = re + (l + 1) * (l + 1);
        for (int m = 0; m <= l; ++m)
          for (int mp = 0; mp <= l; ++mp) {
            const Scalar sign = (mp & 1) ? -1 : 1;
            const Scalar g = pass ? backward(m, mp) : forward(m, mp);
            const Scalar gm = pass ? backward(m, -mp) : forward(m, -mp);
            re[m * (l + 1) + mp] = mp == 0 ? g : g + sign * gm;
            if (m > 0 && mp > 0) im[(m - 1) * l + mp - 1] = (pass ? im_sign : 1) * (g - sign * gm);
          }
      }
    }
  }

  // Translations along z. M2L: T_m(j, l) = (-1)^{j+m} (l+j)! / rho^{l+j+1}, rho = 2 |d| (box
  // half-widths). M2M: T(l, j) = 2^-j t^{l-j} / (l-j)!; L2L: T(j, l) = 2^-j t^{l-j} / (l-j)!
  // (l >= j), t = sqrt(3)/2 (parent half-widths).
  translations_.assign(squares.size(), std::vector<Scalar>(translation_start_.back()));
  for (size_t k = 0; k < squares.size(); ++k) {
    const long double rho = kind == Translation::M2L ? 2 * std::sqrt(static_cast<long double>(squares[k]))
                                                     : std::sqrt(static_cast<long double>(squares[k])) / 2;
    std::vector<long double> irr(static_cast<size_t>(2 * p + 1)), reg(static_cast<size_t>(p + 1));
    irr[0] = 1 / rho;  // n! / rho^{n+1}
    for (int n = 1; n <= 2 * p; ++n) irr[static_cast<size_t>(n)] = irr[static_cast<size_t>(n - 1)] * n / rho;
    reg[0] = 1;  // rho^n / n!
    for (int n = 1; n <= p; ++n) reg[static_cast<size_t>(n)] = reg[static_cast<size_t>(n - 1)] * rho / n;
    for (int m = 0; m <= p; ++m) {
      Scalar* t = &translations_[k][translation_start_[static_cast<size_t>(m)]];
      for (int j = m; j <= p; ++j)
        for (int l = m; l <= p; ++l) {
          long double v = 0;
          if (kind == Translation::M2L) v = ((j + m) & 1 ? -1 : 1) * irr[static_cast<size_t>(l + j)];
          else if (kind == Translation::M2M && j >= l) v = std::ldexp(reg[static_cast<size_t>(j - l)], -l);
          else if (kind == Translation::L2L && l >= j) v = std::ldexp(reg[static_cast<size_t>(l - j)], -j);
          t[(j - m) * (p + 1 - m) + (l - m)] = static_cast<Scalar>(v);
        }
    }
  }
}

void RotatedTranslation::apply(int b, int pt, const Scalar* in, Scalar* out, Scalar* scratch) const {
  const Offset& o = offsets_[static_cast<size_t>(b)];
  const Scalar* rot = rotations_[static_cast<size_t>(o.angle)].data();
  const Scalar* trans = translations_[static_cast<size_t>(o.distance)].data();
  Scalar* x = scratch;
  Scalar* y = scratch + static_cast<size_t>((p_ + 1) * (p_ + 1) * K);
  // z phases: multipoles e^{+i m a} in, e^{-i m a} out; locals the reverse.
  const Scalar s_in = kind_ == Translation::L2L ? -1 : 1, s_out = kind_ == Translation::M2M ? -1 : 1;
#if KINEMA_HAVE_AVX2_CLONES
  static const bool avx2 = use_avx2(), avx512 = use_avx512_kernels();
  if (avx512) {
    apply_avx512(pt, o.cos_ma.data(), o.sin_ma.data(), s_in, s_out, rot, block_start_.data(), trans,
                 translation_start_.data(), p_, in, out, x, y);
    return;
  }
  if (avx2) {
    apply_avx2(pt, o.cos_ma.data(), o.sin_ma.data(), s_in, s_out, rot, block_start_.data(), trans,
               translation_start_.data(), p_, in, out, x, y);
    return;
  }
#endif
  apply_portable(pt, o.cos_ma.data(), o.sin_ma.data(), s_in, s_out, rot, block_start_.data(), trans,
                 translation_start_.data(), p_, in, out, x, y);
}

}  // namespace kinema::fmm3
