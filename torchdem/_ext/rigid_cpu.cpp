// CPU kernels of the drift of torchdem/integrate.py (drift_kernel): half kick, drift,
// midpoint quaternion rotation, sphere positions, angular velocities and the box of the sphere
// displacements since the last neighbour-list build (with the largest length); and of its
// kick (kick_kernel: gravity, masks, second half kick; one pass instead of a dozen tensor
// operations, 0.2 ms a step).
//
// Contract: `drift` computes what `drift_kernel` computes with the quaternion functions of
// torchdem/rigid.py, in float32 or float64, in one pass over the bodies and one over the
// spheres instead of ~70 tensor operations (each a separate sweep over memory plus a few
// microseconds of dispatch: for a few thousand bodies the dispatch dominated the step). It
// returns new tensors (x, v, L, q, xs, omega, displacement [B, 7]: per member the lowest x, y, z
// and highest x, y, z sphere displacement and the largest squared length, non-finite ones left
// out, all 0 when none is finite); nothing passed in is modified. For a system of single spheres,
// each its own body, q is the orientation passed in (a sphere's never turns; drift_spheres).
// Parallel over bodies and spheres (at::parallel_for); each element is written by one thread
// and the displacement extremes are order-independent, so results do not depend on the number
// of threads. They differ from the torch kernel by rounding only.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <torch/library.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <tuple>
#include <vector>

#include "kick.h"
#include "recycle.h"

