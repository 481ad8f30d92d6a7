// CPU kernels for the sphere-sphere and sphere-wall contacts of torchdem.
//
// Contract: `pair_forces` and `wall_forces` compute exactly what `pair_kernel` and
// `wall_kernel` in torchdem/integrate.py compute with the laws of torchdem/contact.py
// (Hertz-Mindlin no-slip with tangential history, EPSD type-C rolling resistance with
// history, periodic minimum image), plus the SJKR cohesion of contact.sjkr_cohesion where the
// caller gives it (integrate.pair_cohesion / wall_cohesion in the torch path), in float32 or
// float64, and return new tensors
// (force, torque, tangential, rolling); nothing passed in is modified. `pair_forces` takes
// the per-pair constants of pair_kernel as per-sphere arrays and the material-pair table
// (see PairData), `wall_forces` as per-contact arrays like wall_kernel.
//
// Per block of 64 contacts: pick the pairs that can touch (about a quarter of a Verlet list;
// the others get zero springs and no row), gather their operands (scalar loads), apply the
// contact law in a branch-free loop that the compiler vectorises across contacts, write the
// springs and a row (force, torques) per touching contact, packed at the front of the block's
// row space. The rows reach the bodies in one of two ways:
//   - ensemble (`members` > 1 and the contacts grouped by member, as the neighbour search
//     returns them): each thread owns whole members, i.e. their contacts and their bodies,
//     and adds every block's rows to its bodies right away (one pass; the rows of a large
//     ensemble never travel through memory);
//   - otherwise two passes: all rows first, then each thread owns a range of bodies and
//     adds the rows of their contacts.
// Either way every body sums its contacts in contact order, each output element is written
// by one thread and no atomics are used: results are bitwise the same for both schemes and
// any number of threads. They differ from the torch kernels by rounding only (operation
// order, fused multiply-add).
//
// Each worker runs with the caller's flush-to-zero / denormals-are-zero flags
// (torch.set_flush_denormal sets them on the calling thread only): contact springs decay
// through subnormal floats, which x86 handles in microcode, many times slower.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>
#include <optional>
#include <vector>

#include "kick.h"
#include "recycle.h"

#if defined(__SSE__) || defined(__x86_64__)
#include <xmmintrin.h>
#define TORCHDEM_HAVE_MXCSR 1
#endif

namespace {

constexpr unsigned kDenormalFlags = 0x8040;  // MXCSR FTZ (bit 15) | DAZ (bit 6)
constexpr double kPi = 3.14159265358979323846;
constexpr int64_t kBlockContacts = 64;  // contacts per block: gathered operands stay in L1

// Applies the caller's denormal flags to a worker thread for one parallel chunk.
class DenormalMode {
 public:
  explicit DenormalMode(unsigned caller) {
#ifdef TORCHDEM_HAVE_MXCSR
    saved_ = _mm_getcsr();
    _mm_setcsr((saved_ & ~kDenormalFlags) | (caller & kDenormalFlags));
#else
    (void)caller;
#endif
  }
  ~DenormalMode() {
#ifdef TORCHDEM_HAVE_MXCSR
    _mm_setcsr(saved_);
#endif
  }
  static unsigned caller() {
#ifdef TORCHDEM_HAVE_MXCSR
    return _mm_getcsr();
#else
    return 0;
#endif
  }

