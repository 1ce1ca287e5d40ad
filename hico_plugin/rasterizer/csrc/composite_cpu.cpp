// Fused CPU compositor: front-to-back alpha blending of binned Gaussians, row by row over the pixels
// of each row's bounding box, with per-pixel early termination, and its analytic backward (3DGS order:
// back to front, recovering each transmittance by division). Same contract and cut-offs as composite.py's vectorised torch version:
//
//   means2d [G,2], conics [G,3] (a, b, c of [[a,b],[b,c]]), opacities [G], features [G,D],
//   gaussian_ids [I] int64 sorted by (tile, depth), tile_offsets [T+1] int64
//   -> features [T,P,D], alpha [T,P] (or, given width and height, the images [C,H,W,D], [C,H,W]),
//      final transmittance [T,P], rows drawn per pixel [T,P] int32, and the Gaussians' records
//      [G, 10 + D] (splat_records), which the backward takes with the transmittance and draw counts
//
// A pair is skipped when sigma < 0 or alpha < alpha_min; alpha is clamped at alpha_max; a pixel stops
// at the first pair whose transmittance after it would be <= t_min (that pair is not drawn).
// Tiles are handed out dynamically (sky tiles are empty, facade tiles hold thousands of rows) to
// at::parallel_for's threads; every output is still independent of the thread count and schedule.

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cstring>
#include <cmath>
#include <memory>
#include <type_traits>
#include <vector>

#include "binning_cpu.h"
#include "expf_cephes.h"

namespace {

template <typename scalar_t>
struct Splats {
  // Raw views of the compositor's inputs (see the contract at the top).
  const scalar_t *means2d, *conics, *opacities, *features;
  const int64_t *ids, *offsets;
  int64_t num_tiles, dim;

  Splats(const at::Tensor& means2d_, const at::Tensor& conics_, const at::Tensor& opacities_,
         const at::Tensor& features_, const at::Tensor& gaussian_ids, const at::Tensor& tile_offsets)
      : means2d(means2d_.data_ptr<scalar_t>()), conics(conics_.data_ptr<scalar_t>()),
        opacities(opacities_.data_ptr<scalar_t>()), features(features_.data_ptr<scalar_t>()),
        ids(gaussian_ids.data_ptr<int64_t>()), offsets(tile_offsets.data_ptr<int64_t>()),
        num_tiles(tile_offsets.size(0) - 1), dim(features_.size(1)) {}
};

struct Span {
  int64_t x0, x1, y0, y1;  // local pixel columns [x0, x1) and rows [y0, y1) of a tile
};

// Everything a tile reads of a Gaussian, in one record per Gaussian, written once per forward and kept
// for the backward: [G, kRecord + D] = cut = log(opacity / alpha_min) (a hair above the exact cut, so
// rounding never rejects a pair the alpha test would keep; -1 where the opacity is not positive), the
// half-sizes hx, hy of the bounding box of its ellipse sigma <= cut (sqrt(2 cut C^-1_xx),
// sqrt(2 cut C^-1_yy) for the conic C; -1 where the conic is not positive definite or anything is not
// finite: every pixel of the tile is tested), q = exp(-c) (FalloffSteps), the mean, conic, opacity and
// features. A tile gathers its rows from one place in memory instead of four arrays, and the backward
// reads the log, square roots and exp instead of recomputing them for every (tile, row).
constexpr int64_t kRecord = 10;  // then the D features

template <typename scalar_t>
at::Tensor splat_records(const Splats<scalar_t>& s, int64_t num_gaussians, scalar_t alpha_min,
                         const at::TensorOptions& options) {
  const int64_t width = kRecord + s.dim;
  auto records = at::empty({num_gaussians, width}, options);
  scalar_t* out = records.data_ptr<scalar_t>();
  at::parallel_for(0, num_gaussians, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t g = begin; g < end; ++g) {
      const scalar_t op = s.opacities[g];
      const scalar_t a = s.conics[3 * g], b = s.conics[3 * g + 1], c = s.conics[3 * g + 2];
      const scalar_t cut = op > 0 ? std::log(op / alpha_min) + scalar_t(1e-3) : scalar_t(-1);
      const scalar_t det = a * c - b * b;
      const scalar_t hx = std::sqrt(2 * cut * c / det), hy = std::sqrt(2 * cut * a / det);
      const bool bounded = det > 0 && a > 0 && std::isfinite(hx) && std::isfinite(hy) &&
                           std::isfinite(s.means2d[2 * g]) && std::isfinite(s.means2d[2 * g + 1]);
      scalar_t* o = out + g * width;
      o[0] = cut;
      o[1] = bounded ? hx : scalar_t(-1);
      o[2] = bounded ? hy : scalar_t(-1);
      o[3] = scalar_t(std::exp(-double(c)));
      o[4] = s.means2d[2 * g]; o[5] = s.means2d[2 * g + 1]; o[6] = a; o[7] = b; o[8] = c; o[9] = op;
      for (int64_t d = 0; d < s.dim; ++d) o[kRecord + d] = s.features[g * s.dim + d];
    }
  });
  return records;
}

template <typename scalar_t>
struct TileRows {
  // The first rows of one tile gathered into contiguous arrays: x, y, a, b, c, opacity, features, and
  // from splat_records: cut (a pair with sigma > cut has alpha < alpha_min, so most pairs of a tile --
  // pixels outside the row's ellipse -- are rejected without an exp), hx, hy and q.
  std::vector<scalar_t> mx, my, ca, cb, cc, op, cut, hx, hy, q, feat;