namespace {

template <typename T>
struct Quat {
  T w, x, y, z;
};
template <typename T>
struct V3 {
  T x, y, z;
};

template <typename T> inline V3<T> cross3(V3<T> a, V3<T> b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

// rigid.quat_rotate: v + w t + u x t with t = 2 u x v.
template <typename T> inline V3<T> rotate(Quat<T> q, V3<T> v) {
  const V3<T> u{q.x, q.y, q.z};
  V3<T> t = cross3(u, v);
  t = {T(2) * t.x, T(2) * t.y, T(2) * t.z};
  const V3<T> c = cross3(u, t);
  return {v.x + q.w * t.x + c.x, v.y + q.w * t.y + c.y, v.z + q.w * t.z + c.z};
}

template <typename T> inline Quat<T> conj(Quat<T> q) { return {q.w, -q.x, -q.y, -q.z}; }

// rigid.quat_mul (Hamilton product).
template <typename T> inline Quat<T> mul(Quat<T> a, Quat<T> b) {
  return {a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z, a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
          a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x, a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w};
}

// rigid.angular_velocity: R diag(1/I) R^T L, with inv_I = 1 / I (computed once per body:
// the drift needs omega three times per body, and divisions dominated its cost).
template <typename T> inline V3<T> angular_velocity(Quat<T> q, V3<T> L, V3<T> inv_I) {
  const V3<T> body = rotate(conj(q), L);
  return rotate(q, V3<T>{body.x * inv_I.x, body.y * inv_I.y, body.z * inv_I.z});
}

// rigid.quat_from_rotation_vector. A body turns by far less than 0.2 rad in one step, and
// there the Taylor series of cos(h) and sin(h) / (2 h) (h = angle / 2, to h^8) are exact to
// double rounding (the first omitted terms are below 3e-17): no libm call, which made the
// drift of a few thousand clumps cost 0.4 ms per step (sin and cos twice per body).
// `from_small_rotation` is the series alone (a2 = |rv|^2 < 0.04), branch-free so that the
// vectorised body pass can run it on every lane.
template <typename T> inline __attribute__((always_inline)) Quat<T> from_small_rotation(V3<T> rv, T a2) {
  const T h2 = T(0.25) * a2;
  const T c = T(1) + h2 * (T(-1.0 / 2) + h2 * (T(1.0 / 24) + h2 * (T(-1.0 / 720) + h2 * T(1.0 / 40320))));
  const T s = T(0.5) * (T(1) + h2 * (T(-1.0 / 6) + h2 * (T(1.0 / 120) + h2 * (T(-1.0 / 5040) + h2 * T(1.0 / 362880)))));
  return {c, rv.x * s, rv.y * s, rv.z * s};
}

template <typename T> inline __attribute__((always_inline)) T norm2(V3<T> v) { return v.x * v.x + v.y * v.y + v.z * v.z; }

template <typename T> inline __attribute__((always_inline)) Quat<T> from_rotation_vector(V3<T> rv) {
  const T a2 = norm2(rv);
  if (a2 < T(0.04)) return from_small_rotation(rv, a2);
  const T angle = std::sqrt(a2);
  const T s = std::sin(T(0.5) * angle) / angle;
  return {std::cos(T(0.5) * angle), rv.x * s, rv.y * s, rv.z * s};
}

template <typename T> inline __attribute__((always_inline)) Quat<T> normalised(Quat<T> n) {
  const T inv_len = T(1) / std::sqrt(n.w * n.w + n.x * n.x + n.y * n.y + n.z * n.z);
  return {n.w * inv_len, n.x * inv_len, n.y * inv_len, n.z * inv_len};
}

// rigid.advance_orientation (midpoint rule at fixed world angular momentum), renormalised.
template <typename T> inline Quat<T> advance(Quat<T> q, V3<T> L, V3<T> inv_I, T dt) {
  const V3<T> w0 = angular_velocity(q, L, inv_I);
  const T h = T(0.5) * dt;
  const Quat<T> q_half = mul(from_rotation_vector(V3<T>{h * w0.x, h * w0.y, h * w0.z}), q);
  const V3<T> wh = angular_velocity(q_half, L, inv_I);
  return normalised(mul(from_rotation_vector(V3<T>{dt * wh.x, dt * wh.y, dt * wh.z}), q));
}

void check(const at::Tensor& t, const char* name, at::ScalarType dtype, int64_t rows, int64_t cols) {
  TORCH_CHECK(t.device().is_cpu(), "drift: ", name, " must be a CPU tensor, got ", t.device());
  TORCH_CHECK(t.scalar_type() == dtype, "drift: ", name, " has dtype ", t.scalar_type(), "; expected ", dtype);
  TORCH_CHECK(t.numel() == rows * std::max<int64_t>(cols, 1), "drift: ", name, " has shape ", t.sizes(),
              "; expected ", rows, " rows of ", std::max<int64_t>(cols, 1));
}

// One body of the drift, scalar: half kick, drift, rotation (isotropic bodies by dt L / I, the
// others by the midpoint rule; inactive bodies keep their orientation), angular velocity.
template <typename T>
inline void drift_body(int64_t b, const T* x0, const T* v0, const T* L0, const T* q0, const T* F, const T* tau,
                       const T* m, const T* I, const bool* active, T* x, T* v, T* L, T* q, T* w, T dt,
                       bool spheres_only) {
  const T h = T(0.5) * dt;
  const T act = active[b] ? T(1) : T(0);
  for (int c = 0; c < 3; ++c) {
    const int64_t k = 3 * b + c;
    v[k] = v0[k] + h * F[k] / m[b];
    L[k] = L0[k] + h * tau[k];
    x[k] = x0[k] + dt * v[k] * act;
  }
  const V3<T> Lb{L[3 * b], L[3 * b + 1], L[3 * b + 2]};
  const V3<T> Ib{I[3 * b], I[3 * b + 1], I[3 * b + 2]};
  Quat<T> qb{q0[4 * b], q0[4 * b + 1], q0[4 * b + 2], q0[4 * b + 3]};
  V3<T> wb;
  if (spheres_only) {
    wb = {Lb.x / Ib.x, Lb.y / Ib.y, Lb.z / Ib.z};
  } else if (Ib.x == Ib.y && Ib.y == Ib.z) {
    // An isotropic body (a single sphere among clumps): omega = L / I in every orientation,
    // so both angular velocities of the midpoint rule are L / I and the rotation is the one
    // by dt L / I. The general path below gives the same up to rounding, at 4x the work.
    const T inv = T(1) / Ib.x;
    wb = {Lb.x * inv, Lb.y * inv, Lb.z * inv};
    if (active[b]) qb = normalised(mul(from_rotation_vector(V3<T>{dt * wb.x, dt * wb.y, dt * wb.z}), qb));
  } else {
    const V3<T> inv_I{T(1) / Ib.x, T(1) / Ib.y, T(1) / Ib.z};
    if (active[b]) qb = advance(qb, Lb, inv_I, dt);
    wb = angular_velocity(qb, Lb, inv_I);
  }
  q[4 * b] = qb.w;
  q[4 * b + 1] = qb.x;
  q[4 * b + 2] = qb.y;
  q[4 * b + 3] = qb.z;
  w[3 * b] = wb.x;
  w[3 * b + 1] = wb.y;
  w[3 * b + 2] = wb.z;
}

constexpr int64_t kLanes = 16;  // bodies per block of the vectorised drift (a 512-bit register of float32)

// One block of the drift's body pass (see drift_impl): bodies base .. base + count - 1 (count <= kLanes).
template <typename T>
void drift_block(int64_t base, int64_t count, const T* __restrict x0, const T* __restrict v0,
                 const T* __restrict L0, const T* __restrict q0, const T* __restrict F, const T* __restrict tau,
                 const T* __restrict m, const T* __restrict I, const bool* __restrict active, T* __restrict x,
                 T* __restrict v, T* __restrict L, T* __restrict q, T* __restrict w, T dt) {
  const T h = T(0.5) * dt;
  // the operands, lane by lane (lanes past the end repeat the last body)
  alignas(64) T ix[3][kLanes], iv[3][kLanes], iL[3][kLanes], iq[4][kLanes], iF[3][kLanes], it[3][kLanes],
      im[kLanes], iI[3][kLanes], iact[kLanes];
  for (int64_t l = 0; l < kLanes; ++l) {
    const int64_t b = base + (l < count ? l : count - 1);
    for (int c = 0; c < 3; ++c) {
      ix[c][l] = x0[3 * b + c];
      iv[c][l] = v0[3 * b + c];
      iL[c][l] = L0[3 * b + c];
      iF[c][l] = F[3 * b + c];
      it[c][l] = tau[3 * b + c];
      iI[c][l] = I[3 * b + c];
    }
    for (int c = 0; c < 4; ++c) iq[c][l] = q0[4 * b + c];
    im[l] = m[b];
    iact[l] = active[b] ? T(1) : T(0);
  }
  alignas(64) T ox[3][kLanes], ov[3][kLanes], oL[3][kLanes], oq[4][kLanes], ow[3][kLanes], slow[kLanes];
  for (int64_t l = 0; l < kLanes; ++l) {
    const T act = iact[l];
    const T vx = iv[0][l] + h * iF[0][l] / im[l], vy = iv[1][l] + h * iF[1][l] / im[l],
            vz = iv[2][l] + h * iF[2][l] / im[l];
    const V3<T> Lb{iL[0][l] + h * it[0][l], iL[1][l] + h * it[1][l], iL[2][l] + h * it[2][l]};
    ov[0][l] = vx;
    ov[1][l] = vy;
    ov[2][l] = vz;
    ox[0][l] = ix[0][l] + dt * vx * act;
    ox[1][l] = ix[1][l] + dt * vy * act;
    ox[2][l] = ix[2][l] + dt * vz * act;
    oL[0][l] = Lb.x;
    oL[1][l] = Lb.y;
    oL[2][l] = Lb.z;
    const Quat<T> q_old{iq[0][l], iq[1][l], iq[2][l], iq[3][l]};
    const V3<T> Ib{iI[0][l], iI[1][l], iI[2][l]};
    const bool iso = Ib.x == Ib.y && Ib.y == Ib.z;
    // isotropic (a sphere among clumps): the rotation by dt L / I
    const T inv = T(1) / Ib.x;
    const V3<T> wi{Lb.x * inv, Lb.y * inv, Lb.z * inv};
    const V3<T> ri{dt * wi.x, dt * wi.y, dt * wi.z};
    const T ai = norm2(ri);
    const Quat<T> qi = normalised(mul(from_small_rotation(ri, ai), q_old));
    // general: the midpoint rule (advance)
    const V3<T> inv_I{T(1) / Ib.x, T(1) / Ib.y, T(1) / Ib.z};
    const V3<T> w0 = angular_velocity(q_old, Lb, inv_I);
    const V3<T> r0{h * w0.x, h * w0.y, h * w0.z};
    const T a0 = norm2(r0);
    const Quat<T> q_half = mul(from_small_rotation(r0, a0), q_old);
    const V3<T> wh = angular_velocity(q_half, Lb, inv_I);
    const V3<T> r1{dt * wh.x, dt * wh.y, dt * wh.z};
    const T a1 = norm2(r1);
    const Quat<T> qg = normalised(mul(from_small_rotation(r1, a1), q_old));
    const bool turns = act != T(0);
    const Quat<T> qn{turns ? (iso ? qi.w : qg.w) : q_old.w, turns ? (iso ? qi.x : qg.x) : q_old.x,
                     turns ? (iso ? qi.y : qg.y) : q_old.y, turns ? (iso ? qi.z : qg.z) : q_old.z};
    const V3<T> wg = angular_velocity(qn, Lb, inv_I);
    oq[0][l] = qn.w;
    oq[1][l] = qn.x;
    oq[2][l] = qn.y;
    oq[3][l] = qn.z;
    ow[0][l] = iso ? wi.x : wg.x;
    ow[1][l] = iso ? wi.y : wg.y;
    ow[2][l] = iso ? wi.z : wg.z;
    const T a_max = iso ? ai : std::max(a0, a1);
    slow[l] = a_max < T(0.04) ? T(0) : T(1);  // NaN too
  }
  for (int64_t l = 0; l < count; ++l) {
    const int64_t b = base + l;
    if (slow[l] != T(0)) {
      drift_body(b, x0, v0, L0, q0, F, tau, m, I, active, x, v, L, q, w, dt, false);
      continue;
    }
    for (int c = 0; c < 3; ++c) {
      x[3 * b + c] = ox[c][l];
      v[3 * b + c] = ov[c][l];
      L[3 * b + c] = oL[c][l];
      w[3 * b + c] = ow[c][l];
    }
    for (int c = 0; c < 4; ++c) q[4 * b + c] = oq[c][l];
  }
}

// The sphere pass of the drift: sphere(s, d) for every sphere s, in chunks of whole members
// (parts per member, fixed by the sphere count and the threads, so the result is the same on any
// number of threads), each writing the sphere's displacement since the last list build to d[3] and
// returning true, or false to stop its chunk. Per member, into disp [members, 7]: the box of the
// finite displacements (lowest x, y, z, highest x, y, z) and the largest squared length, all 0
// when none is finite. Returns -1, or the first sphere (of the lowest such chunk) for which
// sphere() returned false; disp is then not written.
template <typename T, typename Sphere>
int64_t displacement_boxes(int64_t S, int64_t members, T* disp, const Sphere& sphere) {
  const int64_t Ns = S / members;
  const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), (Ns + 1023) / 1024));
  const int64_t chunks = members * parts;
  std::vector<std::array<T, 7>> chunk_disp(chunks);
  std::vector<int64_t> stopped(chunks, -1);
  at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      constexpr T kBig = std::numeric_limits<T>::max();
      T lo[3] = {kBig, kBig, kBig}, hi[3] = {-kBig, -kBig, -kBig}, best = T(0);
      const int64_t member = c / parts, part = c % parts;
      const int64_t s0 = member * Ns + Ns * part / parts, s1 = member * Ns + Ns * (part + 1) / parts;
      for (int64_t s = s0; s < s1; ++s) {
        T d[3];
        if (!sphere(s, d)) {
          stopped[c] = s;
          break;
        }
        const T d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        if (!(d2 <= std::numeric_limits<T>::max())) continue;  // NaN and inf are left out
        best = std::max(best, d2);
        for (int a = 0; a < 3; ++a) {
          lo[a] = std::min(lo[a], d[a]);
          hi[a] = std::max(hi[a], d[a]);
        }
      }
      chunk_disp[c] = {lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], best};
    }
  });
  for (int64_t c = 0; c < chunks; ++c)
    if (stopped[c] >= 0) return stopped[c];
  for (int64_t member = 0; member < members; ++member) {
    std::array<T, 7> box = chunk_disp[member * parts];
    for (int64_t part = 1; part < parts; ++part)
      for (int k = 0; k < 7; ++k) {
        const T value = chunk_disp[member * parts + part][k];
        box[k] = k < 3 ? std::min(box[k], value) : std::max(box[k], value);
      }
    if (box[0] > box[3]) box.fill(T(0));  // no finite displacement
    std::copy(box.begin(), box.end(), disp + 7 * member);
  }
  return -1;
}

