// Fused CPU EWA projection of 3-D Gaussians and its gradient, computing what the torch reference
// project_gaussians (hico_plugin.rasterizer.projection) and gaussian_normals (geometry.py) compute, per camera c
// and Gaussian n (3DGS, Kerbl et al. 2023; EWA splatting, Zwicker et al. 2001):
//
//   mu = W m + t                                     in float64, then rounded to T (city-scale coordinates)
//   zs = z where near < z < far, else 1              (keeps culled Gaussians' maths finite)
//   means2d = (fx x / zs + cx, fy y / zs + cy)
//   J = [[fx / zs, 0, -fx tx / zs^2], [0, fy / zs, -fy ty / zs^2]],  tx = zs clamp(x / zs, -lim_x_neg, lim_x_pos)
//                                                    (the frustum widened by FRUSTUM_MARGIN, as 3DGS / gsplat)
//   F = J W R(q) S;  Sigma2d = F F^T + blur I = [[a, b], [b, c]];  det = max(a c - b^2, det_min)
//   conic = (c / det, -b / det, a / det)
//   n = +-W R[:, argmin s] facing the camera (n . mu <= 0);  distance = |n . mu|        (optional)
//
// plus the drawn extents and int32 radii (no gradient) from the opacity-aware reach [N] the caller computes.
// Each value uses the reference's operations in its order (no FMA: the library is built without -mfma and C++ is
// ISO mode, so no contraction); where torch orders a reduction (norm, matmul) its own way, results agree to
// rounding. Masks are selects, so the gradients follow torch's where / clamp / abs rules: clamp_min passes the
// gradient where x >= min, torch.minimum / maximum split it half and half at an exact tie, |x| has gradient 0 at 0.
//
// The loops run over Gaussians, each over the cameras in order (the backward sums a Gaussian's gradient over
// cameras in that fixed order), so results are bitwise independent of the thread count. The backward recomputes
// the forward's intermediates from the inputs (a few dozen operations) instead of keeping them.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

struct Settings {
  int64_t C, N;
  double width, height, near, far, blur, margin, det_min, quat_eps;
};

// One camera: the viewmat's rotation in T (the covariance and the normals use it in the input dtype, as the
// reference) and in float64 with the translation (world_to_camera), and K's entries and the clamp limits.
template <typename T>
struct Camera {
  T W[9];
  double Wd[9], t[3];
  T fx, fy, cx, cy, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;

  Camera(const T* viewmat, const T* K, const Settings& s) {
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) W[3 * i + j] = viewmat[4 * i + j], Wd[3 * i + j] = double(viewmat[4 * i + j]);
      t[i] = double(viewmat[4 * i + 3]);
    }
    fx = K[0], fy = K[4], cx = K[2], cy = K[5];
    // The reference's (0.5 * width) / fx is a Python number over a tensor, which torch evaluates as
    // fx.reciprocal() * (0.5 * width).
    const T width = T(s.width), height = T(s.height), margin = T(s.margin);
    const T half_x = (T(1) / fx) * T(0.5 * s.width), half_y = (T(1) / fy) * T(0.5 * s.height);
    lim_x_pos = (width - cx) / fx + margin * half_x;
    lim_x_neg = cx / fx + margin * half_x;
    lim_y_pos = (height - cy) / fy + margin * half_y;
    lim_y_neg = cy / fy + margin * half_y;
  }
};

// The camera-independent part of one Gaussian: its normalised quaternion (the identity for a zero one), the
// rotation (row-major; its columns are the axes), the scales and the shortest axis.
template <typename T>
struct Shape {
  T q[4], norm, R[9], s[3];
  bool ok;
  int shortest;

  Shape(const T* quat, const T* scale, const Settings& set) {
    norm = std::sqrt(((quat[0] * quat[0] + quat[1] * quat[1]) + quat[2] * quat[2]) + quat[3] * quat[3]);
    ok = norm > T(set.quat_eps);
    const T divisor = ok ? norm : T(1);
    for (int k = 0; k < 4; ++k) q[k] = (ok ? quat[k] : T(k == 0)) / divisor;
    const T w = q[0], x = q[1], y = q[2], z = q[3];
    const T rows[9] = {1 - 2 * (y * y + z * z), 2 * (x * y - w * z),     2 * (x * z + w * y),
                       2 * (x * y + w * z),     1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                       2 * (x * z - w * y),     2 * (y * z + w * x),     1 - 2 * (x * x + y * y)};
    std::copy(rows, rows + 9, R);
    std::copy(scale, scale + 3, s);
    // torch.argmin: the first minimum, and a NaN counts as the minimum.
    shortest = 0;
    for (int k = 1; k < 3; ++k)
      if (!std::isnan(s[shortest]) && (std::isnan(s[k]) || s[k] < s[shortest])) shortest = k;
  }
};