  TileRows(const Splats<scalar_t>& s, const scalar_t* records, int64_t tile, int64_t count)
      : mx(count), my(count), ca(count), cb(count), cc(count), op(count), cut(count), hx(count),
        hy(count), q(count), feat(count * s.dim) {
    for (int64_t r = 0; r < count; ++r) {
      const int64_t g = s.ids[s.offsets[tile] + r];
      const scalar_t* record = records + g * (kRecord + s.dim);
      cut[r] = record[0]; hx[r] = record[1]; hy[r] = record[2]; q[r] = record[3];
      mx[r] = record[4]; my[r] = record[5];
      ca[r] = record[6]; cb[r] = record[7]; cc[r] = record[8]; op[r] = record[9];
      for (int64_t d = 0; d < s.dim; ++d) feat[r * s.dim + d] = record[kRecord + d];
    }
  }

  // Whether row r reaches pixel (px, py) above the alpha cut-off; sets its offsets and sigma.
  bool reaches(int64_t r, scalar_t px, scalar_t py, scalar_t& dx, scalar_t& dy, scalar_t& sigma) const {
    dx = px - mx[r];
    dy = py - my[r];
    sigma = scalar_t(0.5) * (ca[r] * dx * dx + cc[r] * dy * dy) + cb[r] * dx * dy;
    return sigma >= 0 && sigma <= cut[r];  // (NaN fails both)
  }

  // The local pixels [x0, x1) x [y0, y1) of a tile that row r can reach: the bounding box of its
  // ellipse (splat_records), widened by a pixel so rounding never drops a pixel the exact test above
  // keeps; the whole tile where the box is unbounded (the test above decides every pixel).
  // (ox, oy): the tile's first pixel column and row in the image.
  Span span(int64_t r, int64_t ox, int64_t oy, int64_t tile_size) const {
    if (!(cut[r] >= 0)) return Span{0, 0, 0, 0};  // sigma >= 0 > cut: reaches no pixel
    if (hx[r] < 0) return Span{0, tile_size, 0, tile_size};
    // Pixel i of the tile has its centre at o + i + 0.5: |o + i + 0.5 - m| <= h.
    auto range = [tile_size](scalar_t m, scalar_t h, int64_t o, int64_t& lo, int64_t& hi) {
      const scalar_t first = std::ceil(m - h - scalar_t(0.5) - scalar_t(o)) - 1;
      const scalar_t last = std::floor(m + h - scalar_t(0.5) - scalar_t(o)) + 1;
      const scalar_t size = scalar_t(tile_size);
      lo = int64_t(std::min(std::max(first, scalar_t(0)), size));
      hi = int64_t(std::min(std::max(last + 1, scalar_t(0)), size));
    };
    Span out;
    range(mx[r], hx[r], ox, out.x0, out.x1);
    range(my[r], hy[r], oy, out.y0, out.y1);
    return out;
  }
};

struct Grid {
  int64_t tiles_x, tiles_per_cam, tile_size;
  // Image column and row of the first pixel of tile t.
  void origin(int64_t t, int64_t& ox, int64_t& oy) const {
    const int64_t in_cam = t % tiles_per_cam;
    ox = (in_cam % tiles_x) * tile_size;
    oy = (in_cam / tiles_x) * tile_size;
  }
};

// Where features and alpha are stored: by tile, [T,P,·] (width 0), or as the cameras' images
// [C,H,W,·] cropped to width x height, so the renderer needs no tile-to-image copy (nor, backward,
// the zero-filled uncropped image and the copy back into tiles). Transmittance and draw counts stay
// by tile: only the backward reads them.
struct Layout {
  int64_t width, height;

  // Flat pixel index of tile t's local pixel p, or -1 for a pixel past the image's edge.
  int64_t index(const Grid& grid, int64_t t, int64_t p) const {
    const int64_t ts = grid.tile_size;
    if (width == 0) return t * ts * ts + p;
    int64_t ox, oy;
    grid.origin(t, ox, oy);
    const int64_t x = ox + p % ts, y = oy + p / ts;
    if (x >= width || y >= height) return -1;
    return ((t / grid.tiles_per_cam) * height + y) * width + x;
  }

  // [T,P,D] by tile -> this layout (the float64 loops write by tile).
  at::Tensor from_tiles(const at::Tensor& tiled, const Grid& grid) const {
    if (width == 0) return tiled;
    const int64_t ts = grid.tile_size, tiles_y = grid.tiles_per_cam / grid.tiles_x;
    const int64_t cams = tiled.size(0) / grid.tiles_per_cam, dim = tiled.size(2);
    return tiled.view({cams, tiles_y, grid.tiles_x, ts, ts, dim}).permute({0, 1, 3, 2, 4, 5})
        .reshape({cams, tiles_y * ts, grid.tiles_x * ts, dim}).narrow(1, 0, height).narrow(2, 0, width)
        .contiguous();
  }

  // This layout -> [T,P,D] by tile, zero past the image's edge (the inverse of from_tiles).
  at::Tensor to_tiles(const at::Tensor& stored, const Grid& grid, int64_t num_tiles) const {
    if (width == 0) return stored;
    const int64_t ts = grid.tile_size, tiles_y = grid.tiles_per_cam / grid.tiles_x;
    const int64_t cams = num_tiles / grid.tiles_per_cam, dim = stored.size(3);
    auto full = at::zeros({cams, tiles_y * ts, grid.tiles_x * ts, dim}, stored.options());
    full.narrow(1, 0, height).narrow(2, 0, width).copy_(stored);
    return full.view({cams, tiles_y, ts, grid.tiles_x, ts, dim}).permute({0, 1, 3, 2, 4, 5})
        .reshape({num_tiles, ts * ts, dim}).contiguous();
  }
};

// Runs fn(tile) over all tiles, one parallel_for worker per thread taking the next tile as it frees up.
template <typename Fn>
void for_each_tile(int64_t num_tiles, Fn fn) {
  std::atomic<int64_t> next{0};
  const int64_t threads = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), num_tiles));
  at::parallel_for(0, threads, 1, [&](int64_t, int64_t) {
    for (int64_t t = next++; t < num_tiles; t = next++) fn(t);
  });
}

