// Tile binning: the same intersections as tiling.py's vectorised bin_gaussians, in the same order (contract
// in binning_cpu.h). Each Gaussian's tile rectangle is enumerated and the tiles its ellipse misses are dropped
// (the same float arithmetic as _ellipse_meets_tile); the Gaussians that reach a tile are ordered by depth with
// a stable LSD radix sort (ties by index, as torch's stable argsort), and a counting sort by tile keeps depth
// order within each tile. The per-Gaussian passes run in index order, so their reads are sequential; only the
// writes of the second pass land in depth order.

#include "binning_cpu.h"

#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <type_traits>
#include <vector>

namespace {

struct TileRect {
  int64_t tx0, tx1, ty0, ty1;
  bool empty;
};

template <typename scalar_t>
TileRect tile_rect(scalar_t u, scalar_t v, scalar_t ex, scalar_t ey, int64_t width,
                             int64_t height, int64_t tile_size) {
  auto clamp = [](scalar_t x, scalar_t hi) { return std::min(std::max(x, scalar_t(0)), hi); };
  const scalar_t half = scalar_t(0.5);
  const scalar_t x0 = clamp(std::ceil(u - ex - half), scalar_t(width - 1));
  const scalar_t x1 = clamp(std::floor(u + ex - half), scalar_t(width - 1));
  const scalar_t y0 = clamp(std::ceil(v - ey - half), scalar_t(height - 1));
  const scalar_t y1 = clamp(std::floor(v + ey - half), scalar_t(height - 1));
  const scalar_t ts = scalar_t(tile_size);
  return {int64_t(std::floor(x0 / ts)), int64_t(std::floor(x1 / ts)), int64_t(std::floor(y0 / ts)),
          int64_t(std::floor(y1 / ts)), !(x0 <= x1 && y0 <= y1)};
}

template <typename scalar_t>
bool ellipse_meets_tile(scalar_t mx, scalar_t my, scalar_t a, scalar_t b, scalar_t c, scalar_t reach,
                        int64_t tx, int64_t ty, int64_t tile_size) {
  // (x - m)^T [[a, b], [b, c]] (x - m) <= reach^2 somewhere on the tile's pixel centres.
  const scalar_t x0 = scalar_t(tx * tile_size) + scalar_t(0.5) - mx;
  const scalar_t x1 = x0 + scalar_t(tile_size - 1);
  const scalar_t y0 = scalar_t(ty * tile_size) + scalar_t(0.5) - my;
  const scalar_t y1 = y0 + scalar_t(tile_size - 1);
  if (x0 <= 0 && x1 >= 0 && y0 <= 0 && y1 >= 0) return true;
  auto quad = [&](scalar_t dx, scalar_t dy) { return a * dx * dx + 2 * b * dx * dy + c * dy * dy; };
  auto clip = [](scalar_t x, scalar_t lo, scalar_t hi) { return std::min(std::max(x, lo), hi); };
  scalar_t best = std::numeric_limits<scalar_t>::infinity();
  for (const scalar_t x : {x0, x1}) best = std::min(best, quad(x, clip(-b * x / c, y0, y1)));
  for (const scalar_t y : {y0, y1}) best = std::min(best, quad(clip(-b * y / a, x0, x1), y));
  return best <= reach * reach;
}

// An unsigned integer whose order is the float's order as torch's sort sees it: negatives flipped and
// the sign bit set on the rest, -0 made +0 (equal keys keep index order) and every NaN the largest key.
template <typename scalar_t>
using key_t = std::conditional_t<sizeof(scalar_t) == 4, uint32_t, uint64_t>;

template <typename scalar_t>
key_t<scalar_t> order_key(scalar_t x) {
  using K = key_t<scalar_t>;
  if (std::isnan(x)) return ~K(0);
  x = x + scalar_t(0);  // -0 + 0 = +0 under IEEE round-to-nearest
  K bits;
  std::memcpy(&bits, &x, sizeof(K));
  const K sign = K(1) << (8 * sizeof(K) - 1);
  return (bits & sign) ? ~bits : (bits | sign);
}

// Stable LSD radix sort of ids by key, 11 bits a pass (three passes for float32 keys; the histogram of
// 2,048 buckets stays in L1); a pass whose digit is the same everywhere is skipped.
template <typename K>
void radix_sort(std::vector<K>& keys, std::vector<int64_t>& ids) {
  constexpr size_t kBits = 11, kBuckets = size_t(1) << kBits;
  const size_t count = keys.size();
  std::vector<K> keys_tmp(count);
  std::vector<int64_t> ids_tmp(count);
  std::vector<size_t> hist(kBuckets + 1);
  for (size_t shift = 0; shift < 8 * sizeof(K); shift += kBits) {
    std::fill(hist.begin(), hist.end(), 0);
    for (size_t i = 0; i < count; ++i) ++hist[((keys[i] >> shift) & (kBuckets - 1)) + 1];
    if (std::any_of(hist.begin() + 1, hist.end(), [&](size_t h) { return h == count; })) continue;
    for (size_t b = 0; b < kBuckets; ++b) hist[b + 1] += hist[b];
    for (size_t i = 0; i < count; ++i) {
      const size_t at = hist[(keys[i] >> shift) & (kBuckets - 1)]++;
      keys_tmp[at] = keys[i];
      ids_tmp[at] = ids[i];
    }
    keys.swap(keys_tmp);
    ids.swap(ids_tmp);
  }
}

// The tiles a Gaussian reaches, kept by the counting pass for the writing pass when there are at most
// this many (almost every Gaussian: about two on average), so each ellipse is tested against its tiles once.
constexpr int64_t kCachedTiles = 4;

template <typename scalar_t>
void bin_impl(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& reach,
              const at::Tensor& extents, const at::Tensor& radii, const at::Tensor& depths,
              int64_t n, int64_t width, int64_t height, int64_t tile_size, int64_t tiles_x,
              int64_t tiles_y, at::Tensor& hit_gaussians, at::Tensor& hit_tiles) {
  const scalar_t* m = means2d.data_ptr<scalar_t>();
  const scalar_t* cn = conics.data_ptr<scalar_t>();
  const scalar_t* rc = reach.data_ptr<scalar_t>();
  const scalar_t* ext = extents.data_ptr<scalar_t>();
  const scalar_t* dp = depths.data_ptr<scalar_t>();
  const int32_t* rad = radii.data_ptr<int32_t>();
  const int64_t total = depths.numel();

  // visit(g, emit): every tile of Gaussian g that its ellipse reaches
  auto visit = [&](int64_t g, auto&& emit) {
    if (rad[g] <= 0) return;
    const TileRect r =
        tile_rect<scalar_t>(m[2 * g], m[2 * g + 1], ext[2 * g], ext[2 * g + 1], width, height, tile_size);
    if (r.empty) return;
    const int64_t base = (g / n) * tiles_y * tiles_x;
    for (int64_t ty = r.ty0; ty <= r.ty1; ++ty) {
      for (int64_t tx = r.tx0; tx <= r.tx1; ++tx) {
        if (ellipse_meets_tile<scalar_t>(m[2 * g], m[2 * g + 1], cn[3 * g], cn[3 * g + 1],
                                         cn[3 * g + 2], rc[g % n], tx, ty, tile_size)) {
          emit(base + ty * tiles_x + tx);
        }
      }
    }
  };
  std::vector<int64_t> counts(total);
  std::unique_ptr<int64_t[]> cached(new int64_t[total * kCachedTiles]);
  at::parallel_for(0, total, 1024, [&](int64_t begin, int64_t end) {
    for (int64_t g = begin; g < end; ++g) {
      int64_t c = 0;
      int64_t* mine = &cached[g * kCachedTiles];
      visit(g, [&](int64_t tile) {
        if (c < kCachedTiles) mine[c] = tile;
        ++c;
      });
      counts[g] = c;
    }
  });
  using K = key_t<scalar_t>;
  std::vector<K> keys;
  std::vector<int64_t> order;
  keys.reserve(total);
  order.reserve(total);
  for (int64_t g = 0; g < total; ++g) {
    if (counts[g] > 0) {
      keys.push_back(order_key(dp[g]));
      order.push_back(g);
    }
  }
  radix_sort(keys, order);
  std::vector<int64_t> start(total);  // first hit of each Gaussian, in depth order (read only where it hits)
  int64_t hits = 0;
  for (const int64_t g : order) {
    start[g] = hits;
    hits += counts[g];
  }
  hit_gaussians = at::empty({hits}, at::TensorOptions().dtype(at::kLong));
  hit_tiles = at::empty({hits}, at::TensorOptions().dtype(at::kLong));
  int64_t* hg = hit_gaussians.data_ptr<int64_t>();
  int64_t* ht = hit_tiles.data_ptr<int64_t>();
  at::parallel_for(0, total, 1024, [&](int64_t begin, int64_t end) {
    for (int64_t g = begin; g < end; ++g) {
      if (counts[g] == 0) continue;
      int64_t at = start[g];
      if (counts[g] <= kCachedTiles) {
        for (int64_t c = 0; c < counts[g]; ++c, ++at) {
          ht[at] = cached[g * kCachedTiles + c];
          hg[at] = g;
        }
      } else {
        visit(g, [&](int64_t tile) { ht[at] = tile; hg[at] = g; ++at; });
      }
    }
  });
}

}  // namespace

