// CPU kernel of the cell-list pair search of torchdem/neighbors.py (find_pairs).
//
// Contract: `cell_pairs` takes the (wrapped) sphere positions and the cell grid of find_pairs
// (lower corner, cell size, cells per axis, periods) and returns every pair (i < j) of active
// spheres of different bodies whose minimum-image centre distance is below r_i + r_j + skin,
// as two int64 tensors sorted by (i, j) -- exactly the list of the torch path.
//
// Layout. One axis is the sort axis (the non-periodic axis with the most cells, else the axis
// with the most cells; z on the draw-down slice); the cells along it form columns. The
// active spheres with finite positions are counting-sorted by member, column and cell, then
// by their coordinate on the sort axis within each cell, so every column is one run of slots
// sorted by that coordinate (the cell of a coordinate is monotone in it).
//
// Search, parallel over chunks of whole columns, no atomics. The sphere in slot p of column C
// looks at the slots q > p of C and at every slot of the neighbouring columns C' > C (a half
// stencil: each unordered pair is looked at once, from one side), and only at those whose
// sort-axis coordinate lies within r_p + r_max + skin of its own (in the 3 cells next to p's,
// the window's edges walked from the previous query's; on a periodic sort axis the window
// wraps). Cells are at least one contact distance wide (find_pairs), so no pair lies outside
// the neighbouring columns' 3 cells. The pairs found, as (min, max) sphere index, are then
// grouped by i (count, prefix sum, scatter) and each sphere's partners sorted, so the list
// does not depend on the number of threads.
//
// Two grids (split > 0). A cell sized by the largest sphere holds many small spheres far from
// any contact of theirs. The spheres of radius up to `split` are then searched among
// themselves on a finer grid (cells of 2 split + skin, the 3 cells of each neighbouring
// column scanned whole: with cells that narrow the window walks cost more than they save),
// the larger ones among themselves on the grid (as above), and each larger sphere against the
// small ones on the grid (all 9 neighbouring columns, windows of r_p + the largest small
// radius + skin). Each pair is found once, by exactly one of the three searches, and the
// grouping makes the list the same as one grid's, pair for pair.
//
// Measured on a draw-down slice rebuild (5 members, 35.6k spheres, 175k pairs, one thread): 80
// candidates and 3.5 windows per sphere, 14.6-15.6 ms a call, against 21.8-22.5 ms for the scan
// it replaced (the 27 cells around every sphere, its partners j > i found by a bisection per cell).
// On a lab-geometry member with flat sinter (53,780 spheres of 2.0-8.0 mm, 209k pairs, one thread,
// scripts/bench_search.py): 45 ms with one grid, 34 ms split at 0.6 of the largest radius.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

#if defined(__GNUC__) && !defined(__clang__)
#define TORCHDEM_SCAN_LOOP inline __attribute__((always_inline))
#else
#define TORCHDEM_SCAN_LOOP inline
#endif

struct Grid {
  int64_t dims[3];
  bool periodic[3];
  double period[3];
  int64_t n_cells;
};

// The distinct cell coordinates next to coordinate c along one axis (at most 3): c - 1, c,
// c + 1 clipped at a wall face, wrapped on a periodic axis; a periodic axis of up to 3 cells
// has each of them once.
inline int axis_neighbours(const Grid& g, int a, int64_t c, int64_t* out) {
  const int64_t n = g.dims[a];
  if (g.periodic[a] && n <= 3) {
    for (int64_t k = 0; k < n; ++k) out[k] = k;
    return static_cast<int>(n);
  }
  int m = 0;
  for (int64_t d = -1; d <= 1; ++d) {
    int64_t x = c + d;
    if (g.periodic[a]) x = ((x % n) + n) % n;
    else if (x < 0 || x >= n) continue;
    out[m++] = x;
  }
  return m;
}

// First index in [lo, hi) of the sorted v whose value is >= t (kUpper: > t), hi if none, walked
// from the guess g: the queries of a column come in ascending order, so their window edges in a
// neighbouring column move a slot or two from one query to the next.
template <bool kUpper>
inline int64_t walk(const double* v, int64_t lo, int64_t hi, double t, int64_t g) {
  g = std::min(std::max(g, lo), hi);
  while (g < hi && (kUpper ? v[g] <= t : v[g] < t)) ++g;
  while (g > lo && (kUpper ? v[g - 1] > t : v[g - 1] >= t)) --g;
  return g;
}

// Cells [first, last] of a column along the sort axis, and the shift that brings their
// coordinates next to the query's (0, or -+ the period for the cells wrapped around); windowed:
// whether to narrow them to the query's window (not on a periodic axis of up to 3 cells, where
// the whole column is one run and the minimum image decides).
struct Run {
  int64_t first, last;
  double shift;
  bool windowed;
};

// The runs of cells next to cell c along the sort axis a (at most 2).
inline int sort_axis_runs(const Grid& g, int a, int64_t c, Run* out) {
  const int64_t n = g.dims[a];
  if (!g.periodic[a]) {
    out[0] = {std::max<int64_t>(c - 1, 0), std::min(c + 1, n - 1), 0.0, true};
    return 1;
  }
  if (n <= 3) {
    out[0] = {0, n - 1, 0.0, false};
    return 1;
  }
  if (c == 0) {
    out[0] = {0, 1, 0.0, true};
    out[1] = {n - 1, n - 1, g.period[a], true};  // image below the query: coordinate - period
    return 2;
  }
  if (c == n - 1) {
    out[0] = {n - 2, n - 1, 0.0, true};
    out[1] = {0, 0, -g.period[a], true};
    return 2;
  }
  out[0] = {c - 1, c + 1, 0.0, true};
  return 1;
}

// Candidate slots tested per vectorised pass.
constexpr int64_t kScan = 64;

// One sphere asking for its partners: position, radius, body.
struct Query {
  double x, y, z, r;
  int64_t body;
};

