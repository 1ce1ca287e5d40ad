// Sums of gradient rows by an ascending row index, the backward of a gather whose rows repeat in runs (a
// decoded child's anchor: each anchor's K children are consecutive):
//
//   grad [M, C], rows [M] int64 ascending in [0, N) -> out [N, C], out[r] = the sum of grad[i] over the i
//   with rows[i] == r, added in order of i starting from zero -- the sum zeros.index_add_(0, rows, grad)
//   forms, which torch runs single-threaded on a CPU (it cannot know that no two threads would write a row).
//
// The output rows are split among the threads; each writes its own rows, zero where no index names them,
// so results are bitwise those of index_add_ whatever the thread count. Returns 0, or 1 when rows is not
// ascending within [0, N) (nothing written; the caller uses index_add_).
//
// Rows placed by a strictly ascending index, the backward of a gather that names each row at most once
// (the kept children of the visible anchors, the visible anchors of the field):
//
//   grad [M, B bytes], rows [M] strictly ascending in [0, N) -> out [N, B bytes], out[rows[i]] = grad[i],
//   every other row zero -- zeros.index_copy_(0, rows, grad) in one pass over the output instead of a
//   zero fill of all N rows and a second write of the M named ones. Bytes are copied, so every value
//   (-0, NaN, inf) arrives as index_copy_ would place it. Returns 0, or 1 when rows is not strictly
//   ascending within [0, N) (nothing written).

#include <omp.h>

#include <algorithm>
#include <cstdint>
#include <cstring>

namespace {

// Whether rows [m] lie in [0, n) and ascend (strictly: no value twice).
bool ascending(const int64_t* rows, int64_t m, int64_t n, bool strict) {
  for (int64_t i = 0; i < m; ++i) {
    if (rows[i] < 0 || rows[i] >= n || (i > 0 && (strict ? rows[i] <= rows[i - 1] : rows[i] < rows[i - 1]))) {
      return false;
    }
  }
  return true;
}

// Splits the output rows [0, n) among the threads: fn(first, last, i) writes rows [first, last), of
// which the named ones start at rows[i] (each thread writes only its own rows, so no two collide).
template <typename Fn>
void by_output_rows(const int64_t* rows, int64_t m, int64_t n, int threads, Fn fn) {
#pragma omp parallel num_threads(threads)
  {
    const int64_t parts = omp_get_num_threads(), part = omp_get_thread_num();
    const int64_t first = n * part / parts, last = n * (part + 1) / parts;
    fn(first, last, int64_t(std::lower_bound(rows, rows + m, first) - rows));
  }
}

template <typename T>
int segment_sum(const T* grad, const int64_t* rows, int64_t m, int64_t cols, int64_t n, T* out, int threads) {
  if (!ascending(rows, m, n, false)) return 1;
  by_output_rows(rows, m, n, threads, [&](int64_t first, int64_t last, int64_t i) {
    for (int64_t r = first; r < last; ++r) {
      T* o = out + r * cols;
      std::fill(o, o + cols, T(0));
      for (; i < m && rows[i] == r; ++i) {
        const T* g = grad + i * cols;
        for (int64_t c = 0; c < cols; ++c) o[c] += g[c];
      }
    }
  });
  return 0;
}

int place_rows(const char* grad, const int64_t* rows, int64_t m, int64_t bytes, int64_t n, char* out, int threads) {
  if (!ascending(rows, m, n, true)) return 1;
  by_output_rows(rows, m, n, threads, [&](int64_t first, int64_t last, int64_t i) {
    int64_t r = first;
    for (; i < m && rows[i] < last; ++i) {  // zeros up to the next named row, then that row's gradient
      std::memset(out + r * bytes, 0, (rows[i] - r) * bytes);
      std::memcpy(out + rows[i] * bytes, grad + i * bytes, bytes);
      r = rows[i] + 1;
    }
    std::memset(out + r * bytes, 0, (last - r) * bytes);
  });
  return 0;
}

}  // namespace

extern "C" {

int hico_place_rows(const char* grad, const int64_t* rows, int64_t m, int64_t bytes, int64_t n, char* out,
                    int threads) {
  return place_rows(grad, rows, m, bytes, n, out, threads);
}

int hico_segment_sum_f32(const float* grad, const int64_t* rows, int64_t m, int64_t cols, int64_t n, float* out,
                         int threads) {
  return segment_sum(grad, rows, m, cols, n, out, threads);
}

int hico_segment_sum_f64(const double* grad, const int64_t* rows, int64_t m, int64_t cols, int64_t n, double* out,
                         int threads) {
  return segment_sum(grad, rows, m, cols, n, out, threads);
}

}  // extern "C"