// Both passes go row by row (Gaussian-major) and visit only the pixels of each row's bounding box,
// keeping every pixel's running state in small per-tile arrays: a typical row covers a few dozen of
// a tile's 256 pixels, so most (pixel, row) pairs are never looked at. Each pixel still sees its rows
// in the same order with the same arithmetic as a pixel-by-pixel loop, and each row's gradient sums
// its pixels in raster order, so the results do not depend on the loop order.
template <typename scalar_t>
void forward_impl(const Splats<scalar_t>& s, const scalar_t* records, const Grid grid, scalar_t a_min,
                  scalar_t a_max, scalar_t t_min, at::Tensor& out, at::Tensor& acc, at::Tensor& final_t,
                  at::Tensor& n_drawn) {
  const int64_t ts = grid.tile_size, pixels = ts * ts, dim = s.dim;
  scalar_t* out_p = out.data_ptr<scalar_t>();
  scalar_t* acc_p = acc.data_ptr<scalar_t>();
  scalar_t* t_p = final_t.data_ptr<scalar_t>();
  int32_t* n_p = n_drawn.data_ptr<int32_t>();

  for_each_tile(s.num_tiles, [&](int64_t t) {
    const int64_t count = s.offsets[t + 1] - s.offsets[t];
    const TileRows<scalar_t> rows(s, records, t, count);
    scalar_t* color = out_p + t * pixels * dim;
    scalar_t* weight_sum = acc_p + t * pixels;
    scalar_t* trans = t_p + t * pixels;
    int32_t* drawn = n_p + t * pixels;
    std::fill(color, color + pixels * dim, scalar_t(0));
    std::fill(weight_sum, weight_sum + pixels, scalar_t(0));
    std::fill(trans, trans + pixels, scalar_t(1));
    std::fill(drawn, drawn + pixels, 0);
    std::vector<uint8_t> done(pixels, 0);  // the pixel met a row that would leave T <= t_min
    int64_t active = pixels, ox, oy;
    grid.origin(t, ox, oy);
    for (int64_t r = 0; r < count && active > 0; ++r) {
      const Span box = rows.span(r, ox, oy, ts);
      const scalar_t* fr = &rows.feat[r * dim];
      for (int64_t ly = box.y0; ly < box.y1; ++ly) {
        const scalar_t py = scalar_t(oy + ly) + scalar_t(0.5);
        for (int64_t lx = box.x0; lx < box.x1; ++lx) {
          const int64_t p = ly * ts + lx;
          if (done[p]) continue;
          scalar_t dx, dy, sigma;
          if (!rows.reaches(r, scalar_t(ox + lx) + scalar_t(0.5), py, dx, dy, sigma)) continue;
          const scalar_t alpha = std::min(a_max, rows.op[r] * std::exp(-sigma));
          if (!(alpha >= a_min)) continue;
          const scalar_t next = trans[p] * (1 - alpha);
          if (next <= t_min) {
            done[p] = 1;
            --active;
            continue;
          }
          const scalar_t w = alpha * trans[p];
          for (int64_t d = 0; d < dim; ++d) color[p * dim + d] += w * fr[d];
          weight_sum[p] += w;
          trans[p] = next;
          drawn[p] = int32_t(r + 1);
        }
      }
    }
  });
}

// The backward's last pass: each tile's per-intersection row gradients (rows below the tile's deepest
// drawn row) added to their Gaussians' in intersection order, whichever thread computed them. Each
// thread adds the Gaussians of its own id range (every thread reads the ids, each adds a share of the
// rows), so every Gaussian's sum runs in the same order whatever the thread count. g_all needs no
// zeroing beforehand: each thread zeroes its own range first (one pass in parallel instead of a serial
// memset of the whole [G, 6 + D]).
template <typename scalar_t>
void add_row_grads(const Splats<scalar_t>& s, const std::vector<int32_t>& deepest_of,
                   const scalar_t* row_grads, int64_t stride, scalar_t* g_all, int64_t num_gaussians) {
  const int64_t parts = std::max<int64_t>(1, at::get_num_threads());
  at::parallel_for(0, parts, 1, [&](int64_t p0, int64_t p1) {
    for (int64_t part = p0; part < p1; ++part) {
      const int64_t lo = num_gaussians * part / parts, hi = num_gaussians * (part + 1) / parts;
      std::fill(g_all + lo * stride, g_all + hi * stride, scalar_t(0));
      for (int64_t t = 0; t < s.num_tiles; ++t) {
        for (int64_t i = s.offsets[t]; i < s.offsets[t] + deepest_of[t]; ++i) {
          const int64_t g = s.ids[i];
          if (g < lo || g >= hi) continue;
          scalar_t* dst = g_all + g * stride;
          const scalar_t* src = &row_grads[i * stride];
          for (int64_t k = 0; k < stride; ++k) dst[k] += src[k];
        }
      }
    }
  });
}

