// Fused CPU depth normal of a plane-depth render and its gradient, computing what the torch reference
// depth_to_normal(plane_depth(normal, distance, alpha, Ks), Ks) of hico_plugin.rasterizer.geometry computes:
//
//   r = ((u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy, 1)      the ray through the centre of pixel (u, v)
//   D = d / -(n . r) where alpha > alpha_eps and -(n . r) > denom_eps alpha, else 0
//                                                          (PGSR's plane depth: where the ray meets n . X = -d)
//   P = D r;  a = P[u+1] - P[u-1];  b = P[v-1] - P[v+1];  c = a x b
//   n_d = c / |c| where the four neighbours have D > 0 and |c| > 1e-12 D^2, else 0; negated where n_d . P > 0;
//         0 on the 1-px border (so everywhere in an image narrower or lower than 3 px)
//
// normal [C,H,W,3], distance, alpha [C,H,W,1], Ks [C,3,3] and the results are contiguous. Each value is computed
// with the reference's operations in its order (no FMA: the library is built without -mfma, and C++ is ISO mode,
// so no contraction), so D matches it bitwise and n_d to rounding of the reductions torch orders its own way.
//
// Every pass is a loop over rows whose rows are independent (the backward's scatter of the cross product's
// gradient to the four neighbours is a gather from a scratch image), so results are bitwise independent of the
// thread count. The forward keeps D for the backward (each D is read by five pixels, and keeping it spares the
// backward a pass); everything else the backward needs is a few operations per pixel and is recomputed. A masked
// value is a select, never a product with a 0/1 mask, so a non-finite input outside the mask gives 0, as the
// reference's torch.where does.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

template <typename T>
struct Problem {
  const T *normal, *alpha;
  int64_t C, H, W;
  T alpha_eps, denom_eps;
  std::vector<T> rx, ry;  // [C,W] and [C,H]: the rays' x per column and y per row (z = 1)

  Problem(const T* normal_, const T* alpha_, const T* Ks, int64_t C_, int64_t H_, int64_t W_, double alpha_eps_,
          double denom_eps_)
      : normal(normal_), alpha(alpha_), C(C_), H(H_), W(W_), alpha_eps(T(alpha_eps_)), denom_eps(T(denom_eps_)),
        rx(C_ * W_), ry(C_ * H_) {
    for (int64_t c = 0; c < C; ++c) {
      const T* K = Ks + 9 * c;
      for (int64_t u = 0; u < W; ++u) rx[c * W + u] = (T(u) + T(0.5) - K[2]) / K[0];
      for (int64_t v = 0; v < H; ++v) ry[c * H + v] = (T(v) + T(0.5) - K[5]) / K[4];
    }
  }
  const T* Rx(int64_t row) const { return rx.data() + row / H * W; }  // row: camera * H + image row
  T Ry(int64_t row) const { return ry[row]; }
};

// -(n . r), summed in the order torch sums (n * r).sum(-1).
template <typename T>
inline T denominator(const T* n, T rx, T ry) {
  return -((n[0] * rx + n[1] * ry) + n[2]);
}

template <typename T>
inline bool plane_defined(T alpha, T den, const Problem<T>& p) {
  return (alpha > p.alpha_eps) & (den > p.denom_eps * alpha);
}

// Plane depths D of one row. The division is unconditional (by 1 where D is undefined, as in the reference's
// safe_divide), so the loop has no branch and vectorises.
template <typename T>
void plane_depth_row(const Problem<T>& p, const T* __restrict distance, int64_t row, T* __restrict depth) {
  const int64_t W = p.W;
  const T *n = p.normal + 3 * W * row, *alpha = p.alpha + W * row, *d = distance + W * row, *rx = p.Rx(row);
  const T ry = p.Ry(row);
  T* D = depth + W * row;
  for (int64_t j = 0; j < W; ++j) {
    const T den = denominator(n + 3 * j, rx[j], ry);
    const bool ok = plane_defined(alpha[j], den, p);
    const T q = d[j] / (ok ? den : T(1));
    D[j] = ok ? q : T(0);
  }
}

// The central-difference geometry of interior pixel j of a row: the difference vectors a, b, the length of their
// cross product c, its unit u (0 where n_d is undefined) and whether n_d is flipped to face the camera.
template <typename T>
struct Local {
  T a[3], b[3], u[3], len;
  bool valid, flip;
};