// What the scan reads of the sorted spheres (slots).
struct Sorted {
  const double *x, *y, *z;   // [n] positions by slot, one array per axis (the scan vectorises)
  const double* key;         // x, y or z: the sort-axis coordinate
  const double* radius;      // [n]
  const int64_t* body;       // [n]
  double period[3], inv_period[3];  // 0 on non-periodic axes
  double skin;

  // hit[k] = slot p0 + k is within reach of the query, k < n <= kScan: a branch-free loop the
  // compiler vectorises (hit is 64-bit like the operands: with 8-bit flags GCC vectorised 64
  // slots at a time, more than a window holds, and ran the scalar remainder). Positions are
  // wrapped into one period, so the minimum image is one shift, period * rint(d / period) (0 on
  // a non-periodic axis).
  TORCHDEM_SCAN_LOOP void scan(const Query& p, int64_t p0, int64_t n, int64_t* __restrict__ hit) const {
    const double px = period[0], py = period[1], pz = period[2];
    const double ix = inv_period[0], iy = inv_period[1], iz = inv_period[2];
    const double xp = p.x, yp = p.y, zp = p.z, r = p.r;
    const int64_t b = p.body;
    const double *__restrict__ ax = x + p0, *__restrict__ ay = y + p0, *__restrict__ az = z + p0,
                 *__restrict__ ar = radius + p0;
    const int64_t* __restrict__ ab = body + p0;
    for (int64_t k = 0; k < n; ++k) {
      double dx = xp - ax[k], dy = yp - ay[k], dz = zp - az[k];
      dx -= px * std::rint(dx * ix);
      dy -= py * std::rint(dy * iy);
      dz -= pz * std::rint(dz * iz);
      const double cut = r + ar[k] + skin;
      hit[k] = static_cast<int64_t>((dx * dx + dy * dy + dz * dz < cut * cut) & (ab[k] != b));
    }
  }

  // Calls emit(q) for every slot q in [q0, q1) in contact reach of the query.
  template <typename Emit>
  void scan_range(const Query& p, int64_t q0, int64_t q1, Emit&& emit) const {
    alignas(64) int64_t hit[kScan];
    for (int64_t s = q0; s < q1; s += kScan) {
      const int64_t m = std::min(kScan, q1 - s);
      scan(p, s, m, hit);
      for (int64_t t = 0; t < m; ++t)
        if (hit[t]) emit(s + t);
    }
  }
};

// The sort axis and the two column axes of the grid: axes[2] is the non-periodic axis with
// the most cells (the axis with the most cells when all are periodic).
inline void choose_axes(const Grid& g, int* axes) {
  int s = -1;
  for (int a = 0; a < 3; ++a)
    if (!g.periodic[a] && (s < 0 || g.dims[a] > g.dims[s])) s = a;
  if (s < 0)
    for (int a = 0; a < 3; ++a)
      if (s < 0 || g.dims[a] > g.dims[s]) s = a;
  int k = 0;
  for (int a = 0; a < 3; ++a)
    if (a != s) axes[k++] = a;
  axes[2] = s;
}

// A subset of the spheres counting-sorted into the columns of one grid: by member, column and
// cell, then by the sort-axis coordinate within each cell, so every column is one run of slots
// sorted by that coordinate (the cell of a coordinate is monotone in it).
struct Buckets {
  Grid g;
  int axes[3];
  int64_t members = 0, n_sort = 1, n_columns = 1;
  std::vector<int64_t> start;  // [members * n_cells + 1]: first slot of each member-cell
  std::vector<int64_t> order;  // [n] sphere of each slot
  std::vector<int64_t> cell;   // [n] cell of each slot along the sort axis
  std::vector<double> x, y, z, r;
  std::vector<int64_t> body;
  double r_max = 0.0;

  int64_t size() const { return static_cast<int64_t>(order.size()); }
  int64_t column_first(int64_t column) const { return start[column * n_sort]; }

  Sorted sorted(double skin) const {
    Sorted s{x.data(), y.data(), z.data(), nullptr, r.data(), body.data(), {}, {}, skin};
    s.key = axes[2] == 0 ? s.x : (axes[2] == 1 ? s.y : s.z);
    for (int a = 0; a < 3; ++a) {
      s.period[a] = g.periodic[a] ? g.period[a] : 0.0;
      s.inv_period[a] = g.periodic[a] ? 1.0 / g.period[a] : 0.0;
    }
    return s;
  }
};

