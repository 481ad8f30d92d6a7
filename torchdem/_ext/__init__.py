"""Just-in-time built C++ kernels for CPU tensors.

Contract:
- :func:`cpu_kernels` returns the operators of ``contact_cpu.cpp`` (``pair_forces`` and
  ``wall_forces``: the CPU twins of :func:`torchdem.integrate.pair_kernel` and
  :func:`torchdem.integrate.wall_kernel`; ``forces_kick``: both, then the kick, in one pass
  per ensemble member) and of ``cells_cpu.cpp`` (``cell_pairs``: the
  candidate scan of :func:`torchdem.neighbors.find_pairs`; ``wall_pairs``: that of
  :func:`torchdem.neighbors.find_wall_pairs`) and ``rigid_cpu.cpp`` (``drift`` and ``kick``:
  the twins of :func:`torchdem.integrate.drift_kernel` and :func:`torchdem.integrate.kick_kernel`), registered as
  ``torch.ops.torchdem.*`` and built as one extension, or None
  when they cannot be built (no C++ compiler, no ninja, ...). The first call in a process
  builds or loads them with ``torch.utils.cpp_extension.load`` (about 30 s to build);
  torch caches the build under ``TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``)
  and rebuilds only when the source changes, so later processes load it in well under a second.
- The build is tuned for the CPU it runs on (``-march=native``); its name carries a hash of
  the CPU's instruction-set flags, of the sources and of their directory, so every checkout
  sharing the cache has a build of its own. torch's build file names the sources by path: two
  checkouts of the same sources under one name rebuilt each other's objects, and a build killed
  in one left its lock for the other to wait on.
- A failed build warns once per process (naming the cause) and is not retried; callers
  then use the torch kernels.
- ``TORCHDEM_NO_EXTENSION=1`` in the environment disables the extension (same as a
  failed build, without the warning).
"""
from __future__ import annotations

import hashlib
import os
import platform
import threading
import warnings
from pathlib import Path
from types import SimpleNamespace

import torch

# One extension, three sources: the contact laws, the cell-list pair search, the drift.
SOURCES = [Path(__file__).with_name(name) for name in ("contact_cpu.cpp", "cells_cpu.cpp", "rigid_cpu.cpp")]
HEADERS = [Path(__file__).with_name(name) for name in ("kick.h", "recycle.h")]  # in the build's signature
# -march=native: the loops vectorise across contacts with the widest vector unit of this CPU.
# -fno-math-errno / -fno-trapping-math let sqrt and rounding vectorise; neither changes a result
# (no -ffast-math: no reassociation, NaN and inf keep their IEEE meaning).
# -fopenmp: at::parallel_for (ATen/ParallelOpenMP.h) is a `#pragma omp parallel` compiled into the
# extension; without the flag the pragma is ignored and every kernel runs on one thread. The
# extension links libgomp.so.1, the soname libtorch_cpu has already loaded (torch's own copy),
# so kernels share torch's OpenMP thread pool and follow torch.set_num_threads.
CFLAGS = ["-O3", "-march=native", "-fno-math-errno", "-fno-trapping-math", "-fopenmp"]
LDFLAGS = ["-fopenmp"]

_lock = threading.Lock()
_state: dict[str, object] = {}


def cpu_kernels() -> SimpleNamespace | None:
    """The compiled CPU kernels (``pair_forces``, ``wall_forces``, ``cell_pairs``, ``wall_pairs``,
    ``carry_history``, ``pair_constants``, ``pair_order``, ``drift``, ``kick``, ``forces_kick``), or None if
    they cannot be built (warns once)."""
    if "module" in _state:
        return _state["module"]  # type: ignore[return-value]
    with _lock:
        if "module" not in _state:
            _state["module"] = _build()
    return _state["module"]  # type: ignore[return-value]


def kernels_for(device: torch.device | str, enabled: bool = True) -> SimpleNamespace | None:
    """The compiled kernels for tensors on ``device``: None off the CPU, when ``enabled`` is
    False (the caller asked for the torch path) or when they cannot be built."""
    if not enabled:
        return None
    # asked for at every step: a torch.device is read, not built again (7 us a call)
    kind = device.type if isinstance(device, torch.device) else torch.device(device).type
    return cpu_kernels() if kind == "cpu" else None


def build_error() -> str | None:
    """Why the extension is unavailable (None if it loaded or was not tried yet)."""
    return _state.get("error")  # type: ignore[return-value]


def _module_name() -> str:
    """Extension name tagged with this CPU's instruction sets, the build flags, the sources' contents and their
    directory: a build cache shared between machines (a network home directory) never loads code
    built for another CPU, two checkouts with different sources (two branches, two versions) never
    load the other's operators, and two checkouts never rebuild, or wait on, each other's build."""
    signature = platform.machine() + " ".join(CFLAGS + LDFLAGS) + str(Path(__file__).resolve().parent)
    signature += "".join(hashlib.sha256(p.read_bytes()).hexdigest() for p in SOURCES + HEADERS)
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                signature += line
                break
    except OSError:
        signature += platform.processor()
    return "torchdem_cpu_" + hashlib.sha256(signature.encode()).hexdigest()[:10]


def _build() -> SimpleNamespace | None:
    if os.environ.get("TORCHDEM_NO_EXTENSION", "") not in ("", "0"):
        _state["error"] = "disabled by TORCHDEM_NO_EXTENSION"
        return None
    try:
        import torch
        from torch.utils.cpp_extension import load

        load(name=_module_name(), sources=[str(p) for p in SOURCES], extra_cflags=CFLAGS, extra_ldflags=LDFLAGS,
             is_python_module=False, verbose=False)
        ops = torch.ops.torchdem
        return SimpleNamespace(pair_forces=ops.pair_forces, wall_forces=ops.wall_forces, cell_pairs=ops.cell_pairs,
                               wall_pairs=ops.wall_pairs, carry_history=ops.carry_history, drift=ops.drift,
                               kick=ops.kick, pair_constants=ops.pair_constants, pair_order=ops.pair_order,
                               forces_kick=ops.forces_kick)
    except Exception as err:  # no compiler, no ninja, compile error: fall back to the torch kernels
        message = f"{type(err).__name__}: {err}".strip()
        _state["error"] = message
        warnings.warn(
            f"torchdem: could not build the C++ contact kernels and pair search from {[p.name for p in SOURCES]} ({message.splitlines()[0]}); "
            "using the slower torch kernels on CPU. Install a C++ compiler and ninja to enable them.",
            RuntimeWarning, stacklevel=3)
        return None