// One Gaussian seen by one camera: everything the forward computes and the backward differentiates.
template <typename T>
struct View {
  T mu[3], zs, rx, ry, px, py, j00, j02, j11, j12, V[9], F[6], a, b, c, det_raw, det, u, v;
  bool in_depth;

  View(const Camera<T>& cam, const Shape<T>& g, const T* mean, const Settings& set) {
    for (int i = 0; i < 3; ++i)
      mu[i] = T(((cam.Wd[3 * i] * double(mean[0]) + cam.Wd[3 * i + 1] * double(mean[1])) +
                 cam.Wd[3 * i + 2] * double(mean[2])) + cam.t[i]);
    const T x = mu[0], y = mu[1], z = mu[2];
    in_depth = (z > T(set.near)) & (z < T(set.far));
    zs = in_depth ? z : T(1);
    u = cam.fx * x / zs + cam.cx;
    v = cam.fy * y / zs + cam.cy;
    rx = x / zs, ry = y / zs;
    const T qx = rx > cam.lim_x_pos ? cam.lim_x_pos : rx, qy = ry > cam.lim_y_pos ? cam.lim_y_pos : ry;
    px = qx < -cam.lim_x_neg ? -cam.lim_x_neg : qx, py = qy < -cam.lim_y_neg ? -cam.lim_y_neg : qy;
    const T zz = zs * zs;
    j00 = cam.fx / zs, j02 = -cam.fx * (zs * px) / zz;
    j11 = cam.fy / zs, j12 = -cam.fy * (zs * py) / zz;
    for (int i = 0; i < 3; ++i)
      for (int k = 0; k < 3; ++k)  // W (R S): the scales scale R's columns
        V[3 * i + k] = (cam.W[3 * i] * (g.R[k] * g.s[k]) + cam.W[3 * i + 1] * (g.R[3 + k] * g.s[k])) +
                       cam.W[3 * i + 2] * (g.R[6 + k] * g.s[k]);
    for (int k = 0; k < 3; ++k) {
      F[k] = j00 * V[k] + j02 * V[6 + k];
      F[3 + k] = j11 * V[3 + k] + j12 * V[6 + k];
    }
    a = ((F[0] * F[0] + F[1] * F[1]) + F[2] * F[2]) + T(set.blur);
    b = (F[0] * F[3] + F[1] * F[4]) + F[2] * F[5];
    c = ((F[3] * F[3] + F[4] * F[4]) + F[5] * F[5]) + T(set.blur);
    det_raw = a * c - b * b;
    det = det_raw < T(set.det_min) ? T(set.det_min) : det_raw;  // clamp_min: a NaN stays NaN
  }
};

// The facing normal and plane distance of a Gaussian in one camera; flip: the axis was negated.
template <typename T>
struct Normal {
  T n[3], dot;
  bool flip;

  Normal(const Camera<T>& cam, const Shape<T>& g, const T* mu) {
    const int k = g.shortest;
    for (int i = 0; i < 3; ++i)
      n[i] = (cam.W[3 * i] * g.R[k] + cam.W[3 * i + 1] * g.R[3 + k]) + cam.W[3 * i + 2] * g.R[6 + k];
    flip = (n[0] * mu[0] + n[1] * mu[1]) + n[2] * mu[2] > 0;
    for (int i = 0; i < 3; ++i) n[i] = flip ? -n[i] : n[i];
    dot = (n[0] * mu[0] + n[1] * mu[1]) + n[2] * mu[2];
  }
};

