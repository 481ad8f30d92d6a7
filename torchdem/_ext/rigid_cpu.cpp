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
// out, all 0 when none is finite); nothing passed in is modified.
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
template <typename T> inline __attribute__((always_inline)) Quat<T> from_rotation_vector(V3<T> rv) {
  const T a2 = rv.x * rv.x + rv.y * rv.y + rv.z * rv.z;
  T c, s;
  if (a2 < T(0.04)) {
    const T h2 = T(0.25) * a2;
    c = T(1) + h2 * (T(-1.0 / 2) + h2 * (T(1.0 / 24) + h2 * (T(-1.0 / 720) + h2 * T(1.0 / 40320))));
    s = T(0.5) * (T(1) + h2 * (T(-1.0 / 6) + h2 * (T(1.0 / 120) + h2 * (T(-1.0 / 5040) + h2 * T(1.0 / 362880)))));
  } else {
    const T angle = std::sqrt(a2);
    c = std::cos(T(0.5) * angle);
    s = std::sin(T(0.5) * angle) / angle;
  }
  return {c, rv.x * s, rv.y * s, rv.z * s};
}

// rigid.advance_orientation (midpoint rule at fixed world angular momentum), renormalised.
template <typename T> inline Quat<T> advance(Quat<T> q, V3<T> L, V3<T> inv_I, T dt) {
  const V3<T> w0 = angular_velocity(q, L, inv_I);
  const T h = T(0.5) * dt;
  const Quat<T> q_half = mul(from_rotation_vector(V3<T>{h * w0.x, h * w0.y, h * w0.z}), q);
  const V3<T> wh = angular_velocity(q_half, L, inv_I);
  const Quat<T> n = mul(from_rotation_vector(V3<T>{dt * wh.x, dt * wh.y, dt * wh.z}), q);
  const T inv_len = T(1) / std::sqrt(n.w * n.w + n.x * n.x + n.y * n.y + n.z * n.z);
  return {n.w * inv_len, n.x * inv_len, n.y * inv_len, n.z * inv_len};
}

void check(const at::Tensor& t, const char* name, at::ScalarType dtype, int64_t rows, int64_t cols) {
  TORCH_CHECK(t.device().is_cpu(), "drift: ", name, " must be a CPU tensor, got ", t.device());
  TORCH_CHECK(t.scalar_type() == dtype, "drift: ", name, " has dtype ", t.scalar_type(), "; expected ", dtype);
  TORCH_CHECK(t.numel() == rows * std::max<int64_t>(cols, 1), "drift: ", name, " has shape ", t.sizes(),
              "; expected ", rows, " rows of ", std::max<int64_t>(cols, 1));
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
  const T h = T(0.5) * dt;
  at::parallel_for(0, NB, 512, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
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
        if (active[b]) {
          const Quat<T> n = mul(from_rotation_vector(V3<T>{dt * wb.x, dt * wb.y, dt * wb.z}), qb);
          const T inv_len = T(1) / std::sqrt(n.w * n.w + n.x * n.x + n.y * n.y + n.z * n.z);
          qb = {n.w * inv_len, n.x * inv_len, n.y * inv_len, n.z * inv_len};
        }
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
  });
  // Chunks of spheres within each member: per chunk the displacement box (lowest x, y, z,
  // highest x, y, z) and the largest squared length.
  const int64_t Ns = S / members;
  const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), (Ns + 1023) / 1024));
  const int64_t chunks = members * parts;
  std::vector<std::array<T, 7>> chunk_disp(chunks);
  std::vector<int64_t> chunk_bad(chunks, 0);  // 1 + the last sphere of the chunk with a bad body
  at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      constexpr T kBig = std::numeric_limits<T>::max();
      T lo[3] = {kBig, kBig, kBig}, hi[3] = {-kBig, -kBig, -kBig}, best = T(0);
      const int64_t member = c / parts, part = c % parts;
      const int64_t s0 = member * Ns + Ns * part / parts, s1 = member * Ns + Ns * (part + 1) / parts;
      for (int64_t s = s0; s < s1; ++s) {
        const int64_t b = sb[s];
        if (static_cast<uint64_t>(b) >= static_cast<uint64_t>(NB)) {  // reported after the pass
          chunk_bad[c] = s + 1;
          continue;
        }
        V3<T> p{x[3 * b], x[3 * b + 1], x[3 * b + 2]};
        if (!spheres_only) {
          const Quat<T> qb{q[4 * b], q[4 * b + 1], q[4 * b + 2], q[4 * b + 3]};
          const V3<T> r = rotate(qb, V3<T>{off[3 * s], off[3 * s + 1], off[3 * s + 2]});
          p = {p.x + r.x, p.y + r.y, p.z + r.z};
        }
        xs[3 * s] = p.x;
        xs[3 * s + 1] = p.y;
        xs[3 * s + 2] = p.z;
        const T d[3] = {p.x - ref[3 * s], p.y - ref[3 * s + 1], p.z - ref[3 * s + 2]};
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
  for (int64_t c = 0; c < chunks; ++c) {
    const int64_t s = chunk_bad[c] - 1;
    TORCH_CHECK(s < 0, "drift: sphere ", s, " belongs to body ", sb[s < 0 ? 0 : s], ", outside [0, ", NB, ")");
  }
  T* disp = out[6].data_ptr<T>();
  for (int64_t member = 0; member < members; ++member) {
    std::array<T, 7> box = chunk_disp[member * parts];
    for (int64_t part = 1; part < parts; ++part)
      for (int k = 0; k < 7; ++k) {
        const T v = chunk_disp[member * parts + part][k];
        box[k] = k < 3 ? std::min(box[k], v) : std::max(box[k], v);
      }
    if (box[0] > box[3]) box.fill(T(0));  // no finite displacement
    std::copy(box.begin(), box.end(), disp + 7 * member);
  }
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
  std::vector<at::Tensor> out = {output_like(s, in[0]), output_like(s + 1, in[1]), output_like(s + 2, in[2]),
                                 output_like(s + 3, in[3]), torchdem_recycle::output(s + 4, {S, 3}, in[0].options()),
                                 torchdem_recycle::output(s + 5, {NB, 3}, in[0].options()),
                                 at::empty({members, 7}, in[0].options())};
  AT_DISPATCH_FLOATING_TYPES(dtype, "drift", [&] {
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