// Buckets of the spheres i with take[i] != 0 (active, finite position, of the wanted size
// class) on the grid (lower, size, dims, period); a cell outside the grid is clamped into it.
// by_coordinate false: a cell's spheres stay in index order (for a search without windows,
// which scans whole cells).
template <typename scalar_t>
Buckets bucket(const scalar_t* x, const scalar_t* r, const int64_t* bd, const std::vector<uint8_t>& take, int64_t S,
               int64_t n_per_member, int64_t members, const std::vector<double>& lower, const double* size,
               const int64_t* dims, const std::vector<double>& period, bool by_coordinate = true) {
  Buckets out;
  Grid& g = out.g;
  for (int a = 0; a < 3; ++a) {
    g.dims[a] = dims[a];
    g.period[a] = period[a];
    g.periodic[a] = period[a] > 0;
  }
  g.n_cells = g.dims[0] * g.dims[1] * g.dims[2];
  choose_axes(g, out.axes);
  const int* axes = out.axes;
  out.members = members;
  out.n_sort = g.dims[axes[2]];
  out.n_columns = g.dims[axes[0]] * g.dims[axes[1]];
  const int64_t H = members * g.n_cells;
  TORCH_CHECK(H < (int64_t(1) << 40), "cell_pairs: ", H, " member-cells is too many for the start table");
  std::vector<int64_t> hash(S, H);
  out.start.assign(H + 1, 0);
  // the cells in parallel, the counts (a pass of increments) in order
  at::parallel_for(0, S, 2048, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      if (!take[i]) continue;
      const scalar_t* xi = x + 3 * i;
      int64_t c[3];
      for (int a = 0; a < 3; ++a) {
        const scalar_t f = std::floor((xi[a] - static_cast<scalar_t>(lower[a])) / static_cast<scalar_t>(size[a]));
        c[a] = f < 0 ? 0 : (f > static_cast<scalar_t>(g.dims[a] - 1) ? g.dims[a] - 1 : static_cast<int64_t>(f));
      }
      hash[i] = ((i / n_per_member) * out.n_columns + c[axes[0]] * g.dims[axes[1]] + c[axes[1]]) * out.n_sort + c[axes[2]];
    }
  });
  for (int64_t i = 0; i < S; ++i)
    if (hash[i] < H) ++out.start[hash[i] + 1];
  for (int64_t h = 0; h < H; ++h) out.start[h + 1] += out.start[h];
  const int64_t n = out.start[H];
  out.order.resize(n);
  {
    std::vector<int64_t> fill(out.start.begin(), out.start.end() - 1);
    for (int64_t i = 0; i < S; ++i)
      if (hash[i] < H) out.order[fill[hash[i]]++] = i;
  }
  // within each cell by the sort-axis coordinate (cells hold a few tens of spheres)
  const int s_ax = axes[2];
  auto& order = out.order;
  const auto& start = out.start;
  if (by_coordinate) at::parallel_for(0, H, 4096, [&](int64_t h0, int64_t h1) {
    for (int64_t h = h0; h < h1; ++h)
      if (start[h + 1] - start[h] > 1)
        std::sort(order.begin() + start[h], order.begin() + start[h + 1],
                  [&](int64_t a, int64_t b) { return x[3 * a + s_ax] < x[3 * b + s_ax]; });
  });
  out.x.resize(n), out.y.resize(n), out.z.resize(n), out.r.resize(n), out.body.resize(n), out.cell.resize(n);
  at::parallel_for(0, n, 2048, [&](int64_t p0, int64_t p1) {
    for (int64_t p = p0; p < p1; ++p) {
      const int64_t j = order[p];
      out.x[p] = static_cast<double>(x[3 * j]);
      out.y[p] = static_cast<double>(x[3 * j + 1]);
      out.z[p] = static_cast<double>(x[3 * j + 2]);
      out.r[p] = static_cast<double>(r[j]);
      out.body[p] = bd[j];
      out.cell[p] = hash[j] % out.n_sort;
    }
  });
  out.r_max = n ? *std::max_element(out.r.begin(), out.r.end()) : 0.0;
  return out;
}

// The pairs of a sphere of `q` and a sphere of `t` (two bucketings on one grid) in contact
// reach, appended to `found` as (min, max) sphere index, one flat vector per chunk of columns.
// kHalf (t is q): each unordered pair once, from the slots p < q of a column and the
// neighbouring columns C' > C (a half stencil); otherwise every sphere of q looks at all
// neighbouring columns of t (a full stencil). A query looks only at the slots whose sort-axis
// coordinate lies within r_p + r_max(t) + skin of its own (in the 3 cells next to p's, the
// window's edges walked from the previous query's; on a periodic sort axis the window wraps).
// Cells are at least one contact distance wide (find_pairs), so no pair lies outside the
// neighbouring columns' 3 cells.
//
// Partial searches (cell_pairs with `moved`) pass `asks(i)`, whether sphere i of q looks for
// partners (the others are passed over, so q may be t's own bucketing with a full stencil), and
// `accept(i, j)`, whether to keep a pair found from i.
struct Everyone {
  bool operator()(int64_t) const { return true; }
  bool operator()(int64_t, int64_t) const { return true; }
};

template <bool kHalf, bool kWindow = true, typename Accept = Everyone, typename Asks = Everyone>
void search(const Buckets& q, const Buckets& t, double skin, std::vector<std::vector<int64_t>>& found,
            Accept accept = Accept(), Asks asks = Asks()) {
  const Grid& g = t.g;
  const int* axes = t.axes;
  const int64_t n_sort = t.n_sort, n_columns = t.n_columns;
  const Sorted sq = q.sorted(skin), st = t.sorted(skin);
  // Chunks of whole member-columns of about kChunk query spheres, so the threads share the work evenly.
  constexpr int64_t kChunk = 1024;
  const int64_t G = q.members * n_columns;
  std::vector<int64_t> chunk_first{0};
  for (int64_t c = 0; c < G; ++c)
    if (q.column_first(c + 1) - q.column_first(chunk_first.back()) >= kChunk || c + 1 == G) chunk_first.push_back(c + 1);
  const int64_t n_chunks = static_cast<int64_t>(chunk_first.size()) - 1;
  const size_t base = found.size();
  found.resize(base + std::max<int64_t>(n_chunks, 0));
  at::parallel_for(0, n_chunks, 1, [&](int64_t k0, int64_t k1) {
    for (int64_t k = k0; k < k1; ++k) {
      auto& out = found[base + k];
      out.reserve(2 * 6 * (q.column_first(chunk_first[k + 1]) - q.column_first(chunk_first[k])));
      for (int64_t column = chunk_first[k]; column < chunk_first[k + 1]; ++column) {
        const int64_t p0 = q.column_first(column), p1 = q.column_first(column + 1);
        if (p0 == p1) continue;
        // the neighbouring member-columns (half stencil: from this one on, this one first)
        const int64_t member = column / n_columns, local = column % n_columns;
        int64_t u[3], v[3], next[9];
        const int nu = axis_neighbours(g, axes[0], local / g.dims[axes[1]], u);
        const int nv = axis_neighbours(g, axes[1], local % g.dims[axes[1]], v);
        int n_next = 0;
        if (kHalf) next[n_next++] = column;
        for (int a = 0; a < nu; ++a)
          for (int b = 0; b < nv; ++b) {
            const int64_t c = member * n_columns + u[a] * g.dims[axes[1]] + v[b];
            if (!kHalf || c > column) next[n_next++] = c;
          }
        int64_t lo_edge[9][2] = {}, hi_edge[9][2] = {};  // last window per column and run
        for (int64_t p = p0; p < p1; ++p) {
          const int64_t i = q.order[p];
          if (!asks(i)) continue;
          const Query query{q.x[p], q.y[p], q.z[p], q.r[p], q.body[p]};
          const double key = sq.key[p], reach = (q.r[p] + t.r_max + skin) * (1.0 + 1e-9);
          Run runs[2];
          const int n_runs = sort_axis_runs(g, axes[2], q.cell[p], runs);
          for (int c = 0; c < n_next; ++c)
            for (int k2 = 0; k2 < n_runs; ++k2) {
              const Run& run = runs[k2];
              int64_t q0 = t.start[next[c] * n_sort + run.first], q1 = t.start[next[c] * n_sort + run.last + 1];
              if (kWindow && run.windowed) {
                q0 = lo_edge[c][k2] = walk<false>(st.key, q0, q1, key + run.shift - reach, lo_edge[c][k2]);
                q1 = hi_edge[c][k2] = walk<true>(st.key, q0, q1, key + run.shift + reach, hi_edge[c][k2]);
              }
              if (kHalf && c == 0) q0 = std::max(q0, p + 1);
              st.scan_range(query, q0, q1, [&](int64_t slot) {
                const int64_t j = t.order[slot];
                if (!accept(i, j)) return;
                out.push_back(std::min(i, j));
                out.push_back(std::max(i, j));
              });
            }
        }
      }
    }
  });
}