template <typename T>
void forward(const Settings& set, const std::vector<Camera<T>>& cams, const T* means, const T* quats,
             const T* scales, const T* reach, T* means_cam, T* means2d, T* conics, T* extents, int32_t* radii,
             T* normals, T* distances, int num_threads) {
  const T width = T(set.width), height = T(set.height), radius_max = T(1 << 30);
#pragma omp parallel for num_threads(num_threads) schedule(static)
  for (int64_t n = 0; n < set.N; ++n) {
    const Shape<T> g(quats + 4 * n, scales + 3 * n, set);
    for (int64_t c = 0; c < set.C; ++c) {
      const int64_t cn = c * set.N + n;
      const View<T> p(cams[c], g, means + 3 * n, set);
      std::copy(p.mu, p.mu + 3, means_cam + 3 * cn);
      means2d[2 * cn] = p.u, means2d[2 * cn + 1] = p.v;
      conics[3 * cn] = p.c / p.det, conics[3 * cn + 1] = -p.b / p.det, conics[3 * cn + 2] = p.a / p.det;
      // The drawn ellipse's bounding box: reach (the Mahalanobis radius where alpha falls to 1/255) sigma.
      const T ex = reach[n] * std::sqrt(p.a), ey = reach[n] * std::sqrt(p.c);
      const bool on_image = (p.u + ex > 0) & (p.u - ex < width) & (p.v + ey > 0) & (p.v - ey < height);
      const bool visible = p.in_depth & (reach[n] > 0) & on_image & std::isfinite(p.u) & std::isfinite(p.v);
      extents[2 * cn] = visible ? ex : T(0), extents[2 * cn + 1] = visible ? ey : T(0);
      const T radius = std::ceil(std::min(std::max(ex, ey), radius_max));
      radii[cn] = visible ? std::max(int32_t(radius), int32_t(1)) : 0;
      if (normals != nullptr) {
        const Normal<T> nrm(cams[c], g, p.mu);
        std::copy(nrm.n, nrm.n + 3, normals + 3 * cn);
        distances[cn] = std::abs(nrm.dot);
      }
    }
  }
}

// torch.minimum(x, hi)'s gradient share for x (half at a tie); maximum's is the same with the order reversed.
template <typename T>
inline T min_share(T x, T hi) {
  return x == hi ? T(0.5) : (x > hi ? T(0) : T(1));
}

// dL/dz_safe and dL/dx (or y) of one image axis: means2d's coordinate f x / zs + cc, and the Jacobian entries
// f / zs and -f t / zs^2 with t = zs clamp(x / zs, -lim_neg, lim_pos). g_uv: dL/d(means2d coordinate); g_jd,
// g_jt: dL/d(diagonal entry), dL/d(third column entry).
template <typename T>
inline void axis_grads(T f, T x, T zs, T r, T p, T lim_pos, T lim_neg, T g_uv, T g_jd, T g_jt, T& g_zs, T& g_x) {
  const T zz = zs * zs, t = zs * p;
  const T g_t = g_jt * (-f) / zz;
  const T g_ratio = g_t * zs * min_share(-lim_neg, r > lim_pos ? lim_pos : r) * min_share(r, lim_pos);
  g_x += (g_uv * f + g_ratio) / zs;
  g_zs += -(g_uv * f * x + g_ratio * x) / zz - g_jd * f / zz + g_jt * T(2) * f * t / (zz * zs) + g_t * p;
}

