"""The draw down test, simulated end to end, with KPIs measured the lab's way.

Contract: ``DrawDownTest(mixture, geometry, contact, settings).run(replicates, device=...)``
simulates ``len(parameter sets) x replicates`` draw down tests as one batched ensemble:

1. fill: every member draws its own particles (sieve sampling, seed) and rains them layer
   by layer into the upper box (:mod:`torchdem.fill`); members are padded to equal size with
   inactive bodies;
2. settle with the gate closed for ``settings.fill_time`` seconds;
3. the gate (a wall) vanishes at ``t_open = fill_time``; the run continues for
   ``settings.discharge_time`` seconds while the load cell records the upper-box mass at
   ``loadcell_rate`` Hz (the mass of the bodies whose centres are inside the upper box);
4. at the end it renders front views of the upper and lower boxes (:mod:`torchdem.render`)
   and measures, with :mod:`kpi` exactly as for lab photos and load-cell files: angle of
   repose (lower box), shear angle (upper box), segregation RSD (lower box), mass flow rate
   (Gaussian-filtered load cell, slope 0.5-2.0 s), mass in the lower box (initial minus final
   upper mass) and the maximum heap height (highest body top in the lower box).

Slices: mass-like KPIs are reported for the simulated slice and scaled to the full box by
``depth / slice_depth`` (``*_full`` keys); angles, RSD and heights do not scale.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import torch

from kpi.angles import angle_of_repose, shear_angle
from kpi.errors import KPIInputError
from kpi.loadcell import DischargeConfig, LoadCellSignal, measure_discharge
from kpi.segregation import measure_segregation
from torchdem.contact_params import PAPER_REFERENCE, interaction_pairs
from torchdem.errors import ConfigError, out_of_range
from torchdem.fill import rain_positions
from torchdem.geometry import DrawDownGeometry
from torchdem.integrate import sphere_positions
from torchdem.materials import Material, interaction_table
from torchdem.mixture import Mixture, sample_layers
from torchdem.render import PELLET_LABEL, SINTER_LABEL, View, crop_box_for, render_state
from torchdem.simulation import GuardSettings, Simulation
from torchdem.system import build_system

KPI_UNITS = {
    "angle_of_repose_deg": "deg", "shear_angle_deg": "deg", "mass_flow_rate_kg_s": "kg/s",
    "mass_flow_rate_full_kg_s": "kg/s", "mass_lower_box_kg": "kg", "mass_lower_box_full_kg": "kg",
    "segregation_rsd_vertical": "1", "segregation_rsd_horizontal": "1", "max_heap_height_m": "m",
    "fill_mass_kg": "kg", "fill_mass_full_kg": "kg",
}


@dataclass(frozen=True)
class RunSettings:
    """How a draw down test is simulated.

    Attributes:
        fill_time: settling time with the gate closed, s. discharge_time: time after the
            gate opens, s. loadcell_rate: Hz. time_step_fraction: of the Rayleigh time step.
        shear_modulus: overrides every particle material's G (Pa) when set — the usual
            speed-up (reduced stiffness); None keeps the materials' values.
        geometry_material: Material of the walls. rolling_damping: eta_r for every pair.
        dtype: torch dtype name. compile: torch.compile the kernels. guards: blow-up guards.
        metres_per_pixel: render resolution. rsd_component: which component's RSD to report
            ("sinter" or "pellet").
    """

    fill_time: float = 0.6
    discharge_time: float = 3.5
    loadcell_rate: float = 50.0
    time_step_fraction: float = 0.15
    shear_modulus: float | None = None
    geometry_material: Material = Material("geometry", 2e11, 0.3, 7800.0)
    rolling_damping: float = 0.3
    dtype: str = "float64"
    compile: bool = False
    guards: GuardSettings = GuardSettings(check_every=500)
    metres_per_pixel: float = 0.001
    rsd_component: str = "sinter"
    loose_fraction: float = 0.3

    def validate(self, source: str = "sim") -> "RunSettings":
        for name in ("fill_time", "discharge_time", "loadcell_rate", "metres_per_pixel"):
            if not getattr(self, name) > 0:
                raise out_of_range(name, getattr(self, name), "> 0", source)
        if self.discharge_time < 2.5:
            raise out_of_range("discharge_time", self.discharge_time,
                               ">= 2.5 s (the mass-flow fit window ends 2.0 s after the gate opens and the "
                               "final mass is the mean of the last 0.5 s)", source)
        if self.dtype not in ("float32", "float64"):
            raise out_of_range("dtype", self.dtype, "'float32' or 'float64'", source)
        if self.rsd_component not in ("sinter", "pellet"):
            raise out_of_range("rsd_component", self.rsd_component, "'sinter' or 'pellet'", source)
        return self


@dataclass
class DrawDownResult:
    """KPIs and records of a batched draw down run.

    Attributes:
        kpis: one dict per member (KPI name -> value, units in :data:`KPI_UNITS`).
        loadcell: per member (time_s ``[T]`` since the gate opened, upper-box mass of the
            simulated domain ``[T]`` kg).
        images: per member {"upper": BGR image, "lower": BGR image}.
        members: per member (parameter-set index, replicate index, seed).
        wall_time_s, steps, particles: run statistics.
        conservation: per member (upper, lower, in flight, lost, total) masses at the end, kg.
        errors: per member, KPI name -> message for KPIs that could not be measured.
    """

    kpis: list[dict]
    loadcell: list[tuple[np.ndarray, np.ndarray]]
    images: list[dict]
    members: list[tuple[int, int, int]]
    wall_time_s: float
    steps: int
    particles: list[int]
    conservation: list[dict]
    errors: list[dict] = field(default_factory=list)

    def kpi_table(self, name: str) -> np.ndarray:
        """``[members]`` values of one KPI (NaN where it could not be measured)."""
        return np.array([k.get(name, np.nan) for k in self.kpis], dtype=float)


class DrawDownTest:
    """A draw down test of a mixture in a geometry with given contact parameters."""

    def __init__(self, mixture: Mixture, geometry: DrawDownGeometry,
                 contact: Mapping[str, object] | Sequence[Mapping[str, object]] = PAPER_REFERENCE,
                 settings: RunSettings = RunSettings()):
        self.mixture = mixture.validate()
        self.geometry = geometry.validate()
        self.parameter_sets = [dict(contact)] if isinstance(contact, Mapping) else [dict(c) for c in contact]
        if not self.parameter_sets:
            raise ConfigError("contact: no parameter set given")
        self.settings = settings.validate()

    # -- building ------------------------------------------------------------------------
    def _materials(self) -> list[Material]:
        G = self.settings.shear_modulus
        mats = [Material(m.name, G if G is not None else m.shear_modulus, m.poisson_ratio, m.density)
                for m in self.mixture.materials]
        return mats + [self.settings.geometry_material]

    def build(self, seeds: Sequence[int], parameter_index: Sequence[int], device="cpu"):
        """System and state for members with the given seeds and parameter-set indices."""
        s, g, mix = self.settings, self.geometry, self.mixture
        dtype = getattr(torch, s.dtype)
        fills = []
        for seed in seeds:
            layers = sample_layers(mix, g.depth_scale, seed)
            tmpl = [m.template for m in mix.materials]
            bound = np.array([tmpl[k].bounding_radius() for k in layers.material]) * layers.diameter
            volume = layers.mass / np.array([mix.materials[k].density for k in layers.material])
            fills.append((layers, rain_positions(bound, layers.layer, volume, g, seed, s.loose_fraction)))
        B = len(seeds)
        N = max(f[0].material.shape[0] for f in fills)
        pos = np.zeros((B, N, 3))
        quat = np.zeros((B, N, 4))
        quat[..., 0] = 1.0
        scale = np.ones((B, N))
        material = np.zeros((B, N), dtype=np.int64)
        active = np.zeros((B, N), dtype=bool)
        for b, (layers, fill) in enumerate(fills):
            n = layers.material.shape[0]
            pos[b, :n] = fill.position
            quat[b, :n] = fill.orientation
            scale[b, :n] = layers.diameter
            material[b, :n] = layers.material
            active[b, :n] = True
            if n < N:  # padding bodies: inactive copies of the first particle
                pos[b, n:] = fill.position[0]
                scale[b, n:] = layers.diameter[0]
                material[b, n:] = layers.material[0]
        shapes = sorted({m.shape for m in mix.materials})
        templates = [next(m.template for m in mix.materials if m.shape == sh) for sh in shapes]
        template_of_material = np.array([shapes.index(m.shape) for m in mix.materials])
        materials = self._materials()
        names = [m.name for m in mix.materials]
        per_member = [self.parameter_sets[i] for i in parameter_index]
        keys = sorted(set().union(*per_member))
        stacked = {}
        for k in keys:
            if any(k not in p for p in per_member):
                raise ConfigError(f"contact: parameter {k!r} is missing from some parameter sets")
            stacked[k] = [float(p[k]) for p in per_member]
        pairs = interaction_pairs(stacked, names, s.geometry_material.name,
                                  abbreviations={**{"p": "pellet", "s": "sinter"}, "g": s.geometry_material.name}
                                  if set(names) <= {"pellet", "sinter"} else _letters(names, s.geometry_material.name),
                                  rolling_damping=s.rolling_damping)
        table = interaction_table(materials, pairs, batch=B, dtype=dtype, device=device, source="contact")
        t = lambda a, **kw: torch.as_tensor(a, device=device, **kw)  # noqa: E731
        system, state = build_system(
            t(pos, dtype=dtype), t(material), materials, table,
            templates=templates, template_index=t(template_of_material[material]), scale=t(scale, dtype=dtype),
            orientation=t(quat, dtype=dtype), active=t(active),
            walls=g.walls(s.geometry_material.name, s.fill_time), time_step_fraction=s.time_step_fraction,
            domain=g.domain(), periodic=g.periodic, source="drawdown")
        return system, state, [int(f[0].material.shape[0]) for f in fills]

    # -- running -------------------------------------------------------------------------
    def run(self, replicates: int = 1, device="cpu", seeds: Sequence[int] | None = None,
            progress: Callable[[float, float], None] | None = None) -> DrawDownResult:
        """Run every parameter set ``replicates`` times (different seeds) as one ensemble."""
        if replicates < 1:
            raise out_of_range("replicates", replicates, "an integer >= 1", "DrawDownTest.run")
        P = len(self.parameter_sets)
        seeds = list(seeds) if seeds is not None else list(range(replicates))
        if len(seeds) != replicates:
            raise ConfigError(f"DrawDownTest.run: {len(seeds)} seeds for {replicates} replicates")
        members = [(p, r, seeds[r]) for p in range(P) for r in range(replicates)]
        system, state, counts = self.build([m[2] for m in members], [m[0] for m in members], device)
        s, g = self.settings, self.geometry
        sim = Simulation(system, state, s.guards, compile=s.compile)
        started = time.perf_counter()
        sim.run_until(s.fill_time)
        t_open = s.fill_time
        every = max(1, int(round(1.0 / (s.loadcell_rate * system.dt))))
        times, masses = [], []

        def record(simulation: Simulation) -> None:
            times.append(simulation.time - t_open)
            masses.append(self._upper_mass(simulation).cpu().numpy())
            if progress is not None:
                progress(simulation.time, time.perf_counter() - started)

        record(sim)
        sim.run_until(t_open + s.discharge_time, callback=record, callback_every=every)
        wall = time.perf_counter() - started
        return self._measure(sim, members, counts, np.array(times), np.stack(masses, 1), wall)

    def _upper_mass(self, sim: Simulation) -> torch.Tensor:
        b = sim.state.bodies
        inside = self.geometry.in_upper_box(b.position[..., 0], b.position[..., 2]) & b.active
        return (sim.system.mass * inside).sum(-1)

    def _measure(self, sim, members, counts, times, masses, wall) -> DrawDownResult:
        g, s = self.geometry, self.settings
        system, state = sim.system, sim.state
        scale = 1.0 / g.depth_scale
        labels = {k: (PELLET_LABEL if m.label == "pellet" else SINTER_LABEL)
                  for k, m in enumerate(self.mixture.materials)}
        upper_view = View(-g.upper_width / 2 - 0.02, g.upper_width / 2 + 0.02, g.upper_bottom_z - 0.02,
                          g.upper_bottom_z + g.upper_height, s.metres_per_pixel)
        lower_view = View(-g.lower_width / 2 - 0.02, g.lower_width / 2 + 0.02, -0.02, g.upper_bottom_z,
                          s.metres_per_pixel)
        up_crop = crop_box_for(upper_view, -g.upper_width / 2, g.upper_width / 2, g.upper_bottom_z,
                               g.upper_bottom_z + g.upper_height)
        # below the upper box's bottom plates, whose front view is a band 6 px thick under z_b
        plate_band = 8 * s.metres_per_pixel
        low_crop = crop_box_for(lower_view, -g.lower_width / 2, g.lower_width / 2, 0.0, g.upper_bottom_z - plate_band)
        b = state.bodies
        total = (system.mass * b.active).sum(-1)
        upper = self._upper_mass(sim)
        in_lower = g.in_lower_box(b.position[..., 0], b.position[..., 2]) & b.active
        lower = (system.mass * in_lower).sum(-1)
        kpis, images, errors, conservation, loadcells = [], [], [], [], []
        for m, (p, r, seed) in enumerate(members):
            fill_mass = float((system.mass[m] * (torch.arange(system.n_bodies, device=b.active.device) < counts[m])).sum())
            k: dict[str, float] = {"fill_mass_kg": fill_mass, "fill_mass_full_kg": fill_mass * scale}
            err: dict[str, str] = {}
            signal = LoadCellSignal(times, masses[m], source=f"member {m} load cell")
            try:
                d = measure_discharge(signal, fill_mass, DischargeConfig())
                k["mass_flow_rate_kg_s"] = d.mass_flow_rate_kg_s
                k["mass_flow_rate_full_kg_s"] = d.mass_flow_rate_kg_s * scale
            except KPIInputError as exc:
                err["mass_flow_rate_kg_s"] = str(exc)
            k["mass_lower_box_kg"] = fill_mass - float(masses[m][-1])
            k["mass_lower_box_full_kg"] = k["mass_lower_box_kg"] * scale
            upper_img = render_state(system, state, m, labels, upper_view)
            lower_img = render_state(system, state, m, labels, lower_view)
            for name, fn, img, crop in (("shear_angle_deg", shear_angle, upper_img, up_crop),
                                        ("angle_of_repose_deg", angle_of_repose, lower_img, low_crop)):
                try:
                    k[name] = float(fn(img, crop_box=crop, source=f"member {m} {name}").angle_deg)
                except KPIInputError as exc:
                    err[name] = str(exc)
            try:
                seg = measure_segregation(lower_img, crop_box=low_crop, source=f"member {m} lower box")
                comp = s.rsd_component
                k["segregation_rsd_vertical"] = float(getattr(seg.vertical, f"{comp}_rsd"))
                k["segregation_rsd_horizontal"] = float(getattr(seg.horizontal, f"{comp}_rsd"))
            except KPIInputError as exc:
                err["segregation"] = str(exc)
            xs = sphere_positions(system, state.bodies).reshape(system.batch, system.n_spheres, 3)[m]
            body = system.sphere_body[m]
            sel = in_lower[m][body]
            k["max_heap_height_m"] = float((xs[sel, 2] + system.sphere_radius[m][sel]).max()) if bool(sel.any()) else 0.0
            kpis.append(k)
            errors.append(err)
            images.append({"upper": upper_img, "lower": lower_img})
            loadcells.append((times, masses[m]))
            conservation.append({"upper_kg": float(upper[m]), "lower_kg": float(lower[m]),
                                 "in_flight_kg": float(total[m] - upper[m] - lower[m]),
                                 "lost_bodies": int(state.lost[m]), "total_kg": float(total[m]),
                                 "fill_kg": fill_mass})
        return DrawDownResult(kpis, loadcells, images, members, wall, state.step, counts, conservation, errors)


def _letters(names: Sequence[str], geometry: str) -> dict[str, str]:
    """One-letter abbreviations for arbitrary material names (first free letter of each)."""
    out: dict[str, str] = {"g": geometry}
    for n in names:
        for c in n.lower():
            if c.isalpha() and c not in out:
                out[c] = n
                break
        else:
            raise ConfigError(f"mixture: cannot give material {n!r} a one-letter abbreviation")
    return out