// Every pair (i < j) of active spheres of different bodies closer than r_i + r_j + skin: see the
// file's contract. With split > 0 the spheres of radius up to `split` (the small ones) are
// searched among themselves on the fine grid (cells of 2 split + skin: fine_cell_size,
// fine_dims), the larger ones among themselves and against the small ones on the grid; the
// list is the same.
//
// Partial search (`moved` [S] bool given): only the pairs with at least one moved sphere are
// searched, each moved sphere looking at every neighbouring column (a full stencil); a pair of
// two moved spheres is found from both of its spheres and kept from the lower index. The pairs
// of `keep_i`, `keep_j` (the list of the last build) whose two spheres did not move and are
// active join them, and the grouping sorts the whole. When the unmoved spheres' positions are
// those of the last build, the list is the one a whole search at these positions gives, pair for
// pair (neighbors.find_pairs). Moved large against small: from the large sphere; moved small
// against unmoved large: from the small one.
std::tuple<at::Tensor, at::Tensor> cell_pairs(const at::Tensor& position, const at::Tensor& radius,
                                              const at::Tensor& body, const at::Tensor& active,
                                              std::vector<double> lower, std::vector<double> cell_size,
                                              std::vector<int64_t> dims, std::vector<double> period,
                                              int64_t n_per_member, double skin, double split,
                                              std::vector<double> fine_cell_size, std::vector<int64_t> fine_dims,
                                              const c10::optional<at::Tensor>& moved,
                                              const c10::optional<at::Tensor>& keep_i,
                                              const c10::optional<at::Tensor>& keep_j) {
  TORCH_CHECK(position.device().is_cpu(), "cell_pairs: CPU tensors only");
  TORCH_CHECK(lower.size() == 3 && cell_size.size() == 3 && dims.size() == 3 && period.size() == 3,
              "cell_pairs: lower, cell_size, dims and period need 3 entries");
  TORCH_CHECK(split <= 0 || (fine_cell_size.size() == 3 && fine_dims.size() == 3),
              "cell_pairs: a split radius needs fine_cell_size and fine_dims of 3 entries");
  TORCH_CHECK(n_per_member > 0, "cell_pairs: n_per_member must be positive, got ", n_per_member);
  TORCH_CHECK(position.dim() == 2 && position.size(1) == 3, "cell_pairs: position has shape ", position.sizes(),
              "; expected [S, 3]");
  const int64_t S = position.size(0);
  TORCH_CHECK(radius.numel() == S && body.numel() == S && active.numel() == S, "cell_pairs: radius, body and active ",
              "need ", S, " entries (one per sphere), got ", radius.numel(), ", ", body.numel(), " and ", active.numel());
  TORCH_CHECK(radius.scalar_type() == position.scalar_type(), "cell_pairs: radius has dtype ", radius.scalar_type(),
              "; expected ", position.scalar_type());
  const bool partial = moved.has_value();
  TORCH_CHECK(!partial || moved->numel() == S, "cell_pairs: moved needs ", S, " entries, got ", moved->numel());
  TORCH_CHECK(keep_i.has_value() == keep_j.has_value() && (partial || !keep_i.has_value()),
              "cell_pairs: keep_i and keep_j come together, and only with moved");
  auto pos = position.contiguous();
  auto rad = radius.contiguous();
  auto bod = body.contiguous().to(at::kLong);
  auto act = active.contiguous().to(at::kBool);
  const int64_t members = S ? (S + n_per_member - 1) / n_per_member : 0;
  const bool* active_i = act.data_ptr<bool>();
  const int64_t* bd = bod.data_ptr<int64_t>();
  std::vector<uint8_t> mv;
  if (partial) {
    auto m = moved->contiguous().to(at::kBool);
    const bool* pm = m.data_ptr<bool>();
    mv.assign(pm, pm + S);
  }
  // Spheres with a non-finite position have no pairs (every distance test with one fails).
  std::vector<uint8_t> small(S, 0), large(S, 0);
  std::vector<std::vector<int64_t>> found;  // (min, max) sphere index pairs, flat, per chunk
  AT_DISPATCH_FLOATING_TYPES(pos.scalar_type(), "cell_pairs", [&] {
    const scalar_t* x = pos.data_ptr<scalar_t>();
    const scalar_t* r = rad.data_ptr<scalar_t>();
    for (int64_t i = 0; i < S; ++i) {
      const scalar_t* xi = x + 3 * i;
      if (!active_i[i] || !(std::isfinite(xi[0]) && std::isfinite(xi[1]) && std::isfinite(xi[2]))) continue;
      (static_cast<double>(r[i]) <= split ? small[i] : large[i]) = 1;
    }
    auto grid = [&](const std::vector<uint8_t>& take, bool fine) {
      return fine ? bucket(x, r, bd, take, S, n_per_member, members, lower, fine_cell_size.data(), fine_dims.data(),
                           period, false)  // searched without windows
                  : bucket(x, r, bd, take, S, n_per_member, members, lower, cell_size.data(), dims.data(), period);
    };
    Buckets coarse = grid(large, false);
    if (!partial) {
      search<true>(coarse, coarse, skin, found);
      if (split > 0) {
        {
          const Buckets fine = grid(small, true);
          search<true, false>(fine, fine, skin, found);
        }
        search<false>(coarse, grid(small, false), skin, found);
      }
      return;
    }
    const auto once = [&](int64_t a, int64_t b) { return !mv[b] || a < b; };  // a: the moved query
    const auto unmoved = [&](int64_t, int64_t b) { return !mv[b]; };
    const auto asks = [&](int64_t a) { return mv[a] != 0; };
    search<false>(coarse, coarse, skin, found, once, asks);
    if (split > 0) {
      {
        const Buckets fine = grid(small, true);
        search<false, false>(fine, fine, skin, found, once, asks);
      }
      const Buckets small_coarse = grid(small, false);
      search<false>(coarse, small_coarse, skin, found, Everyone(), asks);
      search<false>(small_coarse, coarse, skin, found, unmoved, asks);
    }
  });
  if (keep_i.has_value()) {
    auto ki = keep_i->contiguous().to(at::kLong), kj = keep_j->contiguous().to(at::kLong);
    TORCH_CHECK(ki.numel() == kj.numel(), "cell_pairs: keep_i has ", ki.numel(), " entries and keep_j ", kj.numel());
    const int64_t *pi = ki.data_ptr<int64_t>(), *pj = kj.data_ptr<int64_t>();
    // in chunks, one found vector each (the grouping below does not depend on their order)
    constexpr int64_t kChunk = 8192;
    const int64_t K = ki.numel(), n_chunks = (K + kChunk - 1) / kChunk;
    const size_t base = found.size();
    found.resize(base + n_chunks);
    at::parallel_for(0, n_chunks, 1, [&](int64_t c0, int64_t c1) {
      for (int64_t c = c0; c < c1; ++c) {
        auto& kept = found[base + c];
        kept.reserve(2 * kChunk);
        for (int64_t e = c * kChunk; e < std::min(K, (c + 1) * kChunk); ++e) {
          const int64_t a = pi[e], b = pj[e];
          TORCH_CHECK(a >= 0 && a < b && b < S, "cell_pairs: kept pair (", a, ", ", b, ") is not i < j in [0, ", S, ")");
          if (!mv[a] && !mv[b] && (small[a] | large[a]) && (small[b] | large[b])) {
            kept.push_back(a);
            kept.push_back(b);
          }
        }
      }
    });
  }
  // Group by i: count, prefix sum, scatter, then sort each sphere's partners.
  std::vector<int64_t> offset(S + 1, 0);
  for (const auto& f : found)
    for (size_t e = 0; e < f.size(); e += 2) ++offset[f[e] + 1];
  for (int64_t i = 0; i < S; ++i) offset[i + 1] += offset[i];
  const int64_t P = offset[S];
  at::Tensor out_i = at::empty({P}, bod.options()), out_j = at::empty({P}, bod.options());
  int64_t* oi = out_i.data_ptr<int64_t>();
  int64_t* oj = out_j.data_ptr<int64_t>();
  {
    std::vector<int64_t> fill(offset.begin(), offset.end() - 1);
    for (const auto& f : found)
      for (size_t e = 0; e < f.size(); e += 2) oj[fill[f[e]]++] = f[e + 1];
  }
  at::parallel_for(0, S, 2048, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      std::fill(oi + offset[i], oi + offset[i + 1], i);
      std::sort(oj + offset[i], oj + offset[i + 1]);
    }
  });
  return {out_i, out_j};
}