template <typename T>
void backward(const Settings& set, const std::vector<Camera<T>>& cams, const T* means, const T* quats,
              const T* scales, const T* g_means_cam, const T* g_means2d, const T* g_conics, const T* g_normals,
              const T* g_distances, T* grad_means, T* grad_quats, T* grad_scales, int num_threads) {
  const bool with_normals = g_normals != nullptr || g_distances != nullptr;
#pragma omp parallel for num_threads(num_threads) schedule(static)
  for (int64_t n = 0; n < set.N; ++n) {
    const Shape<T> g(quats + 4 * n, scales + 3 * n, set);
    double g_mean[3] = {0, 0, 0};
    T g_R[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}, g_s[3] = {0, 0, 0};
    for (int64_t c = 0; c < set.C; ++c) {
      const int64_t cn = c * set.N + n;
      const Camera<T>& cam = cams[c];
      const View<T> p(cam, g, means + 3 * n, set);
      T g_mu[3] = {0, 0, 0};
      if (g_means_cam != nullptr)
        for (int i = 0; i < 3; ++i) g_mu[i] = g_means_cam[3 * cn + i];
      const T g_u = g_means2d != nullptr ? g_means2d[2 * cn] : T(0);
      const T g_v = g_means2d != nullptr ? g_means2d[2 * cn + 1] : T(0);
      T g_j00 = 0, g_j02 = 0, g_j11 = 0, g_j12 = 0;
      if (g_conics != nullptr) {
        const T* gc = g_conics + 3 * cn;
        // conic = (c, -b, a) / det, det = max(a c - b^2, det_min)
        const T g_det = -((gc[0] * p.c - gc[1] * p.b) + gc[2] * p.a) / (p.det * p.det);
        const T g_raw = p.det_raw >= T(set.det_min) ? g_det : T(0);
        const T g_a = gc[2] / p.det + g_raw * p.c, g_c = gc[0] / p.det + g_raw * p.a;
        const T g_b = -gc[1] / p.det - T(2) * g_raw * p.b;
        // a = F0 . F0 + blur, b = F0 . F1, c = F1 . F1 + blur; F = J V; V = W M; M = R S
        T g_F[6], g_V[9];
        for (int k = 0; k < 3; ++k) {
          g_F[k] = T(2) * g_a * p.F[k] + g_b * p.F[3 + k];
          g_F[3 + k] = g_b * p.F[k] + T(2) * g_c * p.F[3 + k];
          g_j00 += g_F[k] * p.V[k], g_j02 += g_F[k] * p.V[6 + k];
          g_j11 += g_F[3 + k] * p.V[3 + k], g_j12 += g_F[3 + k] * p.V[6 + k];
          g_V[k] = p.j00 * g_F[k], g_V[3 + k] = p.j11 * g_F[3 + k];
          g_V[6 + k] = p.j02 * g_F[k] + p.j12 * g_F[3 + k];
        }
        for (int i = 0; i < 3; ++i)
          for (int k = 0; k < 3; ++k) {
            const T g_M = (cam.W[i] * g_V[k] + cam.W[3 + i] * g_V[3 + k]) + cam.W[6 + i] * g_V[6 + k];
            g_R[3 * i + k] += g_M * g.s[k];
            g_s[k] += g_M * g.R[3 * i + k];
          }
      }
      T g_zs = 0;
      axis_grads(cam.fx, p.mu[0], p.zs, p.rx, p.px, cam.lim_x_pos, cam.lim_x_neg, g_u, g_j00, g_j02, g_zs, g_mu[0]);
      axis_grads(cam.fy, p.mu[1], p.zs, p.ry, p.py, cam.lim_y_pos, cam.lim_y_neg, g_v, g_j11, g_j12, g_zs, g_mu[1]);
      g_mu[2] += p.in_depth ? g_zs : T(0);
      if (with_normals) {
        const Normal<T> nrm(cam, g, p.mu);
        T g_n[3] = {0, 0, 0};
        if (g_normals != nullptr)
          for (int i = 0; i < 3; ++i) g_n[i] = g_normals[3 * cn + i];
        if (g_distances != nullptr) {
          const T g_dot = g_distances[cn] * T((nrm.dot > 0) - (nrm.dot < 0));
          for (int i = 0; i < 3; ++i) g_n[i] += g_dot * p.mu[i], g_mu[i] += g_dot * nrm.n[i];
        }
        const int k = g.shortest;
        for (int j = 0; j < 3; ++j) {
          const T g_axis = (cam.W[j] * g_n[0] + cam.W[3 + j] * g_n[1]) + cam.W[6 + j] * g_n[2];
          g_R[3 * j + k] += nrm.flip ? -g_axis : g_axis;
        }
      }
      for (int j = 0; j < 3; ++j)
        g_mean[j] += (cam.Wd[j] * double(g_mu[0]) + cam.Wd[3 + j] * double(g_mu[1])) + cam.Wd[6 + j] * double(g_mu[2]);
    }
    for (int j = 0; j < 3; ++j) grad_means[3 * n + j] = T(g_mean[j]), grad_scales[3 * n + j] = g_s[j];
    // Through Shape's rotation of the normalised q = quat / |quat|, then dL/dquat = (g - q (q . g)) / |quat|; zero
    // for a quaternion read as the identity.
    const T w = g.q[0], x = g.q[1], y = g.q[2], z = g.q[3], x2 = 2 * x, y2 = 2 * y, z2 = 2 * z;
    const T* r = g_R;
    const T g_q[4] = {2 * (((-z * r[1] + y * r[2]) + (z * r[3] - x * r[5])) + (-y * r[6] + x * r[7])),
                      2 * (((y * r[1] + z * r[2]) + (y * r[3] - x2 * r[4])) +
                           ((-w * r[5] + z * r[6]) + (w * r[7] - x2 * r[8]))),
                      2 * (((-y2 * r[0] + x * r[1]) + (w * r[2] + x * r[3])) +
                           ((z * r[5] - w * r[6]) + (z * r[7] - y2 * r[8]))),
                      2 * (((-z2 * r[0] - w * r[1]) + (x * r[2] + w * r[3])) +
                           ((-z2 * r[4] + y * r[5]) + (x * r[6] + y * r[7])))};
    const T along = ((w * g_q[0] + x * g_q[1]) + y * g_q[2]) + z * g_q[3];
    for (int k = 0; k < 4; ++k) grad_quats[4 * n + k] = g.ok ? (g_q[k] - g.q[k] * along) / g.norm : T(0);
  }
}