// up, mid, down: the depth rows i - 1, i, i + 1 and their rays' y; rx the rays' x.
template <typename T>
inline Local<T> local(const T* up, const T* mid, const T* down, const T* rx, T ry_up, T ry, T ry_down, int64_t j) {
  Local<T> g;
  const T l = mid[j - 1], r = mid[j + 1], t = up[j], s = down[j], D = mid[j];
  g.a[0] = r * rx[j + 1] - l * rx[j - 1];
  g.a[1] = r * ry - l * ry;
  g.a[2] = r - l;
  g.b[0] = t * rx[j] - s * rx[j];
  g.b[1] = t * ry_up - s * ry_down;
  g.b[2] = t - s;
  const T c[3] = {g.a[1] * g.b[2] - g.a[2] * g.b[1], g.a[2] * g.b[0] - g.a[0] * g.b[2],
                  g.a[0] * g.b[1] - g.a[1] * g.b[0]};
  g.len = std::sqrt((c[0] * c[0] + c[1] * c[1]) + c[2] * c[2]);
  // A neighbour without depth (D <= 0, or NaN) back-projects to the camera centre and would tilt the normal;
  // a vanishing cross product (relative to D^2: a and b scale with D) has no direction.
  g.valid = (((l > 0) & (r > 0)) & ((t > 0) & (s > 0))) & (g.len > T(1e-12) * (D * D));
  const T len = g.valid ? g.len : T(1);
  for (int k = 0; k < 3; ++k) {
    const T q = c[k] / len;
    g.u[k] = g.valid ? q : T(0);
  }
  g.flip = (g.u[0] * (D * rx[j]) + g.u[1] * (D * ry)) + g.u[2] * D > 0;
  return g;
}

// The rows around `row` for local(); only called for an interior image row.
template <typename T>
struct Around {
  const T *up, *mid, *down, *rx;
  T ry_up, ry, ry_down;
  Around(const Problem<T>& p, const T* depth, int64_t row)
      : up(depth + (row - 1) * p.W), mid(depth + row * p.W), down(depth + (row + 1) * p.W), rx(p.Rx(row)),
        ry_up(p.Ry(row - 1)), ry(p.Ry(row)), ry_down(p.Ry(row + 1)) {}
  Local<T> at(int64_t j) const { return local(up, mid, down, rx, ry_up, ry, ry_down, j); }
};

template <typename T>
bool interior_row(const Problem<T>& p, int64_t row) {
  const int64_t i = row % p.H;
  return i > 0 && i < p.H - 1;
}

template <typename T>
void forward(const Problem<T>& p, const T* distance, T* depth, T* out, int num_threads) {
  const int64_t rows = p.C * p.H, W = p.W;
#pragma omp parallel for num_threads(num_threads) schedule(static)
  for (int64_t row = 0; row < rows; ++row) plane_depth_row(p, distance, row, depth);

#pragma omp parallel for num_threads(num_threads) schedule(static)
  for (int64_t row = 0; row < rows; ++row) {
    T* o = out + 3 * W * row;
    std::fill(o, o + 3 * W, T(0));
    if (!interior_row(p, row)) continue;
    const Around<T> around(p, depth, row);
    for (int64_t j = 1; j < W - 1; ++j) {
      const Local<T> g = around.at(j);
      for (int k = 0; k < 3; ++k) o[3 * j + k] = g.flip ? -g.u[k] : g.u[k];
    }
  }
}

// Scratch row: dL/da (3 planes), dL/db (3 planes) of each interior pixel, 0 elsewhere, planar so that every
// access is unit-stride; each plane has a zero pixel at both ends, so the gather needs no bounds tests.
constexpr int64_t kPlanes = 6;

// Pass 1 of the backward, one row: dL/dc = (g - u (u . g)) / |c| (through u = c / |c|, with g the upstream
// gradient un-flipped), then dL/da = b x dL/dc and dL/db = dL/dc x a (c = a x b).
template <typename T>
void difference_grads_row(const Problem<T>& p, const T* depth, const T* __restrict grad_out, int64_t row,
                          T* __restrict scratch) {
  const int64_t W = p.W, pitch = W + 2;
  T* s = scratch + kPlanes * pitch * row + 1;
  std::fill(s - 1, s - 1 + kPlanes * pitch, T(0));
  if (!interior_row(p, row)) return;
  const Around<T> around(p, depth, row);
  const T* go = grad_out + 3 * W * row;
#pragma omp simd  // each pixel writes its own scratch entries only
  for (int64_t j = 1; j < W - 1; ++j) {
    const Local<T> g = around.at(j);
    T gu[3], gc[3];
    for (int k = 0; k < 3; ++k) gu[k] = g.flip ? -go[3 * j + k] : go[3 * j + k];
    const T dot = (g.u[0] * gu[0] + g.u[1] * gu[1]) + g.u[2] * gu[2];
    const T len = g.valid ? g.len : T(1);
    for (int k = 0; k < 3; ++k) gc[k] = (gu[k] - g.u[k] * dot) / len;
    const T grads[kPlanes] = {g.b[1] * gc[2] - g.b[2] * gc[1], g.b[2] * gc[0] - g.b[0] * gc[2],
                              g.b[0] * gc[1] - g.b[1] * gc[0], gc[1] * g.a[2] - gc[2] * g.a[1],
                              gc[2] * g.a[0] - gc[0] * g.a[2], gc[0] * g.a[1] - gc[1] * g.a[0]};
    for (int k = 0; k < kPlanes; ++k) s[k * pitch + j] = g.valid ? grads[k] : T(0);
  }
}