 private:
  unsigned saved_ = 0;
};

#define TORCHDEM_INLINE inline __attribute__((always_inline))
#if defined(__clang__) || !defined(__GNUC__)
#define TORCHDEM_SCALAR_LOOP __attribute__((noinline))
#else
#define TORCHDEM_SCALAR_LOOP __attribute__((noinline, optimize("no-tree-vectorize")))
#endif

template <typename T>
struct Vec3 {
  T x, y, z;
};

template <typename T> TORCHDEM_INLINE Vec3<T> operator+(Vec3<T> a, Vec3<T> b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
template <typename T> TORCHDEM_INLINE Vec3<T> operator-(Vec3<T> a, Vec3<T> b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
template <typename T> TORCHDEM_INLINE Vec3<T> operator*(T s, Vec3<T> a) { return {s * a.x, s * a.y, s * a.z}; }
template <typename T> TORCHDEM_INLINE T dot(Vec3<T> a, Vec3<T> b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
template <typename T> TORCHDEM_INLINE T norm(Vec3<T> a) { return std::sqrt(dot(a, a)); }
template <typename T> TORCHDEM_INLINE Vec3<T> cross(Vec3<T> a, Vec3<T> b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
template <typename T> TORCHDEM_INLINE Vec3<T> select(bool m, Vec3<T> a, Vec3<T> b) {
  return {m ? a.x : b.x, m ? a.y : b.y, m ? a.z : b.z};
}
template <typename T> TORCHDEM_INLINE Vec3<T> load(const T* p, int64_t k) {
  return {p[3 * k], p[3 * k + 1], p[3 * k + 2]};
}
template <typename T> TORCHDEM_INLINE void store(T* p, int64_t k, Vec3<T> a) {
  p[3 * k] = a.x;
  p[3 * k + 1] = a.y;
  p[3 * k + 2] = a.z;
}

// Shortest periodic image of a separation: period p > 0 with inv_period 1 / p on periodic
// axes; p = inv_period = 0 elsewhere (then the correction is 0 * nearbyint(0) = 0).
template <typename T>
TORCHDEM_INLINE Vec3<T> minimum_image(Vec3<T> d, const T* period, const T* inv_period) {
  return {d.x - period[0] * std::rint(d.x * inv_period[0]), d.y - period[1] * std::rint(d.y * inv_period[1]),
          d.z - period[2] * std::rint(d.z * inv_period[2])};
}

// contact.rotate_history: project onto the tangent plane, keep the length.
template <typename T>
TORCHDEM_INLINE Vec3<T> rotate_history(Vec3<T> s, Vec3<T> n) {
  const Vec3<T> proj = s - dot(s, n) * n;
  const T old_len = norm(s);
  const T new_len = norm(proj);
  const T scale = new_len > 0 ? old_len / std::max(new_len, std::numeric_limits<T>::min()) : T(0);
  return scale * proj;
}

// contact.sjkr_contact_area of two spheres at centre distance dist: the area of the intersection
// circle of their surfaces, 0 unless they overlap.
template <typename T>
TORCHDEM_INLINE T sjkr_pair_area(T overlap, T dist, T ri, T rj) {
  const T d = std::max(dist, std::numeric_limits<T>::min());
  const T area = T(-0.25 * kPi) * (d - ri - rj) * (d + ri - rj) * (d - ri + rj) * (d + ri + rj) / (d * d);
  return overlap > 0 ? std::max(area, T(0)) : T(0);
}

// contact.sjkr_contact_area of a sphere of radius r at distance dist from a wall.
template <typename T>
TORCHDEM_INLINE T sjkr_wall_area(T overlap, T dist, T r) {
  const T area = T(kPi) * (r * r - dist * dist);
  return overlap > 0 ? std::max(area, T(0)) : T(0);
}

// Per-contact constants (one row of PairContacts / WallContacts).
template <typename T>
struct Coefficients {
  T radius_eff, mass_eff, young_eff, shear_eff, beta, mu_s, mu_r, rolling_damping, rolling_inertia;
};

template <typename T>
struct LawResult {
  Vec3<T> force;           // on the first body, N
  Vec3<T> m_roll;          // rolling torque on the first body, N m
  Vec3<T> tangential_new;  // updated spring, m
  Vec3<T> rolling_new;     // updated spring torque, N m
};

// contact.hertz_mindlin followed by contact.rolling_epsd, for one contact. Branch-free
// (selects instead of branches), values in and out (no references), and the stiffness
// model a template argument, so that the loops calling it vectorise after inlining.
// kAi2011: rolling stiffness model "ai2011" (else "tangential").
template <typename T, bool kAi2011>
TORCHDEM_INLINE LawResult<T> contact_law(T overlap, Vec3<T> n, Vec3<T> v_rel, Vec3<T> w_rel, Vec3<T> tangential,
                                         Vec3<T> rolling, Coefficients<T> c, T dt) {
  constexpr T tiny = std::numeric_limits<T>::min();
  const Vec3<T> zero{T(0), T(0), T(0)};
  const T sqrt_5_6 = T(0.91287092917527690);  // sqrt(5/6)
  const bool touching = overlap > 0;
  const T delta = touching ? overlap : T(0);
  // Hertz-Mindlin.
  const T v_n = dot(v_rel, n);
  const Vec3<T> v_t = v_rel - v_n * n;
  const T sqrt_rd = std::sqrt(c.radius_eff * delta);
  const T k_n = T(2) * c.young_eff * sqrt_rd;
  const T k_t = T(8) * c.shear_eff * sqrt_rd;
  const T damp = T(-2) * sqrt_5_6 * c.beta;
  const T f_n_touch = T(2.0 / 3.0) * k_n * delta + damp * std::sqrt(k_n * c.mass_eff) * v_n;
  const T f_n = touching ? f_n_touch : T(0);
  Vec3<T> xi = select(touching, rotate_history(tangential, n) + dt * v_t, zero);
  const Vec3<T> f_spring = (-k_t) * xi;
  const T f_spring_mag = norm(f_spring);
  const T f_limit = c.mu_s * std::abs(f_n);
  const bool sliding = f_spring_mag > f_limit;  // spring at the Coulomb limit, no dashpot
  const T ratio = sliding ? f_limit / std::max(f_spring_mag, tiny) : T(1);
  xi = ratio * xi;
  const Vec3<T> f_t = select(sliding, ratio * f_spring, f_spring - (damp * std::sqrt(k_t * c.mass_eff)) * v_t);
  LawResult<T> out;
  out.force = f_t - f_n * n;
  out.tangential_new = xi;
  // EPSD rolling resistance.
  const Vec3<T> w_t = w_rel - dot(w_rel, n) * n;
  const T r2 = c.radius_eff * c.radius_eff;
  const T k_r = kAi2011 ? T(2.25) * c.mu_r * c.mu_r * r2 * (T(4.0 / 3.0) * c.young_eff * sqrt_rd) : k_t * r2;
  Vec3<T> m_spring = select(touching, rotate_history(rolling, n) - (k_r * dt) * w_t, zero);
  const T mag = norm(m_spring);
  const T limit = c.mu_r * c.radius_eff * std::abs(f_n);
  const bool full = mag > limit;  // spring at its plastic limit, no dashpot
  m_spring = (full ? limit / std::max(mag, tiny) : T(1)) * m_spring;
  const T c_r = c.rolling_damping * T(2) * std::sqrt(c.rolling_inertia * k_r);
  out.m_roll = select(full, m_spring, m_spring - c_r * w_t);
  out.rolling_new = m_spring;
  return out;
}

// Rows of a block of contacts: the contact law writes one row per contact it ran on, packed at
// the front of the block's row space; sel[t] is the contact (offset from the block's first) of
// row t. Contacts without a row (not touching) add nothing, so the rows of the three quarters of
// a Verlet list that do not touch are neither written nor read back.

// A row is the force on the first body (3), the torque on it (3) and, with a second body (width 9),
// the torque on that one (3); the second body gets minus the force.
template <typename T>
TORCHDEM_INLINE void add_to_first(const T* r, T* f, T* t) {
  f[0] += r[0];
  f[1] += r[1];
  f[2] += r[2];
  t[0] += r[3];
  t[1] += r[4];
  t[2] += r[5];
}

template <typename T>
TORCHDEM_INLINE void add_to_second(const T* r, T* f, T* t) {
  f[0] -= r[0];
  f[1] -= r[1];
  f[2] -= r[2];
  t[0] += r[6];
  t[1] += r[7];
  t[2] += r[8];
}

// Adds one row to its bodies (body_b nullptr: one body).
template <typename T>
TORCHDEM_INLINE void add_row(int64_t a, const int64_t* body_b, int64_t e, const T* r, T* force, T* torque) {
  add_to_first<T>(r, force + 3 * a, torque + 3 * a);
  if (body_b != nullptr) add_to_second<T>(r, force + 3 * body_b[e], torque + 3 * body_b[e]);
}

// Adds the packed rows of every block to their bodies: out = in + sum over rows, in contact
// order. Block k covers contacts [k kBlockContacts, ...), has count[k] rows at
// rows + width k kBlockContacts and their offsets at sel + k kBlockContacts; its rows act on
// bodies in [span[2k], span[2k + 1]] only.
// Each thread owns a contiguous range of bodies and scans the rows of the blocks whose span meets
// it, adding only to its own bodies: every body is written by one thread and sums in contact
// order, whatever the number of threads. In spatial body order most blocks meet one thread's
// range, so two threads each read about half the rows, not all of them. Body indices must be in
// [0, n_bodies).
template <typename T>
void scatter_to_bodies(const int64_t* __restrict__ body_a, const int64_t* __restrict__ body_b,
                       const T* __restrict__ rows, const int32_t* __restrict__ sel, const int64_t* count,
                       const int64_t* __restrict__ block_span, int width, int64_t n, int64_t n_bodies,
                       const T* force_in, const T* torque_in, T* force_out, T* torque_out) {
  const int64_t n_blocks = (n + kBlockContacts - 1) / kBlockContacts;
  at::parallel_for(0, n_bodies, 1024, [&](int64_t b0, int64_t b1) {
    const uint64_t span = static_cast<uint64_t>(b1 - b0);
    std::copy(force_in + 3 * b0, force_in + 3 * b1, force_out + 3 * b0);
    std::copy(torque_in + 3 * b0, torque_in + 3 * b1, torque_out + 3 * b0);
    for (int64_t blk = 0; blk < n_blocks; ++blk) {
      if (block_span[2 * blk + 1] < b0 || block_span[2 * blk] >= b1) continue;  // none of its rows is ours
      const int64_t c0 = blk * kBlockContacts;
      for (int64_t t = 0; t < count[blk]; ++t) {
        const int64_t e = c0 + sel[c0 + t];
        const T* r = rows + width * (c0 + t);
        const int64_t a = body_a[e];
        if (static_cast<uint64_t>(a - b0) < span) add_to_first<T>(r, force_out + 3 * a, torque_out + 3 * a);
        if (body_b != nullptr) {
          const int64_t b = body_b[e];
          if (static_cast<uint64_t>(b - b0) < span) add_to_second<T>(r, force_out + 3 * b, torque_out + 3 * b);
        }
      }
    }
  });
}

// Adds the m packed rows of the block starting at contact c0 to their bodies, in order,
// single-threaded.
template <typename T>
TORCHDEM_INLINE void add_rows(const int64_t* body_a, const int64_t* body_b, int64_t c0, const int32_t* sel,
                              const T* rows, int width, int64_t m, T* force, T* torque) {
  for (int64_t t = 0; t < m; ++t) {
    const int64_t e = c0 + sel[t];
    add_row<T>(body_a[e], body_b, e, rows + width * t, force, torque);
  }
}

// Contacts of an ensemble grouped by member: start[m] is the first contact of member m
// (start[members] = n), read off body_a (member = body / bodies_per_member), assuming the
// contacts are sorted by member; callers check ownership while they use it. Empty (use two
// passes) when the bodies do not split evenly into members, or when whole members would load
// the threads unevenly (fewer than two members per thread and not a multiple of them). One
// member on one thread (a campaign worker's run) is one range too: two passes would only write
// every row to a buffer and read it back.
inline std::vector<int64_t> member_starts(const int64_t* body_a, int64_t n, int64_t n_bodies, int64_t members) {
  std::vector<int64_t> start;
  const int64_t threads = at::get_num_threads();
  const bool balanced = members % threads == 0 || members >= 2 * threads;
  if (members < 1 || (members < 2 && threads > 1) || n_bodies % members != 0 || !balanced) return start;
  const int64_t per = n_bodies / members;
  start.resize(members + 1);
  start[0] = 0;
  for (int64_t m = 1; m < members; ++m) {
    const int64_t* first = std::partition_point(body_a + start[m - 1], body_a + n,
                                                [&](int64_t b) { return b < m * per; });
    start[m] = first - body_a;
  }
  start[members] = n;
  return start;
}

// A pass is one list of contacts and its contact law, as the drivers below take it:
//   n, body_a, body_b: the number of contacts and their bodies (body_b nullptr: one body each);
//   kWidth: values per row (9 with body_b, 6 without);
//   ok(c0, m, bad): checks the indices of the block [c0, c0 + m), counting bad ones in `bad`;
//   run(c0, m, rows, sel, bad): writes the packed rows of the block to `rows`, their offsets to
//   `sel`, and returns how many rows it wrote.

// True when every contact of [c0, c1) of `pass` acts on bodies in [lo, hi) only.
template <typename Pass>
bool owns(const Pass& pass, int64_t c0, int64_t c1, int64_t lo, int64_t hi) {
  bool ok = true;
  for (int64_t c = c0; c < c1; ++c) {
    ok &= pass.body_a[c] >= lo && pass.body_a[c] < hi;
    if (pass.body_b != nullptr) ok &= pass.body_b[c] >= lo && pass.body_b[c] < hi;
  }
  return ok;
}

// Runs the blocks of contacts [c0, c1) of `pass` and adds their rows to force/torque, in order.
template <typename T, typename Pass>
void member_blocks(const Pass& pass, int64_t c0, int64_t c1, T* force, T* torque, std::atomic<int64_t>& bad) {
  alignas(64) T rows[Pass::kWidth * kBlockContacts];
  int32_t sel[kBlockContacts];
  for (int64_t c = c0; c < c1; c += kBlockContacts) {
    const int64_t m = std::min(kBlockContacts, c1 - c);
    if (!pass.ok(c, m, bad)) continue;
    const int64_t r = pass.run(c, m, rows, sel, bad);
    add_rows<T>(pass.body_a, pass.body_b, c, sel, rows, Pass::kWidth, r, force, torque);
  }
}

// Runs the passes, one after the other, over the contacts of whole members, each thread owning
// members [m0, m1): it copies the input force/torque of their bodies, adds the rows of every
// pass in turn, then calls epilogue(lo, hi) on their bodies [lo, hi) while they are still in its
// cache. Returns false (outputs then unspecified) when the members cannot be split (see
// member_starts) or some contact of a member's range touches a body of another member: the
// caller then falls back to two passes per list.
template <typename T, typename Epilogue, typename... Pass>
bool per_member(int64_t n_bodies, int64_t members, const T* force_in, const T* torque_in, T* force_out,
                T* torque_out, unsigned csr, std::atomic<int64_t>& bad, Epilogue epilogue, const Pass&... pass) {
  const std::vector<int64_t> starts[] = {member_starts(pass.body_a, pass.n, n_bodies, members)...};
  for (const auto& s : starts)
    if (s.empty()) return false;
  const int64_t per = n_bodies / members;
  std::atomic<bool> foreign{false};
  at::parallel_for(0, members, 1, [&](int64_t m0, int64_t m1) {
    const int64_t lo = m0 * per, hi = m1 * per;
    int k = 0;  // the pass's index in starts; && and , evaluate the passes left to right
    auto owned = [&](const auto& p) {
      const std::vector<int64_t>& s = starts[k++];
      return owns(p, s[m0], s[m1], lo, hi);
    };
    if (!(owned(pass) && ...)) {
      foreign = true;
      return;
    }
    DenormalMode mode(csr);
    std::copy(force_in + 3 * lo, force_in + 3 * hi, force_out + 3 * lo);
    std::copy(torque_in + 3 * lo, torque_in + 3 * hi, torque_out + 3 * lo);
    k = 0;
    auto blocks = [&](const auto& p) {
      const std::vector<int64_t>& s = starts[k++];
      member_blocks<T>(p, s[m0], s[m1], force_out, torque_out, bad);
    };
    (blocks(pass), ...);
    epilogue(lo, hi);
  });
  return !foreign.load();
}

// Per-contact rows live in buffers of the calling thread that are kept between calls
// (allocating ~100 bytes per contact afresh each step costs page faults; a buffer is as large
// as the largest contact list seen by that thread). Slot 0: rows; 1: row offsets; 2: counts;
// 3: the blocks' body spans.
template <typename T>
T* scratch(int slot, int64_t count) {
  thread_local std::vector<double> buffers[4];
  std::vector<double>& buffer = buffers[slot];
  const size_t doubles = (static_cast<size_t>(count) * sizeof(T) + sizeof(double) - 1) / sizeof(double);
  if (buffer.size() < doubles) buffer.resize(doubles);
  return reinterpret_cast<T*>(buffer.data());
}

// The rows of every contact of `pass` into a scratch buffer (parallel over blocks), then
// scatter_to_bodies. Resets `bad` first. Nothing is written to the outputs when an index is bad.
template <typename T, typename Pass>
void two_passes(const Pass& pass, int64_t n_bodies, const T* force_in, const T* torque_in, T* force_out,
                T* torque_out, unsigned csr, std::atomic<int64_t>& bad) {
  bad = 0;
  const int64_t n = pass.n, n_blocks = (n + kBlockContacts - 1) / kBlockContacts;
  T* rows = scratch<T>(0, Pass::kWidth * n);
  int32_t* sel = scratch<int32_t>(1, n);
  int64_t* count = scratch<int64_t>(2, n_blocks);
  int64_t* span = scratch<int64_t>(3, 2 * n_blocks);
  at::parallel_for(0, n_blocks, 4, [&](int64_t b0, int64_t b1) {
    DenormalMode mode(csr);
    for (int64_t blk = b0; blk < b1; ++blk) {
      const int64_t c0 = blk * kBlockContacts, m = std::min(kBlockContacts, n - c0);
      const int64_t r = pass.ok(c0, m, bad) ? pass.run(c0, m, rows + Pass::kWidth * c0, sel + c0, bad) : 0;
      count[blk] = r;
      // The bodies the block's rows act on, lowest and highest (an empty block: none).
      int64_t lo = std::numeric_limits<int64_t>::max(), hi = -1;
      for (int64_t t = 0; t < r; ++t) {
        const int64_t e = c0 + sel[c0 + t];
        lo = std::min(lo, pass.body_a[e]);
        hi = std::max(hi, pass.body_a[e]);
        if (pass.body_b != nullptr) {
          lo = std::min(lo, pass.body_b[e]);
          hi = std::max(hi, pass.body_b[e]);
        }
      }
      span[2 * blk] = lo;
      span[2 * blk + 1] = hi;
    }
  });
  if (bad.load() == 0)
    scatter_to_bodies<T>(pass.body_a, pass.body_b, rows, sel, count, span, Pass::kWidth, n, n_bodies, force_in,
                         torque_in, force_out, torque_out);
}

// Runs the contact law of `pass` over its contacts and adds their rows to the bodies: out = in +
// rows, per member when the contacts allow it, else in two passes.
template <typename T, typename Pass>
void contacts_to_bodies(const Pass& pass, int64_t n_bodies, int64_t members, const T* force_in, const T* torque_in,
                        T* force_out, T* torque_out, unsigned csr, std::atomic<int64_t>& bad) {
  if (!per_member<T>(n_bodies, members, force_in, torque_in, force_out, torque_out, csr, bad,
                     [](int64_t, int64_t) {}, pass))
    two_passes<T>(pass, n_bodies, force_in, torque_in, force_out, torque_out, csr, bad);
}

void check_cpu(const at::Tensor& t, const char* name, at::ScalarType dtype, int64_t rows, int64_t cols) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor, got ", t.device());
  TORCH_CHECK(t.scalar_type() == dtype, name, " has dtype ", t.scalar_type(), "; expected ", dtype);
  if (cols == 0) {
    TORCH_CHECK(t.dim() == 1 && t.size(0) == rows, name, " has shape ", t.sizes(), "; expected [", rows, "]");
  } else {
    TORCH_CHECK(t.dim() == 2 && t.size(0) == rows && t.size(1) == cols, name, " has shape ", t.sizes(),
                "; expected [", rows, ", ", cols, "]");
  }
}

int64_t rows_of(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.dim() >= 1, name, " must have at least one dimension, got shape ", t.sizes());
  return t.size(0);
}

// Inputs and outputs of the pair loop (all arrays contiguous; see pair_kernel).
// The per-pair constants of pair_kernel (radii, R*, m*, I_r*, E*, G*, beta, mu_s, mu_r, eta_r)
// are not streamed per pair: they are looked up, for the pairs that touch only, in per-sphere
// arrays (a few thousand entries per member, cache-resident) and in the [6, R] table of the
// material pairs (rows young_eff, shear_eff, beta, mu_s, mu_r, rolling_damping and, for a
// [7, R] table, the SJKR cohesion energy density; column pair_row[i] + material[j]), and combined
// exactly as integrate.pair_constants combines them.
// That takes 88 of the ~250 bytes a listed pair cost per step off the memory traffic.
template <typename T>
struct PairData {
  const T *x, *X, *V, *W;                 // [S, 3], [NB, 3] x3
  const int64_t *i, *j, *body_i, *body_j;  // [P]
  const T *radius, *mass, *rolling_inertia;  // [S]
  const int64_t *pair_row, *material;      // [S]
  const T* table;                          // [6, R], or [7, R] with cohesion
  int64_t table_columns;                   // R
  bool cohesion;                           // the table has the cohesion row
  const T *tangential, *rolling;          // [P, 3]
  T *tangential_new, *rolling_new;        // [P, 3]
  T period[3], inv_period[3];
  T dt;
  bool ai2011;
  int64_t n_pairs;                         // P
};

// Prefetches the cache lines of rows (lo, hi] of an array of `width` values per row.
template <typename V>
TORCHDEM_INLINE void prefetch_rows(const V* a, int64_t width, int64_t lo, int64_t hi) {
  const char* first = reinterpret_cast<const char*>(a + width * (lo + 1));
  const char* last = reinterpret_cast<const char*>(a + width * (hi + 1));
  for (const char* c = first; c < last; c += 64) __builtin_prefetch(c, 0, 3);
}

// Pairs are sorted by (i, j) and j > i, so the partners j (and their bodies) of a block lie
// ahead of the first spheres i, at the front of what the block before touched; the hardware
// prefetcher follows the sequential i side, not that front, and the loads of the partners'
// velocities missed the cache (the gather's slowest loads). So each block prefetches the
// partners of the next block beyond its own: the sphere rows (x, radius, mass, rolling
// inertia, material) and the body rows (centre unless centred, velocity, angular velocity)
// between this block's largest partner index and the next block's, at most kPrefetchRows.
constexpr int64_t kPrefetchRows = 512;
template <typename T, bool kCentred>
TORCHDEM_INLINE void prefetch_partners(const PairData<T>& data, int64_t p0, int64_t n) {
  const int64_t q0 = p0 + n, q1 = std::min(p0 + 2 * n, data.n_pairs);
  if (q0 >= q1) return;
  int64_t s0 = -1, s1 = -1, b0 = -1, b1 = -1;
  for (int64_t p = p0; p < q0; ++p) {
    s0 = std::max(s0, data.j[p]);
    b0 = std::max(b0, data.body_j[p]);
  }
  for (int64_t p = q0; p < q1; ++p) {
    s1 = std::max(s1, data.j[p]);
    b1 = std::max(b1, data.body_j[p]);
  }
  s0 = std::max(s0, s1 - kPrefetchRows);
  b0 = std::max(b0, b1 - kPrefetchRows);
  prefetch_rows(data.x, 3, s0, s1);
  prefetch_rows(data.radius, 1, s0, s1);
  prefetch_rows(data.mass, 1, s0, s1);
  prefetch_rows(data.rolling_inertia, 1, s0, s1);
  prefetch_rows(data.material, 1, s0, s1);
  if (!kCentred) prefetch_rows(data.X, 3, b0, b1);
  prefetch_rows(data.V, 3, b0, b1);
  prefetch_rows(data.W, 3, b0, b1);
}

constexpr int64_t kBlock = kBlockContacts;

// Gathered operands of a block, one array per component (see pair_block): positions,
// body centres, velocities, angular velocities, springs (3 each), then the per-sphere scalars
// of both spheres (radius, mass, rolling inertia) and the material-pair coefficients. The
// effective R*, m* and I_r* are formed in the vectorised law loop (this loop is scalar).
enum PairOperand {
  kXA, kXB = 3, kBA = 6, kBB = 9, kVA = 12, kVB = 15, kWA = 18, kWB = 21, kTG = 24, kRL = 27,
  kRI = 30, kRJ, kMI, kMJ, kII, kIJ, kE, kG, kBETA, kMUS, kMUR, kETA, kCOH, kPairOperands
};

// Stage 0 of pair_block: the pairs of [p0, p0 + n) that may touch, as offsets from p0 (their
// count is returned). Typically three quarters of a Verlet list are within the skin but not
// touching; their springs reset to zero and their force and torques are zero, so the contact
// law runs on the others only. The test keeps a margin (1e-9 relative) so that rounding can
// never drop a pair the law would find touching; the law itself decides the borderline ones.
template <typename T>
TORCHDEM_SCALAR_LOOP int64_t touching_pairs(const PairData<T>& data, int64_t p0, int64_t n, int64_t* sel) {
  int64_t m = 0;
  for (int64_t k = 0; k < n; ++k) {
    const int64_t p = p0 + k;
    const Vec3<T> d = minimum_image(load(data.x, data.j[p]) - load(data.x, data.i[p]), data.period,
                                    data.inv_period);
    const double reach = (static_cast<double>(data.radius[data.i[p]]) + static_cast<double>(data.radius[data.j[p]])) *
                         (1.0 + 1e-9);
    const double dist2 = static_cast<double>(d.x) * d.x + static_cast<double>(d.y) * d.y +
                         static_cast<double>(d.z) * d.z;
    sel[m] = k;
    m += dist2 < reach * reach ? 1 : 0;
  }
  return m;
}

// Stage 1 of pair_block, kept scalar on purpose: vector gather instructions are slow on
// many x86 CPUs (microcode mitigations of "gather data sampling"), scalar loads are not.
// Gathers the operands of the m pairs p0 + sel[t] into column t; returns how many of them have
// a table column outside [0, R) (their operands are then those of column 0: the call fails).
// kCentred: every sphere is its own body's centre (a system of single spheres); the body
// centres are then not gathered (the law takes the lever arms from the sphere centres).
template <typename T, bool kCentred>
TORCHDEM_SCALAR_LOOP int64_t gather_pairs(const PairData<T>& data, int64_t p0, const int64_t* sel, int64_t m,
                                          T (*g)[kBlock]) {
  int64_t bad = 0;
  const int64_t R = data.table_columns;
  for (int64_t t = 0; t < m; ++t) {
    const int64_t p = p0 + sel[t];
    const int64_t a = data.i[p], b = data.j[p], ba = data.body_i[p], bb = data.body_j[p];
    for (int c = 0; c < 3; ++c) {
      g[kXA + c][t] = data.x[3 * a + c];
      g[kXB + c][t] = data.x[3 * b + c];
      if (!kCentred) {
        g[kBA + c][t] = data.X[3 * ba + c];
        g[kBB + c][t] = data.X[3 * bb + c];
      }
      g[kVA + c][t] = data.V[3 * ba + c];
      g[kVB + c][t] = data.V[3 * bb + c];
      g[kWA + c][t] = data.W[3 * ba + c];
      g[kWB + c][t] = data.W[3 * bb + c];
      g[kTG + c][t] = data.tangential[3 * p + c];
      g[kRL + c][t] = data.rolling[3 * p + c];
    }
    int64_t col = data.pair_row[a] + data.material[b];
    if (static_cast<uint64_t>(col) >= static_cast<uint64_t>(R)) {
      ++bad;
      col = 0;
    }
    g[kRI][t] = data.radius[a];
    g[kRJ][t] = data.radius[b];
    g[kMI][t] = data.mass[a];
    g[kMJ][t] = data.mass[b];
    g[kII][t] = data.rolling_inertia[a];
    g[kIJ][t] = data.rolling_inertia[b];
    g[kE][t] = data.table[col];
    g[kG][t] = data.table[R + col];
    g[kBETA][t] = data.table[2 * R + col];
    g[kMUS][t] = data.table[3 * R + col];
    g[kMUR][t] = data.table[4 * R + col];
    g[kETA][t] = data.table[5 * R + col];
    g[kCOH][t] = data.cohesion ? data.table[6 * R + col] : T(0);
  }
  return bad;
}

// Pairs [p0, p0 + n), n <= kBlock, in four stages: (0) pick the pairs that may touch; (1)
// gather their operands into local arrays, one per component; (2) the contact law on those
// arrays, a loop without gathers or branches that the compiler vectorises across pairs; (3)
// write springs (zeros for the pairs that do not touch, which is what the law gives them up
// to the sign of zero) and rows for the pairs that may touch (the others' would be zero).
// rows, rsel: where the packed rows of this block go (row t at rows + 9 t, for the pair
// p0 + rsel[t]); returns their number. Pairs with a table column out of range are counted in
// `bad`. kCentred: see gather_pairs. kCohesion: add the SJKR cohesion (table row 6).
template <typename T, bool kAi2011, bool kCentred, bool kCohesion>
int64_t pair_block(const PairData<T>& data, int64_t p0, int64_t n, T* rows, int32_t* rsel, std::atomic<int64_t>& bad) {
  enum { XA = kXA, XB = kXB, BA = kBA, BB = kBB, VA = kVA, VB = kVB, WA = kWA, WB = kWB, TG = kTG, RL = kRL };
  int64_t sel[kBlock];
  prefetch_partners<T, kCentred>(data, p0, n);
  const int64_t m = touching_pairs(data, p0, n, sel);
  alignas(64) T g[kPairOperands][kBlock];
  const int64_t bad_columns = gather_pairs<T, kCentred>(data, p0, sel, m, g);
  if (bad_columns) bad += bad_columns;
  // Stage 2: contact law. o[c][t]: outputs.
  enum { F = 0, TI = 3, TJ = 6, TN = 9, RN = 12, NO = 15 };
  alignas(64) T o[NO][kBlock];
  const T per[3] = {data.period[0], data.period[1], data.period[2]};
  const T inv_per[3] = {data.inv_period[0], data.inv_period[1], data.inv_period[2]};
  const T dt = data.dt;
  auto vec = [&](int c, int64_t k) { return Vec3<T>{g[c][k], g[c + 1][k], g[c + 2][k]}; };
  auto put = [&](int c, int64_t k, Vec3<T> v) {
    o[c][k] = v.x;
    o[c + 1][k] = v.y;
    o[c + 2][k] = v.z;
  };
  for (int64_t k = 0; k < m; ++k) {  // vectorised by the compiler (see contact_law)
    const T ri = g[kRI][k], rj = g[kRJ][k];
    const Vec3<T> xa = vec(XA, k);
    const Vec3<T> d = minimum_image(vec(XB, k) - xa, per, inv_per);
    const T dist = norm(d);
    const T overlap = ri + rj - dist;
    const Vec3<T> nrm = (T(1) / std::max(dist, T(1e-30))) * d;
    // Lever arms from the body centres to the contact point; a centred sphere's body centre is
    // its own centre, and the other centre is at xa + d (the image that touches).
    const Vec3<T> to_cp = (ri - T(0.5) * overlap) * nrm;
    const Vec3<T> cp = xa + to_cp;
    const Vec3<T> arm_i = kCentred ? to_cp : minimum_image(cp - vec(BA, k), per, inv_per);
    const Vec3<T> arm_j = kCentred ? to_cp - d : minimum_image(cp - vec(BB, k), per, inv_per);
    const Vec3<T> wi = vec(WA, k), wj = vec(WB, k);
    const Vec3<T> v_rel = vec(VA, k) + cross(wi, arm_i) - vec(VB, k) - cross(wj, arm_j);
    const T mi = g[kMI][k], mj = g[kMJ][k], Ii = g[kII][k], Ij = g[kIJ][k];
    const Coefficients<T> c{ri * rj / (ri + rj), mi * mj / (mi + mj), g[kE][k], g[kG][k], g[kBETA][k],
                            g[kMUS][k],  g[kMUR][k],  g[kETA][k], Ii * Ij / (Ii + Ij)};
    const LawResult<T> r = contact_law<T, kAi2011>(overlap, nrm, v_rel, wi - wj, vec(TG, k), vec(RL, k), c, dt);
    // SJKR cohesion: k_c A pulling i towards j, at the same contact point.
    const Vec3<T> f = kCohesion ? r.force + (g[kCOH][k] * sjkr_pair_area(overlap, dist, ri, rj)) * nrm : r.force;
    put(F, k, f);
    put(TI, k, cross(arm_i, f) + r.m_roll);
    put(TJ, k, cross(f, arm_j) - r.m_roll);
    put(TN, k, r.tangential_new);
    put(RN, k, r.rolling_new);
  }
  // Stage 3: springs [P, 3] (each written once: the law's for the pairs it ran on, zeros for
  // the others) and the packed rows of the pairs the law ran on (sel is ascending).
  for (int64_t k = 0, t = 0; k < n; ++k) {
    T* tang = data.tangential_new + 3 * (p0 + k);
    T* roll = data.rolling_new + 3 * (p0 + k);
    if (t < m && sel[t] == k) {
      T* row = rows + 9 * t;
      for (int c = 0; c < 9; ++c) row[c] = o[F + c][t];
      rsel[t] = static_cast<int32_t>(k);
      for (int c = 0; c < 3; ++c) {
        tang[c] = o[TN + c][t];
        roll[c] = o[RN + c][t];
      }
      ++t;
    } else {
      for (int c = 0; c < 3; ++c) tang[c] = roll[c] = T(0);
    }
  }
  return m;
}

// Number of entries of idx [n] outside [0, limit) (vectorised; no early exit).
inline int64_t count_out_of_range(const int64_t* __restrict__ idx, int64_t n, int64_t limit) {
  int64_t bad = 0;
  const uint64_t lim = static_cast<uint64_t>(limit);
#pragma omp simd reduction(+ : bad)
  for (int64_t k = 0; k < n; ++k) bad += static_cast<uint64_t>(idx[k]) >= lim ? 1 : 0;
  return bad;
}


// The sphere-sphere pass of pair_forces (see "A pass" above), on validated contiguous inputs
// `in` (pair_forces' tensors in order) writing the springs to tang_out and roll_out.
template <typename T>
struct PairPass {
  static constexpr int kWidth = 9;
  PairData<T> data;
  int64_t n, S, NB;
  const int64_t *body_a, *body_b;
  bool centred;

  PairPass(const std::vector<at::Tensor>& in, at::Tensor& tang_out, at::Tensor& roll_out, double dt,
           at::ArrayRef<double> period, bool ai2011, bool periodic, bool centred)
      : n(in[6].size(0)), S(in[0].size(0)), NB(in[1].size(0)), centred(centred) {
    data.x = in[0].data_ptr<T>();
    data.X = in[1].data_ptr<T>();
    data.V = in[2].data_ptr<T>();
    data.W = in[3].data_ptr<T>();
    data.i = in[6].data_ptr<int64_t>();
    data.j = in[7].data_ptr<int64_t>();
    data.body_i = in[8].data_ptr<int64_t>();
    data.body_j = in[9].data_ptr<int64_t>();
    data.radius = in[10].data_ptr<T>();
    data.mass = in[11].data_ptr<T>();
    data.rolling_inertia = in[12].data_ptr<T>();
    data.pair_row = in[13].data_ptr<int64_t>();
    data.material = in[14].data_ptr<int64_t>();
    data.table = in[15].data_ptr<T>();
    data.table_columns = in[15].size(1);
    data.cohesion = in[15].size(0) == 7;
    data.tangential = in[16].data_ptr<T>();
    data.rolling = in[17].data_ptr<T>();
    data.tangential_new = tang_out.data_ptr<T>();
    data.rolling_new = roll_out.data_ptr<T>();
    for (int d = 0; d < 3; ++d) {
      data.period[d] = periodic && period[d] > 0 ? T(period[d]) : T(0);
      data.inv_period[d] = data.period[d] > 0 ? T(1) / data.period[d] : T(0);
    }
    data.dt = T(dt);
    data.ai2011 = ai2011;
    data.n_pairs = n;
    body_a = data.body_i;
    body_b = data.body_j;
  }

  // Checks a block's indices before anything reads through them (a block with a bad index is
  // skipped and the call fails after the pass).
  bool ok(int64_t p0, int64_t m, std::atomic<int64_t>& bad) const {
    const int64_t n_bad = count_out_of_range(data.i + p0, m, S) + count_out_of_range(data.j + p0, m, S) +
                          count_out_of_range(data.body_i + p0, m, NB) + count_out_of_range(data.body_j + p0, m, NB);
    if (n_bad) bad += n_bad;
    return n_bad == 0;
  }

  int64_t run(int64_t p0, int64_t m, T* rows, int32_t* sel, std::atomic<int64_t>& bad) const {
    return data.cohesion ? run_model<true>(p0, m, rows, sel, bad) : run_model<false>(p0, m, rows, sel, bad);
  }

  template <bool kCohesion>
  int64_t run_model(int64_t p0, int64_t m, T* rows, int32_t* sel, std::atomic<int64_t>& bad) const {
    if (centred) {
      return data.ai2011 ? pair_block<T, true, true, kCohesion>(data, p0, m, rows, sel, bad)
                         : pair_block<T, false, true, kCohesion>(data, p0, m, rows, sel, bad);
    }
    return data.ai2011 ? pair_block<T, true, false, kCohesion>(data, p0, m, rows, sel, bad)
                       : pair_block<T, false, false, kCohesion>(data, p0, m, rows, sel, bad);
  }

  void fail_if_bad(const std::atomic<int64_t>& bad) const {
    TORCH_CHECK(bad.load() == 0, "pair_forces: ", bad.load(), " sphere, body or table indices are outside [0, ", S,
                ") (spheres), [0, ", NB, ") (bodies) or [0, ", data.table_columns,
                ") (columns of the material-pair table)");
  }
};

// Validates pair_forces' tensors (in its argument order) and returns them contiguous.
std::vector<at::Tensor> pair_inputs(std::vector<at::Tensor> in) {
  TORCH_CHECK(in.size() == 18, "pair_forces takes 18 tensors, got ", in.size());
  at::Tensor &xs = in[0], &X = in[1], &i = in[6], &table = in[15];
  const auto dtype = xs.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "xs has dtype ", dtype, "; expected float32 or float64");
  const int64_t S = rows_of(xs, "xs"), NB = rows_of(X, "X"), P = rows_of(i, "i");
  check_cpu(xs, "xs", dtype, S, 3);
  for (int k = 1; k <= 5; ++k) check_cpu(in[k], "body tensor", dtype, NB, 3);             // X V omega force torque
  for (int k = 6; k <= 9; ++k) check_cpu(in[k], "index tensor", at::kLong, P, 0);         // i j body_i body_j
  for (int k = 10; k <= 12; ++k) check_cpu(in[k], "per-sphere tensor", dtype, S, 0);      // radius mass I_r
  for (int k = 13; k <= 14; ++k) check_cpu(in[k], "per-sphere index tensor", at::kLong, S, 0);
  TORCH_CHECK(table.dim() == 2 && (table.size(0) == 6 || table.size(0) == 7), "table has shape ", table.sizes(),
              "; expected [6, R] (no cohesion) or [7, R] (the last row the SJKR cohesion)");
  check_cpu(table, "table", dtype, table.size(0), table.size(1));
  check_cpu(in[16], "tangential", dtype, P, 3);
  check_cpu(in[17], "rolling", dtype, P, 3);
  for (auto& t : in) t = t.contiguous();
  return in;
}

std::vector<at::Tensor> pair_forces(
    at::Tensor xs, at::Tensor X, at::Tensor V, at::Tensor omega, at::Tensor force, at::Tensor torque,
    at::Tensor i, at::Tensor j, at::Tensor body_i, at::Tensor body_j, at::Tensor sphere_radius,
    at::Tensor sphere_mass, at::Tensor sphere_rolling_inertia, at::Tensor sphere_pair_row,
    at::Tensor sphere_material, at::Tensor table, at::Tensor tangential, at::Tensor rolling, double dt,
    at::ArrayRef<double> period, bool ai2011, bool periodic, int64_t members, bool centred) {
  TORCH_CHECK(period.size() == 3, "period has ", period.size(), " entries; expected 3");
  const std::vector<at::Tensor> in =
      pair_inputs({xs, X, V, omega, force, torque, i, j, body_i, body_j, sphere_radius, sphere_mass,
                   sphere_rolling_inertia, sphere_pair_row, sphere_material, table, tangential, rolling});
  using torchdem_recycle::output_like;
  const int s = torchdem_recycle::kPairForces;
  at::Tensor force_out = output_like(s, in[4]), torque_out = output_like(s + 1, in[5]);
  at::Tensor tang_out = output_like(s + 2, in[16]), roll_out = output_like(s + 3, in[17]);
  AT_DISPATCH_FLOATING_TYPES(xs.scalar_type(), "pair_forces", [&] {
    const PairPass<scalar_t> pass(in, tang_out, roll_out, dt, period, ai2011, periodic, centred);
    std::atomic<int64_t> bad{0};
    contacts_to_bodies<scalar_t>(pass, pass.NB, members, in[4].data_ptr<scalar_t>(), in[5].data_ptr<scalar_t>(),
                                 force_out.data_ptr<scalar_t>(), torque_out.data_ptr<scalar_t>(),
                                 DenormalMode::caller(), bad);
    pass.fail_if_bad(bad);
  });
  return {force_out, torque_out, tang_out, roll_out};
}

// Gathered operands of a sphere-wall block, one array per component (see wall_block).
enum WallOperand { kWXW, kWC = 3, kWU = 6, kWVV = 9, kWWV = 12, kWBX = 15, kWBV = 18, kWBW = 21, kWTG = 24,
                   kWRL = 27, kWHU = 30, kWHV, kWPR, kWallOperands };

// Stage 1 of wall_block, scalar like gather_pairs.
template <typename T>
TORCHDEM_SCALAR_LOOP void gather_walls(const std::vector<at::Tensor>& in, int64_t q0, int64_t n, T (*g)[kBlock]) {
  const T* x = in[0].data_ptr<T>();
  const T* Xb = in[1].data_ptr<T>();
  const T* Vb = in[2].data_ptr<T>();
  const T* Wb = in[3].data_ptr<T>();
  const int64_t* ps = in[6].data_ptr<int64_t>();
  const int64_t* pb = in[7].data_ptr<int64_t>();
  const int64_t* pw = in[8].data_ptr<int64_t>();
  const T *wc = in[9].data_ptr<T>(), *wu = in[10].data_ptr<T>(), *wv = in[11].data_ptr<T>(),
          *hu = in[12].data_ptr<T>(), *hv = in[13].data_ptr<T>(), *wvel = in[14].data_ptr<T>();
  const bool* present = in[15].data_ptr<bool>();
  const T* tang = in[25].data_ptr<T>();
  const T* roll = in[26].data_ptr<T>();
  for (int64_t k = 0; k < n; ++k) {
    const int64_t q = q0 + k;
    const int64_t s = ps[q], b = pb[q], w = pw[q];
    for (int c = 0; c < 3; ++c) {
      g[kWXW + c][k] = x[3 * s + c];
      g[kWC + c][k] = wc[3 * w + c];
      g[kWU + c][k] = wu[3 * w + c];
      g[kWVV + c][k] = wv[3 * w + c];
      g[kWWV + c][k] = wvel[3 * w + c];
      g[kWBX + c][k] = Xb[3 * b + c];
      g[kWBV + c][k] = Vb[3 * b + c];
      g[kWBW + c][k] = Wb[3 * b + c];
      g[kWTG + c][k] = tang[3 * q + c];
      g[kWRL + c][k] = roll[3 * q + c];
    }
    g[kWHU][k] = hu[w];
    g[kWHV][k] = hv[w];
    g[kWPR][k] = present[w] ? T(1) : T(0);
  }
}

// Prefetches the sphere and body rows of the sphere-wall contacts [q0, q1): the spheres that
// touch a wall are a sparse subset, so the hardware prefetcher does not see their rows coming.
template <typename T>
TORCHDEM_INLINE void prefetch_wall_rows(const std::vector<at::Tensor>& in, int64_t q0, int64_t q1) {
  const T *x = in[0].data_ptr<T>(), *Xb = in[1].data_ptr<T>(), *Vb = in[2].data_ptr<T>(), *Wb = in[3].data_ptr<T>();
  const int64_t *ps = in[6].data_ptr<int64_t>(), *pb = in[7].data_ptr<int64_t>();
  for (int64_t q = q0; q < q1; ++q) {
    __builtin_prefetch(x + 3 * ps[q], 0, 3);
    __builtin_prefetch(Xb + 3 * pb[q], 0, 3);
    __builtin_prefetch(Vb + 3 * pb[q], 0, 3);
    __builtin_prefetch(Wb + 3 * pb[q], 0, 3);
  }
}

// Sphere-wall contacts [q0, q0 + n), n <= kBlock; stages 1-3 of pair_block, on every contact
// (a wall list is short): row k at rows + 6 k, rsel[k] = k; returns n. kCohesion: add the SJKR
// cohesion, k_c per contact in in[27].
template <typename T, bool kAi2011, bool kCohesion>
int64_t wall_block(const std::vector<at::Tensor>& in, T* tang_new, T* roll_new, T* rows, int32_t* rsel, T dt,
                   int64_t q0, int64_t n) {
  enum { XW = kWXW, C = kWC, U = kWU, VV = kWVV, WV = kWWV, BX = kWBX, BV = kWBV, BW = kWBW, TG = kWTG, RL = kWRL,
         HU = kWHU, HV = kWHV, PR = kWPR };
  alignas(64) T g[kWallOperands][kBlock];
  prefetch_wall_rows<T>(in, q0 + n, std::min(q0 + 2 * n, in[6].size(0)));  // the next block's
  gather_walls(in, q0, n, g);
  // Stage 2: contact law.
  enum { F = 0, TQ = 3, TN = 6, RN = 9, NO = 12 };
  alignas(64) T o[NO][kBlock];
  const T *__restrict__ rad = in[16].data_ptr<T>() + q0, *__restrict__ meff = in[17].data_ptr<T>() + q0,
          *__restrict__ E = in[18].data_ptr<T>() + q0, *__restrict__ G = in[19].data_ptr<T>() + q0,
          *__restrict__ bt = in[20].data_ptr<T>() + q0, *__restrict__ mus = in[21].data_ptr<T>() + q0,
          *__restrict__ mur = in[22].data_ptr<T>() + q0, *__restrict__ eta = in[23].data_ptr<T>() + q0,
          *__restrict__ Ir = in[24].data_ptr<T>() + q0;
  const T* __restrict__ coh = kCohesion ? in[27].data_ptr<T>() + q0 : nullptr;
  auto vec = [&](int c, int64_t k) { return Vec3<T>{g[c][k], g[c + 1][k], g[c + 2][k]}; };
  auto put = [&](int c, int64_t k, Vec3<T> v) {
    o[c][k] = v.x;
    o[c + 1][k] = v.y;
    o[c + 2][k] = v.z;
  };
  for (int64_t k = 0; k < n; ++k) {  // vectorised by the compiler (see contact_law)
    const Vec3<T> xw = vec(XW, k), c = vec(C, k), u = vec(U, k), v = vec(VV, k);
    const Vec3<T> rel = xw - c;
    const T h_u = g[HU][k], h_v = g[HV][k];
    const T su = std::max(std::min(dot(rel, u), h_u), -h_u);
    const T sv = std::max(std::min(dot(rel, v), h_v), -h_v);
    const Vec3<T> d = c + su * u + sv * v - xw;
    const T dist = norm(d);
    const T overlap = g[PR][k] > 0 ? rad[k] - dist : T(-1);
    const Vec3<T> nrm = (T(1) / std::max(dist, T(1e-30))) * d;
    const Vec3<T> cp = xw + (rad[k] - T(0.5) * overlap) * nrm;
    const Vec3<T> arm = cp - vec(BX, k);
    const Vec3<T> wb = vec(BW, k);
    const Vec3<T> v_rel = vec(BV, k) + cross(wb, arm) - vec(WV, k);
    const Coefficients<T> co{rad[k], meff[k], E[k], G[k], bt[k], mus[k], mur[k], eta[k], Ir[k]};
    const LawResult<T> r = contact_law<T, kAi2011>(overlap, nrm, v_rel, wb, vec(TG, k), vec(RL, k), co, dt);
    const Vec3<T> f = kCohesion ? r.force + (coh[k] * sjkr_wall_area(overlap, dist, rad[k])) * nrm : r.force;
    put(F, k, f);
    put(TQ, k, cross(arm, f) + r.m_roll);
    put(TN, k, r.tangential_new);
    put(RN, k, r.rolling_new);
  }
  // Stage 3: springs [Q, 3] and rows [Q, 6].
  for (int64_t k = 0; k < n; ++k) {
    const int64_t q = q0 + k;
    for (int c = 0; c < 6; ++c) rows[6 * k + c] = o[F + c][k];
    rsel[k] = static_cast<int32_t>(k);
    for (int c = 0; c < 3; ++c) {
      tang_new[3 * q + c] = o[TN + c][k];
      roll_new[3 * q + c] = o[RN + c][k];
    }
  }
  return n;
}

// The sphere-wall pass of wall_forces (see "A pass" above), on validated contiguous inputs
// `in` (wall_forces' tensors in order) writing the springs to tang_out and roll_out.
template <typename T>
struct WallPass {
  static constexpr int kWidth = 6;
  const std::vector<at::Tensor>& in;
  int64_t n, S, NB, W;
  const int64_t *body_a, *body_b = nullptr, *sphere, *wall;
  T *tang_new, *roll_new;
  T dt;
  bool ai2011, cohesion;

  WallPass(const std::vector<at::Tensor>& in, at::Tensor& tang_out, at::Tensor& roll_out, double dt, bool ai2011)
      : in(in), n(in[6].size(0)), S(in[0].size(0)), NB(in[1].size(0)), W(in[9].size(0)),
        body_a(in[7].data_ptr<int64_t>()), sphere(in[6].data_ptr<int64_t>()), wall(in[8].data_ptr<int64_t>()),
        tang_new(tang_out.data_ptr<T>()), roll_new(roll_out.data_ptr<T>()), dt(T(dt)), ai2011(ai2011),
        cohesion(in.size() == 28) {}

  bool ok(int64_t q0, int64_t m, std::atomic<int64_t>& bad) const {
    const int64_t n_bad = count_out_of_range(sphere + q0, m, S) + count_out_of_range(body_a + q0, m, NB) +
                          count_out_of_range(wall + q0, m, W);
    if (n_bad) bad += n_bad;
    return n_bad == 0;
  }

  int64_t run(int64_t q0, int64_t m, T* rows, int32_t* sel, std::atomic<int64_t>&) const {
    if (cohesion)
      return ai2011 ? wall_block<T, true, true>(in, tang_new, roll_new, rows, sel, dt, q0, m)
                    : wall_block<T, false, true>(in, tang_new, roll_new, rows, sel, dt, q0, m);
    return ai2011 ? wall_block<T, true, false>(in, tang_new, roll_new, rows, sel, dt, q0, m)
                  : wall_block<T, false, false>(in, tang_new, roll_new, rows, sel, dt, q0, m);
  }

  void fail_if_bad(const std::atomic<int64_t>& bad) const {
    TORCH_CHECK(bad.load() == 0, "wall_forces: ", bad.load(), " sphere, body or wall indices are out of range (",
                S, " spheres, ", NB, " bodies, ", W, " walls)");
  }
};

// Validates wall_forces' tensors (in its argument order, then the per-contact cohesion if given)
// and returns them contiguous.
std::vector<at::Tensor> wall_inputs(std::vector<at::Tensor> in) {
  TORCH_CHECK(in.size() == 27 || in.size() == 28, "wall_forces takes 27 tensors (28 with cohesion), got ",
              in.size());
  const at::Tensor &xs = in[0], &X = in[1], &sphere = in[6], &wall_centre = in[9];
  const auto dtype = xs.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "xs has dtype ", dtype, "; expected float32 or float64");
  const int64_t S = rows_of(xs, "xs"), NB = rows_of(X, "X"), Q = rows_of(sphere, "sphere");
  const int64_t W = rows_of(wall_centre, "wall_centre");
  check_cpu(xs, "xs", dtype, S, 3);
  for (int k = 1; k <= 5; ++k) check_cpu(in[k], "body tensor", dtype, NB, 3);      // X V omega force torque
  for (int k = 6; k <= 8; ++k) check_cpu(in[k], "index tensor", at::kLong, Q, 0);  // sphere body wall
  for (int k : {9, 10, 11, 14}) check_cpu(in[k], "wall tensor", dtype, W, 3);      // centre u v velocity
  for (int k = 12; k <= 13; ++k) check_cpu(in[k], "wall half-extent", dtype, W, 0);
  check_cpu(in[15], "wall_present", at::kBool, W, 0);
  for (int k = 16; k <= 24; ++k) check_cpu(in[k], "per-contact tensor", dtype, Q, 0);
  check_cpu(in[25], "tangential", dtype, Q, 3);
  check_cpu(in[26], "rolling", dtype, Q, 3);
  if (in.size() == 28) check_cpu(in[27], "cohesion", dtype, Q, 0);
  for (auto& t : in) t = t.contiguous();
  return in;
}

std::vector<at::Tensor> wall_forces(
    at::Tensor xs, at::Tensor X, at::Tensor V, at::Tensor omega, at::Tensor force, at::Tensor torque,
    at::Tensor sphere, at::Tensor body, at::Tensor wall, at::Tensor wall_centre, at::Tensor wall_u,
    at::Tensor wall_v, at::Tensor half_u, at::Tensor half_v, at::Tensor wall_velocity, at::Tensor wall_present,
    at::Tensor radius, at::Tensor mass_eff, at::Tensor young_eff, at::Tensor shear_eff, at::Tensor beta,
    at::Tensor mu_s, at::Tensor mu_r, at::Tensor rolling_damping, at::Tensor rolling_inertia,
    at::Tensor tangential, at::Tensor rolling, double dt, bool ai2011, int64_t members,
    const std::optional<at::Tensor>& cohesion) {
  std::vector<at::Tensor> tensors{xs, X, V, omega, force, torque, sphere, body, wall, wall_centre, wall_u, wall_v,
                                  half_u, half_v, wall_velocity, wall_present, radius, mass_eff, young_eff,
                                  shear_eff, beta, mu_s, mu_r, rolling_damping, rolling_inertia, tangential, rolling};
  if (cohesion.has_value()) tensors.push_back(*cohesion);
  const std::vector<at::Tensor> in = wall_inputs(std::move(tensors));
  using torchdem_recycle::output_like;
  const int s = torchdem_recycle::kWallForces;
  at::Tensor force_out = output_like(s, in[4]), torque_out = output_like(s + 1, in[5]);
  at::Tensor tang_out = output_like(s + 2, in[25]), roll_out = output_like(s + 3, in[26]);
  AT_DISPATCH_FLOATING_TYPES(xs.scalar_type(), "wall_forces", [&] {
    const WallPass<scalar_t> pass(in, tang_out, roll_out, dt, ai2011);
    std::atomic<int64_t> bad{0};
    contacts_to_bodies<scalar_t>(pass, pass.NB, members, in[4].data_ptr<scalar_t>(), in[5].data_ptr<scalar_t>(),
                                 force_out.data_ptr<scalar_t>(), torque_out.data_ptr<scalar_t>(),
                                 DenormalMode::caller(), bad);
    pass.fail_if_bad(bad);
  });
  return {force_out, torque_out, tang_out, roll_out};
}

// forces_kick: pair_forces, then wall_forces on its force and torque, then kick (gravity, masks,
// second half kick) in one call, with the same bits as the three calls. `pair`: pair_forces'
// 18 tensors in order (its force and torque are the input sums, zeros in a step); `wall`:
// wall_forces' tensors from `sphere` on (21, or 22 with the per-contact cohesion; the rest are
// shared with `pair`); `kick`: velocity,
// angular_momentum, mass, gravity, active as for kick. Returns (f, tau, v, L) of kick, shaped like
// velocity, then the pair springs (tangential, rolling) and the wall springs.
// When the contacts split into members, each thread runs the pairs, the walls and the kick of its
// own members one after the other, while their bodies are in its cache: one parallel region
// instead of three, and the bodies' force, torque, velocity and momentum pass through memory once
// (not in four sweeps: two force copies, the kick's reads and its writes).
std::vector<at::Tensor> forces_kick(std::vector<at::Tensor> pair, std::vector<at::Tensor> wall,
                                    std::vector<at::Tensor> kick, double dt, at::ArrayRef<double> period,
                                    bool ai2011, bool periodic, int64_t members, bool centred) {
  using torchdem_kick::kick_bodies;
  TORCH_CHECK(period.size() == 3, "period has ", period.size(), " entries; expected 3");
  TORCH_CHECK(wall.size() == 21 || wall.size() == 22,
              "forces_kick: wall takes the 21 tensors of wall_forces from sphere to rolling (22 with cohesion), got ",
              wall.size());
  TORCH_CHECK(kick.size() == 5, "forces_kick: kick takes 5 tensors (velocity, angular_momentum, mass, gravity, "
              "active), got ", kick.size());
  const std::vector<at::Tensor> in_p = pair_inputs(std::move(pair));
  wall.insert(wall.begin(), in_p.begin(), in_p.begin() + 6);
  const std::vector<at::Tensor> in_w = wall_inputs(std::move(wall));
  const auto dtype = in_p[0].scalar_type();
  const int64_t NB = in_p[1].size(0);
  const std::vector<at::Tensor> in_k = torchdem_kick::kick_inputs(std::move(kick), dtype, NB, "forces_kick");
  using torchdem_recycle::output_like;
  const int s = torchdem_recycle::kForcesKick;
  at::Tensor force_out = output_like(s, in_k[0]), torque_out = output_like(s + 1, in_k[0]);
  at::Tensor velocity_out = output_like(s + 2, in_k[0]), momentum_out = output_like(s + 3, in_k[1]);
  at::Tensor tang_out = output_like(s + 4, in_p[16]), roll_out = output_like(s + 5, in_p[17]);
  at::Tensor wtang_out = output_like(s + 6, in_w[25]), wroll_out = output_like(s + 7, in_w[26]);
  AT_DISPATCH_FLOATING_TYPES(dtype, "forces_kick", [&] {
    using T = scalar_t;
    const PairPass<T> pairs(in_p, tang_out, roll_out, dt, period, ai2011, periodic, centred);
    const WallPass<T> walls(in_w, wtang_out, wroll_out, dt, ai2011);
    T *f = force_out.data_ptr<T>(), *tau = torque_out.data_ptr<T>();
    // The kick runs in place on the contact sums f and tau.
    const auto k = torchdem_kick::kick_data<T>(in_k, f, tau, force_out, torque_out, velocity_out, momentum_out,
                                              T(dt));
    const T *f_in = in_p[4].data_ptr<T>(), *tau_in = in_p[5].data_ptr<T>();
    const unsigned csr = DenormalMode::caller();
    std::atomic<int64_t> bad{0};
    const bool fused = per_member<T>(NB, members, f_in, tau_in, f, tau, csr, bad,
                                     [&](int64_t lo, int64_t hi) { kick_bodies<T>(k, lo, hi); }, pairs, walls);
    if (!fused || bad.load() != 0) {
      // The three steps one after the other (and, for bad indices, their own errors).
      at::Tensor pf = at::empty_like(in_p[4]), pt = at::empty_like(in_p[5]);
      bad = 0;
      contacts_to_bodies<T>(pairs, NB, members, f_in, tau_in, pf.data_ptr<T>(), pt.data_ptr<T>(), csr, bad);
      pairs.fail_if_bad(bad);
      bad = 0;
      contacts_to_bodies<T>(walls, NB, members, pf.data_ptr<T>(), pt.data_ptr<T>(), f, tau, csr, bad);
      walls.fail_if_bad(bad);
      at::parallel_for(0, NB, 2048, [&](int64_t b0, int64_t b1) { kick_bodies<T>(k, b0, b1); });
    }
  });
  return {force_out, torque_out, velocity_out, momentum_out, tang_out, roll_out, wtang_out, wroll_out};
}

}  // namespace

