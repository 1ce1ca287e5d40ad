// Fused CPU SSIM (Wang et al., "Image quality assessment: from error visibility to structural
// similarity", IEEE TIP 2004) and its gradient w.r.t. the prediction, computing what pytorch-msssim's
// ssim(X, Y, data_range=1, size_average=False) computes:
//
//   pred, target [B,H,W,C] channel-last; win_v [kv], win_h [kh] (pytorch-msssim's Gaussian, or [1] along
//   a dimension it leaves unsmoothed); Ho = H - kv + 1, Wo = W - kh + 1 ('valid' filtering, no padding)
//   -> value [B] (the SSIM map averaged over the Ho x Wo pixels of each channel, then over channels),
//      and, for the backward, the partial derivatives of each output pixel's SSIM S w.r.t. its window's
//      mu_x, E[x^2] and E[xy] (each with the other two held fixed), [B,C,Ho,Wo] each;
//   backward: pred, target, those partials, dL/dvalue [B] -> dL/dpred [B,H,W,C].
//
// As in fused-ssim (R. Goel et al., github.com/rahul-goel/fused-ssim, used by Taming 3DGS), one separable
// pass per direction filters the five maps x, y, x^2, y^2, xy; S depends on each pixel q only through
// mu_x, E[x^2] and E[xy] of the windows covering q, so dL/dx(q) = G^T(dS/dmu_x) + 2 x(q) G^T(dS/dE[x^2])
// + y(q) G^T(dS/dE[xy]), G^T being the transposed ('full') filtering. Work is planar: each task takes
// one channel of one image and a block of rows, reads its rows strided and keeps the horizontally
// filtered rows its vertical pass needs in a ring of kv rows, so scratch stays a few rows per thread.
// Every output row is computed by the same operations in the same order whichever thread takes it, and
// the per-image mean adds per-row sums in row order after the parallel loop, so results are bitwise
// independent of the thread count.

#include <algorithm>
#include <cstdint>
#include <vector>