template <typename scalar_t>
void backward_impl(const Splats<scalar_t>& s, const scalar_t* records, const Grid grid, scalar_t a_min,
                   scalar_t a_max, const at::Tensor& final_t, const at::Tensor& n_drawn,
                   const at::Tensor& grad_out, const at::Tensor& grad_acc, at::Tensor& grads) {
  // grads [G, 6 + D]: d means2d (2), d conics (3), d opacity (1), d features (D). Each tile writes
  // its rows' gradients (summed over its pixels) into its own slice of a per-intersection buffer;
  // one serial pass then adds them up by Gaussian in intersection order, so the result does not
  // depend on which thread took which tile (bitwise reproducible backward, any thread count).
  const int64_t ts = grid.tile_size, pixels = ts * ts, dim = s.dim, stride = 6 + dim;
  std::vector<scalar_t> row_grads(s.offsets[s.num_tiles] * stride, scalar_t(0));
  std::vector<int32_t> deepest_of(s.num_tiles, 0);
  const scalar_t* t_p = final_t.data_ptr<scalar_t>();
  const int32_t* n_p = n_drawn.data_ptr<int32_t>();
  const scalar_t* go = grad_out.data_ptr<scalar_t>();
  const scalar_t* ga = grad_acc.data_ptr<scalar_t>();
  scalar_t* g_all = grads.data_ptr<scalar_t>();

  for_each_tile(s.num_tiles, [&](int64_t t) {
    const int32_t* drawn = n_p + t * pixels;
    const int32_t deepest = *std::max_element(drawn, drawn + pixels);
    deepest_of[t] = deepest;
    if (deepest == 0) return;
    const TileRows<scalar_t> rows(s, records, t, deepest);
    scalar_t* g_rows = &row_grads[s.offsets[t] * stride];  // this tile's rows, summed over its pixels
    // Per pixel: the transmittance in front of the current row (recovered back to front by division)
    // and the colour (and alpha) composited behind it.
    std::vector<scalar_t> trans(t_p + t * pixels, t_p + (t + 1) * pixels);
    std::vector<scalar_t> behind(pixels * (dim + 1), scalar_t(0));
    int64_t ox, oy;
    grid.origin(t, ox, oy);
    for (int64_t r = deepest - 1; r >= 0; --r) {
      const Span box = rows.span(r, ox, oy, ts);
      scalar_t* g = &g_rows[r * stride];
      const scalar_t* fr = &rows.feat[r * dim];
      for (int64_t ly = box.y0; ly < box.y1; ++ly) {
        const scalar_t py = scalar_t(oy + ly) + scalar_t(0.5);
        for (int64_t lx = box.x0; lx < box.x1; ++lx) {
          const int64_t p = ly * ts + lx;
          if (drawn[p] <= r) continue;  // row r lies beyond where this pixel stopped
          scalar_t dx, dy, sigma;
          if (!rows.reaches(r, scalar_t(ox + lx) + scalar_t(0.5), py, dx, dy, sigma)) continue;
          const scalar_t falloff = std::exp(-sigma);
          const scalar_t raw = rows.op[r] * falloff;
          const scalar_t alpha = std::min(a_max, raw);
          if (!(alpha >= a_min)) continue;
          const int64_t pix = t * pixels + p;
          trans[p] /= (1 - alpha);  // transmittance in front of row r
          const scalar_t w = alpha * trans[p];
          const scalar_t* g_color = &go[pix * dim];
          scalar_t* bh = &behind[p * (dim + 1)];
          // d out / d alpha_r = T_r (f_r - behind_r) per channel; the alpha channel has f = 1.
          scalar_t g_a = ga[pix] * (1 - bh[dim]);
          for (int64_t d = 0; d < dim; ++d) {
            g[6 + d] += w * g_color[d];
            g_a += g_color[d] * (fr[d] - bh[d]);
            bh[d] = alpha * fr[d] + (1 - alpha) * bh[d];
          }
          bh[dim] = alpha + (1 - alpha) * bh[dim];
          g_a *= trans[p];
          if (raw > a_max) continue;  // clamped: no gradient to opacity or shape
          g[5] += g_a * falloff;
          const scalar_t g_sigma = -g_a * alpha;
          g[0] -= g_sigma * (rows.ca[r] * dx + rows.cb[r] * dy);
          g[1] -= g_sigma * (rows.cc[r] * dy + rows.cb[r] * dx);
          g[2] += g_sigma * scalar_t(0.5) * dx * dx;
          g[3] += g_sigma * dx * dy;
          g[4] += g_sigma * scalar_t(0.5) * dy * dy;
        }
      }
    }
  });
  add_row_grads(s, deepest_of, row_grads.data(), stride, g_all, grads.size(0));
}

// ----- float32: a vector of pixels at a time ---------------------------------------------------------
// float32, the production type, runs kLanes neighbouring pixels of a row's bounding box at once with
// GCC/Clang vector extensions: 8 when the build targets AVX2 (fused.py adds -mavx2 where torch reports
// that the CPU has it), else 4, SSE2's width, which every x86-64 CPU has. Per-lane masks replace the
// scalar loops' branches, whose outcome at an ellipse's rim is a coin flip the CPU mispredicts. A
// masked-out lane's update multiplies by a zero weight (or blends with a zero alpha) only where the row's
// features and the tile's gradients are all finite, else it is a select (an inf feature times 0 is NaN):
// either way the lane's state is left bit for bit as it was.
// exp(-sigma) is Cephes' expf polynomial, within a few ulp of libm's over the sigma <= cut range that
// can pass the alpha test, or, in most boxes, the same exp stepped from scanline to scanline
// (FalloffSteps below). Per-pixel state lives in planar per-tile arrays padded by one vector, so a
// vector that runs past the box reads and rewrites pixels it leaves unchanged. The arithmetic is
// otherwise the scalar loops' own, operation for operation; float64 keeps those loops (gradcheck
// sees libm's exp).

#if defined(__AVX2__)
constexpr int64_t kLanes = 8;
#else
constexpr int64_t kLanes = 4;
#endif
typedef float fvec __attribute__((vector_size(4 * kLanes)));
typedef int32_t ivec __attribute__((vector_size(4 * kLanes)));