// Pass 2 of the backward, one row: each pixel gathers dL/dP from the difference vectors it enters (a of its
// left and right neighbours, b of the ones above and below), then dL/dD = dL/dP . r and, through
// D = d / -(n . r), dL/dd = dL/dD / den and dL/dn = dL/dD (D / den) r where D is defined, else 0.
template <typename T>
void plane_grads_row(const Problem<T>& p, const T* __restrict depth, const T* scratch, const T* zeros, int64_t row,
                     T* __restrict grad_normal, T* __restrict grad_distance) {
  const int64_t W = p.W, i = row % p.H, pitch = W + 2, stride = kPlanes * pitch;
  const T* mid = scratch + stride * row + 1;
  const T *up = (i > 0 ? mid - stride : zeros) + 3 * pitch, *down = (i < p.H - 1 ? mid + stride : zeros) + 3 * pitch;
  const T *n = p.normal + 3 * W * row, *alpha = p.alpha + W * row, *D = depth + W * row, *rx = p.Rx(row);
  const T ry = p.Ry(row);
  T *gn = grad_normal + 3 * W * row, *gd = grad_distance + W * row;
#pragma omp simd
  for (int64_t j = 0; j < W; ++j) {
    T gp[3];
    for (int k = 0; k < 3; ++k)
      gp[k] = (mid[k * pitch + j - 1] - mid[k * pitch + j + 1]) + (down[k * pitch + j] - up[k * pitch + j]);
    const T g_depth = (gp[0] * rx[j] + gp[1] * ry) + gp[2];
    const T den = denominator(n + 3 * j, rx[j], ry);
    const bool ok = plane_defined(alpha[j], den, p);
    const T den_or_1 = ok ? den : T(1);
    const T g_dist = g_depth / den_or_1, g_sum = g_depth * (D[j] / den_or_1);
    gd[j] = ok ? g_dist : T(0);
    gn[3 * j] = ok ? g_sum * rx[j] : T(0);
    gn[3 * j + 1] = ok ? g_sum * ry : T(0);
    gn[3 * j + 2] = ok ? g_sum : T(0);
  }
}

template <typename T>
void backward(const Problem<T>& p, const T* depth, const T* grad_out, T* scratch, T* grad_normal, T* grad_distance,
              int num_threads) {
  const int64_t rows = p.C * p.H;
  const std::vector<T> zeros(kPlanes * (p.W + 2), T(0));
#pragma omp parallel for num_threads(num_threads) schedule(static)
  for (int64_t row = 0; row < rows; ++row) difference_grads_row(p, depth, grad_out, row, scratch);

#pragma omp parallel for num_threads(num_threads) schedule(static)
  for (int64_t row = 0; row < rows; ++row)
    plane_grads_row(p, depth, scratch, zeros.data(), row, grad_normal, grad_distance);
}

}  // namespace

// The C API, for T = float (f32) and double (f64); every array contiguous, alpha_eps and denom_eps as in the
// header. forward: depth [C,H,W] (the plane depth D, for backward) and out [C,H,W,3] (n_d). backward: from the
// forward's depth and dL/dn_d grad_out [C,H,W,3], grad_normal [C,H,W,3] and grad_distance [C,H,W,1]; scratch is
// C * H * 6 * (W + 2) elements of any contents (allocated by the caller, so that running out of memory is an
// error there, not an exception through C).
#define HICO_DEPTH_NORMAL_API(T, SUFFIX)                                                                         \
  extern "C" void hico_depth_normal_forward_##SUFFIX(const T* normal, const T* distance, const T* alpha,         \
                                                     const T* Ks, int64_t C, int64_t H, int64_t W,               \
                                                     double alpha_eps, double denom_eps, T* depth, T* out,       \
                                                     int num_threads) {                                          \
    const Problem<T> p(normal, alpha, Ks, C, H, W, alpha_eps, denom_eps);                                        \
    forward(p, distance, depth, out, std::max(num_threads, 1));                                                  \
  }                                                                                                              \
  extern "C" void hico_depth_normal_backward_##SUFFIX(                                                           \
      const T* normal, const T* alpha, const T* Ks, const T* depth, const T* grad_out, int64_t C, int64_t H,     \
      int64_t W, double alpha_eps, double denom_eps, T* scratch, T* grad_normal, T* grad_distance,               \
      int num_threads) {                                                                                         \
    const Problem<T> p(normal, alpha, Ks, C, H, W, alpha_eps, denom_eps);                                        \
    backward(p, depth, grad_out, scratch, grad_normal, grad_distance, std::max(num_threads, 1));                 \
  }

HICO_DEPTH_NORMAL_API(float, f32)
HICO_DEPTH_NORMAL_API(double, f64)