// Below this many (Gaussian, camera) pairs (~0.2 ms of work) one thread does it all: waking a team costs
// microseconds on idle cores and a scheduler time slice on busy ones.
constexpr int64_t kMinParallelPairs = 2048;

int team_size(const Settings& set, int num_threads) {
  return set.N * set.C < kMinParallelPairs ? 1 : std::max(num_threads, 1);
}

template <typename T>
std::vector<Camera<T>> cameras(const T* viewmats, const T* Ks, const Settings& set) {
  std::vector<Camera<T>> cams;
  for (int64_t c = 0; c < set.C; ++c) cams.emplace_back(viewmats + 16 * c, Ks + 9 * c, set);
  return cams;
}

}  // namespace

// The C API, for T = float (f32) and double (f64); every array contiguous. Inputs: means [N,3], quats [N,4],
// scales [N,3], viewmats [C,4,4] (world->camera), Ks [C,3,3]; the forward also takes reach [N]. Settings: the
// image size, near / far planes, COV2D_BLUR, FRUSTUM_MARGIN, the determinant's floor and the zero-quaternion
// threshold of the reference. forward writes means_cam, conics [C,N,3], means2d, extents [C,N,2], radii [C,N]
// int32, and normals [C,N,3] and distances [C,N] unless normals is null. backward takes the cotangents of
// means_cam, means2d, conics, normals and distances (each null where it is zero: its terms are skipped) and writes
// grad_means [N,3], grad_quats [N,4], grad_scales [N,3].
#define HICO_PROJECTION_API(T, SUFFIX)                                                                            \
  extern "C" void hico_projection_forward_##SUFFIX(                                                               \
      const T* means, const T* quats, const T* scales, const T* reach, const T* viewmats, const T* Ks, int64_t C, \
      int64_t N, double width, double height, double near, double far, double blur, double margin,                \
      double det_min, double quat_eps, T* means_cam, T* means2d, T* conics, T* extents, int32_t* radii,           \
      T* normals, T* distances, int num_threads) {                                                                \
    const Settings set{C, N, width, height, near, far, blur, margin, det_min, quat_eps};                          \
    forward(set, cameras(viewmats, Ks, set), means, quats, scales, reach, means_cam, means2d, conics, extents,    \
            radii, normals, distances, team_size(set, num_threads));                                              \
  }                                                                                                               \
  extern "C" void hico_projection_backward_##SUFFIX(                                                              \
      const T* means, const T* quats, const T* scales, const T* viewmats, const T* Ks, int64_t C, int64_t N,      \
      double width, double height, double near, double far, double blur, double margin, double det_min,           \
      double quat_eps, const T* g_means_cam, const T* g_means2d, const T* g_conics, const T* g_normals,           \
      const T* g_distances, T* grad_means, T* grad_quats, T* grad_scales, int num_threads) {                      \
    const Settings set{C, N, width, height, near, far, blur, margin, det_min, quat_eps};                          \
    backward(set, cameras(viewmats, Ks, set), means, quats, scales, g_means_cam, g_means2d, g_conics, g_normals,  \
             g_distances, grad_means, grad_quats, grad_scales, team_size(set, num_threads));                      \
  }

HICO_PROJECTION_API(float, f32)
HICO_PROJECTION_API(double, f64)