template <typename T>
void drift_impl(const std::vector<at::Tensor>& in, std::vector<at::Tensor>& out, int64_t NB, int64_t S,
                int64_t members, T dt, bool spheres_only) {
  const T *x0 = in[0].data_ptr<T>(), *v0 = in[1].data_ptr<T>(), *L0 = in[2].data_ptr<T>(), *q0 = in[3].data_ptr<T>(),
          *F = in[4].data_ptr<T>(), *tau = in[5].data_ptr<T>(), *m = in[6].data_ptr<T>(), *I = in[7].data_ptr<T>();
  const bool* active = in[8].data_ptr<bool>();
  const int64_t* sb = in[9].data_ptr<int64_t>();
  const T *off = in[10].data_ptr<T>(), *ref = in[11].data_ptr<T>();
  T *x = out[0].data_ptr<T>(), *v = out[1].data_ptr<T>(), *L = out[2].data_ptr<T>(), *q = out[3].data_ptr<T>(),
    *xs = out[4].data_ptr<T>(), *w = out[5].data_ptr<T>();
  // Bodies in blocks of kLanes, fixed by index (so a body's bits never depend on the threads):
  // each block runs branch-free across its lanes, both rotation paths computed and one kept,
  // which the compiler vectorises; a lane whose body turns by 0.2 rad or more in a step (the
  // series' range, never met in a settled or flowing bed) or has a non-finite rotation is done
  // again by the scalar path. Spheres only: the scalar path (a few operations per body).
  const int64_t blocks = (NB + kLanes - 1) / kLanes;
  at::parallel_for(0, blocks, 32, [&](int64_t k0, int64_t k1) {
    for (int64_t k = k0; k < k1; ++k) {
      const int64_t base = k * kLanes, count = std::min<int64_t>(kLanes, NB - base);
      if (spheres_only) {
        for (int64_t b = base; b < base + count; ++b) drift_body(b, x0, v0, L0, q0, F, tau, m, I, active, x, v, L, q, w, dt, true);
        continue;
      }
      drift_block(base, count, x0, v0, L0, q0, F, tau, m, I, active, x, v, L, q, w, dt);
    }
  });
  const int64_t bad = displacement_boxes<T>(S, members, out[6].data_ptr<T>(), [&](int64_t s, T* d) {
    const int64_t b = sb[s];
    if (static_cast<uint64_t>(b) >= static_cast<uint64_t>(NB)) return false;  // reported below
    V3<T> p{x[3 * b], x[3 * b + 1], x[3 * b + 2]};
    if (!spheres_only) {
      const Quat<T> qb{q[4 * b], q[4 * b + 1], q[4 * b + 2], q[4 * b + 3]};
      const V3<T> r = rotate(qb, V3<T>{off[3 * s], off[3 * s + 1], off[3 * s + 2]});
      p = {p.x + r.x, p.y + r.y, p.z + r.z};
    }
    xs[3 * s] = p.x;
    xs[3 * s + 1] = p.y;
    xs[3 * s + 2] = p.z;
    d[0] = p.x - ref[3 * s];
    d[1] = p.y - ref[3 * s + 1];
    d[2] = p.z - ref[3 * s + 2];
    return true;
  });
  TORCH_CHECK(bad < 0, "drift: sphere ", bad, " belongs to body ", sb[bad < 0 ? 0 : bad], ", outside [0, ", NB, ")");
}

