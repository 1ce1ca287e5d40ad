// CLCA's relation and pooling on CPU (paper Sec. 3.3, Eqs. 2-4): the same graph and the same weighted
// means as context_graph.py / context.py's torch versions, in a few passes over anchors and edges instead
// of some fifty torch ops (sorts, masks, CSR assembly) a view.
//
//   trilinear_parents(keys [V,4] long (level, grid index), fork, weight_like)
//     -> anchor [E] long ascending, parent keys [E,4] long, weight [E] (weight_like's dtype)
//   build_graph(keys [V,4], edge_anchor [E], edge_keys [E,4], edge_weight [E])
//     -> cell [V], count [K], anchor [E'], edge_cell [E'], weight [E'], by_cell [E'], members [V]
//   lookup_forward(x [V,d], graph, missing [2,d], fallback) -> [V,3,d] (c_parent, c_self, c_child)
//   lookup_backward(grad [V,3,d], graph, fallback) -> grad x [V,d], grad missing [2,d]
//
// Cells are numbered in order of first appearance among the anchors; an edge whose parent cell holds no
// anchor is dropped. Every loop writes one row per iteration (gathers, no scatter), so the outputs do
// not depend on the thread count.

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <vector>

namespace {

// Open-addressing hash tables from a cell key to its dense id (linear probing, power-of-two capacity),
// each slot holding its key next to its id, so a probe reads one place in memory. CellTable packs a key
// into 64 bits (16 per part: level and grid index each in [-2^15, 2^15), an octree up to 32,768 finest
// cells a side), a 16-byte slot; WideCellTable keeps the four parts (40 bytes) for anchors beyond that.
// find(key, insert): the key's id, inserting it with the next id when absent (insert) or returning -1.
bool pack_key(const int64_t* key, uint64_t& packed) {
  packed = 0;
  for (int i = 0; i < 4; ++i) {
    if (key[i] < -32768 || key[i] > 32767) return false;
    packed = (packed << 16) | uint64_t(uint16_t(key[i]));
  }
  return true;
}

uint64_t mix(uint64_t x) {  // splitmix64's finaliser
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31);
}

uint64_t table_mask(int64_t expected) {
  int64_t capacity = 16;
  while (capacity < 2 * expected) capacity <<= 1;
  return uint64_t(capacity - 1);
}

class CellTable {
 public:
  explicit CellTable(int64_t expected) : mask_(table_mask(expected)), slots_(size_t(mask_ + 1), Slot{0, -1}) {}

  // Every key of an inserted anchor must pack (build_graph checks); a lookup key that does not pack
  // cannot equal one and is absent.
  int64_t find(const int64_t* key, bool insert) {
    uint64_t packed;
    if (!pack_key(key, packed)) return -1;
    for (uint64_t at = mix(packed) & mask_;; at = (at + 1) & mask_) {
      Slot& slot = slots_[at];
      if (slot.id < 0) {
        if (!insert) return -1;
        slot = Slot{packed, size_++};
        return slot.id;
      }
      if (slot.key == packed) return slot.id;
    }
  }

  int64_t size() const { return size_; }

 private:
  struct Slot {
    uint64_t key;
    int64_t id;
  };
  uint64_t mask_;
  std::vector<Slot> slots_;
  int64_t size_ = 0;
};

class WideCellTable {
 public:
  explicit WideCellTable(int64_t expected) : mask_(table_mask(expected)), slots_(size_t(mask_ + 1)) {}

  int64_t find(const int64_t* key, bool insert) {
    uint64_t h = 0x9e3779b97f4a7c15ULL;
    for (int i = 0; i < 4; ++i) h = mix(h ^ uint64_t(key[i]));
    for (uint64_t at = h & mask_;; at = (at + 1) & mask_) {
      Slot& slot = slots_[at];
      if (slot.id < 0) {
        if (!insert) return -1;
        slot = Slot{{key[0], key[1], key[2], key[3]}, size_++};
        return slot.id;
      }
      if (slot.key[0] == key[0] && slot.key[1] == key[1] && slot.key[2] == key[2] && slot.key[3] == key[3]) {
        return slot.id;
      }
    }
  }