inline fvec splat(float x) { return fvec{} + x; }
inline ivec splat_i(int32_t x) { return ivec{} + x; }
inline fvec vload(const float* p) { fvec v; std::memcpy(&v, p, sizeof v); return v; }
inline ivec vload(const int32_t* p) { ivec v; std::memcpy(&v, p, sizeof v); return v; }
inline void vstore(float* p, fvec v) { std::memcpy(p, &v, sizeof v); }
inline void vstore(int32_t* p, ivec v) { std::memcpy(p, &v, sizeof v); }
inline bool any(ivec m) {
  int64_t q[kLanes / 2];
  std::memcpy(q, &m, sizeof q);
  int64_t all = 0;
  for (int64_t i = 0; i < kLanes / 2; ++i) all |= q[i];
  return all != 0;
}
inline float hsum(fvec v) {
  float total = 0;
  for (int64_t i = 0; i < kLanes; ++i) total += v[i];
  return total;
}
inline int32_t count(ivec m) {  // lanes set (a set lane is -1)
  int32_t total = 0;
  for (int64_t i = 0; i < kLanes; ++i) total -= m[i];
  return total;
}
inline fvec select(ivec m, fvec a, fvec b) { return m ? a : b; }
inline ivec lane_numbers() {  // 0, 1, ..., kLanes - 1
  ivec lanes;
  for (int64_t i = 0; i < kLanes; ++i) lanes[i] = int32_t(i);
  return lanes;
}

// e^x for -87 <= x <= top (Cephes expf, expf_cephes.h; n = floor(x / ln 2 + 1/2), 2^n from the exponent
// bits). Lanes below -87 or NaN give e^-87, lanes above top e^top; their results are masked out by the callers.
inline fvec vexp(fvec x, float top = 0.f) {
  x = select(x > splat(-87.f), x, splat(-87.f));
  x = select(x < splat(top), x, splat(top));
  const fvec t = x * splat(1.44269504088896341f) + splat(0.5f);
  ivec n = __builtin_convertvector(t, ivec);  // toward zero; one less where that rounded up
  n = __builtin_convertvector(n, fvec) > t ? n - 1 : n;
  const fvec nf = __builtin_convertvector(n, fvec);
  const fvec p = hico::expf_poly(hico::expf_reduce(x, nf));
  const ivec bits = (n + 127) << 23;
  fvec scale;
  std::memcpy(&scale, &bits, sizeof scale);
  return p * scale;
}

// Row r's falloff exp(-sigma) over its box, one scanline after another. Along a pixel column,
// sigma = 0.5 a dx^2 + b dx dy + 0.5 c dy^2 has the constant second difference c in dy, so
//   e(y + 1) = e(y) ratio(y),   ratio(y + 1) = ratio(y) q,   ratio(y0) = exp(-(c (dy0 + 1/2) + b dx)),   q = exp(-c),
// and two products replace the exp of every scanline after the box's first (the exp took about a third
// of the forward's time on a 540x960 capture, whose boxes span about a dozen scanlines). Only where every
// factor stays in float32's normal range and the products stay close to the exp: a positive-definite
// conic (sigma >= 0 and convex, so its largest value over the box is at a corner) with sigma < 60 at
// the box's corners, a box of 3 to 16 scanlines and at most kStepColumns vectors per scanline. The
// products' rounding adds to that of the float32 sigma: measured against exp of the exact sigma over the
// 31M drawn pairs of a 540x960 view, the stepped falloff is off by 3e-7 (median) and 5e-6 (99.9 %),
// the exp of the float32 sigma by 7e-8 and 3e-6; the largest error of both, 1.1e-4, is the float32
// sigma's own (a needle's large terms cancelling).
constexpr int64_t kStepColumns = 16 / kLanes;

struct FalloffSteps {
  bool on = false;
  fvec e[kStepColumns], ratio[kStepColumns], q;

  FalloffSteps(const TileRows<float>& rows, int64_t r, const Span& box, int64_t ox, int64_t oy) {
    const float a = rows.ca[r], b = rows.cb[r], c = rows.cc[r];
    const int64_t height = box.y1 - box.y0;
    if (!(a > 0 && a * c - b * b > 0) || height < 3 || height > 16 ||
        box.x1 - box.x0 > kStepColumns * kLanes) return;
    float top = 0;
    for (const int64_t y : {box.y0, box.y1 - 1}) {
      for (const int64_t x : {box.x0, box.x1 - 1}) {
        const float dx = float(ox + x) + 0.5f - rows.mx[r], dy = float(oy + y) + 0.5f - rows.my[r];
        const float sigma = 0.5f * (a * dx * dx + c * dy * dy) + b * dx * dy;
        if (!(sigma <= top)) top = sigma;  // a NaN corner makes top NaN
      }
    }
    on = top < 60.f;  // (NaN fails)
    q = splat(rows.q[r]);
  }

  // exp(-sigma) at column col of the current scanline (dx, dy: its lanes' offsets from the centre; the
  // box's first scanline seeds the column), then one scanline on.
  fvec take(int64_t col, bool first, fvec dx, fvec dy, fvec ca, fvec cb, fvec cc) {
    if (first) {
      e[col] = vexp(-(splat(0.5f) * (ca * dx * dx + cc * dy * dy) + cb * dx * dy));
      ratio[col] = vexp(-(cc * dy + splat(0.5f) * cc + cb * dx), 60.f);
    }
    const fvec out = e[col];
    e[col] *= ratio[col];
    ratio[col] *= q;
    return out;
  }
};