// Every (sphere, wall) pair of an active sphere and a live wall whose gap (distance from the
// sphere centre to the closest point of the wall rectangle, minus the radius) is below the
// skin, sorted by (sphere, wall): what neighbors.find_wall_pairs computes with an [A, L]
// broadcast, in one pass over the spheres (parallel over chunks, copied out in order).
// Partial (`moved` [S] bool given): only the moved spheres are tested; an active sphere that did
// not move keeps its pairs of `keep_sphere`, `keep_wall` (the last build's list, sorted by
// sphere) with the walls that are live.
std::tuple<at::Tensor, at::Tensor> wall_pairs(const at::Tensor& position, const at::Tensor& radius,
                                              const at::Tensor& active, const at::Tensor& centre,
                                              const at::Tensor& axis_u, const at::Tensor& axis_v,
                                              const at::Tensor& half_u, const at::Tensor& half_v,
                                              const at::Tensor& wall_active, double skin,
                                              const c10::optional<at::Tensor>& moved,
                                              const c10::optional<at::Tensor>& keep_sphere,
                                              const c10::optional<at::Tensor>& keep_wall) {
  TORCH_CHECK(position.device().is_cpu(), "wall_pairs: CPU tensors only");
  const int64_t S = position.size(0), W = centre.size(0);
  TORCH_CHECK(radius.numel() == S && active.numel() == S, "wall_pairs: radius/active need ", S, " entries");
  const bool partial = moved.has_value();
  TORCH_CHECK(!partial || (moved->numel() == S && keep_sphere.has_value() && keep_wall.has_value() &&
                           keep_sphere->numel() == keep_wall->numel()),
              "wall_pairs: moved needs ", S, " entries and the kept list (keep_sphere, keep_wall) of equal length");
  at::Tensor mv, ks, kw;
  const bool* pm = nullptr;
  const int64_t *pks = nullptr, *pkw = nullptr;
  int64_t Q = 0;
  if (partial) {
    mv = moved->contiguous().to(at::kBool);
    ks = keep_sphere->contiguous().to(at::kLong);
    kw = keep_wall->contiguous().to(at::kLong);
    pm = mv.data_ptr<bool>();
    pks = ks.data_ptr<int64_t>();
    pkw = kw.data_ptr<int64_t>();
    Q = ks.numel();
    for (int64_t e = 0; e < Q; ++e)
      TORCH_CHECK(pks[e] >= 0 && pks[e] < S && pkw[e] >= 0 && pkw[e] < W && (e == 0 || pks[e] >= pks[e - 1]),
                  "wall_pairs: the kept list must be sorted by sphere, with spheres in [0, ", S, ") and walls in [0, ",
                  W, ")");
  }
  TORCH_CHECK(axis_u.size(0) == W && axis_v.size(0) == W && half_u.numel() == W && half_v.numel() == W &&
                  wall_active.numel() == W, "wall_pairs: wall tensors need ", W, " rows");
  auto pos = position.contiguous().to(at::kDouble);
  auto rad = radius.contiguous().to(at::kDouble);
  auto act = active.contiguous().to(at::kBool);
  auto c = centre.contiguous().to(at::kDouble);
  auto u = axis_u.contiguous().to(at::kDouble);
  auto v = axis_v.contiguous().to(at::kDouble);
  auto hu = half_u.contiguous().to(at::kDouble);
  auto hv = half_v.contiguous().to(at::kDouble);
  auto live = wall_active.contiguous().to(at::kBool);
  const double *x = pos.data_ptr<double>(), *r = rad.data_ptr<double>(), *pc = c.data_ptr<double>(),
               *pu = u.data_ptr<double>(), *pv = v.data_ptr<double>(), *phu = hu.data_ptr<double>(),
               *phv = hv.data_ptr<double>();
  const bool *a = act.data_ptr<bool>(), *l = live.data_ptr<bool>();
  // The unit normal of each wall (u x v of its orthonormal axes): a sphere's distance from the wall's
  // plane is a lower bound on its distance from the rectangle, so a sphere farther than the skin
  // from the plane (by a relative margin of 1e-5, above the 1e-6 the walls' axes may be off unit
  // length and square) is passed over with one dot product; most sphere-wall combinations of a box
  // are (the wall list was 4 % of a lab member's step).
  std::vector<double> normal(3 * W);
  for (int64_t w = 0; w < W; ++w) {
    const double* uw = pu + 3 * w;
    const double* vw = pv + 3 * w;
    normal[3 * w] = uw[1] * vw[2] - uw[2] * vw[1];
    normal[3 * w + 1] = uw[2] * vw[0] - uw[0] * vw[2];
    normal[3 * w + 2] = uw[0] * vw[1] - uw[1] * vw[0];
  }
  constexpr int64_t kChunk = 1024;
  const int64_t n_chunks = (S + kChunk - 1) / kChunk;
  std::vector<std::vector<int64_t>> chunk_s(n_chunks), chunk_w(n_chunks);
  at::parallel_for(0, n_chunks, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t ch = c0; ch < c1; ++ch) {
      int64_t kept = partial ? std::lower_bound(pks, pks + Q, ch * kChunk) - pks : 0;
      for (int64_t i = ch * kChunk; i < std::min(S, (ch + 1) * kChunk); ++i) {
        while (kept < Q && pks[kept] < i) ++kept;  // the old pairs of moved spheres
        if (partial && !pm[i]) {
          for (; kept < Q && pks[kept] == i; ++kept)
            if (a[i] && l[pkw[kept]]) {
              chunk_s[ch].push_back(i);
              chunk_w[ch].push_back(pkw[kept]);
            }
          continue;
        }
        if (!a[i]) continue;
        for (int64_t w = 0; w < W; ++w) {
          if (!l[w]) continue;
          const double d[3] = {x[3 * i] - pc[3 * w], x[3 * i + 1] - pc[3 * w + 1], x[3 * i + 2] - pc[3 * w + 2]};
          const double* nw = normal.data() + 3 * w;
          const double plane = std::abs(d[0] * nw[0] + d[1] * nw[1] + d[2] * nw[2]);
          if (plane - r[i] > skin + 1e-5 * (plane + r[i] + skin)) continue;
          const double* uw = pu + 3 * w;
          const double* vw = pv + 3 * w;
          const double su = std::min(std::max(d[0] * uw[0] + d[1] * uw[1] + d[2] * uw[2], -phu[w]), phu[w]);
          const double sv = std::min(std::max(d[0] * vw[0] + d[1] * vw[1] + d[2] * vw[2], -phv[w]), phv[w]);
          double g2 = 0;
          for (int k = 0; k < 3; ++k) {
            const double e = d[k] - su * uw[k] - sv * vw[k];
            g2 += e * e;
          }
          if (std::sqrt(g2) - r[i] < skin) {
            chunk_s[ch].push_back(i);
            chunk_w[ch].push_back(w);
          }
        }
      }
    }
  });
  std::vector<int64_t> offset(n_chunks + 1, 0);
  for (int64_t ch = 0; ch < n_chunks; ++ch) offset[ch + 1] = offset[ch] + static_cast<int64_t>(chunk_s[ch].size());
  auto opts = at::TensorOptions().dtype(at::kLong);
  at::Tensor out_s = at::empty({offset[n_chunks]}, opts), out_w = at::empty({offset[n_chunks]}, opts);
  int64_t *os = out_s.data_ptr<int64_t>(), *ow = out_w.data_ptr<int64_t>();
  for (int64_t ch = 0; ch < n_chunks; ++ch) {
    std::copy(chunk_s[ch].begin(), chunk_s[ch].end(), os + offset[ch]);
    std::copy(chunk_w[ch].begin(), chunk_w[ch].end(), ow + offset[ch]);
  }
  return {out_s, out_w};
}