namespace {

// Rows per task: enough tasks to balance two threads on one image, few enough that the kv - 1 rows a
// block re-filters at its top stay a small overhead.
constexpr int64_t kRowBlock = 64;

// Taps of pytorch-msssim's default window: that length is compiled with the tap loop unrolled, so each
// output stays in a register across its taps; other lengths (1 along an unsmoothed dimension) use K = 0.
constexpr int64_t kTaps = 11;

// out[j] = sum_t w[t] * in[j + t], j < n: the cross-correlation conv2d computes ('valid'), vectorised
// over j; each output adds its taps in order t = 0, 1, ... whichever lane computes it.
template <typename T, int64_t K>
void correlate(const T* __restrict in, const T* __restrict w, int64_t k, int64_t n, T* __restrict out) {
  const int64_t taps = K > 0 ? K : k;
#pragma omp simd
  for (int64_t j = 0; j < n; ++j) {
    T sum = w[0] * in[j];
    for (int64_t t = 1; t < taps; ++t) sum += w[t] * in[j + t];
    out[j] = sum;
  }
}

// out[j] = sum_t w[t] * rows[t][j], t < k, j < n: the vertical pass over rows held in the ring.
template <typename T, int64_t K>
void combine(const T* const* __restrict rows, const T* __restrict w, int64_t k, int64_t n, T* __restrict out) {
  const int64_t taps = K > 0 ? K : k;
#pragma omp simd
  for (int64_t j = 0; j < n; ++j) {
    T sum = w[0] * rows[0][j];
    for (int64_t t = 1; t < taps; ++t) sum += w[t] * rows[t][j];
    out[j] = sum;
  }
}

template <typename T>
void correlate_any(const T* in, const T* w, int64_t k, int64_t n, T* out) {
  (k == kTaps ? correlate<T, kTaps> : correlate<T, 0>)(in, w, k, n, out);
}

template <typename T>
void combine_any(const T* const* rows, const T* w, int64_t k, int64_t n, T* out) {
  (k == kTaps ? combine<T, kTaps> : combine<T, 0>)(rows, w, k, n, out);
}

// One row of the SSIM map from the filtered statistics, as pytorch-msssim's _ssim (sigma = E[.] - mu mu,
// same operation order), and with Grad its partial derivatives w.r.t. mu_x, E[x^2], E[xy] (the chain
// through the sigmas folded into d_mu).
template <typename T, bool Grad>
void ssim_row(const T* __restrict mu_x, const T* __restrict mu_y, const T* __restrict e_xx,
              const T* __restrict e_yy, const T* __restrict e_xy, int64_t n, T C1, T C2, T* __restrict s_map,
              T* __restrict d_mu, T* __restrict d_xx, T* __restrict d_xy) {
#pragma omp simd
  for (int64_t j = 0; j < n; ++j) {
    const T mx = mu_x[j], my = mu_y[j];
    const T mxx = mx * mx, myy = my * my, mxy = mx * my;
    const T sxx = e_xx[j] - mxx, syy = e_yy[j] - myy, sxy = e_xy[j] - mxy;
    const T num_l = 2 * mxy + C1, den_l = mxx + myy + C1;
    const T num_cs = 2 * sxy + C2, den_cs = sxx + syy + C2;
    const T cs = num_cs / den_cs, lum = num_l / den_l, s = lum * cs;
    s_map[j] = s;
    if (Grad) {
      const T g_xx = -s / den_cs, g_xy = 2 * lum / den_cs;  // dS/dsigma_x^2, dS/dsigma_xy
      d_xx[j] = g_xx;
      d_xy[j] = g_xy;
      d_mu[j] = 2 * cs * (my - mx * lum) / den_l - 2 * mx * g_xx - my * g_xy;
    }
  }
}

template <typename T>
void ssim_forward(const T* x, const T* y, int64_t B, int64_t H, int64_t W, int64_t C, const T* wv,
                  int64_t kv, const T* wh, int64_t kh, double c1, double c2, T* value, T* d_mu, T* d_xx,
                  T* d_xy, int num_threads) {
  const int64_t Ho = H - kv + 1, Wo = W - kh + 1, blocks = (Ho + kRowBlock - 1) / kRowBlock;
  const T C1 = T(c1), C2 = T(c2);
  std::vector<double> row_sums(B * C * Ho);
#pragma omp parallel num_threads(num_threads)
  {
    std::vector<T> maps(5 * W), ring(5 * kv * Wo), stats(5 * Wo);
    std::vector<const T*> rows(kv);
#pragma omp for schedule(dynamic, 1)
    for (int64_t task = 0; task < B * C * blocks; ++task) {
      const int64_t plane = task / blocks, b = plane / C, c = plane % C;
      const int64_t r0 = task % blocks * kRowBlock, r1 = std::min(Ho, r0 + kRowBlock);
      for (int64_t i = r0; i < r1 + kv - 1; ++i) {
        // Input row i of channel c -> x, y, x^2, y^2, xy, filtered horizontally into ring slot i % kv.
        const T* xi = x + (b * H + i) * W * C + c;
        const T* yi = y + (b * H + i) * W * C + c;
        for (int64_t j = 0; j < W; ++j) {
          const T xv = xi[j * C], yv = yi[j * C];
          maps[j] = xv; maps[W + j] = yv; maps[2 * W + j] = xv * xv; maps[3 * W + j] = yv * yv;
          maps[4 * W + j] = xv * yv;
        }
        for (int64_t m = 0; m < 5; ++m)
          correlate_any(&maps[m * W], wh, kh, Wo, &ring[(m * kv + i % kv) * Wo]);
        const int64_t r = i - kv + 1;  // the output row whose window ends at input row i
        if (r < r0) continue;
        for (int64_t m = 0; m < 5; ++m) {
          for (int64_t t = 0; t < kv; ++t) rows[t] = &ring[(m * kv + (r + t) % kv) * Wo];
          combine_any(rows.data(), wv, kv, Wo, &stats[m * Wo]);
        }
        const int64_t at = (plane * Ho + r) * Wo;
        T* s_map = &maps[0];  // the input maps are no longer needed
        const T* st = stats.data();
        if (d_mu)
          ssim_row<T, true>(st, st + Wo, st + 2 * Wo, st + 3 * Wo, st + 4 * Wo, Wo, C1, C2, s_map, d_mu + at,
                            d_xx + at, d_xy + at);
        else
          ssim_row<T, false>(st, st + Wo, st + 2 * Wo, st + 3 * Wo, st + 4 * Wo, Wo, C1, C2, s_map, nullptr,
                             nullptr, nullptr);
        double sum = 0.0;  // in index order: no vectorised reduction whose order could vary
        for (int64_t j = 0; j < Wo; ++j) sum += s_map[j];
        row_sums[plane * Ho + r] = sum;
      }
    }
  }
  for (int64_t b = 0; b < B; ++b) {
    double total = 0.0;
    for (int64_t c = 0; c < C; ++c) {
      double channel = 0.0;
      for (int64_t r = 0; r < Ho; ++r) channel += row_sums[(b * C + c) * Ho + r];
      total += channel / double(Ho * Wo);
    }
    value[b] = T(total / double(C));
  }
}

template <typename T>
void ssim_backward(const T* x, const T* y, const T* d_mu, const T* d_xx, const T* d_xy, const T* grad_value,
                   int64_t B, int64_t H, int64_t W, int64_t C, const T* wv, int64_t kv, const T* wh,
                   int64_t kh, T* grad_x, int num_threads) {
  const int64_t Ho = H - kv + 1, Wo = W - kh + 1, blocks = (H + kRowBlock - 1) / kRowBlock;
  const int64_t padded = Wo + 2 * (kh - 1);
  // The transposed horizontal pass is a 'valid' correlation of the zero-padded row with the reversed window.
  std::vector<T> wh_rev(wh, wh + kh);
  std::reverse(wh_rev.begin(), wh_rev.end());
  const T* partials[3] = {d_mu, d_xx, d_xy};
#pragma omp parallel num_threads(num_threads)
  {
    std::vector<T> pad(3 * padded, T(0)), ring(3 * kv * W), acc(3 * W), weights(kv);
    std::vector<const T*> rows(kv);
#pragma omp for schedule(dynamic, 1)
    for (int64_t task = 0; task < B * C * blocks; ++task) {
      const int64_t plane = task / blocks, b = plane / C, c = plane % C;
      const int64_t q0 = task % blocks * kRowBlock, q1 = std::min(H, q0 + kRowBlock);
      const T scale = T(double(grad_value[b]) / double(C * Ho * Wo));  // d(mean over channels, pixels)
      int64_t next = std::max<int64_t>(0, q0 - kv + 1);  // next partial-derivative row to filter
      for (int64_t q = q0; q < q1; ++q) {
        // Output rows p = q - t (0 <= t < kv, 0 <= p < Ho) cover input row q; filter any not yet in the ring.
        for (; next <= std::min(q, Ho - 1); ++next)
          for (int64_t m = 0; m < 3; ++m) {
            std::copy_n(partials[m] + (plane * Ho + next) * Wo, Wo, &pad[m * padded + kh - 1]);
            correlate_any(&pad[m * padded], wh_rev.data(), kh, W, &ring[(m * kv + next % kv) * W]);
          }
        for (int64_t m = 0; m < 3; ++m) {
          int64_t n = 0;
          for (int64_t t = 0; t < kv; ++t) {
            const int64_t p = q - t;
            if (p < 0 || p >= Ho) continue;
            weights[n] = wv[t];
            rows[n++] = &ring[(m * kv + p % kv) * W];
          }
          combine_any(rows.data(), weights.data(), n, W, &acc[m * W]);
        }
        const T* xq = x + (b * H + q) * W * C + c;
        const T* yq = y + (b * H + q) * W * C + c;
        T* gq = grad_x + (b * H + q) * W * C + c;
        for (int64_t j = 0; j < W; ++j)
          gq[j * C] = scale * (acc[j] + 2 * xq[j * C] * acc[W + j] + yq[j * C] * acc[2 * W + j]);
      }
    }
  }
}

}  // namespace