  int64_t size() const { return size_; }

 private:
  struct Slot {
    int64_t key[4];
    int64_t id = -1;
  };
  uint64_t mask_;
  std::vector<Slot> slots_;
  int64_t size_ = 0;
};

void check_keys(const at::Tensor& keys, const char* what) {
  TORCH_CHECK(keys.device().is_cpu() && keys.is_contiguous() && keys.scalar_type() == at::kLong &&
                  keys.dim() == 2 && keys.size(1) == 4,
              "context_cpu: ", what, " must be a contiguous CPU int64 tensor [n,4]");
}

int64_t floor_div(int64_t a, int64_t b) {
  const int64_t q = a / b;
  return (a % b != 0 && ((a < 0) != (b < 0))) ? q - 1 : q;
}

// The 1-8 grid points of level l-1 around a level-l anchor with index k (k / fork in level-(l-1) units)
// with their trilinear weights, corners in x-slowest order, zero weights left out (parent_edges).
// Two passes over the anchors, each split among the threads: count each anchor's corners, then write
// them at the anchor's offset (the prefix sum of the counts), so the order is the serial loop's.
template <typename scalar_t>
struct Corners {
  int64_t base[3];
  scalar_t weight[8];

  // shift: log2(fork) when fork is a power of two (the octree's 2), else -1 (integer division)
  Corners(const int64_t* key, int64_t fork, int shift) {
    scalar_t axis[3][2];
    for (int i = 0; i < 3; ++i) {
      base[i] = shift >= 0 ? key[1 + i] >> shift : floor_div(key[1 + i], fork);  // >> floors
      const scalar_t frac = scalar_t(key[1 + i] - base[i] * fork) / scalar_t(fork);
      axis[i][0] = scalar_t(1) - frac;
      axis[i][1] = frac;
    }
    for (int corner = 0; corner < 8; ++corner) {
      weight[corner] = axis[0][(corner >> 2) & 1] * axis[1][(corner >> 1) & 1] * axis[2][corner & 1];
    }
  }
};

std::vector<at::Tensor> trilinear_parents(const at::Tensor& keys, int64_t fork, const at::Tensor& weight_like) {
  check_keys(keys, "keys");
  TORCH_CHECK(fork >= 2, "context_cpu: fork must be >= 2");
  const int64_t num = keys.size(0);
  const int64_t* k = keys.data_ptr<int64_t>();
  auto long_opts = at::TensorOptions().dtype(at::kLong);
  at::Tensor anchor_t, parent_t, weight;
  const int shift = (fork & (fork - 1)) == 0 ? __builtin_ctzll(uint64_t(fork)) : -1;  // log2 of a power of two
  AT_DISPATCH_FLOATING_TYPES(weight_like.scalar_type(), "trilinear_parents", [&] {
    std::vector<int64_t> start(size_t(num) + 1, 0);
    at::parallel_for(0, num, 2048, [&](int64_t begin, int64_t end) {
      for (int64_t a = begin; a < end; ++a) {
        if (k[4 * a] <= 0) continue;
        const Corners<scalar_t> c(k + 4 * a, fork, shift);
        start[size_t(a) + 1] = std::count_if(c.weight, c.weight + 8, [](scalar_t w) { return w > 0; });
      }
    });
    for (int64_t a = 0; a < num; ++a) start[size_t(a) + 1] += start[size_t(a)];
    const int64_t edges = start[size_t(num)];
    anchor_t = at::empty({edges}, long_opts);
    parent_t = at::empty({edges, 4}, long_opts);
    weight = at::empty({edges}, weight_like.options());
    int64_t* an = anchor_t.data_ptr<int64_t>();
    int64_t* pa = parent_t.data_ptr<int64_t>();
    scalar_t* we = weight.data_ptr<scalar_t>();
    at::parallel_for(0, num, 2048, [&](int64_t begin, int64_t end) {
      for (int64_t a = begin; a < end; ++a) {
        if (k[4 * a] <= 0) continue;
        const Corners<scalar_t> c(k + 4 * a, fork, shift);
        int64_t e = start[size_t(a)];
        for (int corner = 0; corner < 8; ++corner) {
          if (!(c.weight[corner] > 0)) continue;
          an[e] = a;
          int64_t* p = pa + 4 * e;
          p[0] = k[4 * a] - 1;
          p[1] = c.base[0] + ((corner >> 2) & 1);
          p[2] = c.base[1] + ((corner >> 1) & 1);
          p[3] = c.base[2] + (corner & 1);
          we[e] = c.weight[corner];
          ++e;
        }
      }
    });
  });
  return {anchor_t, parent_t, weight};
}