template <int kDim>
void forward_simd(const Splats<float>& s, const float* records, const Grid grid, const Layout layout,
                  float a_min, float a_max, float t_min, at::Tensor& out, at::Tensor& acc, at::Tensor& final_t, at::Tensor& n_drawn) {
  const int64_t ts = grid.tile_size, pixels = ts * ts, dim = kDim > 0 ? kDim : s.dim;
  const int64_t padded = pixels + kLanes;
  float* out_p = out.data_ptr<float>();
  float* acc_p = acc.data_ptr<float>();
  float* t_p = final_t.data_ptr<float>();
  int32_t* n_p = n_drawn.data_ptr<int32_t>();
  const ivec lane_i = lane_numbers();
  const fvec lane_f = __builtin_convertvector(lane_i, fvec);

  for_each_tile(s.num_tiles, [&](int64_t t) {
    const int64_t count_rows = s.offsets[t + 1] - s.offsets[t];
    const TileRows<float> rows(s, records, t, count_rows);
    std::vector<float> trans(padded, 1.f), weight(padded, 0.f), color(dim * padded, 0.f);
    std::vector<int32_t> drawn(padded, 0), stopped(padded, 0);
    std::vector<fvec> fr(dim);
    int64_t active = pixels, ox, oy;
    grid.origin(t, ox, oy);
    for (int64_t r = 0; r < count_rows && active > 0; ++r) {
      const Span box = rows.span(r, ox, oy, ts);
      const float mx = rows.mx[r], my = rows.my[r], op = rows.op[r], cut = rows.cut[r];
      const fvec ca = splat(rows.ca[r]), cb = splat(rows.cb[r]), cc = splat(rows.cc[r]);
      bool finite = true;
      for (int64_t d = 0; d < dim; ++d) {
        fr[d] = splat(rows.feat[r * dim + d]);
        finite &= std::isfinite(rows.feat[r * dim + d]);
      }
      const ivec row_number = splat_i(int32_t(r + 1));
      FalloffSteps steps(rows, r, box, ox, oy);
      for (int64_t ly = box.y0; ly < box.y1; ++ly) {
        const fvec dy = splat(float(oy + ly) + 0.5f - my);
        for (int64_t lx = box.x0, col = 0; lx < box.x1; lx += kLanes, ++col) {
          const int64_t p = ly * ts + lx;
          const fvec dx = ((splat(float(ox + lx)) + lane_f) + splat(0.5f)) - splat(mx);
          const fvec sigma = splat(0.5f) * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
          const fvec stepped = steps.on ? steps.take(col, ly == box.y0, dx, dy, ca, cb, cc) : fvec{};
          ivec m = ((lane_i + int32_t(lx)) < int32_t(box.x1)) & (sigma >= splat(0.f)) & (sigma <= splat(cut)) &
                 ~vload(&stopped[p]);
          if (!any(m)) continue;
          const fvec raw = splat(op) * (steps.on ? stepped : vexp(-sigma));
          const fvec alpha = select(raw < splat(a_max), raw, splat(a_max));
          m &= alpha >= splat(a_min);
          const fvec before = vload(&trans[p]);
          const fvec next = before * (splat(1.f) - alpha);
          const ivec stop = m & (next <= splat(t_min));
          const ivec draw = m & ~stop;
          if (any(stop)) {
            vstore(&stopped[p], vload(&stopped[p]) | stop);
            active -= count(stop);
          }
          if (!any(draw)) continue;
          const fvec w = select(draw, alpha * before, splat(0.f));
          for (int64_t d = 0; d < dim; ++d) {  // w * f is 0 on the lanes not drawn unless f is inf
            float* c = &color[d * padded + p];
            vstore(c, vload(c) + (finite ? w * fr[d] : select(draw, w * fr[d], splat(0.f))));
          }
          vstore(&weight[p], vload(&weight[p]) + w);
          vstore(&trans[p], select(draw, next, before));
          vstore(&drawn[p], draw ? row_number : vload(&drawn[p]));
        }
      }
    }
    for (int64_t p = 0; p < pixels; ++p) {
      const int64_t at = layout.index(grid, t, p);
      if (at < 0) continue;
      for (int64_t d = 0; d < dim; ++d) out_p[at * dim + d] = color[d * padded + p];
      acc_p[at] = weight[p];
    }
    std::copy(trans.begin(), trans.begin() + pixels, t_p + t * pixels);
    std::copy(drawn.begin(), drawn.begin() + pixels, n_p + t * pixels);
  });
}

