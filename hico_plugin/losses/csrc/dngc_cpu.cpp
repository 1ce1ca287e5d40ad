// Fused CPU DNGC loss terms (HiCo-GS Sec. 3.4) and their gradient, computing what the torch reference
// hico_plugin.losses.dngc.dngc_losses computes, in one pass over the images each way:
//
//   u = v / |v| where |v| > eps, else (1,1,1) / sqrt(3) with zero gradient (the reference replaces an
//       undefined vector by ones before normalising, so nothing non-finite enters the sums)
//   L_nc = sum_p w_p ||u_r(p) - u_d(p)||_1 / max(sum_p w_p, 1e-8),   w_p = alpha_p [n_r(p), n_d(p) defined]
//   e_x  = exp(-beta mean_c |dx rgb|), e_y likewise (the edge weights; rgb and alpha carry no gradient)
//   L_ns = sum_x e_x m_x mean_c |dx u_r| / N_x + sum_y e_y m_y mean_c |dy u_r| / N_y,  m: both n_r defined
//   L_ds = sum_x e_x |dx d| / N_x + sum_y e_y |dy d| / N_y
//
// with forward differences dx (within a row) and dy (between rows), N_x = B H (W-1) and N_y = B (H-1) W
// the numbers of difference positions (at least 1: a 1-px image contributes 0), and |.|' = sign, sign(0) = 0,
// as torch's abs. Inputs are [B,H,W,K] with any batch / row / pixel strides (in elements) and adjacent
// channels, so slices of a packed render tensor are read in place; gradients are contiguous [B,H,W,K].
//
// Work is split into blocks of rows of one image. A block copies each input row once into contiguous
// per-thread rows (normalising n_r) and keeps the rows its differences need in a small ring, plus one halo
// row recomputed at the block's top. The backward is a gather: each pixel adds the contributions of the (up
// to four) differences it takes part in, so rows are independent. Every row is computed by the same code
// whichever thread takes it, each row's sums are accumulated in double over lanes fixed by index, and the
// rows' sums are added in row order by one thread, so results are bitwise independent of the thread count.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "expf_cephes.h"