// Stable counting sort of 0..n-1 by bucket (values in [0, buckets)).
at::Tensor order_by(const int64_t* bucket, int64_t n, int64_t buckets) {
  std::vector<int64_t> start(size_t(buckets) + 1, 0);
  for (int64_t i = 0; i < n; ++i) ++start[size_t(bucket[i]) + 1];
  for (int64_t b = 0; b < buckets; ++b) start[size_t(b) + 1] += start[size_t(b)];
  auto order = at::empty({n}, at::TensorOptions().dtype(at::kLong));
  int64_t* out = order.data_ptr<int64_t>();
  for (int64_t i = 0; i < n; ++i) out[start[size_t(bucket[i])]++] = i;
  return order;
}

std::vector<at::Tensor> build_graph(const at::Tensor& keys, const at::Tensor& edge_anchor,
                                    const at::Tensor& edge_keys, const at::Tensor& edge_weight) {
  check_keys(keys, "keys");
  check_keys(edge_keys, "edge_keys");
  TORCH_CHECK(edge_anchor.is_contiguous() && edge_anchor.scalar_type() == at::kLong &&
                  edge_weight.is_contiguous() && edge_weight.size(0) == edge_anchor.size(0) &&
                  edge_keys.size(0) == edge_anchor.size(0),
              "context_cpu: edge_anchor [E] int64, edge_keys [E,4] and edge_weight [E] must match");
  const int64_t num = keys.size(0), num_edges = edge_anchor.size(0);
  const int64_t* k = keys.data_ptr<int64_t>();
  const int64_t* ek = edge_keys.data_ptr<int64_t>();
  const int64_t* ea = edge_anchor.data_ptr<int64_t>();
  for (int64_t e = 0; e < num_edges; ++e) {
    TORCH_CHECK(ea[e] >= 0 && ea[e] < num && (e == 0 || ea[e] >= ea[e - 1]),
                "context_cpu: edge_anchor must be ascending anchor indices");
  }
  auto long_opts = at::TensorOptions().dtype(at::kLong);
  auto cell = at::empty({num}, long_opts);
  int64_t* c = cell.data_ptr<int64_t>();
  std::vector<int64_t> found(static_cast<size_t>(num_edges));
  int64_t num_cells = 0;
  // Cells numbered by first appearance among the anchors; then each edge's parent cell, or -1.
  auto number_cells = [&](auto& table) {
    for (int64_t a = 0; a < num; ++a) c[a] = table.find(k + 4 * a, true);
    num_cells = table.size();
    at::parallel_for(0, num_edges, 4096, [&](int64_t begin, int64_t end) {
      for (int64_t e = begin; e < end; ++e) found[size_t(e)] = table.find(ek + 4 * e, false);
    });
  };
  uint64_t unused;
  bool packs = true;
  for (int64_t a = 0; a < num && packs; ++a) packs = pack_key(k + 4 * a, unused);
  if (packs) {
    CellTable table(num);
    number_cells(table);
  } else {
    WideCellTable table(num);
    number_cells(table);
  }
  auto count = at::zeros({num_cells}, long_opts);
  int64_t* n = count.data_ptr<int64_t>();
  for (int64_t a = 0; a < num; ++a) ++n[c[a]];
  std::vector<int64_t> kept;
  kept.reserve(size_t(num_edges));
  for (int64_t e = 0; e < num_edges; ++e) {
    if (found[size_t(e)] >= 0) kept.push_back(e);
  }
  const int64_t num_kept = int64_t(kept.size());
  auto anchor = at::empty({num_kept}, long_opts);
  auto edge_cell = at::empty({num_kept}, long_opts);
  auto kept_t = at::empty({num_kept}, long_opts);
  int64_t* an = anchor.data_ptr<int64_t>();
  int64_t* ec = edge_cell.data_ptr<int64_t>();
  std::copy(kept.begin(), kept.end(), kept_t.data_ptr<int64_t>());
  for (int64_t i = 0; i < num_kept; ++i) {
    an[i] = ea[kept[size_t(i)]];
    ec[i] = found[size_t(kept[size_t(i)])];
  }
  auto weight = edge_weight.index_select(0, kept_t);
  return {cell, count, anchor, edge_cell, weight, order_by(ec, num_kept, num_cells), order_by(c, num, num_cells)};
}