// History of a rebuilt contact list (neighbors.carry_history): for every new key, the row of
// each old value tensor whose key matches (old keys sorted, unique), zeros when none does.
// Rebuilt lists come out sorted by key, so each chunk of new keys walks the old keys forward
// from where its previous key matched (a few steps) and binary-searches only when the new
// keys go backwards or the walk gets long: O(P) for sorted lists, O(P log P) otherwise. It
// replaces a searchsorted and two masked copies per tensor (three passes and two temporaries).
std::vector<at::Tensor> carry_history(const at::Tensor& old_key, const std::vector<at::Tensor>& old_values,
                                      const at::Tensor& new_key) {
  TORCH_CHECK(old_key.device().is_cpu() && new_key.device().is_cpu(), "carry_history: CPU tensors only");
  TORCH_CHECK(old_key.dim() == 1 && new_key.dim() == 1, "carry_history: keys must be 1-D, got ", old_key.sizes(),
              " and ", new_key.sizes());
  auto ok = old_key.contiguous().to(at::kLong);
  auto nk = new_key.contiguous().to(at::kLong);
  const int64_t n_old = ok.size(0), n_new = nk.size(0);
  const int64_t* o = ok.data_ptr<int64_t>();
  const int64_t* k = nk.data_ptr<int64_t>();
  // match[e]: row of the old list for new key e, or -1.
  std::vector<int64_t> match(n_new, -1);
  constexpr int64_t kChunk = 4096;
  at::parallel_for(0, (n_new + kChunk - 1) / kChunk, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      const int64_t e0 = c * kChunk, e1 = std::min(n_new, e0 + kChunk);
      int64_t p = 0;
      for (int64_t e = e0; e < e1; ++e) {
        const int64_t key = k[e];
        if (e == e0 || key < k[e - 1]) {
          p = std::lower_bound(o, o + n_old, key) - o;
        } else {
          int steps = 0;
          while (p < n_old && o[p] < key && steps < 16) ++p, ++steps;
          if (p < n_old && o[p] < key) p = std::lower_bound(o + p, o + n_old, key) - o;
        }
        if (p < n_old && o[p] == key) match[e] = p;
      }
    }
  });
  std::vector<at::Tensor> out;
  out.reserve(old_values.size());
  for (const auto& value : old_values) {
    TORCH_CHECK(value.device().is_cpu(), "carry_history: CPU tensors only");
    TORCH_CHECK(value.dim() >= 1 && value.size(0) == n_old, "carry_history: a value has shape ", value.sizes(),
                "; expected [", n_old, ", ...]");
    auto v = value.contiguous();
    auto shape = v.sizes().vec();
    shape[0] = n_new;
    at::Tensor result = at::empty(shape, v.options());
    int64_t width = 1;
    for (int64_t d = 1; d < v.dim(); ++d) width *= v.size(d);
    AT_DISPATCH_FLOATING_TYPES(v.scalar_type(), "carry_history", [&] {
      const scalar_t* src = v.data_ptr<scalar_t>();
      scalar_t* dst = result.data_ptr<scalar_t>();
      at::parallel_for(0, n_new, 4096, [&](int64_t e0, int64_t e1) {
        for (int64_t e = e0; e < e1; ++e) {
          scalar_t* row = dst + width * e;
          if (match[e] < 0) std::fill(row, row + width, scalar_t(0));
          else std::copy(src + width * match[e], src + width * (match[e] + 1), row);
        }
      });
    });
    out.push_back(result);
  }
  return out;
}

}  // namespace

