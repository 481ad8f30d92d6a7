"""Trajectory output that ParaView opens: legacy VTK PolyData, one file per frame and member.

Contract: :func:`write_vtk_frame` writes ``<directory>/<prefix>_m<member>_<step>.vtk`` for
every requested ensemble member: the active spheres as points (vertices) with point data
``id`` (sphere index as built), ``body`` (body index as built: ids survive a spatial reorder,
``State.sphere_id`` / ``State.body_id``), ``material`` (material id), ``radius`` (m) and
``velocity`` (m/s, of the sphere centre). Each frame is a binary (big-endian) legacy VTK file,
which ParaView reads directly; use the "Glyph" filter with ``radius`` as the scale to see
spheres. :class:`VTKWriter` calls it every ``interval`` steps and keeps a ``.pvd``-free file
series that ParaView groups by name.

Save/restore of the full state lives in :meth:`torchdem.simulation.Simulation.save`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from torchdem.integrate import body_angular_velocity, sphere_active, sphere_positions
from torchdem.state import State
from torchdem.system import System


def _sphere_velocity(system: System, state: State) -> torch.Tensor:
    B, Nb = system.batch, system.n_bodies
    body = system.sphere_body_flat
    v = state.bodies.velocity.reshape(B * Nb, 3)[body]
    if system.spheres_only:
        return v
    omega = body_angular_velocity(system, state.bodies)[body]
    arm = sphere_positions(system, state.bodies) - state.bodies.position.reshape(B * Nb, 3)[body]
    return v + torch.linalg.cross(omega, arm, dim=-1)


def write_vtk_frame(directory: str | Path, system: System, state: State, members: Sequence[int] | None = None,
                    prefix: str = "particles") -> list[Path]:
    """Write one legacy-VTK file per member for the current state; return the paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    B, Ns = system.batch, system.n_spheres
    xs = sphere_positions(system, state.bodies).reshape(B, Ns, 3).detach().cpu().double().numpy()
    vs = _sphere_velocity(system, state).reshape(B, Ns, 3).detach().cpu().double().numpy()
    act = sphere_active(system, state.bodies).reshape(B, Ns).cpu().numpy()
    rad = system.sphere_radius.detach().cpu().double().numpy()
    mat = system.sphere_material.cpu().numpy()
    body = torch.gather(state.body_id, 1, system.sphere_body).cpu().numpy()
    sphere_id = state.sphere_id.cpu().numpy()
    paths = []
    for m in (range(B) if members is None else members):
        sel = np.nonzero(act[m])[0]
        n = sel.shape[0]
        path = directory / f"{prefix}_m{m:03d}_{state.step:09d}.vtk"
        with open(path, "wb") as fh:
            head = (f"# vtk DataFile Version 3.0\ntorchdem step {state.step} t={system.time_of(state.step):.9g} s "
                    f"member {m}\nBINARY\nDATASET POLYDATA\nPOINTS {n} double\n")
            fh.write(head.encode())
            fh.write(xs[m, sel].astype(">f8").tobytes())
            fh.write(f"\nVERTICES {n} {2 * n}\n".encode())
            verts = np.stack([np.ones(n, dtype=np.int64), np.arange(n, dtype=np.int64)], 1)
            fh.write(verts.astype(">i4").tobytes())
            fh.write(f"\nPOINT_DATA {n}\n".encode())
            for name, arr, kind in (("id", sphere_id[m, sel], "int"), ("body", body[m, sel], "int"),
                                    ("material", mat[m, sel], "int"), ("radius", rad[m, sel], "double")):
                fh.write(f"SCALARS {name} {kind} 1\nLOOKUP_TABLE default\n".encode())
                fh.write(np.asarray(arr).astype(">i4" if kind == "int" else ">f8").tobytes())
                fh.write(b"\n")
            fh.write(b"VECTORS velocity double\n")
            fh.write(vs[m, sel].astype(">f8").tobytes())
            fh.write(b"\n")
        paths.append(path)
    return paths


def read_vtk_points(path: str | Path) -> dict[str, np.ndarray]:
    """Read back a frame written by :func:`write_vtk_frame` (points and point data)."""
    data = Path(path).read_bytes()
    out: dict[str, np.ndarray] = {}
    pos = 0

    def line() -> str:
        nonlocal pos
        end = data.index(b"\n", pos)
        text = data[pos:end].decode()
        pos = end + 1
        return text

    for _ in range(4):
        line()
    n = int(line().split()[1])
    out["points"] = np.frombuffer(data[pos:pos + 24 * n], dtype=">f8").reshape(n, 3)
    pos += 24 * n + 1
    line()
    pos += 8 * n + 1
    line()
    while pos < len(data):
        head = line().split()
        if not head:
            continue
        if head[0] == "SCALARS":
            line()
            size, dt = (4, ">i4") if head[2] == "int" else (8, ">f8")
            out[head[1]] = np.frombuffer(data[pos:pos + size * n], dtype=dt)
            pos += size * n + 1
        elif head[0] == "VECTORS":
            out[head[1]] = np.frombuffer(data[pos:pos + 24 * n], dtype=">f8").reshape(n, 3)
            pos += 24 * n + 1
    return out


class VTKWriter:
    """Callback for :meth:`Simulation.advance` writing a frame every ``interval`` steps."""

    def __init__(self, directory: str | Path, interval: int, members: Sequence[int] | None = None):
        if interval < 1:
            raise ValueError(f"VTKWriter: interval = {interval}; expected an integer >= 1 step")
        self.directory = Path(directory)
        self.interval = interval
        self.members = members
        self.paths: list[Path] = []

    def __call__(self, sim) -> None:
        if sim.state.step % self.interval == 0:
            self.paths += write_vtk_frame(self.directory, sim.system, sim.state, self.members)
