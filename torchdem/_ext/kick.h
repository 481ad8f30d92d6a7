// The kick of torchdem/integrate.py (kick_kernel: gravity, inactive bodies masked, second half
// kick), shared by `kick` (rigid_cpu.cpp) and `forces_kick` (contact_cpu.cpp), so that both give
// the same bits.
#pragma once

#include <ATen/core/Tensor.h>

#include <algorithm>
#include <cstdint>
#include <string>
#include <vector>

namespace torchdem_kick {

// Validates (velocity, angular_momentum, mass, gravity, active) for NB bodies of dtype `dtype`
// and returns them contiguous; `op` names the calling operator in the errors.
inline std::vector<at::Tensor> kick_inputs(std::vector<at::Tensor> in, at::ScalarType dtype, int64_t NB,
                                           const char* op) {
  const char* names[] = {"velocity", "angular_momentum", "mass", "gravity", "active"};
  const int64_t numel[] = {3 * NB, 3 * NB, NB, 3, NB};
  for (int k = 0; k < 5; ++k) {
    const at::Tensor& t = in[k];
    const at::ScalarType want = k == 4 ? at::kBool : dtype;
    TORCH_CHECK(t.device().is_cpu(), op, ": ", names[k], " must be a CPU tensor, got ", t.device());
    TORCH_CHECK(t.scalar_type() == want, op, ": ", names[k], " has dtype ", t.scalar_type(), "; expected ", want);
    TORCH_CHECK(t.numel() == numel[k], op, ": ", names[k], " has shape ", t.sizes(), "; expected ", numel[k],
                " elements");
  }
  for (auto& t : in) t = t.contiguous();
  return in;
}

// Operands of the kick. F, tau: contact force and torque [NB, 3] (may alias f, t: each element
// is read before it is written); v0, L0 [NB, 3], m [NB], g [3], active [NB]; outputs f, t (force
// with gravity and torque, both masked), v, L.
template <typename T>
struct KickData {
  const T *F, *tau, *v0, *L0, *m;
  T g[3];
  const bool* active;
  T *f, *t, *v, *L;
  T h;  // dt / 2
};

// Kicks bodies [b0, b1).
template <typename T>
inline void kick_bodies(const KickData<T>& k, int64_t b0, int64_t b1) {
  for (int64_t b = b0; b < b1; ++b) {
    const T act = k.active[b] ? T(1) : T(0);
    for (int c = 0; c < 3; ++c) {
      const int64_t e = 3 * b + c;
      const T f = (k.F[e] + k.m[b] * k.g[c]) * act;
      const T t = k.tau[e] * act;
      k.f[e] = f;
      k.t[e] = t;
      k.v[e] = k.v0[e] + k.h * f / k.m[b];
      k.L[e] = k.L0[e] + k.h * t;
    }
  }
}

// KickData over the validated inputs `in` (kick_inputs) and the contact force and torque.
template <typename T>
inline KickData<T> kick_data(const std::vector<at::Tensor>& in, const T* F, const T* tau, at::Tensor& f,
                             at::Tensor& t, at::Tensor& v, at::Tensor& L, T dt) {
  const T* g = in[3].data_ptr<T>();
  return KickData<T>{F, tau, in[0].data_ptr<T>(), in[1].data_ptr<T>(), in[2].data_ptr<T>(), {g[0], g[1], g[2]},
                     in[4].data_ptr<bool>(), f.data_ptr<T>(), t.data_ptr<T>(), v.data_ptr<T>(), L.data_ptr<T>(),
                     T(0.5) * dt};
}

}  // namespace torchdem_kick