// The graph as raw pointers plus the offsets the passes need: members and by-cell edges grouped by cell,
// edges grouped by anchor, and the weight totals per anchor (parent) and per cell (child).
template <typename scalar_t>
struct Graph {
  int64_t num, num_cells, num_edges;
  const int64_t *cell, *count, *anchor, *edge_cell, *by_cell, *members;
  const scalar_t* weight;
  std::vector<int64_t> member_start, edge_start, cell_edge_start;
  std::vector<scalar_t> parent_total, child_total;

  Graph(const std::vector<at::Tensor>& g)
      : num(g[0].size(0)), num_cells(g[1].size(0)), num_edges(g[2].size(0)),
        cell(g[0].data_ptr<int64_t>()), count(g[1].data_ptr<int64_t>()), anchor(g[2].data_ptr<int64_t>()),
        edge_cell(g[3].data_ptr<int64_t>()), by_cell(g[5].data_ptr<int64_t>()),
        members(g[6].data_ptr<int64_t>()), weight(g[4].data_ptr<scalar_t>()),
        member_start(size_t(num_cells) + 1, 0), edge_start(size_t(num) + 1, 0),
        cell_edge_start(size_t(num_cells) + 1, 0), parent_total(size_t(num), 0),
        child_total(size_t(num_cells), 0) {
    for (int64_t k = 0; k < num_cells; ++k) member_start[size_t(k) + 1] = member_start[size_t(k)] + count[k];
    for (int64_t e = 0; e < num_edges; ++e) {
      TORCH_CHECK(e == 0 || anchor[e] >= anchor[e - 1], "context_cpu: the edges must be sorted by anchor");
      ++edge_start[size_t(anchor[e]) + 1];
      ++cell_edge_start[size_t(edge_cell[e]) + 1];
      parent_total[size_t(anchor[e])] += weight[e];
      child_total[size_t(edge_cell[e])] += weight[e];
    }
    for (int64_t a = 0; a < num; ++a) edge_start[size_t(a) + 1] += edge_start[size_t(a)];
    for (int64_t k = 0; k < num_cells; ++k) cell_edge_start[size_t(k) + 1] += cell_edge_start[size_t(k)];
  }

  // Weight of edge e in its anchor's parent mean / in its cell's child mean (context_graph's clamp).
  scalar_t parent_share(int64_t e) const {
    return weight[e] / std::max(parent_total[size_t(anchor[e])], scalar_t(1e-12));
  }
  scalar_t child_share(int64_t e) const {
    return weight[e] / std::max(child_total[size_t(edge_cell[e])], scalar_t(1e-12));
  }
  bool parent_found(int64_t a) const { return parent_total[size_t(a)] > 0; }
  bool child_found(int64_t k) const { return child_total[size_t(k)] > 0; }
  scalar_t member_share(int64_t k) const { return scalar_t(1) / scalar_t(std::max<int64_t>(count[k], 1)); }
};