namespace hico {

std::vector<at::Tensor> bin(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& reach,
                            const at::Tensor& extents, const at::Tensor& radii, const at::Tensor& depths,
                            int64_t num_cams, int64_t n, int64_t width, int64_t height,
                            int64_t tile_size) {
  for (const at::Tensor* t : {&means2d, &conics, &reach, &extents, &radii, &depths}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "bin_cpu: inputs must be contiguous CPU tensors");
  }
  TORCH_CHECK(radii.scalar_type() == at::kInt, "bin_cpu: radii must be int32");
  TORCH_CHECK(depths.scalar_type() == means2d.scalar_type(), "bin_cpu: depths must have the means' dtype");
  const int64_t tiles_x = (width + tile_size - 1) / tile_size;
  const int64_t tiles_y = (height + tile_size - 1) / tile_size;
  const int64_t num_tiles = num_cams * tiles_x * tiles_y;
  at::Tensor gaussians, tiles;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_cpu", [&] {
    bin_impl<scalar_t>(means2d, conics, reach, extents, radii, depths, n, width, height, tile_size,
                       tiles_x, tiles_y, gaussians, tiles);
  });
  // Counting sort by tile, stable (depth order survives within each tile), in parallel: each thread
  // counts and places one contiguous block of the hits, and within a tile block p's hits go after those
  // of blocks before it, so the order is the serial sort's whatever the thread count.
  const int64_t hits = tiles.numel();
  const int64_t* ht = tiles.data_ptr<int64_t>();
  const int64_t* hg = gaussians.data_ptr<int64_t>();
  const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), hits / 4096 + 1));
  std::vector<int64_t> place(size_t(parts * num_tiles), 0);  // [part][tile]: counts, then write cursors
  auto block = [&](int64_t part, int64_t& lo, int64_t& hi) {
    lo = hits * part / parts;
    hi = hits * (part + 1) / parts;
  };
  at::parallel_for(0, parts, 1, [&](int64_t p0, int64_t p1) {
    for (int64_t part = p0; part < p1; ++part) {
      int64_t lo, hi;
      block(part, lo, hi);
      int64_t* mine = &place[size_t(part * num_tiles)];
      for (int64_t i = lo; i < hi; ++i) ++mine[ht[i]];
    }
  });
  auto long_opts = at::TensorOptions().dtype(at::kLong);
  auto offsets = at::empty({num_tiles + 1}, long_opts);
  int64_t* off = offsets.data_ptr<int64_t>();
  int64_t running = 0;
  for (int64_t t = 0; t < num_tiles; ++t) {
    off[t] = running;
    for (int64_t part = 0; part < parts; ++part) {
      const int64_t count = place[size_t(part * num_tiles + t)];
      place[size_t(part * num_tiles + t)] = running;
      running += count;
    }
  }
  off[num_tiles] = running;
  auto gaussian_ids = at::empty({hits}, long_opts);
  auto tile_ids = at::empty({hits}, long_opts);
  int64_t* gid = gaussian_ids.data_ptr<int64_t>();
  int64_t* tid = tile_ids.data_ptr<int64_t>();
  at::parallel_for(0, parts, 1, [&](int64_t p0, int64_t p1) {
    for (int64_t part = p0; part < p1; ++part) {
      int64_t lo, hi;
      block(part, lo, hi);
      int64_t* cursor = &place[size_t(part * num_tiles)];
      for (int64_t i = lo; i < hi; ++i) {
        const int64_t at = cursor[ht[i]]++;
        gid[at] = hg[i];
        tid[at] = ht[i];
      }
    }
  });
  return {gaussian_ids, tile_ids, offsets};
}

}  // namespace hico