template <int kDim>
void backward_simd(const Splats<float>& s, const float* records, const Grid grid, const Layout layout,
                   float a_min, float a_max, const at::Tensor& final_t, const at::Tensor& n_drawn, const at::Tensor& grad_out,
                   const at::Tensor& grad_acc, at::Tensor& grads) {
  // As backward_impl; each row's gradient sums its pixels lane by lane, then the lanes (a fixed
  // order, so the result is still independent of threads and schedule). Every row above a tile's
  // deepest drawn row gets its gradient written (zeros where it reached no pixel), and add_row_grads
  // reads no other, so the per-intersection buffer is left unfilled: on a 540x960 view it is tens of MB,
  // which one thread would otherwise zero every step.
  const int64_t ts = grid.tile_size, pixels = ts * ts, dim = kDim > 0 ? kDim : s.dim, stride = 6 + dim;
  const int64_t padded = pixels + kLanes;
  std::unique_ptr<float[]> row_grads(new float[s.offsets[s.num_tiles] * stride]);
  std::vector<int32_t> deepest_of(s.num_tiles, 0);
  const float* t_p = final_t.data_ptr<float>();
  const int32_t* n_p = n_drawn.data_ptr<int32_t>();
  const float* go = grad_out.data_ptr<float>();
  const float* ga = grad_acc.data_ptr<float>();
  float* g_all = grads.data_ptr<float>();
  const ivec lane_i = lane_numbers();
  const fvec lane_f = __builtin_convertvector(lane_i, fvec);
  const fvec zero = splat(0.f), one = splat(1.f);

  for_each_tile(s.num_tiles, [&](int64_t t) {
    const int32_t* drawn_t = n_p + t * pixels;
    const int32_t deepest = *std::max_element(drawn_t, drawn_t + pixels);
    deepest_of[t] = deepest;
    if (deepest == 0) return;
    const TileRows<float> rows(s, records, t, deepest);
    float* g_rows = row_grads.get() + s.offsets[t] * stride;
    std::vector<float> trans(padded, 1.f), g_alpha(padded, 0.f), g_color(dim * padded, 0.f);
    std::vector<float> behind((dim + 1) * padded, 0.f);
    std::vector<int32_t> drawn(padded, 0);
    std::copy(t_p + t * pixels, t_p + (t + 1) * pixels, trans.begin());
    std::copy(drawn_t, drawn_t + pixels, drawn.begin());
    bool finite = true;  // every colour gradient of the tile: then w * gradient is 0 on a masked lane
    for (int64_t p = 0; p < pixels; ++p) {  // a pixel past the image's edge was cropped: gradient 0
      const int64_t at = layout.index(grid, t, p);
      if (at < 0) continue;
      g_alpha[p] = ga[at];
      for (int64_t d = 0; d < dim; ++d) {
        g_color[d * padded + p] = go[at * dim + d];
        finite &= std::isfinite(go[at * dim + d]);
      }
    }
    std::vector<fvec> fr(dim), sums(stride);
    int64_t ox, oy;
    grid.origin(t, ox, oy);
    for (int64_t r = deepest - 1; r >= 0; --r) {
      const Span box = rows.span(r, ox, oy, ts);
      const float mx = rows.mx[r], my = rows.my[r], op = rows.op[r], cut = rows.cut[r];
      const fvec ca = splat(rows.ca[r]), cb = splat(rows.cb[r]), cc = splat(rows.cc[r]);
      bool row_finite = true;
      for (int64_t d = 0; d < dim; ++d) {
        fr[d] = splat(rows.feat[r * dim + d]);
        row_finite &= std::isfinite(rows.feat[r * dim + d]);
      }
      std::fill(sums.begin(), sums.end(), zero);
      const ivec row_index = splat_i(int32_t(r));
      bool touched = false;
      FalloffSteps steps(rows, r, box, ox, oy);
      for (int64_t ly = box.y0; ly < box.y1; ++ly) {
        const fvec dy = splat(float(oy + ly) + 0.5f - my);
        for (int64_t lx = box.x0, col = 0; lx < box.x1; lx += kLanes, ++col) {
          const int64_t p = ly * ts + lx;
          const fvec dx = ((splat(float(ox + lx)) + lane_f) + splat(0.5f)) - splat(mx);
          const fvec stepped = steps.on ? steps.take(col, ly == box.y0, dx, dy, ca, cb, cc) : fvec{};
          ivec m = ((lane_i + int32_t(lx)) < int32_t(box.x1)) & (vload(&drawn[p]) > row_index);
          if (!any(m)) continue;
          const fvec sigma = splat(0.5f) * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
          m &= (sigma >= zero) & (sigma <= splat(cut));
          if (!any(m)) continue;
          const fvec falloff = steps.on ? stepped : vexp(-sigma);
          const fvec raw = splat(op) * falloff;
          const fvec alpha = select(raw < splat(a_max), raw, splat(a_max));
          m &= alpha >= splat(a_min);
          if (!any(m)) continue;
          touched = true;
          // alpha, 0 on masked lanes: there T / (1 - 0), T + 0 (f - T) and w = 0 leave every state as it was
          const fvec a_m = select(m, alpha, zero);
          const fvec in_front = vload(&trans[p]) / (one - a_m);
          vstore(&trans[p], in_front);
          const fvec w = a_m * in_front;
          float* bh_alpha = &behind[dim * padded + p];
          const fvec behind_alpha = vload(bh_alpha);
          fvec g_a = vload(&g_alpha[p]) * (one - behind_alpha);
          for (int64_t d = 0; d < dim; ++d) {
            const fvec gc = vload(&g_color[d * padded + p]);
            float* bh = &behind[d * padded + p];
            const fvec behind_d = vload(bh);
            sums[6 + d] += finite ? w * gc : select(m, w * gc, zero);
            g_a += gc * (fr[d] - behind_d);
            const fvec blended = a_m * fr[d] + (one - a_m) * behind_d;
            vstore(bh, row_finite ? blended : select(m, blended, behind_d));
          }
          vstore(bh_alpha, a_m + (one - a_m) * behind_alpha);
          g_a *= in_front;
          const ivec shaped = m & ~(raw > splat(a_max));  // clamped: no gradient to opacity or shape
          const fvec g_sigma = -g_a * alpha;
          sums[5] += select(shaped, g_a * falloff, zero);
          sums[0] -= select(shaped, g_sigma * (ca * dx + cb * dy), zero);
          sums[1] -= select(shaped, g_sigma * (cc * dy + cb * dx), zero);
          sums[2] += select(shaped, g_sigma * splat(0.5f) * dx * dx, zero);
          sums[3] += select(shaped, g_sigma * dx * dy, zero);
          sums[4] += select(shaped, g_sigma * splat(0.5f) * dy * dy, zero);
        }
      }
      float* g = &g_rows[r * stride];
      if (touched) {
        for (int64_t k = 0; k < stride; ++k) g[k] = hsum(sums[k]);
      } else {
        std::fill(g, g + stride, 0.f);
      }
    }
  });
  add_row_grads(s, deepest_of, row_grads.get(), stride, g_all, grads.size(0));
}

