// Solid harmonics by their Cartesian recurrences (no trigonometry) and the translations of
// the 3D Laplace FMM (see kernels3d.h for the conventions).
#include "fmm/kernels3d.h"

#include <cmath>

namespace kinema::fmm3 {

void regular(Scalar x, Scalar y, Scalar z, int p, Complex* out) {
  const Scalar r2 = x * x + y * y + z * z;
  const Complex w(x, y);
  out[0] = 1;
  for (int l = 0; l < p; ++l) {
    out[cidx(l + 1, l + 1)] = -w * out[cidx(l, l)] / Scalar(2 * l + 2);
    for (int m = 0; m <= l; ++m) {
      const Complex prev = l - 1 >= m ? out[cidx(l - 1, m)] : Complex(0);
      out[cidx(l + 1, m)] =
          (Scalar(2 * l + 1) * z * out[cidx(l, m)] - r2 * prev) / Scalar((l + 1) * (l + 1) - m * m);
    }
  }
}

void irregular(Scalar x, Scalar y, Scalar z, int p, Complex* out) {
  const Scalar r2 = x * x + y * y + z * z;
  const Scalar inv_r2 = 1 / r2;
  const Complex w(x, y);
  out[0] = 1 / std::sqrt(r2);
  for (int l = 0; l < p; ++l) {
    out[cidx(l + 1, l + 1)] = -Scalar(2 * l + 1) * w * out[cidx(l, l)] * inv_r2;
    for (int m = 0; m <= l; ++m) {
      const Complex prev = l - 1 >= m ? out[cidx(l - 1, m)] : Complex(0);
      out[cidx(l + 1, m)] =
          (Scalar(2 * l + 1) * z * out[cidx(l, m)] - Scalar(l * l - m * m) * prev) * inv_r2;
    }
  }
}

void to_complex(const Scalar* real, int p, Complex* out) {
  for (int l = 0; l <= p; ++l) {
    const Scalar* r = real + l * l;
    out[cidx(l, 0)] = Complex(r[0], 0);
    for (int m = 1; m <= l; ++m) out[cidx(l, m)] = Complex(r[2 * m - 1], r[2 * m]);
  }
}

void add_real(const Complex* c, int p, Scalar scale, Scalar* real) {
  for (int l = 0; l <= p; ++l) {
    Scalar* r = real + l * l;
    r[0] += scale * c[cidx(l, 0)].real();
    for (int m = 1; m <= l; ++m) {
      r[2 * m - 1] += scale * c[cidx(l, m)].real();
      r[2 * m] += scale * c[cidx(l, m)].imag();
    }
  }
}

void p2m(int p, const Scalar* c, Scalar h, const Scalar* const xyz[3], const Scalar* q, Index n,
         Index stride, Scalar* multipole) {
  std::vector<Complex> r(static_cast<size_t>(complex_count(p)));
  std::vector<Complex> acc(r.size(), Complex(0));
  const Scalar inv_h = 1 / h;
  for (Index j = 0; j < n; ++j) {
    regular((xyz[0][j] - c[0]) * inv_h, (xyz[1][j] - c[1]) * inv_h, (xyz[2][j] - c[2]) * inv_h, p,
            r.data());
    const Scalar w = q[j * stride];
    for (size_t k = 0; k < r.size(); ++k) acc[k] += w * std::conj(r[k]);
  }
  add_real(acc.data(), p, 1.0, multipole);
}

void m2m(int p, const Scalar* child, const Scalar* cc, const Scalar* cp, Scalar h, Scalar* parent) {
  const int count = complex_count(p);
  std::vector<Complex> mc(static_cast<size_t>(count)), rd(static_cast<size_t>(count)),
      acc(static_cast<size_t>(count), Complex(0));
  to_complex(child, p, mc.data());
  regular((cc[0] - cp[0]) / h, (cc[1] - cp[1]) / h, (cc[2] - cp[2]) / h, p, rd.data());
  // The child's coefficients are scaled by (h/2)^j: 2^-j converts them to the parent's scale.
  for (int j = 0; j <= p; ++j) {
    const Scalar s = std::ldexp(1.0, -j);
    for (int k = 0; k <= j; ++k) mc[cidx(j, k)] *= s;
  }
  for (int l = 0; l <= p; ++l)
    for (int m = 0; m <= l; ++m) {
      Complex sum = 0;
      for (int j = 0; j <= l; ++j)
        for (int k = -j; k <= j; ++k) {
          const int dm = m - k;
          if (dm > l - j || dm < -(l - j)) continue;
          sum += coefficient(mc.data(), p, j, k) * std::conj(coefficient(rd.data(), p, l - j, dm));
        }
      acc[cidx(l, m)] = sum;
    }
  add_real(acc.data(), p, 1.0, parent);
}

void l2l(int p, const Scalar* parent, const Scalar* cp, Scalar h, const Scalar* cc, Scalar* child) {
  const int count = complex_count(p);
  std::vector<Complex> lp(static_cast<size_t>(count)), rd(static_cast<size_t>(count)),
      acc(static_cast<size_t>(count), Complex(0));
  to_complex(parent, p, lp.data());
  regular((cc[0] - cp[0]) / h, (cc[1] - cp[1]) / h, (cc[2] - cp[2]) / h, p, rd.data());
  for (int j2 = 0; j2 <= p; ++j2) {
    const Scalar s = std::ldexp(1.0, -j2);
    for (int k2 = 0; k2 <= j2; ++k2) {
      Complex sum = 0;
      for (int j = j2; j <= p; ++j)
        for (int k = -j; k <= j; ++k) {
          const int dk = k - k2;
          if (dk > j - j2 || dk < -(j - j2)) continue;
          sum += coefficient(lp.data(), p, j, k) * std::conj(coefficient(rd.data(), p, j - j2, dk));
        }
      acc[cidx(j2, k2)] = s * sum;
    }
  }
  add_real(acc.data(), p, 1.0, child);
}

void p2l(int p, const Scalar* c, Scalar h, const Scalar* const xyz[3], const Scalar* q, Index n,
         Index stride, Scalar* local) {
  std::vector<Complex> v(static_cast<size_t>(complex_count(p)));
  std::vector<Complex> acc(v.size(), Complex(0));
  const Scalar inv_h = 1 / h;
  for (Index j = 0; j < n; ++j) {
    irregular((c[0] - xyz[0][j]) * inv_h, (c[1] - xyz[1][j]) * inv_h, (c[2] - xyz[2][j]) * inv_h,
              p, v.data());
    const Scalar w = q[j * stride];
    for (int l = 0; l <= p; ++l) {
      const Scalar sign = (l & 1) ? -w : w;
      for (int m = 0; m <= l; ++m) acc[cidx(l, m)] += sign * v[cidx(l, m)];
    }
  }
  add_real(acc.data(), p, inv_h, local);
}

void m2l_matrix(int p, const int offset[3], Scalar* matrix) {
  // L_jk = (-1)^j sum_lm M_lm I_{l+j, m+k}(2 d); with M_{l,-m} = (-1)^m conj(M_lm), the
  // m > 0 terms M I1 + (-1)^m conj(M) I2 = a (I1 + s I2) + i b (I1 - s I2), M = a + i b.
  const int q = 2 * p;
  std::vector<Complex> ir(static_cast<size_t>(complex_count(q)));
  irregular(2.0 * offset[0], 2.0 * offset[1], 2.0 * offset[2], q, ir.data());
  // I_{n,m} for all -n <= m <= n as a dense table (row n, column m + q), zero outside.
  const int w = 2 * q + 1;
  std::vector<Complex> table(static_cast<size_t>((q + 1) * w), Complex(0));
  for (int nn = 0; nn <= q; ++nn)
    for (int m = -nn; m <= nn; ++m) table[static_cast<size_t>(nn * w + m + q)] = coefficient(ir.data(), q, nn, m);
  const int n = coefficient_count(p);
  for (int j = 0; j <= p; ++j)
    for (int k = 0; k <= j; ++k) {
      const Scalar sj = (j & 1) ? -1.0 : 1.0;
      const int row_re = j * j + (k == 0 ? 0 : 2 * k - 1);
      Scalar* re = matrix + static_cast<size_t>(row_re) * n;
      Scalar* im = k > 0 ? re + n : nullptr;
      for (int l = 0; l <= p; ++l) {
        const Complex* row = &table[static_cast<size_t>((l + j) * w + q)];
        const Complex d0 = sj * row[k];
        re[l * l] = d0.real();
        if (im) im[l * l] = d0.imag();
        for (int m = 1; m <= l; ++m) {
          const Complex i1 = row[m + k], i2 = row[k - m];
          const Scalar s = (m & 1) ? -sj : sj;
          // da = sj (i1 + s' i2), db = i sj (i1 - s' i2) with s' = (-1)^m
          const Complex da = sj * i1 + s * i2;
          const Complex dif = sj * i1 - s * i2;
          re[l * l + 2 * m - 1] = da.real();
          re[l * l + 2 * m] = -dif.imag();
          if (im) {
            im[l * l + 2 * m - 1] = da.imag();
            im[l * l + 2 * m] = dif.real();
          }
        }
      }
    }
}

void local_derivative(const Complex* local, int p, int axis, Complex* out) {
  // d/du_z R_lm = R_{l-1,m}, d/du_x R_lm = (R_{l-1,m+1} - R_{l-1,m-1})/2,
  // d/du_y R_lm = -i (R_{l-1,m-1} + R_{l-1,m+1})/2, applied to sum L_lm conj(R_lm).
  for (int j = 0; j < p; ++j)
    for (int k = 0; k <= j; ++k) {
      const Complex up = coefficient(local, p, j + 1, k + 1), down = coefficient(local, p, j + 1, k - 1);
      Complex v;
      if (axis == 0) v = 0.5 * (down - up);
      else if (axis == 1) v = Complex(0, 0.5) * (up + down);
      else v = coefficient(local, p, j + 1, k);
      out[cidx(j, k)] = v;
    }
}

void multipole_derivative(const Complex* multipole, int p, int axis, Complex* out) {
  // d/du_z I_lm = -I_{l+1,m}, d/du_x I_lm = (I_{l+1,m+1} - I_{l+1,m-1})/2,
  // d/du_y I_lm = -i (I_{l+1,m+1} + I_{l+1,m-1})/2, applied to sum M_lm I_lm.
  for (int l = 0; l <= p + 1; ++l)
    for (int m = 0; m <= l; ++m) {
      const Complex a = coefficient(multipole, p, l - 1, m - 1), b = coefficient(multipole, p, l - 1, m + 1);
      Complex v;
      if (axis == 0) v = 0.5 * (a - b);
      else if (axis == 1) v = Complex(0, -0.5) * (a + b);
      else v = -coefficient(multipole, p, l - 1, m);
      out[cidx(l, m)] = v;
    }
}

Scalar local_sum(const Complex* local, const Complex* r, int p) {
  Scalar sum = 0;
  for (int l = 0; l <= p; ++l) {
    const Complex* a = local + cidx(l, 0);
    const Complex* b = r + cidx(l, 0);
    Scalar s = 0;
    for (int m = 1; m <= l; ++m) s += a[m].real() * b[m].real() + a[m].imag() * b[m].imag();
    sum += a[0].real() * b[0].real() + a[0].imag() * b[0].imag() + 2 * s;
  }
  return sum;
}

Scalar multipole_sum(const Complex* multipole, const Complex* v, int p) {
  Scalar sum = 0;
  for (int l = 0; l <= p; ++l) {
    const Complex* a = multipole + cidx(l, 0);
    const Complex* b = v + cidx(l, 0);
    Scalar s = 0;
    for (int m = 1; m <= l; ++m) s += a[m].real() * b[m].real() - a[m].imag() * b[m].imag();
    sum += a[0].real() * b[0].real() - a[0].imag() * b[0].imag() + 2 * s;
  }
  return sum;
}

}  // namespace kinema::fmm3