void check_graph(const std::vector<at::Tensor>& g, const at::Tensor& x) {
  TORCH_CHECK(g.size() == 7, "context_cpu: the graph is (cell, count, anchor, edge_cell, weight, by_cell, members)");
  for (size_t i = 0; i < g.size(); ++i) {
    TORCH_CHECK(g[i].device().is_cpu() && g[i].is_contiguous(), "context_cpu: graph tensors must be contiguous CPU");
    TORCH_CHECK(g[i].scalar_type() == (i == 4 ? x.scalar_type() : at::kLong),
                "context_cpu: graph index tensors must be int64 and its weights of the features' dtype");
  }
  TORCH_CHECK(x.device().is_cpu() && x.is_contiguous() && x.dim() >= 2 && x.size(0) == g[0].size(0),
              "context_cpu: features must be a contiguous CPU tensor with one row per anchor");
}

// out += s in over d values; d = 32 (the features' width) is unrolled at compile time.
template <typename scalar_t>
inline void axpy(scalar_t* out, const scalar_t* in, scalar_t s, int64_t d) {
  if (d == 32) {
    for (int64_t j = 0; j < 32; ++j) out[j] += s * in[j];
  } else {
    for (int64_t j = 0; j < d; ++j) out[j] += s * in[j];
  }
}

// fallback: 0 = the missing row (missing [2,d]: parent, child) where a context is absent (trilinear
// rule); 1 = c_self there (the paper's rule). Every output row is written once.
std::vector<at::Tensor> lookup_forward(const at::Tensor& x, const std::vector<at::Tensor>& graph,
                                       const at::Tensor& missing, int64_t fallback) {
  check_graph(graph, x);
  TORCH_CHECK(x.dim() == 2 && missing.is_contiguous() && missing.scalar_type() == x.scalar_type() &&
                  missing.dim() == 2 && missing.size(0) == 2 && missing.size(1) == x.size(1),
              "context_cpu: features must be [V,d] and missing [2,d] of their dtype");
  const int64_t d = x.size(1);
  auto out = at::empty({x.size(0), 3, d}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "lookup_forward", [&] {
    const Graph<scalar_t> g(graph);
    const scalar_t* xs = x.data_ptr<scalar_t>();
    const scalar_t* miss = missing.data_ptr<scalar_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    std::vector<scalar_t> pooled(size_t(g.num_cells * d), 0), child(size_t(g.num_cells * d), 0);
    at::parallel_for(0, g.num_cells, 256, [&](int64_t begin, int64_t end) {
      for (int64_t k = begin; k < end; ++k) {
        const scalar_t share = g.member_share(k);
        for (int64_t i = g.member_start[size_t(k)]; i < g.member_start[size_t(k) + 1]; ++i) {
          axpy(&pooled[size_t(k * d)], xs + g.members[i] * d, share, d);
        }
        for (int64_t i = g.cell_edge_start[size_t(k)]; i < g.cell_edge_start[size_t(k) + 1]; ++i) {
          const int64_t e = g.by_cell[i];
          axpy(&child[size_t(k * d)], xs + g.anchor[e] * d, g.child_share(e), d);
        }
      }
    });
    at::parallel_for(0, g.num, 256, [&](int64_t begin, int64_t end) {
      for (int64_t a = begin; a < end; ++a) {
        scalar_t* row = o + a * 3 * d;
        const scalar_t* own = &pooled[size_t(g.cell[a] * d)];
        std::copy_n(own, d, row + d);
        if (g.parent_found(a)) {
          std::fill_n(row, d, scalar_t(0));
          for (int64_t e = g.edge_start[size_t(a)]; e < g.edge_start[size_t(a) + 1]; ++e) {
            axpy(row, &pooled[size_t(g.edge_cell[e] * d)], g.parent_share(e), d);
          }
        } else {
          std::copy_n(fallback == 1 ? own : miss, d, row);
        }
        const bool child_found = g.child_found(g.cell[a]);
        std::copy_n(child_found ? &child[size_t(g.cell[a] * d)] : (fallback == 1 ? own : miss + d), d, row + 2 * d);
      }
    });
  });
  return {out};
}