// torch.ops.torchdem.cell_pairs and wall_pairs (a fragment: contact_cpu.cpp, built into the same extension,
// defines the library).
// The per-pair constants of a rebuilt sphere-sphere list (integrate.rebuild), in one pass
// instead of ~25 tensor operations over the list: index [3, P] int64 (key i S + j, body_i,
// body_j) and value [5 + F, P] (radius_i, radius_j, R*, m*, I_r* of the EPSD damping, then the F
// rows of `table` [F, R] at column pair_row[i] + material[j]). Each row is contiguous, so its
// views are what the pair kernel reads. Per sphere [S]: radius, mass, rolling_inertia (the
// body's), body, pair_row, material. Indices are checked; the values are what the torch path
// computes, bit for bit (same operations in the same order). values = false: value is [0, P] (the
// C++ pair kernel looks the constants up per sphere; a rebuild for it writes the index only: a
// flowing lab member's step 4 % faster, 8.71 against 8.33 ms in three alternating pairs).
std::vector<at::Tensor> pair_constants(const at::Tensor& i, const at::Tensor& j, const at::Tensor& radius,
                                       const at::Tensor& mass, const at::Tensor& rolling_inertia,
                                       const at::Tensor& body, const at::Tensor& pair_row, const at::Tensor& material,
                                       const at::Tensor& table, bool values) {
  TORCH_CHECK(i.device().is_cpu() && table.device().is_cpu(), "pair_constants: CPU tensors only");
  const int64_t P = i.numel(), S = radius.numel(), F = table.size(0), R = table.size(1);
  TORCH_CHECK(j.numel() == P, "pair_constants: i has ", P, " entries and j ", j.numel());
  for (const at::Tensor* t : {&mass, &rolling_inertia, &body, &pair_row, &material})
    TORCH_CHECK(t->numel() == S, "pair_constants: a per-sphere tensor has ", t->numel(), " entries; expected ", S);
  TORCH_CHECK(table.dim() == 2, "pair_constants: table must be [F, R], got ", table.sizes());
  for (const at::Tensor* t : {&mass, &rolling_inertia, &table})
    TORCH_CHECK(t->scalar_type() == radius.scalar_type(), "pair_constants: mixed dtypes ", t->scalar_type(), " and ",
                radius.scalar_type());
  auto ic = i.contiguous().to(at::kLong), jc = j.contiguous().to(at::kLong), bc = body.contiguous().to(at::kLong),
       rc = pair_row.contiguous().to(at::kLong), mc = material.contiguous().to(at::kLong);
  auto rad = radius.contiguous(), ms = mass.contiguous(), ir = rolling_inertia.contiguous(), tab = table.contiguous();
  const int64_t *pi = ic.data_ptr<int64_t>(), *pj = jc.data_ptr<int64_t>(), *pb = bc.data_ptr<int64_t>(),
                *prow = rc.data_ptr<int64_t>(), *pmat = mc.data_ptr<int64_t>();
  at::Tensor index = at::empty({3, P}, ic.options());
  at::Tensor value = at::empty({values ? 5 + F : 0, P}, rad.options());
  int64_t* key = index.data_ptr<int64_t>();
  int64_t *body_i = key + P, *body_j = key + 2 * P;
  std::atomic<int64_t> bad{0};
  AT_DISPATCH_FLOATING_TYPES(rad.scalar_type(), "pair_constants", [&] {
    const scalar_t *r = rad.data_ptr<scalar_t>(), *m = ms.data_ptr<scalar_t>(), *I = ir.data_ptr<scalar_t>(),
                   *t = tab.data_ptr<scalar_t>();
    scalar_t* v = value.data_ptr<scalar_t>();
    at::parallel_for(0, P, 4096, [&](int64_t p0, int64_t p1) {
      int64_t n_bad = 0;
      for (int64_t p = p0; p < p1; ++p) {
        const int64_t a = pi[p], b = pj[p];
        if (static_cast<uint64_t>(a) >= static_cast<uint64_t>(S) || static_cast<uint64_t>(b) >= static_cast<uint64_t>(S)) {
          ++n_bad;
          continue;
        }
        const int64_t col = prow[a] + pmat[b];
        if (static_cast<uint64_t>(col) >= static_cast<uint64_t>(R)) {
          ++n_bad;
          continue;
        }
        key[p] = a * S + b;
        body_i[p] = pb[a];
        body_j[p] = pb[b];
        if (!values) continue;
        const scalar_t ri = r[a], rj = r[b], mi = m[a], mj = m[b], Ii = I[a], Ij = I[b];
        v[p] = ri;
        v[P + p] = rj;
        v[2 * P + p] = ri * rj / (ri + rj);
        v[3 * P + p] = mi * mj / (mi + mj);
        v[4 * P + p] = Ii * Ij / (Ii + Ij);
        for (int64_t f = 0; f < F; ++f) v[(5 + f) * P + p] = t[f * R + col];
      }
      bad += n_bad;
    });
  });
  TORCH_CHECK(bad.load() == 0, "pair_constants: ", bad.load(), " pairs have a sphere index outside [0, ", S,
              ") or a table column outside [0, ", R, ")");
  return {index, value};
}

