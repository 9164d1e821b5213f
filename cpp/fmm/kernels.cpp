// Translation operators of the complex-form 2D Laplace FMM; the formulas are those of
// Greengard & Rokhlin 1987 (Lemmas 2.3-2.5) rewritten for the h-scaled coefficients of kernels.h.
#include "fmm/kernels.h"

namespace kinema::fmm {

Operators::Operators(int p_) : p(p_) {
  // Pascal's triangle up to row 2p, in double (C(128, 64) ~ 2.4e37 is still exact enough).
  const int rows = 2 * p + 1;
  std::vector<Scalar> pascal(static_cast<size_t>(rows * rows), 0.0);
  auto C = [&](int n, int k) -> Scalar& { return pascal[static_cast<size_t>(n * rows + k)]; };
  for (int n = 0; n < rows; ++n) {
    C(n, 0) = 1;
    for (int k = 1; k <= n; ++k) C(n, k) = C(n - 1, k - 1) + (k <= n - 1 ? C(n - 1, k) : 0);
  }
  m2l.resize(static_cast<size_t>(p * p));
  for (int l = 1; l <= p; ++l)
    for (int k = 1; k <= p; ++k) m2l[static_cast<size_t>((l - 1) * p + (k - 1))] = C(k + l - 1, l);
  m2m.assign(static_cast<size_t>((p + 1) * (p + 1)), 0.0);
  for (int l = 1; l <= p; ++l)
    for (int k = 1; k <= l; ++k) m2m[static_cast<size_t>(l * (p + 1) + k)] = C(l - 1, k - 1);
  inverse.resize(static_cast<size_t>(p + 1));
  inverse[0] = 0;
  for (int l = 1; l <= p; ++l) inverse[static_cast<size_t>(l)] = 1.0 / l;
}

void p2m(const Operators& op, Scalar cx, Scalar cy, Scalar h, const Scalar* sx, const Scalar* sy,
         const Scalar* q, Index n, Scalar* re, Scalar* im) {
  const int p = op.p;
  const Scalar inv_h = 1.0 / h;
  for (Index j = 0; j < n; ++j) {
    const Scalar ur = (sx[j] - cx) * inv_h, ui = (sy[j] - cy) * inv_h;
    re[0] += q[j];
    Scalar pr = ur * q[j], pi = ui * q[j];  // q u^k
    for (int k = 1; k <= p; ++k) {
      re[k] -= pr * op.inverse[k];
      im[k] -= pi * op.inverse[k];
      const Scalar tr = pr * ur - pi * ui;
      pi = pr * ui + pi * ur;
      pr = tr;
    }
  }
}

void m2m(const Operators& op, const Scalar* re1, const Scalar* im1, Scalar c1x, Scalar c1y,
         Scalar h1, Scalar* re0, Scalar* im0, Scalar c0x, Scalar c0y, Scalar h0) {
  // a0_l += -a_0 t^l / l + sum_{k=1..l} a1_k s^k C(l-1, k-1) t^(l-k),  t = (c1 - c0)/h0, s = h1/h0.
  const int p = op.p;
  const Scalar tr = (c1x - c0x) / h0, ti = (c1y - c0y) / h0, s = h1 / h0;
  std::vector<Scalar> ur(p + 1), ui(p + 1), pr(p + 1), pi(p + 1);
  Scalar sk = 1;
  pr[0] = 1;
  pi[0] = 0;
  for (int k = 1; k <= p; ++k) {
    sk *= s;
    ur[k] = re1[k] * sk;
    ui[k] = im1[k] * sk;
    pr[k] = pr[k - 1] * tr - pi[k - 1] * ti;
    pi[k] = pr[k - 1] * ti + pi[k - 1] * tr;
  }
  const Scalar a0 = re1[0];
  re0[0] += a0;
  for (int l = 1; l <= p; ++l) {
    Scalar sr = -a0 * pr[l] * op.inverse[l], si = -a0 * pi[l] * op.inverse[l];
    const Scalar* row = &op.m2m[static_cast<size_t>(l * (p + 1))];
    for (int k = 1; k <= l; ++k) {
      const Scalar c = row[k];
      sr += c * (ur[k] * pr[l - k] - ui[k] * pi[l - k]);
      si += c * (ur[k] * pi[l - k] + ui[k] * pr[l - k]);
    }
    re0[l] += sr;
    im0[l] += si;
  }
}

void m2l(const Operators& op, const Scalar* re_s, const Scalar* im_s, Scalar csx, Scalar csy,
         Scalar hs, Scalar* re_t, Scalar* im_t, Scalar ctx, Scalar cty, Scalar ht) {
  // With z0 = cs - ct, alpha = hs/z0, beta = ht/z0 and c_k = a_k (-alpha)^k:
  //   b_0 += a_0 log|z0| + sum_k c_k,   b_l += beta^l (-a_0/l + sum_k C(k+l-1, l) c_k).
  const int p = op.p;
  const Scalar zr = csx - ctx, zi = csy - cty;
  const Scalar r2 = zr * zr + zi * zi;
  const Scalar ir = zr / r2, ii = -zi / r2;  // 1/z0
  const Scalar ar = -hs * ir, ai = -hs * ii;  // -alpha
  const Scalar br = ht * ir, bi = ht * ii;    // beta
  Scalar cr[128], ci[128];
  Scalar pr = 1, pi = 0;
  Scalar sum_r = 0, sum_i = 0;
  for (int k = 1; k <= p; ++k) {
    const Scalar tr = pr * ar - pi * ai;
    pi = pr * ai + pi * ar;
    pr = tr;
    cr[k - 1] = re_s[k] * pr - im_s[k] * pi;
    ci[k - 1] = re_s[k] * pi + im_s[k] * pr;
    sum_r += cr[k - 1];
    sum_i += ci[k - 1];
  }
  const Scalar a0 = re_s[0];
  re_t[0] += a0 * 0.5 * std::log(r2) + sum_r;
  im_t[0] += sum_i;
  Scalar qr = 1, qi = 0;  // beta^l
  for (int l = 1; l <= p; ++l) {
    const Scalar* row = &op.m2l[static_cast<size_t>((l - 1) * p)];
    Scalar sr = 0, si = 0;
#pragma omp simd reduction(+ : sr, si)
    for (int k = 0; k < p; ++k) {
      sr += row[k] * cr[k];
      si += row[k] * ci[k];
    }
    sr -= a0 * op.inverse[l];
    const Scalar tr = qr * br - qi * bi;
    qi = qr * bi + qi * br;
    qr = tr;
    re_t[l] += sr * qr - si * qi;
    im_t[l] += sr * qi + si * qr;
  }
}

void l2l(const Operators& op, const Scalar* re0, const Scalar* im0, Scalar c0x, Scalar c0y,
         Scalar h0, Scalar* re1, Scalar* im1, Scalar c1x, Scalar c1y, Scalar h1) {
  // f = sum b_k v0^k with v0 = s v1 + t: Taylor-shift the polynomial by t, then scale by s^l.
  const int p = op.p;
  const Scalar tr = (c1x - c0x) / h0, ti = (c1y - c0y) / h0, s = h1 / h0;
  Scalar dr[129], di[129];
  for (int k = 0; k <= p; ++k) {
    dr[k] = re0[k];
    di[k] = im0[k];
  }
  for (int i = 0; i < p; ++i)
    for (int k = p - 1; k >= i; --k) {
      dr[k] += tr * dr[k + 1] - ti * di[k + 1];
      di[k] += tr * di[k + 1] + ti * dr[k + 1];
    }
  Scalar sl = 1;
  for (int l = 0; l <= p; ++l) {
    re1[l] += dr[l] * sl;
    im1[l] += di[l] * sl;
    sl *= s;
  }
}

void p2l(const Operators& op, Scalar cx, Scalar cy, Scalar h, const Scalar* sx, const Scalar* sy,
         const Scalar* q, Index n, Scalar* re, Scalar* im) {
  // q log(z - z_j) about c: b_0 = q log|z_j - c|, b_l = -q (h / (z_j - c))^l / l.
  const int p = op.p;
  for (Index j = 0; j < n; ++j) {
    const Scalar zr = sx[j] - cx, zi = sy[j] - cy;
    const Scalar r2 = zr * zr + zi * zi;
    const Scalar wr = h * zr / r2, wi = -h * zi / r2;
    re[0] += q[j] * 0.5 * std::log(r2);
    Scalar pr = q[j] * wr, pi = q[j] * wi;
    for (int l = 1; l <= p; ++l) {
      re[l] -= pr * op.inverse[l];
      im[l] -= pi * op.inverse[l];
      const Scalar tr = pr * wr - pi * wi;
      pi = pr * wi + pi * wr;
      pr = tr;
    }
  }
}

}  // namespace kinema::fmm