// The drift of a system of single spheres whose sphere s is body s (the engine benchmark's dense
// box): the body pass and the sphere pass above in one sweep (displacement_boxes), and the
// orientation not copied (a sphere's never turns: the caller
// returns the input's). The same arithmetic as drift_body's spheres-only path; it
// removes one of the two sweeps over the spheres' rows and the orientation's 32 bytes a sphere (the
// drift was 14 % of the benchmark's B = 16 step). Returns false when sphere_body is not the
// identity (nothing it wrote is used: drift_impl runs instead).
template <typename T>
bool drift_spheres(const std::vector<at::Tensor>& in, std::vector<at::Tensor>& out, int64_t S, int64_t members,
                   T dt) {
  const T *x0 = in[0].data_ptr<T>(), *v0 = in[1].data_ptr<T>(), *L0 = in[2].data_ptr<T>(),
          *F = in[4].data_ptr<T>(), *tau = in[5].data_ptr<T>(), *m = in[6].data_ptr<T>(), *I = in[7].data_ptr<T>();
  const bool* active = in[8].data_ptr<bool>();
  const int64_t* sb = in[9].data_ptr<int64_t>();
  const T* ref = in[11].data_ptr<T>();
  T *x = out[0].data_ptr<T>(), *v = out[1].data_ptr<T>(), *L = out[2].data_ptr<T>(), *xs = out[4].data_ptr<T>(),
    *w = out[5].data_ptr<T>();
  const T h = T(0.5) * dt;
  return displacement_boxes<T>(S, members, out[6].data_ptr<T>(), [&](int64_t s, T* d) {
    if (sb[s] != s) return false;
    const T act = active[s] ? T(1) : T(0);
    for (int a = 0; a < 3; ++a) {
      const int64_t k = 3 * s + a;
      const T vk = v0[k] + h * F[k] / m[s];
      const T Lk = L0[k] + h * tau[k];
      const T xk = x0[k] + dt * vk * act;
      v[k] = vk;
      L[k] = Lk;
      x[k] = xk;
      xs[k] = xk;
      w[k] = Lk / I[k];
      d[a] = xk - ref[k];
    }
    return true;
  }) < 0;
}

