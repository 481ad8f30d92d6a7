// Output tensors of the per-step kernels, recycled between calls.
//
// A step allocates its outputs afresh: ~20 MB for 16 members of 3,400 spheres (springs, forces,
// velocities). glibc serves allocations of this size from memory it maps and unmaps (or trims)
// call after call, and the kernel then zeroes every 4 KB page on first touch: one fault per page,
// hundreds per step, 10-20 % of a step measured on the engine benchmark. Here every output slot of
// an operator keeps the last few tensors it returned; when the caller has dropped one (the state
// that held it was replaced), the next call hands its memory out again instead of fresh memory.
// Memory anyone still references (a saved state, a view, a NumPy array over it) is never reused.
// The cost: each thread that calls the kernels keeps up to kHeldPerSlot storages per slot until the
// process ends (about 60 MB for the 16-member benchmark; nothing on CUDA, which never gets here).
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>

#include <cstdint>
#include <vector>

namespace torchdem_recycle {

// Output slots of the operators (one per returned tensor that is allocated per call).
enum Slot : int {
  kPairForces = 0,               // 4 slots: force, torque, tangential, rolling
  kWallForces = kPairForces + 4,  // 4
  kForcesKick = kWallForces + 4,  // 8: f, tau, v, L, pair springs (2), wall springs (2)
  kDrift = kForcesKick + 8,       // 6: x, v, L, q, xs, omega
  kKick = kDrift + 6,             // 4: f, tau, v, L
  kSlots = kKick + 4
};

constexpr size_t kHeldPerSlot = 3;  // two alternate in a step loop; one spare for a held state

// A contiguous tensor of `sizes` and `options` for output `slot`, over recycled memory where it
// can: the pool keeps the storage (not the tensor: a tensor returned to Python stays alive with its
// Python object, so its count never drops) of the last tensors it handed out, and reuses one that
// nobody else references any more and that is large enough; else it allocates, and keeps the new
// storage while it holds fewer than kHeldPerSlot (a free one that is too small makes room).
// Contents are unspecified, as with at::empty. Pools are per calling thread.
inline at::Tensor output(int slot, at::IntArrayRef sizes, const at::TensorOptions& options) {
  thread_local std::vector<std::vector<c10::Storage>> pool(kSlots);
  std::vector<c10::Storage>& held = pool[slot];
  int64_t numel = 1;
  for (int64_t s : sizes) numel *= s;
  const size_t item = options.dtype().itemsize();
  const size_t bytes = static_cast<size_t>(numel) * item;
  for (size_t k = 0; k < held.size(); ++k) {
    c10::Storage& s = held[k];
    // not memory of another element size that does not divide into this one's (a float64 tensor over
    // the 492 bytes of 123 float32 values: torch.save then writes more bytes than its header states)
    if (s.use_count() != 1 || s.device() != options.device() || s.nbytes() % item != 0) continue;
    if (s.nbytes() >= bytes) return at::empty({0}, options).set_(s, 0, sizes);
    held.erase(held.begin() + static_cast<std::ptrdiff_t>(k));  // free but too small: make room
    break;
  }
  at::Tensor t = at::empty(sizes, options);
  if (held.size() < kHeldPerSlot) held.push_back(t.storage());
  return t;
}

// output() shaped and typed like `like`.
inline at::Tensor output_like(int slot, const at::Tensor& like) {
  return output(slot, like.sizes(), like.options());
}

}  // namespace torchdem_recycle