// Calls fn with std::integral_constant<int, D> for the channel counts the renderer packs (rgb 3;
// rgb + one depth channel 4; rgb + normal + distance 7; and 8 with camera z), else with D = 0
// (the count read at run time): a known count lets the compiler unroll the per-channel loops.
template <typename Fn>
void with_channels(int64_t dim, Fn fn) {
  switch (dim) {
    case 3: fn(std::integral_constant<int, 3>{}); break;
    case 4: fn(std::integral_constant<int, 4>{}); break;
    case 7: fn(std::integral_constant<int, 7>{}); break;
    case 8: fn(std::integral_constant<int, 8>{}); break;
    default: fn(std::integral_constant<int, 0>{});
  }
}

void check_inputs(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                  const at::Tensor& features, const at::Tensor& gaussian_ids,
                  const at::Tensor& tile_offsets) {
  for (const at::Tensor* t : {&means2d, &conics, &opacities, &features, &gaussian_ids, &tile_offsets}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "composite_cpu: inputs must be contiguous CPU tensors");
  }
  TORCH_CHECK(gaussian_ids.scalar_type() == at::kLong && tile_offsets.scalar_type() == at::kLong,
              "composite_cpu: gaussian_ids and tile_offsets must be int64");
}

std::vector<at::Tensor> forward(const at::Tensor& means2d, const at::Tensor& conics,
                                const at::Tensor& opacities, const at::Tensor& features,
                                const at::Tensor& gaussian_ids, const at::Tensor& tile_offsets,
                                int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size,
                                double alpha_min, double alpha_max, double t_min, int64_t width,
                                int64_t height) {
  check_inputs(means2d, conics, opacities, features, gaussian_ids, tile_offsets);
  const int64_t num_tiles = tile_offsets.size(0) - 1, pixels = tile_size * tile_size, dim = features.size(1);
  const Grid grid{tiles_x, tiles_per_cam, tile_size};
  const Layout layout{width, height};
  auto final_t = at::empty({num_tiles, pixels}, features.options());
  auto n_drawn = at::empty({num_tiles, pixels}, features.options().dtype(at::kInt));
  at::Tensor out, acc, records;
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "composite_cpu_forward", [&] {
    const Splats<scalar_t> splats(means2d, conics, opacities, features, gaussian_ids, tile_offsets);
    records = splat_records<scalar_t>(splats, features.size(0), scalar_t(alpha_min), features.options());
    const scalar_t* records_p = records.data_ptr<scalar_t>();
    if constexpr (std::is_same_v<scalar_t, float>) {
      const int64_t cams = num_tiles / tiles_per_cam;
      out = width ? at::empty({cams, height, width, dim}, features.options())
                  : at::empty({num_tiles, pixels, dim}, features.options());
      acc = width ? at::empty({cams, height, width}, features.options())
                  : at::empty({num_tiles, pixels}, features.options());
      with_channels(dim, [&](auto channels) {
        forward_simd<decltype(channels)::value>(splats, records_p, grid, layout, alpha_min, alpha_max, t_min,
                                                out, acc, final_t, n_drawn);
      });
    } else {
      out = at::empty({num_tiles, pixels, dim}, features.options());
      acc = at::empty({num_tiles, pixels}, features.options());
      forward_impl<scalar_t>(splats, records_p, grid, alpha_min, alpha_max, t_min, out, acc, final_t, n_drawn);
      out = layout.from_tiles(out, grid);
      acc = layout.from_tiles(acc.unsqueeze(-1), grid).squeeze(-1);
    }
  });
  return {out, acc, final_t, n_drawn, records};
}

std::vector<at::Tensor> backward(const at::Tensor& means2d, const at::Tensor& conics,
                                 const at::Tensor& opacities, const at::Tensor& features,
                                 const at::Tensor& gaussian_ids, const at::Tensor& tile_offsets,
                                 int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size,
                                 double alpha_min, double alpha_max, const at::Tensor& final_t,
                                 const at::Tensor& n_drawn, const at::Tensor& records,
                                 const at::Tensor& grad_out, const at::Tensor& grad_acc, int64_t width,
                                 int64_t height) {
  check_inputs(means2d, conics, opacities, features, gaussian_ids, tile_offsets);
  TORCH_CHECK(grad_out.is_contiguous() && grad_acc.is_contiguous(), "composite_cpu: grads must be contiguous");
  TORCH_CHECK(records.is_contiguous() && records.scalar_type() == features.scalar_type() &&
                  records.size(0) == features.size(0) && records.size(1) == kRecord + features.size(1),
              "composite_cpu: records must be the forward's [G, 10 + D]");
  // add_row_grads zeroes it
  auto grads = at::empty({features.size(0), 6 + features.size(1)}, features.options());
  const Grid grid{tiles_x, tiles_per_cam, tile_size};
  const Layout layout{width, height};
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "composite_cpu_backward", [&] {
    const Splats<scalar_t> splats(means2d, conics, opacities, features, gaussian_ids, tile_offsets);
    const scalar_t* records_p = records.data_ptr<scalar_t>();
    if constexpr (std::is_same_v<scalar_t, float>) {
      with_channels(features.size(1), [&](auto channels) {
        backward_simd<decltype(channels)::value>(splats, records_p, grid, layout, alpha_min, alpha_max,
                                                 final_t, n_drawn, grad_out, grad_acc, grads);
      });
    } else {
      const int64_t num_tiles = tile_offsets.size(0) - 1;
      backward_impl<scalar_t>(splats, records_p, grid, alpha_min, alpha_max, final_t, n_drawn,
                              layout.to_tiles(grad_out, grid, num_tiles),
                              layout.to_tiles(grad_acc.unsqueeze(-1), grid, num_tiles).squeeze(-1), grads);
    }
  });
  return {grads.slice(1, 0, 2), grads.slice(1, 2, 5), grads.select(1, 5), grads.slice(1, 6)};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "fused CPU compositor, forward");
  m.def("backward", &backward, "fused CPU compositor, backward");
  m.def("bin", &hico::bin, "tile binning: intersections sorted by (tile, depth)");
}