std::vector<at::Tensor> drift(at::Tensor position, at::Tensor velocity, at::Tensor angular_momentum,
                              at::Tensor orientation, at::Tensor force, at::Tensor torque, at::Tensor mass,
                              at::Tensor inertia, at::Tensor active, at::Tensor sphere_body, at::Tensor sphere_offset,
                              at::Tensor reference, double dt, bool spheres_only) {
  const auto dtype = position.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "drift: position has dtype ", dtype,
              "; expected float32 or float64");
  const int64_t NB = position.numel() / 3, S = sphere_body.numel();
  const int64_t members = position.dim() == 3 ? position.size(0) : 1;  // [B, Nb, 3] or [Nb, 3]
  TORCH_CHECK(members > 0 && S % members == 0, "drift: ", S, " spheres do not split into ", members, " members");
  for (auto* p : {&position, &velocity, &angular_momentum, &force, &torque, &inertia}) check(*p, "body vector", dtype, NB, 3);
  check(orientation, "orientation", dtype, NB, 4);
  check(mass, "mass", dtype, NB, 0);
  check(active, "active", at::kBool, NB, 0);
  check(sphere_body, "sphere_body", at::kLong, S, 0);
  check(sphere_offset, "sphere_offset", dtype, S, 3);
  check(reference, "reference", dtype, S, 3);
  std::vector<at::Tensor> in = {position, velocity, angular_momentum, orientation, force, torque, mass, inertia,
                                active, sphere_body, sphere_offset, reference};
  for (auto& t : in) t = t.contiguous();
  using torchdem_recycle::output_like;
  const int s = torchdem_recycle::kDrift;
  // the orientation: the input's when every body is a single sphere of its own (drift_spheres)
  const bool own_spheres = spheres_only && S == NB;
  std::vector<at::Tensor> out = {output_like(s, in[0]), output_like(s + 1, in[1]), output_like(s + 2, in[2]),
                                 own_spheres ? in[3] : output_like(s + 3, in[3]),
                                 torchdem_recycle::output(s + 4, {S, 3}, in[0].options()),
                                 torchdem_recycle::output(s + 5, {NB, 3}, in[0].options()),
                                 at::empty({members, 7}, in[0].options())};
  AT_DISPATCH_FLOATING_TYPES(dtype, "drift", [&] {
    if (own_spheres && drift_spheres<scalar_t>(in, out, S, members, static_cast<scalar_t>(dt))) return;
    if (own_spheres) out[3] = output_like(s + 3, in[3]);
    drift_impl<scalar_t>(in, out, NB, S, members, static_cast<scalar_t>(dt), spheres_only);
  });
  return out;
}

