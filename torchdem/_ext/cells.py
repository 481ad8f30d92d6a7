"""Just-in-time built C++ cell-list pair search for CPU tensors (``cells_cpu.cpp``).

Contract: :func:`cells_cpu` returns ``torch.ops.torchdem.cell_pairs`` (the CPU twin of the
candidate scan in :func:`torchdem.neighbors.find_pairs`), or None when it cannot be built or
``TORCHDEM_NO_EXTENSION=1`` is set; a failed build warns once per process and is not
retried, and callers use the torch path. Built and cached like :mod:`torchdem._ext`.
"""
from __future__ import annotations

import os
import threading
import warnings
from pathlib import Path

SOURCE = Path(__file__).with_name("cells_cpu.cpp")
MODULE_NAME = "torchdem_cells_cpu"

_lock = threading.Lock()
_state: dict[str, object] = {}


def cells_cpu():
    """``torch.ops.torchdem.cell_pairs`` or None (see the module docstring)."""
    if "op" not in _state:
        with _lock:
            if "op" not in _state:
                _state["op"] = _build()
    return _state["op"]


def _build():
    if os.environ.get("TORCHDEM_NO_EXTENSION", "") not in ("", "0"):
        return None
    try:
        import torch
        from torch.utils.cpp_extension import load

        load(name=MODULE_NAME, sources=[str(SOURCE)], extra_cflags=["-O3"], is_python_module=False, verbose=False)
        return torch.ops.torchdem.cell_pairs
    except Exception as err:  # no compiler or ninja: the torch path is used
        warnings.warn(f"torchdem: could not build the C++ pair search from {SOURCE} "
                      f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); "
                      "using the slower torch path on CPU", RuntimeWarning, stacklevel=3)
        return None