// Registered as torch.ops.torchdem.pair_forces / wall_forces (a TORCH_LIBRARY fragment: other
// torchdem extensions add ops to the same namespace; not pybind11:
// the pybind11 headers of torch take ~4x longer to compile than the whole kernel).
TORCH_LIBRARY_FRAGMENT(torchdem, m) {
  m.def("pair_forces(Tensor xs, Tensor X, Tensor V, Tensor omega, Tensor force, Tensor torque, Tensor i, "
        "Tensor j, Tensor body_i, Tensor body_j, Tensor sphere_radius, Tensor sphere_mass, "
        "Tensor sphere_rolling_inertia, Tensor sphere_pair_row, Tensor sphere_material, Tensor table, "
        "Tensor tangential, Tensor rolling, float dt, float[] period, bool ai2011, bool periodic, "
        "int members=1, bool centred=False) -> Tensor[]",
        &pair_forces);
  m.def("wall_forces(Tensor xs, Tensor X, Tensor V, Tensor omega, Tensor force, Tensor torque, Tensor sphere, "
        "Tensor body, Tensor wall, Tensor wall_centre, Tensor wall_u, Tensor wall_v, Tensor half_u, "
        "Tensor half_v, Tensor wall_velocity, Tensor wall_present, Tensor radius, Tensor mass_eff, "
        "Tensor young_eff, Tensor shear_eff, Tensor beta, Tensor mu_s, Tensor mu_r, Tensor rolling_damping, "
        "Tensor rolling_inertia, Tensor tangential, Tensor rolling, float dt, bool ai2011, int members=1, "
        "Tensor? cohesion=None) -> Tensor[]",
        &wall_forces);
  m.def("forces_kick(Tensor[] pair, Tensor[] wall, Tensor[] kick, float dt, float[] period, bool ai2011, "
        "bool periodic, int members=1, bool centred=False) -> Tensor[]",
        &forces_kick);
}