// The twin of integrate.kick_kernel: gravity, inactive bodies masked, second half kick.
// force, torque [NB, 3] (flat); velocity, angular_momentum [..., 3] and mass, active [...]
// with NB bodies in all; gravity [3]. Returns (f, tau, v, L) shaped like velocity.
std::vector<at::Tensor> kick(at::Tensor force, at::Tensor torque, at::Tensor velocity, at::Tensor angular_momentum,
                             at::Tensor mass, at::Tensor gravity, at::Tensor active, double dt) {
  const auto dtype = velocity.scalar_type();
  TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, "kick: velocity has dtype ", dtype,
              "; expected float32 or float64");
  const int64_t NB = velocity.numel() / 3;
  for (auto* p : {&force, &torque}) check(*p, "body vector", dtype, NB, 3);
  const at::Tensor F = force.contiguous(), tau = torque.contiguous();
  const std::vector<at::Tensor> in =
      torchdem_kick::kick_inputs({velocity, angular_momentum, mass, gravity, active}, dtype, NB, "kick");
  using torchdem_recycle::output_like;
  const int s = torchdem_recycle::kKick;
  at::Tensor f = output_like(s, in[0]), t = output_like(s + 1, in[0]), v = output_like(s + 2, in[0]),
             L = output_like(s + 3, in[1]);
  AT_DISPATCH_FLOATING_TYPES(dtype, "kick", [&] {
    const auto k = torchdem_kick::kick_data<scalar_t>(in, F.data_ptr<scalar_t>(), tau.data_ptr<scalar_t>(), f, t, v,
                                                      L, static_cast<scalar_t>(dt));
    at::parallel_for(0, NB, 2048, [&](int64_t b0, int64_t b1) { torchdem_kick::kick_bodies<scalar_t>(k, b0, b1); });
  });
  return {f, t, v, L};
}

}  // namespace

// torch.ops.torchdem.drift (a fragment of the library that contact_cpu.cpp defines).
TORCH_LIBRARY_FRAGMENT(torchdem, m) {
  m.def("drift(Tensor position, Tensor velocity, Tensor angular_momentum, Tensor orientation, Tensor force, "
        "Tensor torque, Tensor mass, Tensor inertia, Tensor active, Tensor sphere_body, Tensor sphere_offset, "
        "Tensor reference, float dt, bool spheres_only) -> Tensor[]");
  m.impl("drift", c10::DispatchKey::CPU, TORCH_FN(drift));
  m.def("kick(Tensor force, Tensor torque, Tensor velocity, Tensor angular_momentum, Tensor mass, Tensor gravity, "
        "Tensor active, float dt) -> Tensor[]");
  m.impl("kick", c10::DispatchKey::CPU, TORCH_FN(kick));
}