namespace {

constexpr int64_t kRowBlock = 32;  // rows per task: enough tasks to balance two threads on one image
constexpr int kSums = 6;           // per-row sums: nc numerator, nc weight, ns x, ns y, ds x, ds y

// One input: element (b, i, j, c) at data[b * sb + i * sh + j * sw + c].
template <typename T>
struct Image {
  const T* data;
  int64_t sb, sh, sw;
  const T* row(int64_t b, int64_t i) const { return data + b * sb + i * sh; }
};

template <typename T>
struct Inputs {
  Image<T> rgb, alpha, normal, depth_normal, distance;
  int64_t B, H, W, C;  // C: rgb channels
  T neg_beta, eps;
};

template <typename T>
inline T sgn(T x) {
  return T(x > 0) - T(x < 0);
}

// sum of x[0, n) in double over 8 lanes chosen by index, added in a fixed order: vectorisable, and the same
// bits wherever the row sits in memory and whichever thread sums it.
template <typename T>
double sum_row(const T* __restrict x, int64_t n) {
  double lane[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  int64_t j = 0;
  for (; j + 8 <= n; j += 8)
    for (int l = 0; l < 8; ++l) lane[l] += double(x[j + l]);
  for (int l = 0; j < n; ++j, ++l) lane[l] += double(x[j]);
  return ((lane[0] + lane[1]) + (lane[2] + lane[3])) + ((lane[4] + lane[5]) + (lane[6] + lane[7]));
}

// Unit vectors u [n,3], the defined mask ok [n] (0/1) and the normalised length len [n] of the contiguous
// 3-vectors v [n,3], as the reference's _unit. Selects and divisions have loops of their own: GCC does not
// vectorise a select feeding a division (it branches around the division). The square root vectorises
// because the library is built with -fno-math-errno (see dngc_fused.py).
template <typename T>
void unit_row(const T* __restrict v, int64_t n, T eps, T* __restrict u, T* __restrict ok, T* __restrict len) {
#pragma omp simd
  for (int64_t j = 0; j < n; ++j)
    len[j] = std::sqrt(v[3 * j] * v[3 * j] + v[3 * j + 1] * v[3 * j + 1] + v[3 * j + 2] * v[3 * j + 2]);
  const T ones_norm = std::sqrt(T(1) * T(1) + T(1) * T(1) + T(1) * T(1));  // |(1, 1, 1)| as torch finds it
#pragma omp simd
  for (int64_t j = 0; j < n; ++j) {
    const T x = v[3 * j], y = v[3 * j + 1], z = v[3 * j + 2], l = len[j];
    const bool defined = l > eps;
    ok[j] = defined ? T(1) : T(0);
    len[j] = defined ? l : ones_norm;
    u[3 * j] = defined ? x : T(1);
    u[3 * j + 1] = defined ? y : T(1);
    u[3 * j + 2] = defined ? z : T(1);
  }
#pragma omp simd
  for (int64_t j = 0; j < n; ++j)
    for (int c = 0; c < 3; ++c) u[3 * j + c] /= len[j];
}

// In place, g [n,3] = dL/du -> dL/dv through u = v / |v|: (g - u (u . g)) / |v|, times the defined mask
// (an undefined v was replaced by ones: zero gradient; g is finite, so that is an exact 0).
template <typename T>
void through_unit(const T* __restrict u, const T* __restrict ok, const T* __restrict len, int64_t n,
                  T* __restrict g) {
#pragma omp simd
  for (int64_t j = 0; j < n; ++j) {
    const T* p = u + 3 * j;
    T* q = g + 3 * j;
    const T dot = (p[0] * q[0] + p[1] * q[1]) + p[2] * q[2];
    for (int c = 0; c < 3; ++c) q[c] = ok[j] * (q[c] - p[c] * dot) / len[j];
  }
}

// In place e = exp(e). libm's exp is a call GCC does not vectorise, so float takes Cephes' expf
// (expf_cephes.h), which loops vectorise; about 1 ulp, as torch's own vectorised exp. n is rounded to
// nearest by adding and subtracting 1.5 * 2^23. At or below -87.34 (denormal results) it gives 0. Double
// (the reference precision, used by tests) keeps libm.
inline void exp_row(double* e, int64_t n) {
  for (int64_t k = 0; k < n; ++k) e[k] = std::exp(e[k]);
}

inline void exp_row(float* __restrict e, int64_t n) {
  constexpr float kLow = -87.33654f, kHigh = 88.72284f, kRound = 12582912.0f;  // 1.5 * 2^23: round to integer
  // The clamp has a loop of its own: GCC would fold the polynomial of a clamped constant into a branch.
#pragma omp simd
  for (int64_t k = 0; k < n; ++k) {
    const float low = e[k] < kLow ? kLow : e[k];
    e[k] = low > kHigh ? kHigh : low;
  }
#pragma omp simd
  for (int64_t k = 0; k < n; ++k) {
    const float x = e[k];
    const float m = (x * 1.44269504088896341f + kRound) - kRound;  // n, in [-126, 128]
    const float p = hico::expf_poly(hico::expf_reduce(x, m));
    // 2^n from its exponent bits; n = 128 as 2 * 2^127 (2^128 is no float).
    const int32_t ni = int32_t(m), top = ni > 127 ? 1 : 0, bits = (ni - top + 127) << 23;
    float scale;
    std::memcpy(&scale, &bits, sizeof scale);
    const float keep = x > kLow ? 1.0f : 0.0f;  // a factor: GCC branches around a select of arithmetic
    e[k] = p * scale * float(1 + top) * keep;
  }
}

// Edge weights e[k] = exp(-beta mean_c |b[k] - a[k]|) between the pixels of contiguous rows a, b of C
// channels: along a row with b = a + C (n = W - 1), across rows with b the next row (n = W). The channel
// count is a template constant for RGB (Kc = 3: the pixel loop vectorises) and read at run time otherwise.
template <typename T, int64_t Kc>
void edge_weights(const T* __restrict a, const T* __restrict b, int64_t C, int64_t n, T neg_beta,
                  T* __restrict e) {
  const int64_t channels = Kc > 0 ? Kc : C;
#pragma omp simd
  for (int64_t k = 0; k < n; ++k) {
    T sum = std::abs(b[k * channels] - a[k * channels]);
    for (int64_t c = 1; c < channels; ++c) sum += std::abs(b[k * channels + c] - a[k * channels + c]);
    e[k] = neg_beta * (sum / T(channels));
  }
  exp_row(e, n);
}

template <typename T>
void edge_weights(const T* a, const T* b, int64_t C, int64_t n, T neg_beta, T* e) {
  (C == 3 ? edge_weights<T, 3> : edge_weights<T, 0>)(a, b, C, n, neg_beta, e);
}

// Row buffers of one thread. A ring of slots holds consecutive image rows as the differences need them:
// the rgb and distance rows copied to contiguous memory and n_r normalised (u, mask ok, length len); the
// rest is for the current row. Reading each strided input element once here, every later loop reads
// contiguous rows with channel counts known at compile time, which GCC vectorises well.
template <typename T>
struct Rows {
  int64_t W, C;
  std::vector<T> rgb, d, u, ok, len, v, ud, okd, lend, ex, ey, t0, t1;
  Rows(int64_t width, int64_t channels, int ring)
      : W(width), C(channels), rgb(ring * C * W), d(ring * W), u(ring * 3 * W), ok(ring * W), len(ring * W),
        v(3 * W), ud(3 * W), okd(W), lend(W), ex(W + 1), ey(2 * W), t0(3 * (W + 1)), t1(W + 1) {}
  T* Rgb(int64_t slot) { return rgb.data() + slot * C * W; }
  T* D(int64_t slot) { return d.data() + slot * W; }
  T* U(int64_t slot) { return u.data() + slot * 3 * W; }
  T* Ok(int64_t slot) { return ok.data() + slot * W; }
  T* Len(int64_t slot) { return len.data() + slot * W; }
  T* Ey(int64_t slot) { return ey.data() + slot * W; }
};

// dst [n,K] = the n pixels of K channels at src, pixel stride sw.
template <typename T>
void gather(const T* __restrict src, int64_t sw, int64_t K, int64_t n, T* __restrict dst) {
  if (sw == K) {
    std::memcpy(dst, src, sizeof(T) * K * n);
    return;
  }
  for (int64_t j = 0; j < n; ++j)
    for (int64_t c = 0; c < K; ++c) dst[j * K + c] = src[j * sw + c];
}

// Image row k of rgb, distance and n_r (normalised) into ring slot `slot`.
template <typename T>
void stage_row(const Inputs<T>& in, Rows<T>& r, int64_t b, int64_t k, int64_t slot) {
  gather(in.rgb.row(b, k), in.rgb.sw, in.C, in.W, r.Rgb(slot));
  gather(in.distance.row(b, k), in.distance.sw, 1, in.W, r.D(slot));
  gather(in.normal.row(b, k), in.normal.sw, 3, in.W, r.v.data());
  unit_row(r.v.data(), in.W, in.eps, r.U(slot), r.Ok(slot), r.Len(slot));
}

// Unit n_d of image row i into r.ud, r.okd, r.lend.
template <typename T>
void depth_normal_row(const Inputs<T>& in, Rows<T>& r, int64_t b, int64_t i) {
  gather(in.depth_normal.row(b, i), in.depth_normal.sw, 3, in.W, r.v.data());
  unit_row(r.v.data(), in.W, in.eps, r.ud.data(), r.okd.data(), r.lend.data());
}

// The six sums of row i; rows i and i + 1 are staged in slots i % 2 and (i + 1) % 2.
template <typename T>
void forward_row(const Inputs<T>& in, Rows<T>& r, int64_t b, int64_t i, bool has_next, double* sums) {
  const int64_t W = in.W, C = in.C, sa = in.alpha.sw;
  const T *ur = r.U(i % 2), *okr = r.Ok(i % 2), *d = r.D(i % 2), *rgb = r.Rgb(i % 2), *alpha = in.alpha.row(b, i);
  T *ud = r.ud.data(), *okd = r.okd.data(), *ex = r.ex.data(), *t0 = r.t0.data(), *t1 = r.t1.data();
  depth_normal_row(in, r, b, i);
#pragma omp simd
  for (int64_t j = 0; j < W; ++j) {
    const T w = alpha[j * sa] * (okr[j] * okd[j]);
    t0[j] = w * ((std::abs(ur[3 * j] - ud[3 * j]) + std::abs(ur[3 * j + 1] - ud[3 * j + 1])) +
                 std::abs(ur[3 * j + 2] - ud[3 * j + 2]));
    t1[j] = w;
  }
  sums[0] = sum_row(t0, W);
  sums[1] = sum_row(t1, W);

  edge_weights(rgb, rgb + C, C, W - 1, in.neg_beta, ex);
#pragma omp simd
  for (int64_t k = 0; k < W - 1; ++k) {
    const T* p = ur + 3 * k;
    const T mean = ((std::abs(p[3] - p[0]) + std::abs(p[4] - p[1])) + std::abs(p[5] - p[2])) / T(3);
    t0[k] = mean * ex[k] * (okr[k] * okr[k + 1]);
    t1[k] = std::abs(d[k + 1] - d[k]) * ex[k];
  }
  sums[2] = sum_row(t0, W - 1);
  sums[4] = sum_row(t1, W - 1);

  sums[3] = sums[5] = 0;
  if (!has_next) return;
  const T *un = r.U((i + 1) % 2), *okn = r.Ok((i + 1) % 2), *dn = r.D((i + 1) % 2);
  T* ey = r.Ey(0);
  edge_weights(rgb, r.Rgb((i + 1) % 2), C, W, in.neg_beta, ey);
#pragma omp simd
  for (int64_t j = 0; j < W; ++j) {
    const T *p = ur + 3 * j, *q = un + 3 * j;
    const T mean = ((std::abs(q[0] - p[0]) + std::abs(q[1] - p[1])) + std::abs(q[2] - p[2])) / T(3);
    t0[j] = mean * ey[j] * (okr[j] * okn[j]);
    t1[j] = std::abs(dn[j] - d[j]) * ey[j];
  }
  sums[3] = sum_row(t0, W);
  sums[5] = sum_row(t1, W);
}

// Scales of the backward: dL/d(per-position term) of each sum, from the upstream gradients.
template <typename T>
struct Scales {
  T nc, ns_x, ns_y, ds_x, ds_y;
};

// Gradients of row i. Rows i - 1, i, i + 1 are staged in slots (i + 2) % 3, i % 3, (i + 1) % 3; the edge
// weights between rows i - 1, i are in Ey(i % 2) and between i, i + 1 in Ey((i + 1) % 2). A missing
// neighbour row is replaced by row i itself with zero weights, so its difference contributes nothing.
template <typename T>
void backward_row(const Inputs<T>& in, Rows<T>& r, const T* zeros, const Scales<T>& s, int64_t b, int64_t i,
                  bool has_prev, bool has_next, T* __restrict gn, T* __restrict gnd, T* __restrict gd) {
  const int64_t W = in.W, C = in.C, sa = in.alpha.sw;
  const int64_t cur = i % 3, prev = has_prev ? (i + 2) % 3 : cur, next = has_next ? (i + 1) % 3 : cur;
  const T *ur = r.U(cur), *okr = r.Ok(cur), *lenr = r.Len(cur), *up = r.U(prev), *okup = r.Ok(prev),
          *dnr = r.U(next), *okdn = r.Ok(next), *d = r.D(cur), *dup = r.D(prev), *ddn = r.D(next);
  const T *eyu = has_prev ? r.Ey(i % 2) : zeros, *eyd = has_next ? r.Ey((i + 1) % 2) : zeros;
  const T *alpha = in.alpha.row(b, i), *rgb = r.Rgb(cur);
  T *ud = r.ud.data(), *okd = r.okd.data(), *ex = r.ex.data(), *px = r.t0.data(), *qx = r.t1.data();
  depth_normal_row(in, r, b, i);
  edge_weights(rgb, rgb + C, C, W - 1, in.neg_beta, ex);

  // x differences, padded with a zero at both ends: px[3 (k + 1) + c] = dL_ns / du_r(k + 1, c) of the
  // difference between pixels k and k + 1 (and minus that for pixel k); qx the same for L_ds.
  for (int c = 0; c < 3; ++c) px[c] = px[3 * W + c] = 0;
  qx[0] = qx[W] = 0;
#pragma omp simd
  for (int64_t k = 0; k < W - 1; ++k) {
    const T e = s.ns_x * ex[k] * (okr[k] * okr[k + 1]);
    for (int c = 0; c < 3; ++c) px[3 * (k + 1) + c] = e * sgn(ur[3 * (k + 1) + c] - ur[3 * k + c]);
    qx[k + 1] = s.ds_x * ex[k] * sgn(d[k + 1] - d[k]);
  }

#pragma omp simd
  for (int64_t j = 0; j < W; ++j) {
    const T w = s.nc * (alpha[j * sa] * (okr[j] * okd[j]));
    const T eu = s.ns_y * eyu[j] * (okup[j] * okr[j]), ed = s.ns_y * eyd[j] * (okr[j] * okdn[j]);
    for (int c = 0; c < 3; ++c) {
      const int64_t q = 3 * j + c;
      const T g_nc = w * sgn(ur[q] - ud[q]);
      gnd[q] = -g_nc;
      gn[q] = g_nc + (px[q] - px[q + 3]) + (eu * sgn(ur[q] - up[q]) - ed * sgn(dnr[q] - ur[q]));
    }
    gd[j] = (qx[j] - qx[j + 1]) + s.ds_y * (eyu[j] * sgn(d[j] - dup[j]) - eyd[j] * sgn(ddn[j] - d[j]));
  }
  through_unit(ur, okr, lenr, W, gn);
  through_unit(ud, okd, r.lend.data(), W, gnd);
}

template <typename T>
Inputs<T> inputs(const T* rgb, const T* alpha, const T* normal, const T* depth_normal, const T* distance,
                 const int64_t* st, int64_t B, int64_t H, int64_t W, int64_t C, double beta, double eps) {
  return {{rgb, st[0], st[1], st[2]},    {alpha, st[3], st[4], st[5]},
          {normal, st[6], st[7], st[8]}, {depth_normal, st[9], st[10], st[11]},
          {distance, st[12], st[13], st[14]}, B, H, W, C, T(-beta), T(eps)};
}

// The numbers of x and y difference positions, at least 1 (a 1-px image contributes 0, not NaN).
inline double count_x(int64_t B, int64_t H, int64_t W) { return double(std::max<int64_t>(B * H * (W - 1), 1)); }
inline double count_y(int64_t B, int64_t H, int64_t W) { return double(std::max<int64_t>(B * (H - 1) * W, 1)); }

// out = [L_nc, L_ns, L_ds, sum_p w_p] (the weight sum before clamping, for the backward).
template <typename T>
void forward(const Inputs<T>& in, double* out, int num_threads) {
  const int64_t B = in.B, H = in.H, W = in.W, blocks = (H + kRowBlock - 1) / kRowBlock;
  std::vector<double> partial(B * H * kSums, 0.0);
  if (W > 0) {
#pragma omp parallel num_threads(num_threads)
    {
      Rows<T> r(W, in.C, 2);
#pragma omp for schedule(dynamic, 1)
      for (int64_t task = 0; task < B * blocks; ++task) {
        const int64_t b = task / blocks, i0 = task % blocks * kRowBlock, i1 = std::min(i0 + kRowBlock, H);
        // Step k stages row k (one row past the block, for its last y differences) and then sums row
        // k - 1: one call site each, so every row is computed by the same code.
        for (int64_t k = i0; k <= i1; ++k) {
          if (k < H) stage_row(in, r, b, k, k % 2);
          if (k > i0) forward_row(in, r, b, k - 1, k < H, &partial[((b * H) + k - 1) * kSums]);
        }
      }
    }
  }
  double sums[kSums] = {0, 0, 0, 0, 0, 0};
  for (int64_t row = 0; row < B * H; ++row)
    for (int m = 0; m < kSums; ++m) sums[m] += partial[row * kSums + m];
  const double nx = count_x(B, H, W), ny = count_y(B, H, W);
  out[0] = sums[0] / std::max(sums[1], 1e-8);
  out[1] = sums[2] / nx + sums[3] / ny;
  out[2] = sums[4] / nx + sums[5] / ny;
  out[3] = sums[1];
}

template <typename T>
void backward(const Inputs<T>& in, double grad_nc, double grad_ns, double grad_ds, double weight_sum, T* gn,
              T* gnd, T* gd, int num_threads) {
  const int64_t B = in.B, H = in.H, W = in.W, blocks = (H + kRowBlock - 1) / kRowBlock;
  if (W == 0) return;
  const double nx = count_x(B, H, W), ny = count_y(B, H, W);
  const Scales<T> s{T(grad_nc / std::max(weight_sum, 1e-8)), T(grad_ns / (3 * nx)), T(grad_ns / (3 * ny)),
                    T(grad_ds / nx), T(grad_ds / ny)};
  const std::vector<T> zeros(W, T(0));
#pragma omp parallel num_threads(num_threads)
  {
    Rows<T> r(W, in.C, 3);
#pragma omp for schedule(dynamic, 1)
    for (int64_t task = 0; task < B * blocks; ++task) {
      const int64_t b = task / blocks, i0 = task % blocks * kRowBlock, i1 = std::min(i0 + kRowBlock, H);
      // Step k stages row k, finds the edge weights between rows k - 1 and k, then differentiates row
      // k - 1 (whose neighbours k - 2 and k are ready); the block starts one halo row above.
      for (int64_t k = std::max<int64_t>(i0 - 1, 0); k <= i1; ++k) {
        if (k < H) stage_row(in, r, b, k, k % 3);
        if (k >= std::max<int64_t>(i0, 1) && k < H)
          edge_weights(r.Rgb((k + 2) % 3), r.Rgb(k % 3), in.C, W, in.neg_beta, r.Ey(k % 2));
        if (k > i0) {
          const int64_t i = k - 1, at = (b * H + i) * W;
          backward_row(in, r, zeros.data(), s, b, i, i > 0, k < H, gn + 3 * at, gnd + 3 * at, gd + at);
        }
      }
    }
  }
}

}  // namespace

// The C API, for T = float (f32) and double (f64). strides: [5][3] int64, the (batch, row, pixel) strides in
// elements of rgb, alpha, normal, depth_normal, distance; C: rgb channels; eps: the "defined" length.
// forward: out [4] = L_nc, L_ns, L_ds and the L_nc weight sum (for backward). backward: the gradients of
// grad_nc L_nc + grad_ns L_ns + grad_ds L_ds w.r.t. normal, depth_normal, distance, contiguous [B,H,W,3/3/1].
#define HICO_DNGC_API(T, SUFFIX)                                                                              \
  extern "C" void hico_dngc_forward_##SUFFIX(const T* rgb, const T* alpha, const T* normal,                 \
                                             const T* depth_normal, const T* distance, const int64_t* strides, \
                                             int64_t B, int64_t H, int64_t W, int64_t C, double beta,         \
                                             double eps, double* out, int num_threads) {                     \
    forward(inputs(rgb, alpha, normal, depth_normal, distance, strides, B, H, W, C, beta, eps), out,          \
            num_threads);                                                                                     \
  }                                                                                                           \
  extern "C" void hico_dngc_backward_##SUFFIX(                                                                \
      const T* rgb, const T* alpha, const T* normal, const T* depth_normal, const T* distance,               \
      const int64_t* strides, int64_t B, int64_t H, int64_t W, int64_t C, double beta, double eps,            \
      double grad_nc, double grad_ns, double grad_ds, double weight_sum, T* grad_normal,                     \
      T* grad_depth_normal, T* grad_distance, int num_threads) {                                              \
    backward(inputs(rgb, alpha, normal, depth_normal, distance, strides, B, H, W, C, beta, eps), grad_nc,     \
             grad_ns, grad_ds, weight_sum, grad_normal, grad_depth_normal, grad_distance, num_threads);       \
  }

HICO_DNGC_API(float, f32)
HICO_DNGC_API(double, f64)
