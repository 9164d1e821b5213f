// Rotation-based M2L (see rotation3d.h): construction of the Wigner d-matrices and of the
// z-axis translations, and their application to kColumns expansions at a time.
#include "fmm/rotation3d.h"

#include <Eigen/Eigenvalues>
#include <cmath>
#include <complex>
#include <map>

#include "core/simd.h"

namespace kinema::fmm3 {

namespace {

constexpr int K = RotatedM2l::kColumns;

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

KINEMA_ALWAYS_INLINE void axpy(Scalar* acc, Scalar a, const Scalar* x) {
  for (int c = 0; c < K; ++c) acc[c] += a * x[c];
}

// Position of (Re or Im) coefficient (l, m) of the rotated frame, layout grouped by m:
// Re X_{m..pt, m} then (m > 0) Im X_{m..pt, m}.
inline int group_start(int m, int pt) {
  return m == 0 ? 0 : (pt + 1) + 2 * ((m - 1) * (pt + 1) - m * (m - 1) / 2);
}
inline int interleaved(int l, int m, bool imag) { return l * l + (m == 0 ? 0 : 2 * m - 1 + imag); }

KINEMA_ALWAYS_INLINE void apply_body(int pt, const Scalar* cos_ma, const Scalar* sin_ma,
                                     const Scalar* rot, const size_t* block_start,
                                     const Scalar* trans, const size_t* trans_start, int p,
                                     const Scalar* in, Scalar* out, Scalar* x, Scalar* y) {
  // 1. About z: X_lm = e^{i m a} M_lm.
  for (int l = 0; l <= pt; ++l) {
    for (int c = 0; c < K; ++c) x[(l * l) * K + c] = in[(l * l) * K + c];
    for (int m = 1; m <= l; ++m) {
      const Scalar co = cos_ma[m], si = sin_ma[m];
      const Scalar* re = in + interleaved(l, m, false) * K;
      const Scalar* im = in + interleaved(l, m, true) * K;
      Scalar* xr = x + interleaved(l, m, false) * K;
      Scalar* xi = x + interleaved(l, m, true) * K;
      for (int c = 0; c < K; ++c) {
        xr[c] = co * re[c] - si * im[c];
        xi[c] = si * re[c] + co * im[c];
      }
    }
  }
  // 2. About y, degree by degree, into the layout grouped by m.
  for (int l = 0; l <= pt; ++l) {
    const Scalar* fre = rot + block_start[l];
    const Scalar* fim = fre + (l + 1) * (l + 1);
    for (int m = 0; m <= l; ++m) {
      Scalar acc[K] = {};
      for (int mp = 0; mp <= l; ++mp) axpy(acc, fre[m * (l + 1) + mp], x + interleaved(l, mp, false) * K);
      Scalar* dst = y + (group_start(m, pt) + l - m) * K;
      for (int c = 0; c < K; ++c) dst[c] = acc[c];
    }
    for (int m = 1; m <= l; ++m) {
      Scalar acc[K] = {};
      for (int mp = 1; mp <= l; ++mp) axpy(acc, fim[(m - 1) * l + mp - 1], x + interleaved(l, mp, true) * K);
      Scalar* dst = y + (group_start(m, pt) + (pt + 1 - m) + l - m) * K;
      for (int c = 0; c < K; ++c) dst[c] = acc[c];
    }
  }
  // 3. Along z, one matrix per m for both parts (the sign of the imaginary part is in the
  // backward rotation).
  for (int m = 0; m <= pt; ++m) {
    const Scalar* t = trans + trans_start[m];
    const int stride = p + 1 - m;
    for (int part = 0; part < (m == 0 ? 1 : 2); ++part) {
      const Scalar* src = y + (group_start(m, pt) + part * (pt + 1 - m)) * K;
      Scalar* dst = x + (group_start(m, pt) + part * (pt + 1 - m)) * K;
      for (int j = m; j <= pt; ++j) {
        Scalar acc[K] = {};
        const Scalar* row = t + (j - m) * stride;
        for (int l = m; l <= pt; ++l) axpy(acc, row[l - m], src + (l - m) * K);
        for (int c = 0; c < K; ++c) dst[(j - m) * K + c] = acc[c];
      }
    }
  }
  // 4. Back about y into the interleaved layout, 5. back about z.
  for (int l = 0; l <= pt; ++l) {
    const Scalar* bre = rot + block_start[l] + (l + 1) * (l + 1) + l * l;
    const Scalar* bim = bre + (l + 1) * (l + 1);
    Scalar re[K], im[K];
    for (int mp = 0; mp <= l; ++mp) {
      for (int c = 0; c < K; ++c) re[c] = 0, im[c] = 0;
      for (int m = 0; m <= l; ++m) axpy(re, bre[mp * (l + 1) + m], x + (group_start(m, pt) + l - m) * K);
      if (mp > 0)
        for (int m = 1; m <= l; ++m)
          axpy(im, bim[(mp - 1) * l + m - 1], x + (group_start(m, pt) + (pt + 1 - m) + l - m) * K);
      if (mp == 0) {
        Scalar* dst = out + (l * l) * K;
        for (int c = 0; c < K; ++c) dst[c] = re[c];
        continue;
      }
      const Scalar co = cos_ma[mp], si = sin_ma[mp];
      Scalar* dr = out + interleaved(l, mp, false) * K;
      Scalar* di = out + interleaved(l, mp, true) * K;
      for (int c = 0; c < K; ++c) {
        dr[c] = co * re[c] - si * im[c];
        di[c] = si * re[c] + co * im[c];
      }
    }
  }
}

void apply_portable(int pt, const Scalar* cos_ma, const Scalar* sin_ma, const Scalar* rot,
                    const size_t* block_start, const Scalar* trans, const size_t* trans_start,
                    int p, const Scalar* in, Scalar* out, Scalar* x, Scalar* y) {
  apply_body(pt, cos_ma, sin_ma, rot, block_start, trans, trans_start, p, in, out, x, y);
}

#if KINEMA_HAVE_AVX2_CLONES
__attribute__((target("avx2,fma"))) void apply_avx2(
    int pt, const Scalar* cos_ma, const Scalar* sin_ma, const Scalar* rot, const size_t* block_start,
    const Scalar* trans, const size_t* trans_start, int p, const Scalar* in, Scalar* out, Scalar* x,
    Scalar* y) {
  apply_body(pt, cos_ma, sin_ma, rot, block_start, trans, trans_start, p, in, out, x, y);
}
#endif

}  // namespace

RotatedM2l::RotatedM2l(int p, const std::vector<int>& canonical) : p_(p), offsets_(64) {
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

  // Rotations. With Q = Ry(-b) Rz(-a) taking the offset to +z, R(Q y) = D R(y) where, on the
  // scaled harmonics, D = S^-1 Dn S (S = diag s_lm), Dn_{mm'} = d^l_{m'm}(b) e^{-i m' a}.
  // Forward (multipoles, conj(R)): X = e^{i m a} M, Y_m = sum_m' Ds_{mm'} X_m'; backward
  // (locals): L_m' = e^{i m' a} sum_m Ds_{mm'} Y_m. With X_{-m} = (-1)^m conj(X_m) each splits
  // into a block on the real parts and one on the imaginary parts.
  rotations_.assign(angles.size(), std::vector<Scalar>(block_start_.back()));
  for (int l = 0; l <= p; ++l) {
    const Generator generator(l);
    std::vector<long double> s(static_cast<size_t>(l + 1));
    for (int m = 0; m <= l; ++m) s[static_cast<size_t>(m)] = harmonic_scale(l, m);
    for (size_t a = 0; a < angles.size(); ++a) {
      const Eigen::MatrixXd d = generator.wigner(angles[a]);
      // Ds(m, m') for -l <= m, m' <= l.
      auto ds = [&](int m, int mp) {
        return static_cast<Scalar>(static_cast<long double>(d(mp + l, m + l)) *
                                   s[static_cast<size_t>(std::abs(mp))] / s[static_cast<size_t>(std::abs(m))]);
      };
      Scalar* fre = &rotations_[a][block_start_[static_cast<size_t>(l)]];
      Scalar* fim = fre + (l + 1) * (l + 1);
      Scalar* bre = fim + l * l;
      Scalar* bim = bre + (l + 1) * (l + 1);
      for (int m = 0; m <= l; ++m)
        for (int mp = 0; mp <= l; ++mp) {
          const Scalar sign = (mp & 1) ? -1 : 1;
          fre[m * (l + 1) + mp] = mp == 0 ? ds(m, 0) : ds(m, mp) + sign * ds(m, -mp);
          if (m > 0 && mp > 0) fim[(m - 1) * l + mp - 1] = ds(m, mp) - sign * ds(m, -mp);
        }
      for (int mp = 0; mp <= l; ++mp)
        for (int m = 0; m <= l; ++m) {
          const Scalar sign = (m & 1) ? -1 : 1;
          bre[mp * (l + 1) + m] = m == 0 ? ds(0, mp) : ds(m, mp) + sign * ds(-m, mp);
          // The z translation gives Im L = -(...) Im Y: its sign is folded in here.
          if (m > 0 && mp > 0) bim[(mp - 1) * l + m - 1] = -(ds(m, mp) - sign * ds(-m, mp));
        }
    }
  }

  // Translations: T_m(j, l) = (-1)^{j+m} (l+j)! / rho^{l+j+1}, rho = 2 |d| (box half-widths).
  translations_.assign(squares.size(), std::vector<Scalar>(translation_start_.back()));
  for (size_t k = 0; k < squares.size(); ++k) {
    const long double rho = 2 * std::sqrt(static_cast<long double>(squares[k]));
    std::vector<long double> irr(static_cast<size_t>(2 * p + 1));  // n! / rho^{n+1}
    irr[0] = 1 / rho;
    for (int n = 1; n <= 2 * p; ++n) irr[static_cast<size_t>(n)] = irr[static_cast<size_t>(n - 1)] * n / rho;
    for (int m = 0; m <= p; ++m) {
      Scalar* t = &translations_[k][translation_start_[static_cast<size_t>(m)]];
      for (int j = m; j <= p; ++j)
        for (int l = m; l <= p; ++l)
          t[(j - m) * (p + 1 - m) + (l - m)] =
              static_cast<Scalar>(((j + m) & 1 ? -1 : 1) * irr[static_cast<size_t>(l + j)]);
    }
  }
}

void RotatedM2l::apply(int b, int pt, const Scalar* in, Scalar* out, Scalar* scratch) const {
  const Offset& o = offsets_[static_cast<size_t>(b)];
  const Scalar* rot = rotations_[static_cast<size_t>(o.angle)].data();
  const Scalar* trans = translations_[static_cast<size_t>(o.distance)].data();
  Scalar* x = scratch;
  Scalar* y = scratch + static_cast<size_t>((p_ + 1) * (p_ + 1) * K);
#if KINEMA_HAVE_AVX2_CLONES
  static const bool avx2 = use_avx2();
  if (avx2) {
    apply_avx2(pt, o.cos_ma.data(), o.sin_ma.data(), rot, block_start_.data(), trans,
               translation_start_.data(), p_, in, out, x, y);
    return;
  }
#endif
  apply_portable(pt, o.cos_ma.data(), o.sin_ma.data(), rot, block_start_.data(), trans,
                 translation_start_.data(), p_, in, out, x, y);
}

}  // namespace kinema::fmm3