// The order that sorts a list of pairs (lo, hi) [P] of indices in [0, n) by lo, then hi: what
// torch.argsort(lo * n + hi) gives for unique pairs (reorder's renumbered lists), by a counting
// sort on lo and a sort of each lo's few partners, about 5x faster on one thread than the
// comparison sort of the keys.
at::Tensor pair_order(const at::Tensor& lo, const at::Tensor& hi, int64_t n) {
  TORCH_CHECK(lo.device().is_cpu() && hi.device().is_cpu(), "pair_order: CPU tensors only");
  TORCH_CHECK(lo.dim() == 1 && hi.dim() == 1 && lo.numel() == hi.numel(), "pair_order: lo and hi must be 1-D of ",
              "one length, got ", lo.sizes(), " and ", hi.sizes());
  auto lc = lo.contiguous().to(at::kLong), hc = hi.contiguous().to(at::kLong);
  const int64_t P = lc.numel();
  const int64_t *pl = lc.data_ptr<int64_t>(), *ph = hc.data_ptr<int64_t>();
  std::vector<int64_t> offset(n + 1, 0);
  for (int64_t e = 0; e < P; ++e) {
    TORCH_CHECK(pl[e] >= 0 && pl[e] < n && ph[e] >= 0 && ph[e] < n, "pair_order: pair (", pl[e], ", ", ph[e],
                ") is outside [0, ", n, ")");
    ++offset[pl[e] + 1];
  }
  for (int64_t i = 0; i < n; ++i) offset[i + 1] += offset[i];
  at::Tensor order = at::empty({P}, lc.options());
  int64_t* po = order.data_ptr<int64_t>();
  {
    std::vector<int64_t> fill(offset.begin(), offset.end() - 1);
    for (int64_t e = 0; e < P; ++e) po[fill[pl[e]]++] = e;
  }
  at::parallel_for(0, n, 2048, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i)
      std::sort(po + offset[i], po + offset[i + 1], [&](int64_t a, int64_t b) { return ph[a] < ph[b] || (ph[a] == ph[b] && a < b); });
  });
  return order;
}

TORCH_LIBRARY_FRAGMENT(torchdem, m) {
  m.def("pair_order(Tensor lo, Tensor hi, int n) -> Tensor");
  m.impl("pair_order", c10::DispatchKey::CPU, TORCH_FN(pair_order));
  m.def("cell_pairs(Tensor position, Tensor radius, Tensor body, Tensor active, float[] lower, float[] cell_size, "
        "int[] dims, float[] period, int n_per_member, float skin, float split=0., float[] fine_cell_size=[], "
        "int[] fine_dims=[], Tensor? moved=None, Tensor? keep_i=None, Tensor? keep_j=None) -> (Tensor, Tensor)");
  m.impl("cell_pairs", c10::DispatchKey::CPU, TORCH_FN(cell_pairs));
  m.def("wall_pairs(Tensor position, Tensor radius, Tensor active, Tensor centre, Tensor axis_u, Tensor axis_v, "
        "Tensor half_u, Tensor half_v, Tensor wall_active, float skin, Tensor? moved=None, Tensor? keep_sphere=None, "
        "Tensor? keep_wall=None) -> (Tensor, Tensor)");
  m.impl("wall_pairs", c10::DispatchKey::CPU, TORCH_FN(wall_pairs));
  m.def("carry_history(Tensor old_key, Tensor[] old_values, Tensor new_key) -> Tensor[]");
  m.impl("carry_history", c10::DispatchKey::CPU, TORCH_FN(carry_history));
  m.def("pair_constants(Tensor i, Tensor j, Tensor radius, Tensor mass, Tensor rolling_inertia, Tensor body, "
        "Tensor pair_row, Tensor material, Tensor table, bool values=True) -> Tensor[]");
  m.impl("pair_constants", c10::DispatchKey::CPU, TORCH_FN(pair_constants));
}