// -> the gradients w.r.t. the features [V,d] and the missing rows [2,d] (0 under the paper's rule).
std::vector<at::Tensor> lookup_backward(const at::Tensor& grad, const std::vector<at::Tensor>& graph,
                                        int64_t fallback) {
  TORCH_CHECK(grad.dim() == 3 && grad.size(1) == 3, "context_cpu: the gradient must be [V,3,d]");
  check_graph(graph, grad);
  const int64_t d = grad.size(2);
  auto grad_x = at::empty({grad.size(0), d}, grad.options());
  auto grad_missing = at::zeros({2, d}, grad.options());
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "lookup_backward", [&] {
    const Graph<scalar_t> g(graph);
    const scalar_t* gr = grad.data_ptr<scalar_t>();
    scalar_t* gx = grad_x.data_ptr<scalar_t>();
    // Per cell: the gradient of its pooled mean (own rows of its members, parent rows of the anchors
    // reading it, and under the paper's rule the rows that fell back to c_self) and of its child mean
    // (child rows of its members that found one).
    std::vector<scalar_t> grad_pooled(size_t(g.num_cells * d), 0), grad_child(size_t(g.num_cells * d), 0);
    at::parallel_for(0, g.num_cells, 256, [&](int64_t begin, int64_t end) {
      for (int64_t k = begin; k < end; ++k) {
        scalar_t* gp = &grad_pooled[size_t(k * d)];
        const bool child_found = g.child_found(k);
        for (int64_t i = g.member_start[size_t(k)]; i < g.member_start[size_t(k) + 1]; ++i) {
          const int64_t a = g.members[i];
          const scalar_t* row = gr + a * 3 * d;
          axpy(gp, row + d, scalar_t(1), d);
          if (child_found) {
            axpy(&grad_child[size_t(k * d)], row + 2 * d, scalar_t(1), d);
          } else if (fallback == 1) {
            axpy(gp, row + 2 * d, scalar_t(1), d);
          }
          if (fallback == 1 && !g.parent_found(a)) axpy(gp, row, scalar_t(1), d);
        }
        for (int64_t i = g.cell_edge_start[size_t(k)]; i < g.cell_edge_start[size_t(k) + 1]; ++i) {
          const int64_t e = g.by_cell[i];
          axpy(gp, gr + g.anchor[e] * 3 * d, g.parent_share(e), d);
        }
      }
    });
    at::parallel_for(0, g.num, 256, [&](int64_t begin, int64_t end) {
      for (int64_t a = begin; a < end; ++a) {
        const int64_t k = g.cell[a];
        scalar_t* row = gx + a * d;
        const scalar_t share = g.member_share(k);
        const scalar_t* gp = &grad_pooled[size_t(k * d)];
        for (int64_t j = 0; j < d; ++j) row[j] = share * gp[j];
        for (int64_t e = g.edge_start[size_t(a)]; e < g.edge_start[size_t(a) + 1]; ++e) {
          axpy(row, &grad_child[size_t(g.edge_cell[e] * d)], g.child_share(e), d);
        }
      }
    });
    if (fallback == 0) {  // serial: the same sum whatever the thread count
      scalar_t* gm = grad_missing.data_ptr<scalar_t>();
      for (int64_t a = 0; a < g.num; ++a) {
        if (!g.parent_found(a)) axpy(gm, gr + a * 3 * d, scalar_t(1), d);
        if (!g.child_found(g.cell[a])) axpy(gm + d, gr + a * 3 * d + 2 * d, scalar_t(1), d);
      }
    }
  });
  return {grad_x, grad_missing};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("trilinear_parents", &trilinear_parents, "CLCA: trilinear parent candidates of each anchor");
  m.def("build_graph", &build_graph, "CLCA: one view's relation from cell keys and parent edges");
  m.def("lookup_forward", &lookup_forward, "CLCA: (c_parent, c_self, c_child) of every anchor");
  m.def("lookup_backward", &lookup_backward, "CLCA: the lookup's gradient w.r.t. the features");
}