extern "C" {

void hico_ssim_forward_f32(const float* pred, const float* target, int64_t batch, int64_t height,
                           int64_t width, int64_t channels, const float* win_v, int64_t kv, const float* win_h,
                           int64_t kh, double c1, double c2, float* value, float* d_mu, float* d_xx,
                           float* d_xy, int num_threads) {
  ssim_forward(pred, target, batch, height, width, channels, win_v, kv, win_h, kh, c1, c2, value, d_mu, d_xx,
               d_xy, num_threads);
}

void hico_ssim_forward_f64(const double* pred, const double* target, int64_t batch, int64_t height,
                           int64_t width, int64_t channels, const double* win_v, int64_t kv,
                           const double* win_h, int64_t kh, double c1, double c2, double* value, double* d_mu,
                           double* d_xx, double* d_xy, int num_threads) {
  ssim_forward(pred, target, batch, height, width, channels, win_v, kv, win_h, kh, c1, c2, value, d_mu, d_xx,
               d_xy, num_threads);
}

void hico_ssim_backward_f32(const float* pred, const float* target, const float* d_mu, const float* d_xx,
                            const float* d_xy, const float* grad_value, int64_t batch, int64_t height,
                            int64_t width, int64_t channels, const float* win_v, int64_t kv,
                            const float* win_h, int64_t kh, float* grad_pred, int num_threads) {
  ssim_backward(pred, target, d_mu, d_xx, d_xy, grad_value, batch, height, width, channels, win_v, kv, win_h,
                kh, grad_pred, num_threads);
}

void hico_ssim_backward_f64(const double* pred, const double* target, const double* d_mu, const double* d_xx,
                            const double* d_xy, const double* grad_value, int64_t batch, int64_t height,
                            int64_t width, int64_t channels, const double* win_v, int64_t kv,
                            const double* win_h, int64_t kh, double* grad_pred, int num_threads) {
  ssim_backward(pred, target, d_mu, d_xx, d_xy, grad_value, batch, height, width, channels, win_v, kv, win_h,
                kh, grad_pred, num_threads);
}

}  // extern "C"
