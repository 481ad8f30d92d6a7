"""The draw down test, simulated end to end, with KPIs measured the lab's way.

Contract: ``DrawDownTest(mixture, geometry, contact, settings).run(replicates, device=...)``
simulates ``len(parameter sets) x replicates`` draw down tests as one batched ensemble:

1. fill: every member draws its own particles (sieve sampling, seed) and rains them layer
   by layer into the upper box (:mod:`torchdem.fill`); members are padded to equal size with
   inactive bodies;
2. settle with the gate closed for ``settings.fill_time`` seconds (with a share of the frictions
   when a parameter set gives :data:`FILL_FRICTION_PARAMETER`); as the gate opens, the fill's bulk
   density (``fill_bulk_density_kg_m3``: upper-box mass over the box's width, simulated depth and
   mean height of the fill's top, grains in the air left out) and its pellets' share in each quarter
   of its mass from the floor up (``fill_pellet_share_q1`` .. ``q4``: how far the rained layers have
   mixed) are taken;
3. the gate (a wall) vanishes at ``t_open = fill_time``; the run continues for
   ``settings.discharge_time`` seconds while the load cell records the upper-box mass at
   ``loadcell_rate`` Hz (the mass of the bodies whose centres are inside the upper box);
   with ``settings.max_discharge_time`` set, the run goes on past ``discharge_time`` until
   every member's discharge has ended (its upper-box mass steady over the last
   ``final_window`` s), as the lab photographs "once the discharge is finished", or until
   ``max_discharge_time``; ``discharge_ended`` says which (1 or 0), ``discharge_duration_s``
   how long it flowed;
4. at the end it renders front views of the upper and lower boxes (:mod:`torchdem.render`)
   of the bodies at rest (speed below :data:`AT_REST_SPEED_M_S`): the lab photographs the boxes
   once the discharge has ended, so grains still trickling from the slot or bouncing off the
   heap are not in its photo (drawn, a falling stream joins the heap's apex and tilts both
   fitted flanks by up to 5 deg), and measures, with :mod:`kpi` exactly as for lab photos and load-cell files: angle of
   repose (lower box), shear angle (upper box), segregation RSD (lower box), mass flow rate
   (Gaussian-filtered load cell, slope 0.5-2.0 s), mass in the lower box (initial minus final
   upper mass) and the maximum heap height (highest top of a body at rest in the lower box).
   A discharge that let less than :data:`JAM_FRACTION` of the fill out has jammed
   (``discharge_jammed`` 1): its level surfaces read 0 deg instead of failing to measure.

Slices: mass-like KPIs are reported for the simulated slice and scaled to the full box by
``depth / slice_depth`` (``*_full`` keys); angles, RSD and heights do not scale.
"""
from __future__ import annotations

import dataclasses
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import torch

from kpi.angles import angle_of_repose, shear_angle
from kpi.errors import KPIInputError
from kpi.loadcell import DischargeConfig, LoadCellSignal, fit_mass_flow_rate, measure_discharge
from kpi.segregation import measure_segregation
from torchdem.contact_params import PAPER_REFERENCE, interaction_pairs
from torchdem.errors import ConfigError, out_of_range
from torchdem.clumps import ClumpTemplate, principal_template
from torchdem.fill import rain_to_fit
from torchdem.geometry import MIRROR_MATERIAL, DrawDownGeometry
from torchdem.integrate import evaluate_forces, sphere_positions
from torchdem.io import VTKWriter
from torchdem.materials import Material, interaction_table
from torchdem.mixture import Mixture, sample_layers, scalp_mixture
from torchdem.neighbors import cell_grid, find_pairs
from torchdem.render import PELLET_LABEL, SINTER_LABEL, View, crop_box_for, member_spheres, render_front
from torchdem.simulation import GuardSettings, Simulation
from torchdem.state import to_dict
from torchdem.system import build_system

#: Contact parameter setting the EPSD viscous rolling damping ratio of every pair, per parameter
#: set (default: ``RunSettings.rolling_damping``).
ROLLING_DAMPING_PARAMETER = "eta_r"

#: Contact parameter setting, per parameter set, the share of every sliding and rolling friction
#: coefficient (particles and walls) the fill settles with; the gate opens with the full ones. 1 (the
#: default) fills with the model's frictions; below 1 the bed packs denser, as a fill poured by hand in
#: layers may (:mod:`torchdem.mechanisms.fill_friction`).
FILL_FRICTION_PARAMETER = "fill_friction"

KPI_UNITS = {
    "angle_of_repose_deg": "deg", "shear_angle_deg": "deg", "mass_flow_rate_kg_s": "kg/s",
    "mass_flow_rate_full_kg_s": "kg/s", "mass_lower_box_kg": "kg", "mass_lower_box_full_kg": "kg",
    "segregation_rsd_vertical": "1", "segregation_rsd_horizontal": "1", "max_heap_height_m": "m",
    "fill_mass_kg": "kg", "fill_mass_full_kg": "kg", "discharge_duration_s": "s", "discharge_ended": "1",
    "discharge_jammed": "1", "fill_bulk_density_kg_m3": "kg/m^3",
    "mass_flow_rate_pellet_full_kg_s": "kg/s", "mass_flow_rate_sinter_full_kg_s": "kg/s",
    "mass_flow_rate_early_full_kg_s": "kg/s", "mass_flow_rate_late_full_kg_s": "kg/s",
    "fill_pellet_share_q1": "1", "fill_pellet_share_q2": "1", "fill_pellet_share_q3": "1", "fill_pellet_share_q4": "1",
}
#: The fill's layering as the gate opens: the pellets' mass share in each quarter of the upper box's mass,
#: counted from the floor up in columns across the box's width (``q1`` the bottom quarter, over the slot
#: and beside it). Four unmixed layers read 1, 0, 1, 0 (pellets at the bottom) or 0, 1, 0, 1 (reverse);
#: pellets that sank into the sinter below them move the shares towards the fill's own.
FILL_LAYERING_KPIS: tuple[str, ...] = ("fill_pellet_share_q1", "fill_pellet_share_q2", "fill_pellet_share_q3",
                                       "fill_pellet_share_q4")
#: The model's own view of the flow, which one load cell cannot give the lab: each material's share of
#: ``mass_flow_rate_full_kg_s`` over the same fit window (pellet + sinter = the whole, the slope fit
#: being linear in the mass), and the whole flow over the window's first and second halves (how the
#: rate changes as the layers reach the slot).
FLOW_BREAKDOWN_KPIS: tuple[str, ...] = ("mass_flow_rate_pellet_full_kg_s", "mass_flow_rate_sinter_full_kg_s",
                                        "mass_flow_rate_early_full_kg_s", "mass_flow_rate_late_full_kg_s")
#: The DEM names of the four KPIs the paper calibrates on (``torchdem.measured.CALIBRATION_KPIS``), the
#: masses those of the whole box (a slice or half box scales its own up).
CALIBRATION_KPIS_DEM: tuple[str, ...] = ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s",
                                         "mass_lower_box_full_kg")

#: The discharge has ended when the upper-box mass stays within this share of the fill mass of its
#: final value (the lab's 0.2 kg of 40 kg; :class:`kpi.loadcell.DischargeConfig` ``end_tolerance_kg``).
DISCHARGE_END_TOLERANCE = 0.005


#: A discharge that has let less than this share of the fill out of the upper box has jammed
#: (``discharge_jammed`` 1): the grains arched over the slot. A jammed box keeps its fill's level surface,
#: so there is no shear surface to photograph: its shear angle is that of a level surface, 0 deg, as
#: the lab's line fit would read it, and the angle of repose of an empty lower box is 0 deg too. A
#: calibration thus sees a jammed run as the total miss it is (its flow and lower-box mass near 0)
#: instead of losing it as unmeasured.
JAM_FRACTION = 0.05

#: Bodies slower than this (m/s) are at rest: the photos show them, the heap height counts them.
AT_REST_SPEED_M_S = 0.1

#: Two spheres closer than this share of their radii's sum beyond touching still rest on each other: the
#: fill's ruler (``fill_bulk_density_kg_m3``) reads a grain in the air, one that touches no other body and not
#: the floor, as no part of the fill's top.
RESTING_GAP = 0.05

@dataclass(frozen=True)
class RunSettings:
    """How a draw down test is simulated.

    Attributes:
        fill_time: settling time with the gate closed, s. discharge_time: time after the
            gate opens, s (the least, with ``max_discharge_time``). max_discharge_time: None
            stops every run at ``discharge_time``; else the run goes on until every member's
            discharge has ended (upper-box mass within half of :data:`DISCHARGE_END_TOLERANCE`
            of the fill over the last ``final_window`` s), at most this long after the gate
            opens, s. loadcell_rate: Hz. time_step_fraction: of the Rayleigh time step.
        discharge_time_step_fraction: of the Rayleigh time step from the gate's opening on; None:
            ``time_step_fraction`` throughout. The fill lands from up to three box heights and packs
            while it settles; the discharge's contacts are gentler, and it takes most of a run's steps.
        shear_modulus: overrides every particle material's G (Pa) when set — the usual
            speed-up (reduced stiffness); None keeps the materials' values.
        geometry_material: Material of the walls. rolling_damping: eta_r for every pair.
        dtype: torch dtype name. compile: torch.compile the kernels. guards: blow-up guards.
        metres_per_pixel: render resolution. rsd_component: which component's RSD to report
            ("sinter" or "pellet"). photo_shadow_depth: surfaces more than this (m) behind the front
            layer are painted in shadow in the photos (:func:`torchdem.render.render_front`); None: none.
            loose_fraction: packing fraction of the rained fill (a member
            whose loose stack would overflow the fill column is rained denser, up to 0.375:
            :func:`torchdem.fill.rain_to_fit`).
        skin_fraction: Verlet skin as a fraction of the largest sphere radius.
        flow_window: (start, end) s after the gate opens of the mass-flow fit (the lab's
            0.5-2.0 s; a smaller box that empties sooner needs an earlier window).
        final_window: s at the end of the record averaged for the final upper-box mass.
        fines_cut: sieve size (m) below which fines are scalped into the next class up, keeping
            mass (:func:`torchdem.mixture.scalp_mixture`); None models the full distribution.
        rolling_stiffness: rolling stiffness model of :func:`torchdem.system.build_system`
            (``"tangential"`` or ``"ai2011"``).
        front_back_material: Material of the front and back walls (full box or walled slice,
            ``DrawDownGeometry.slice_walls``); None: ``geometry_material``. Its contact
            parameters use the letter ``w`` (``mu_s_pw``, ``e_sw``, ...); a coefficient not
            given is that of the geometry pair (``mu_s_pg`` ...).
        reorder_every: neighbour rebuilds between spatial reorders of the bodies
            (:mod:`torchdem.reorder`); 0 never reorders.
        fill_packing: how the rained fill keeps particles apart: ``"bounding"`` (each particle's
            bounding sphere) or ``"lobes"`` (its own spheres, so a flat clump takes the room of
            its lobes; needed where flat sinter would overflow the fill column).
        retry_time_steps: factors (each in (0, 1), decreasing) of the time step at which a
            campaign run that blew up is run again, alone, in turn
            (:func:`bo.campaign.dem.evaluate_batch`); () fails it at once. How a failed run is
            recovered, not what a run gives: left out of the repr, so checkpoint names and store
            hashes do not see it.
    """

    fill_time: float = 0.8
    discharge_time: float = 3.5
    max_discharge_time: float | None = None
    loadcell_rate: float = 50.0
    time_step_fraction: float = 0.15
    discharge_time_step_fraction: float | None = None
    shear_modulus: float | None = None
    geometry_material: Material = Material("geometry", 2e11, 0.3, 7800.0)
    rolling_damping: float = 0.3
    dtype: str = "float64"
    compile: bool = False
    guards: GuardSettings = GuardSettings(check_every=500)
    metres_per_pixel: float = 0.001
    rsd_component: str = "sinter"
    photo_shadow_depth: float | None = None
    loose_fraction: float = 0.3
    fines_cut: float | None = None
    skin_fraction: float = 0.2
    flow_window: tuple[float, float] = (0.5, 2.0)
    final_window: float = 0.5
    rolling_stiffness: str = "tangential"
    front_back_material: Material | None = None
    reorder_every: int = 0
    fill_packing: str = "bounding"
    retry_time_steps: tuple[float, ...] = field(default=(), repr=False)

    def validate(self, source: str = "sim") -> "RunSettings":
        if self.rolling_stiffness not in ("tangential", "ai2011"):
            raise out_of_range("rolling_stiffness", self.rolling_stiffness, "'tangential' or 'ai2011'", source)
        if self.front_back_material is not None and self.front_back_material.name == self.geometry_material.name:
            raise out_of_range("front_back_material.name", self.front_back_material.name,
                               f"a name other than the geometry material's {self.geometry_material.name!r}", source)
        for name in ("fill_time", "discharge_time", "loadcell_rate", "metres_per_pixel"):
            if not getattr(self, name) > 0:
                raise out_of_range(name, getattr(self, name), "> 0", source)
        lo, hi = self.flow_window
        if not 0 <= lo < hi:
            raise out_of_range("flow_window", self.flow_window, "(start, end) with 0 <= start < end, s", source)
        if not self.final_window > 0:
            raise out_of_range("final_window", self.final_window, "> 0 s", source)
        if self.discharge_time < hi + self.final_window:
            raise out_of_range("discharge_time", self.discharge_time,
                               f">= {hi + self.final_window:g} s (the mass-flow fit window ends {hi:g} s after the gate "
                               f"opens and the final mass is the mean of the last {self.final_window:g} s)", source)
        if self.max_discharge_time is not None and not self.max_discharge_time >= self.discharge_time:
            raise out_of_range("max_discharge_time", self.max_discharge_time,
                               f"null or >= discharge_time ({self.discharge_time:g} s)", source)
        if self.fill_packing not in ("bounding", "lobes"):
            raise out_of_range("fill_packing", self.fill_packing, "'bounding' or 'lobes'", source)
        if self.dtype not in ("float32", "float64"):
            raise out_of_range("dtype", self.dtype, "'float32' or 'float64'", source)
        if self.fines_cut is not None and not self.fines_cut > 0:
            raise out_of_range("fines_cut", self.fines_cut, "> 0 m or null", source)
        if not 0 < self.skin_fraction <= 2:
            raise out_of_range("skin_fraction", self.skin_fraction, "(0, 2] of the largest sphere radius", source)
        if isinstance(self.reorder_every, bool) or not isinstance(self.reorder_every, int) or self.reorder_every < 0:
            raise out_of_range("reorder_every", self.reorder_every, "an int >= 0 (neighbour rebuilds between spatial "
                               "reorders; 0: never)", source)
        if not 0 < self.loose_fraction < 0.6:
            raise out_of_range("loose_fraction", self.loose_fraction, "(0, 0.6)", source)
        if not 0 < self.time_step_fraction <= 1:
            raise out_of_range("time_step_fraction", self.time_step_fraction, "(0, 1] of the Rayleigh time step", source)
        if self.discharge_time_step_fraction is not None and not 0 < self.discharge_time_step_fraction <= 1:
            raise out_of_range("discharge_time_step_fraction", self.discharge_time_step_fraction,
                               "(0, 1] of the Rayleigh time step, or null (time_step_fraction throughout)", source)
        retry = self.retry_time_steps
        if not isinstance(retry, tuple) or any(isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f < 1
                                               for f in retry) or any(b >= a for a, b in zip(retry, retry[1:])):
            raise out_of_range("retry_time_steps", retry, "a decreasing list of factors in (0, 1) of the time step "
                               "(e.g. [0.8, 0.6]), or [] for no retry", source)
        if self.shear_modulus is not None and not self.shear_modulus > 0:
            raise out_of_range("shear_modulus", self.shear_modulus, "> 0 Pa or null", source)
        if self.rsd_component not in ("sinter", "pellet"):
            raise out_of_range("rsd_component", self.rsd_component, "'sinter' or 'pellet'", source)
        if self.photo_shadow_depth is not None and not self.photo_shadow_depth > 0:
            raise out_of_range("photo_shadow_depth", self.photo_shadow_depth,
                               "> 0 m behind the front layer, or null (no shadows)", source)
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
        conservation: per member (upper, lower, in flight, lost, total) masses at the end, kg,
            and the largest body speed when the gate opened (how settled the fill was), m/s.
        errors: per member, KPI name -> message for KPIs that could not be measured.
        build_time_s: wall time of placing the particles (part of ``wall_time_s``).
        spheres: spheres per member (padded to the largest member), dt: time step, s (of the fill;
            ``discharge_dt`` from the gate's opening on).
        failed: member -> cause, for members the blow-up guard isolated
            (``guards.on_blowup = "isolate"``); their KPIs are not measured.
        photo_scenes: per member {"upper" | "lower": {"centres" ``[N, 3]`` m, "radii" ``[N]`` m,
            "labels" ``[N]``, "view": the :class:`torchdem.render.View`, "crop": the
            :class:`kpi.io.CropBox` the KPI was measured in}}: the spheres each photo shows (float32
            centres and radii), so it can be drawn and measured again (``render_front``).
        kpis_at_discharge_time: with ``max_discharge_time`` and ``run_members(...,
            kpis_at_discharge_time=True)``: the KPIs each member would have had had the run
            stopped at ``discharge_time`` (same trajectory); else empty.
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
    build_time_s: float = 0.0
    spheres: int = 0
    dt: float = 0.0
    discharge_dt: float = 0.0
    failed: dict[int, str] = field(default_factory=dict)
    kpis_at_discharge_time: list[dict] = field(default_factory=list)
    photo_scenes: list[dict] = field(default_factory=list)

    def kpi_table(self, name: str) -> np.ndarray:
        """``[members]`` values of one KPI (NaN where it could not be measured)."""
        return np.array([k.get(name, np.nan) for k in self.kpis], dtype=float)


class DrawDownTest:
    """A draw down test of a mixture in a geometry with given contact parameters."""

    def __init__(self, mixture: Mixture, geometry: DrawDownGeometry,
                 contact: Mapping[str, object] | Sequence[Mapping[str, object]] = PAPER_REFERENCE,
                 settings: RunSettings = RunSettings(), mixtures: Sequence[Mixture] | None = None):
        """``mixtures`` (optional): one mixture per parameter set, with the materials of ``mixture``
        (same names, in order) but any fractions, layering, mass, densities and shapes, so several
        test conditions or material variants run as one ensemble."""
        self.mixture = scalp_mixture(mixture.validate(), settings.fines_cut, "sim.fines_cut").validate()
        self.geometry = geometry.validate()
        self.parameter_sets = [dict(contact)] if isinstance(contact, Mapping) else [dict(c) for c in contact]
        if not self.parameter_sets:
            raise ConfigError("contact: no parameter set given")
        self.settings = settings.validate()
        self.member_mixtures = None
        if mixtures is not None:
            names = [m.name for m in self.mixture.materials]
            if len(mixtures) != len(self.parameter_sets):
                raise ConfigError(f"DrawDownTest: {len(mixtures)} mixtures for {len(self.parameter_sets)} parameter sets")
            self.member_mixtures = []
            for k, mx in enumerate(mixtures):
                if [m.name for m in mx.materials] != names:
                    raise ConfigError(f"DrawDownTest: mixtures[{k}] has materials {[m.name for m in mx.materials]}; "
                                      f"expected {names} (those of the main mixture, in order)")
                self.member_mixtures.append(scalp_mixture(mx.validate(f"mixtures[{k}]"), settings.fines_cut,
                                                          "sim.fines_cut").validate())
        # contact parameters are checked now, not after minutes of filling
        self._interaction_table(range(len(self.parameter_sets)))
        self._fill_friction(range(len(self.parameter_sets)))

    # -- building ------------------------------------------------------------------------
    def _interaction_table(self, parameter_index: Sequence[int], dtype=torch.float64, device="cpu"):
        """The ``[B, M, M]`` interaction table of members using the given parameter sets."""
        s, mix = self.settings, self.mixture
        names = [m.name for m in mix.materials]
        per_member = [self.parameter_sets[i] for i in parameter_index]
        keys = sorted(set().union(*per_member) - {FILL_FRICTION_PARAMETER})  # the fill's share: _fill_friction
        stacked = {}
        for k in keys:
            if any(k not in p for p in per_member):
                raise ConfigError(f"contact: parameter {k!r} is missing from some parameter sets")
            stacked[k] = [float(p[k]) for p in per_member]
        # eta_r: the EPSD viscous rolling damping ratio of every pair, per member (default: the settings')
        rolling_damping = s.rolling_damping
        if ROLLING_DAMPING_PARAMETER in stacked:
            rolling_damping = stacked.pop(ROLLING_DAMPING_PARAMETER)
            bad = [v for v in rolling_damping if not (math.isfinite(v) and v >= 0)]
            if bad:
                raise out_of_range(ROLLING_DAMPING_PARAMETER, bad[0], ">= 0 (viscous rolling damping ratio)", "contact")
        fb = s.front_back_material
        own = {}
        if fb is not None:  # front/back wall pairs: letter w, defaulting to the geometry pair's value
            own = {k: v for k, v in stacked.items() if k.endswith("w")}
            stacked = {k: v for k, v in stacked.items() if k not in own}

        def abbreviations(wall: str) -> dict[str, str]:
            return ({**{"p": "pellet", "s": "sinter"}, "g": wall} if set(names) <= {"pellet", "sinter"}
                    else _letters(names, wall))

        pairs = interaction_pairs(stacked, names, s.geometry_material.name, abbreviations=abbreviations(
            s.geometry_material.name), rolling_damping=rolling_damping)
        if self.geometry.mirror:  # the symmetry plane: frictionless and elastic for every material
            pairs.update({(m, MIRROR_MATERIAL): {"mu_s": 0.0, "mu_r": 0.0, "restitution": 1.0, "rolling_damping": 0.0}
                          for m in names})
        if fb is not None:
            walled = {**stacked, **{k[:-1] + "g": v for k, v in own.items()}}
            pairs.update({k: v for k, v in interaction_pairs(walled, names, fb.name, abbreviations=abbreviations(
                fb.name), rolling_damping=rolling_damping, source="contact (front/back walls)").items()
                if fb.name in k})
        density = None
        if self.member_mixtures is not None:
            density = {m.name: [self.member_mixtures[i].materials[k].density for i in parameter_index]
                       for k, m in enumerate(mix.materials)}
        return interaction_table(self._materials(), pairs, batch=len(per_member), dtype=dtype, device=device,
                                 density=density, source="contact")

    def _fill_friction(self, parameter_index: Sequence[int]) -> list[float]:
        """Per member, the share of its friction coefficients the fill settles with
        (:data:`FILL_FRICTION_PARAMETER`, 1 when not given)."""
        out = []
        for i in parameter_index:
            v = float(self.parameter_sets[i].get(FILL_FRICTION_PARAMETER, 1.0))
            if not (math.isfinite(v) and 0.0 <= v <= 1.0):
                raise out_of_range(FILL_FRICTION_PARAMETER, v, "[0, 1] (share of the friction coefficients the fill "
                                   "settles with)", "contact")
            out.append(v)
        return out

    def _materials(self) -> list[Material]:
        G = self.settings.shear_modulus
        mats = [Material(m.name, G if G is not None else m.shear_modulus, m.poisson_ratio, m.density)
                for m in self.mixture.materials]
        fb = self.settings.front_back_material
        g = self.settings.geometry_material
        mirror = [Material(MIRROR_MATERIAL, g.shear_modulus, g.poisson_ratio, g.density)] if self.geometry.mirror else []
        return mats + [g] + ([fb] if fb is not None else []) + mirror

    def mixture_of(self, parameter_index: int) -> Mixture:
        """The mixture members of parameter set ``parameter_index`` fill (see ``mixtures``)."""
        return self.mixture if self.member_mixtures is None else self.member_mixtures[parameter_index]

    def build(self, seeds: Sequence[int], parameter_index: Sequence[int], device="cpu"):
        """System and state for members with the given seeds and parameter-set indices."""
        s, g = self.settings, self.geometry
        dtype = getattr(torch, s.dtype)
        fills = []
        # a walled or mirrored slice fills like a full box of the slice's depth (walls, not periodic images)
        fill_geometry = (dataclasses.replace(g, depth=g.slice_depth, slice_depth=None, slice_walls=False, mirror=False)
                         if g.is_slice and g.has_front_back_walls else g)
        mixes = [self.mixture_of(p) for p in parameter_index]
        for seed, mix_b in zip(seeds, mixes):
            layers = sample_layers(mix_b, g.depth_scale, seed)
            tmpl = [m.template for m in mix_b.materials]
            bound = np.array([tmpl[k].bounding_radius() for k in layers.material]) * layers.diameter
            volume = layers.mass / np.array([mix_b.materials[k].density for k in layers.material])
            lobes = _lobes(tmpl, layers.material, layers.diameter) if s.fill_packing == "lobes" else None
            fill, _ = rain_to_fit(bound, layers.layer, volume, fill_geometry, seed, s.loose_fraction,
                                  max_top=g.upper_bottom_z + 3 * g.upper_height, lobes=lobes)
            fills.append((layers, fill))
        fill_top = max(f[1].top for f in fills)
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
        shapes = sorted({m.shape for mx in mixes for m in mx.materials})
        templates = [next(m.template for mx in mixes for m in mx.materials if m.shape == sh) for sh in shapes]
        template_of_material = np.array([[shapes.index(m.shape) for m in mx.materials] for mx in mixes])  # [B, M]
        template_of_body = np.take_along_axis(template_of_material, material, 1)
        materials = self._materials()
        table = self._interaction_table(parameter_index, dtype, device)
        largest_sphere = np.array([tp.radii.max() for tp in templates])[template_of_body] * scale
        t = lambda a, **kw: torch.as_tensor(a, device=device, **kw)  # noqa: E731
        system, state = build_system(
            t(pos, dtype=dtype), t(material), materials, table,
            templates=templates, template_index=t(template_of_body), scale=t(scale, dtype=dtype),
            orientation=t(quat, dtype=dtype), active=t(active),
            walls=g.walls(s.geometry_material.name, s.fill_time, fill_top,
                          None if s.front_back_material is None else s.front_back_material.name),
            time_step_fraction=s.time_step_fraction, rolling_stiffness=s.rolling_stiffness,
            domain=g.domain(fill_top=fill_top), periodic=g.periodic, source="drawdown",
            skin=s.skin_fraction * float(largest_sphere[active].max()))
        return system, state, [int(f[0].material.shape[0]) for f in fills]

    # -- running -------------------------------------------------------------------------
    def run(self, replicates: int = 1, device="cpu", seeds: Sequence[int] | None = None,
            progress: Callable[[float, float], None] | None = None, vtk: tuple[str | Path, float] | None = None,
            checkpoint: str | Path | None = None, checkpoint_every: float = 0.5) -> DrawDownResult:
        """Run every parameter set ``replicates`` times (different seeds) as one ensemble.

        Args:
            replicates: runs per parameter set; ``seeds`` (default ``0 .. replicates-1``) seed
                the fills; every parameter set uses the same seeds (paired replicates).
            device: torch device of the ensemble.
            progress: called as ``progress(simulated_s, wall_s)`` about every 0.02 s of
                simulated time; the run ends at ``total_time``.
            vtk: ``(directory, interval_s)``: write VTK frames of every member that often.
            checkpoint: a file: the run saves its full state there every ``checkpoint_every``
                simulated seconds and, if the file exists when the run starts (same members),
                resumes from it instead of starting over. The file is removed at the end.
        """
        if replicates < 1:
            raise out_of_range("replicates", replicates, "an integer >= 1", "DrawDownTest.run")
        seeds = list(seeds) if seeds is not None else list(range(replicates))
        if len(seeds) != replicates:
            raise ConfigError(f"DrawDownTest.run: {len(seeds)} seeds for {replicates} replicates")
        members = [(p, r, int(seeds[r])) for p in range(len(self.parameter_sets)) for r in range(replicates)]
        return self.run_members(members, device, progress, vtk, checkpoint, checkpoint_every)

    @property
    def total_time(self) -> float:
        """Simulated time of a run, s (fill plus discharge; with ``max_discharge_time``, the
        longest a run may take)."""
        s = self.settings
        return s.fill_time + (s.discharge_time if s.max_discharge_time is None else s.max_discharge_time)

    def run_members(self, members: Sequence[tuple[int, int, int]], device="cpu",
                    progress: Callable[[float, float], None] | None = None,
                    vtk: tuple[str | Path, float] | None = None, checkpoint: str | Path | None = None,
                    checkpoint_every: float = 0.5, threads: Callable[[], int] | None = None,
                    kpis_at_discharge_time: bool = False) -> DrawDownResult:
        """Run arbitrary members ``(parameter-set index, replicate index, seed)`` as one ensemble
        (what a calibration batch needs: each candidate with its own seeds); see :meth:`run`.
        ``threads``: asked at the start and at every load-cell sample how many torch threads the
        run may use now (a campaign worker takes the cores its idle neighbours left,
        :class:`bo.campaign.cores.CoreShare`); the results do not depend on it, and the thread
        count the caller had is restored at the end. ``kpis_at_discharge_time``: with
        ``max_discharge_time``, measure the KPIs at ``discharge_time`` too, before the run goes on
        (:attr:`DrawDownResult.kpis_at_discharge_time`; not when resumed from a checkpoint past it)."""
        threads_before = torch.get_num_threads()
        try:
            if threads is not None:
                _use_threads(threads())
            return self._run_members(members, device, progress, vtk, checkpoint, checkpoint_every, threads,
                                     kpis_at_discharge_time)
        finally:
            _use_threads(threads_before)

    def _run_members(self, members, device, progress, vtk, checkpoint, checkpoint_every, threads,
                     kpis_at_discharge_time=False) -> DrawDownResult:
        members = [(int(p), int(r), int(seed)) for p, r, seed in members]
        if not members:
            raise ConfigError("DrawDownTest.run_members: no members given")
        for p, _, _ in members:
            if not 0 <= p < len(self.parameter_sets):
                raise out_of_range("parameter-set index", p, f"0 .. {len(self.parameter_sets) - 1}",
                                   "DrawDownTest.run_members")
        s = self.settings
        started = time.perf_counter()
        system, state, counts = self.build([m[2] for m in members], [m[0] for m in members], device)
        build_s = time.perf_counter() - started
        full_tables = None  # the model's frictions, when the fill settles with a share of them
        share = self._fill_friction([m[0] for m in members])
        if any(f != 1.0 for f in share):
            full_tables = system.tables
            f = torch.tensor(share, dtype=full_tables.mu_s.dtype, device=full_tables.mu_s.device)[:, None, None]
            system = dataclasses.replace(system, tables=dataclasses.replace(
                full_tables, mu_s=full_tables.mu_s * f, mu_r=full_tables.mu_r * f))

        def with_full_friction(simulation: Simulation) -> None:
            """The gate opens: the model's own frictions from here on (lists and forces again)."""
            if full_tables is not None and simulation.system.tables is not full_tables:
                simulation.system = dataclasses.replace(simulation.system, tables=full_tables)
                simulation.state = evaluate_forces(simulation.system, simulation.state, simulation.time,
                                                   simulation.kernels)
        dt_fill = system.dt
        dt_discharge = (dt_fill if s.discharge_time_step_fraction is None
                        else dt_fill * s.discharge_time_step_fraction / s.time_step_fraction)
        every_fill = max(1, int(round(1.0 / (s.loadcell_rate * dt_fill))))
        every = max(1, int(round(1.0 / (s.loadcell_rate * dt_discharge))))  # load-cell samples from the gate on
        t_open, t_end = s.fill_time, s.fill_time + s.discharge_time
        k_open = int(math.ceil(round(t_open / dt_fill, 6)))  # the step run_until(t_open) stops at
        times: list[float] = []
        masses: list[np.ndarray] = []
        pellet_masses: list[np.ndarray] = []  # the pellets' share of ``masses``
        ckpt = Path(checkpoint) if checkpoint is not None else None
        gate_speed = [math.nan] * len(members)
        fill_density = [math.nan] * len(members)
        fill_layering = np.full((len(members), len(FILL_LAYERING_KPIS)), np.nan)
        wall_before = 0.0
        sim = None
        if ckpt is not None and ckpt.exists():
            saved = torch.load(ckpt, weights_only=True, map_location="cpu")  # the state: Simulation.load
            if [tuple(m) for m in saved["members"]] != members:
                raise ConfigError(f"{ckpt}: checkpoint belongs to members {saved['members']}, not {members}; "
                                  "remove it or use another checkpoint path")
            sim = Simulation.load(ckpt, system, s.guards, s.compile, reorder_every=s.reorder_every)
            times = [float(t) for t in saved["times"]]
            masses = [m.numpy() for m in saved["masses"]]
            pellet_masses = ([m.numpy() for m in saved["pellet_masses"]] if "pellet_masses" in saved
                             else [np.full_like(m, np.nan) for m in masses])  # a checkpoint from before it
            wall_before = float(saved["wall_s"])
            gate_speed[:] = saved["gate_speed"].tolist()
            fill_density[:] = saved.get("fill_density", torch.full((len(members),), math.nan)).tolist()
            if "fill_layering" in saved:
                fill_layering[:] = saved["fill_layering"].numpy()
        else:
            sim = Simulation(system, state, s.guards, compile=s.compile, reorder_every=s.reorder_every)
        ckpt_steps = max(every, int(round(checkpoint_every / dt_fill)))
        writer = None
        if vtk is not None:
            directory, interval_s = vtk
            if not interval_s > 0:
                raise out_of_range("vtk interval", interval_s, "> 0 s", "DrawDownTest.run")
            writer = VTKWriter(directory, max(1, int(round(interval_s / dt_fill))))

        def with_discharge_step(simulation: Simulation) -> None:
            """From the gate's opening on: the discharge's time step (and VTK frames as often in time)."""
            if simulation.system.dt != dt_discharge:  # not switched yet (a resumed run may be)
                simulation.system = simulation.system.with_time_step(dt_discharge, k_open)
                if writer is not None:
                    writer.interval = max(1, int(round(vtk[1] / dt_discharge)))

        if sim.state.step > k_open:  # resumed from a checkpoint saved in the discharge
            with_discharge_step(sim)

        def save_checkpoint(simulation: Simulation) -> None:
            tmp = ckpt.with_suffix(ckpt.suffix + ".tmp")
            torch.save({"state": to_dict(simulation.state), "failed": simulation.failed,
                        "skin": simulation.system.skin, "members": members,
                        "times": torch.tensor(times, dtype=torch.float64),
                        "masses": [torch.as_tensor(m) for m in masses],
                        "pellet_masses": [torch.as_tensor(m) for m in pellet_masses],
                        "gate_speed": torch.tensor(gate_speed, dtype=torch.float64),
                        "fill_density": torch.tensor(fill_density, dtype=torch.float64),
                        "fill_layering": torch.as_tensor(fill_layering),
                        "wall_s": wall_before + time.perf_counter() - started}, tmp)
            os.replace(tmp, ckpt)

        is_pellet = _labelled(self.mixture, sim.system.body_material, "pellet")  # the load cell's second trace

        def on_step(simulation: Simulation) -> None:
            k = simulation.state.step
            if writer is not None:
                writer(simulation)
            if k == k_open:  # how settled the fill is when the gate opens
                b = simulation.state.bodies
                gate_speed[:] = (b.velocity.norm(dim=-1) * b.active).amax(-1).cpu().tolist()
                fill_density[:] = self._fill_bulk_density(simulation).tolist()
                fill_layering[:] = self._fill_layering(simulation)
            if k >= k_open and (k - k_open) % every == 0:  # 50 Hz from the gate opening on
                times.append(simulation.time - t_open)
                total, pellets = self._upper_mass(simulation, is_pellet).cpu().numpy()
                masses.append(total)
                pellet_masses.append(pellets)
            tick = (k - k_open) % every == 0 if k >= k_open else k % every_fill == 0
            if tick and progress is not None:
                progress(simulation.time, wall_before + time.perf_counter() - started)
            if tick and threads is not None:
                _use_threads(threads())
            if ckpt is not None and k % ckpt_steps == 0:
                save_checkpoint(simulation)

        if sim.time < t_open - 0.5 * system.dt:
            sim.run_until(t_open, callback=on_step, callback_every=1)
        with_full_friction(sim)
        with_discharge_step(sim)
        before = sim.time
        sim.run_until(t_end, callback=on_step, callback_every=1)
        early = []
        if kpis_at_discharge_time and s.max_discharge_time is not None and before < t_end - 0.5 * dt_discharge:
            early = self._measure(sim, members, counts, np.array(times), np.stack(masses, 1), 0.0,
                                  np.stack(pellet_masses, 1)).kpis
        if s.max_discharge_time is not None:  # on until every member's discharge has ended
            tolerance = 0.5 * DISCHARGE_END_TOLERANCE * _fill_masses(system, sim.state, counts).cpu().numpy()
            tail = max(2, int(round(s.final_window * s.loadcell_rate)) + 1)
            t_last = t_open + s.max_discharge_time
            while sim.time < t_last - 0.5 * dt_discharge and not bool(
                    _discharges_ended(np.stack(masses[-tail:], 1), tail, tolerance, sim.failed).all()):
                sim.run_until(min(sim.time + 5.0 / s.loadcell_rate, t_last), callback=on_step, callback_every=1)
        wall = wall_before + time.perf_counter() - started
        result = self._measure(sim, members, counts, np.array(times), np.stack(masses, 1), wall,
                               np.stack(pellet_masses, 1))
        for kpis in (result.kpis, early):  # the fill as the gate opened, for both measurements
            for k, v, shares in zip(kpis, fill_density, fill_layering):
                k["fill_bulk_density_kg_m3"] = v
                k.update(zip(FILL_LAYERING_KPIS, map(float, shares)))
        for c, v in zip(result.conservation, gate_speed):
            c["max_speed_at_gate_open_m_s"] = v
        result = dataclasses.replace(result, build_time_s=build_s, spheres=int(system.n_spheres), dt=float(dt_fill),
                                     discharge_dt=float(dt_discharge),
                                     failed=dict(sim.failed), kpis_at_discharge_time=early)
        if ckpt is not None and ckpt.exists():
            ckpt.unlink()
        return result

    def _fill_bulk_density(self, sim: Simulation) -> np.ndarray:
        """``[B]`` bulk density of each member's fill as the gate opens, kg/m^3: its upper-box mass over
        the box's width x the simulated depth x the fill's height, the mean over the box's width (in
        bins about four of the largest spheres wide) of the highest top of a sphere resting on the fill
        above the box's floor, as a ruler held to the front wall would read it. A grain still in the air
        (:func:`_resting`; bouncing pellets on top of the reverse layering) is not the fill's top."""
        g, system, b = self.geometry, sim.system, sim.state.bodies
        xs = sphere_positions(system, b).reshape(system.batch, system.n_spheres, 3)
        active = torch.gather(b.active, 1, system.sphere_body)
        top = xs[..., 2] + system.sphere_radius
        inside = active & g.in_upper_box(xs[..., 0], xs[..., 2])
        rests = _resting(xs, system.sphere_radius, system.sphere_body_flat, inside, g.upper_bottom_z)
        x, n_bins = _fill_columns(g, system, xs[..., 0])
        height = torch.full((system.batch, n_bins), g.upper_bottom_z, dtype=top.dtype, device=top.device)
        height = height.scatter_reduce(1, x, torch.where(rests, top, torch.full_like(top, g.upper_bottom_z)), "amax")
        fill_height = (height.mean(-1) - g.upper_bottom_z).cpu().numpy()
        mass = self._upper_mass(sim).cpu().numpy()
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(fill_height > 0, mass / (g.upper_width * g.simulated_depth * fill_height), np.nan)

    def _fill_layering(self, sim: Simulation) -> np.ndarray:
        """``[B, 4]`` the pellets' share of each quarter of each member's upper-box mass, from the floor
        up (:data:`FILL_LAYERING_KPIS`), by body centres in columns as wide as in :meth:`_fill_bulk_density`."""
        g, system, b = self.geometry, sim.system, sim.state.bodies
        x, z = b.position[..., 0], b.position[..., 2]
        inside = (self.geometry.in_upper_box(x, z) & b.active).cpu().numpy()
        is_pellet = _labelled(self.mixture, system.body_material, "pellet").cpu().numpy()
        column, n_bins = _fill_columns(g, system, x)
        column = column.cpu().numpy()
        z, mass = z.cpu().numpy(), system.mass.cpu().numpy()
        out = np.full((system.batch, len(FILL_LAYERING_KPIS)), np.nan)
        for m in range(system.batch):
            quarter = np.zeros(inside.shape[1], dtype=int)
            for c in range(n_bins):
                i = np.flatnonzero(inside[m] & (column[m] == c))
                i = i[np.argsort(z[m, i], kind="stable")]
                w = mass[m, i]
                if w.size:  # the mass share below each body's centre: its quarter of the column
                    q = (np.cumsum(w) - 0.5 * w) / w.sum()
                    quarter[i] = np.minimum((q * len(FILL_LAYERING_KPIS)).astype(int), len(FILL_LAYERING_KPIS) - 1)
            w = np.where(inside[m], mass[m], 0.0)
            total = np.bincount(quarter, w, len(FILL_LAYERING_KPIS))
            pel = np.bincount(quarter, w * is_pellet[m], len(FILL_LAYERING_KPIS))
            with np.errstate(invalid="ignore", divide="ignore"):
                out[m] = np.where(total > 0, pel / total, np.nan)
        return out

    def _upper_mass(self, sim: Simulation, is_pellet: torch.Tensor | None = None) -> torch.Tensor:
        """``[B]`` mass in each member's upper box, kg; with ``is_pellet`` (``[B, Nb]`` bool, the pellet
        bodies): ``[2, B]``, that and its pellets' share (the load cell's two traces from one look at the box)."""
        b = sim.state.bodies
        mass = sim.system.mass * (self.geometry.in_upper_box(b.position[..., 0], b.position[..., 2]) & b.active)
        if is_pellet is None:
            return mass.sum(-1)
        return torch.stack([mass.sum(-1), (mass * is_pellet).sum(-1)])

    def _measure(self, sim, members, counts, times, masses, wall, pellet_masses=None) -> DrawDownResult:
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
        kpis, images, errors, conservation, loadcells, scenes = [], [], [], [], [], []
        fill_masses = _fill_masses(system, state, counts)
        for m, (p, r, seed) in enumerate(members):
            fill_mass = float(fill_masses[m])
            k: dict[str, float] = {"fill_mass_kg": fill_mass, "fill_mass_full_kg": fill_mass * scale}
            err: dict[str, str] = {}
            if m in sim.failed:  # isolated by the blow-up guard: nothing to measure
                kpis.append(k)
                errors.append({"blowup": sim.failed[m]})
                images.append({})
                scenes.append({})
                loadcells.append((times, masses[m]))
                conservation.append({"fill_kg": fill_mass, "lost_bodies": int(state.lost[m])})
                continue
            signal = LoadCellSignal(times, masses[m], source=f"member {m} load cell")
            discharge = DischargeConfig(fit_window_s=tuple(s.flow_window), final_window_s=s.final_window,
                                        end_tolerance_kg=DISCHARGE_END_TOLERANCE * fill_mass)
            try:
                ended = measure_discharge(signal, fill_mass, discharge)
                rate = ended.mass_flow_rate_kg_s
                k["discharge_ended"] = 1.0
                k["discharge_duration_s"] = ended.discharge_duration_s
            except KPIInputError as exc:
                k["discharge_ended"] = 0.0
                # Still trickling at the end of the run (or worse): the lower-box mass below is
                # then a lower bound, noted here; the flow rate needs only its fit window.
                err["discharge_end"] = str(exc)
                try:
                    rate = fit_mass_flow_rate(signal, discharge)[0]
                except KPIInputError as exc2:
                    rate = None
                    err["mass_flow_rate_kg_s"] = str(exc2)
            if rate is not None:
                k["mass_flow_rate_kg_s"] = rate
                k["mass_flow_rate_full_kg_s"] = rate * scale
                if pellet_masses is not None:
                    k.update(flow_breakdown(times, masses[m], pellet_masses[m], discharge, scale,
                                            f"member {m} load cell"))
            k["mass_lower_box_kg"] = fill_mass - float(masses[m][-1])
            k["mass_lower_box_full_kg"] = k["mass_lower_box_kg"] * scale
            jammed = k["mass_lower_box_kg"] < JAM_FRACTION * fill_mass
            k["discharge_jammed"] = float(jammed)
            at_rest = b.velocity[m].norm(dim=-1) < AT_REST_SPEED_M_S  # the photo after the discharge
            # the bodies at rest, taken from the state once for both photos and kept with them
            centres, radii, sphere_labels = member_spheres(system, state, m, labels, shown=at_rest)
            upper_img, lower_img = (render_front(centres, radii, sphere_labels, view, walls=system.walls,
                                                 time=system.time_of(state.step), shadow_depth=s.photo_shadow_depth)
                                    for view in (upper_view, lower_view))
            kept = {"centres": centres.astype(np.float32), "radii": radii.astype(np.float32),
                    "labels": sphere_labels.astype(np.int8)}
            scene = {"upper": {**kept, "view": upper_view, "crop": up_crop},
                     "lower": {**kept, "view": lower_view, "crop": low_crop}}
            scenes.append(scene)
            for name, fn, img, crop in (("shear_angle_deg", shear_angle, upper_img, up_crop),
                                        ("angle_of_repose_deg", angle_of_repose, lower_img, low_crop)):
                if jammed and name == "shear_angle_deg":
                    k[name] = 0.0  # the fill's level surface (JAM_FRACTION)
                    continue
                try:
                    k[name] = float(fn(img, crop_box=crop, source=f"member {m} {name}").angle_deg)
                except KPIInputError as exc:
                    if jammed:  # no heap in the lower box: its floor is level
                        k[name] = 0.0
                    else:
                        err[name] = str(exc)
            try:
                seg = measure_segregation(lower_img, crop_box=low_crop, source=f"member {m} lower box")
                comp = s.rsd_component
                k["segregation_rsd_vertical"] = float(getattr(seg.vertical, f"{comp}_rsd"))
                k["segregation_rsd_horizontal"] = float(getattr(seg.horizontal, f"{comp}_rsd"))
            except KPIInputError as exc:
                err["segregation"] = str(exc)
            xs = sphere_positions(system, state.bodies).reshape(system.batch, system.n_spheres, 3)[m]
            # heap = bodies at rest in the lower box, below the upper box's bottom plates (not
            # the falling stream, not grains jammed in the slot)
            body = system.sphere_body[m]
            top = xs[:, 2] + system.sphere_radius[m]
            sel = in_lower[m][body] & at_rest[body] & (top < g.upper_bottom_z)
            k["max_heap_height_m"] = float(top[sel].max()) if bool(sel.any()) else 0.0
            kpis.append(k)
            errors.append(err)
            images.append({"upper": upper_img, "lower": lower_img})
            loadcells.append((times, masses[m]))
            conservation.append({"upper_kg": float(upper[m]), "lower_kg": float(lower[m]),
                                 "in_flight_kg": float(total[m] - upper[m] - lower[m]),
                                 "lost_bodies": int(state.lost[m]), "total_kg": float(total[m]),
                                 "fill_kg": fill_mass})
        return DrawDownResult(kpis, loadcells, images, members, wall, state.step, counts, conservation, errors,
                              photo_scenes=scenes)


def flow_breakdown(times: np.ndarray, mass: np.ndarray, pellet_mass: np.ndarray, discharge: DischargeConfig,
                   scale: float = 1.0, source: str = "load cell") -> dict[str, float]:
    """The model's breakdown of a run's flow (:data:`FLOW_BREAKDOWN_KPIS`), kg/s of the whole box.

    Args:
        times: ``[T]`` s since the gate opened. mass: ``[T]`` upper-box mass, kg. pellet_mass: ``[T]``
            its pellets' share, kg (NaN where it was not recorded: a run resumed from a checkpoint
            written before it was; then nothing is returned). discharge: the fit window and filter of
            ``mass_flow_rate_full_kg_s``. scale: simulated domain to whole box.

    A half window with fewer than 3 load-cell samples (a short window of a coarse record) is left out,
    as the whole window's rate would be.
    """
    if not np.isfinite(pellet_mass).all():
        return {}
    lo, hi = discharge.fit_window_s
    mid = 0.5 * (lo + hi)

    def rate(m: np.ndarray, window: tuple[float, float]) -> float:
        fit = dataclasses.replace(discharge, fit_window_s=window)
        try:
            return fit_mass_flow_rate(LoadCellSignal(times, m, source=source), fit)[0] * scale
        except KPIInputError:  # a short window of a coarse record: fewer than 3 samples in a half
            return math.nan

    out = {"mass_flow_rate_pellet_full_kg_s": rate(pellet_mass, (lo, hi)),
           "mass_flow_rate_sinter_full_kg_s": rate(mass - pellet_mass, (lo, hi)),
           "mass_flow_rate_early_full_kg_s": rate(mass, (lo, mid)),
           "mass_flow_rate_late_full_kg_s": rate(mass, (mid, hi))}
    return {k: v for k, v in out.items() if math.isfinite(v)}


def _fill_columns(geometry: DrawDownGeometry, system, x: torch.Tensor) -> tuple[torch.Tensor, int]:
    """The column across the upper box's width (int64, like ``x``) of each x, m, and the number of columns:
    about four of the largest spheres wide, at least 4 (the fill's ruler and its layering)."""
    n = max(4, int(geometry.upper_width / (8.0 * float(system.sphere_radius.max()))))
    return ((x + geometry.upper_width / 2) / geometry.upper_width * n).floor().clamp(0, n - 1).long(), n


def _resting(xs: torch.Tensor, radius: torch.Tensor, body: torch.Tensor, inside: torch.Tensor,
             floor_z: float) -> torch.Tensor:
    """``[B, Ns]`` bool: the spheres of ``inside`` that rest on something, touching a sphere of another body
    or the floor within :data:`RESTING_GAP` of the radii's sum; the others are grains in the air.

    xs ``[B, Ns, 3]`` sphere positions, radius ``[B, Ns]``, body ``[B * Ns]`` flat body index of each
    sphere, inside ``[B, Ns]`` bool. The touching pairs come from the engine's cell search
    (:func:`torchdem.neighbors.find_pairs`), with a skin as wide as the gap."""
    n_per_member = inside.shape[1]
    pos, r, live = xs.reshape(-1, 3), radius.reshape(-1), inside.reshape(-1)
    rests = live & (pos[:, 2] - r <= floor_z + RESTING_GAP * r)
    if bool(live.any()):
        r_max = float(r[live].max())
        skin = 2.0 * RESTING_GAP * r_max
        cell = 2.0 * r_max + skin
        grid = cell_grid((pos[live].amin(0) - cell).tolist(), (pos[live].amax(0) + cell).tolist(), cell,
                         dtype=pos.dtype, device=pos.device)
        i, j = find_pairs(pos, r, body, live, n_per_member, grid, skin)
        touch = (pos[i] - pos[j]).norm(dim=-1) <= (r[i] + r[j]) * (1.0 + RESTING_GAP)
        rests[i[touch]] = True
        rests[j[touch]] = True
    return rests.reshape(inside.shape)


def _labelled(mixture: Mixture, body_material: torch.Tensor, label: str) -> torch.Tensor:
    """``[B, Nb]`` bool: the bodies of the mixture's materials labelled ``label`` (the walls' materials,
    numbered after the mixture's, are not)."""
    of_label = torch.zeros(int(body_material.max()) + 1, dtype=torch.bool, device=body_material.device)
    of_label[[k for k, m in enumerate(mixture.materials) if m.label == label]] = True
    return of_label[body_material]


def _fill_masses(system, state, counts) -> torch.Tensor:
    """``[B]`` mass filled into each member's upper box, kg (its bodies as built, lost or not)."""
    built = state.body_id < torch.as_tensor(counts, device=state.body_id.device)[:, None]
    return (system.mass * built).sum(-1)


def _discharges_ended(masses: np.ndarray, tail: int, tolerance: np.ndarray, failed: Mapping[int, str]) -> np.ndarray:
    """``[B]`` bool: each member's discharge has ended: its last ``tail`` load-cell samples
    (``masses`` ``[B, T]``, kg) lie within ``tolerance`` ``[B]`` kg of one another. A member
    the blow-up guard isolated has ended (nothing of it is measured)."""
    if masses.shape[1] < tail:
        return np.zeros(masses.shape[0], dtype=bool)
    last = masses[:, -tail:]
    ended = last.max(1) - last.min(1) <= tolerance
    ended[list(failed)] = True
    return ended


def _use_threads(n: int) -> None:
    """Let torch (and the C++ kernels, which share its thread pool) use ``n`` threads from now on."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise out_of_range("threads", n, "an int >= 1", "DrawDownTest.run_members(threads=...)")
    if n != torch.get_num_threads():
        torch.set_num_threads(n)


def _lobes(templates: Sequence[ClumpTemplate], material: np.ndarray, diameter: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """Each particle's spheres as the DEM builds them (principal frame, about the centre of mass,
    scaled by the sieve size): offsets ``[N, K, 3]`` and radii ``[N, K]``, padded by repeating
    a particle's first sphere (:func:`torchdem.fill.rain_positions` ``lobes``)."""
    principal = [principal_template(t).template for t in templates]
    K = max(p.n_spheres for p in principal)
    off = np.zeros((len(principal), K, 3))
    rad = np.zeros((len(principal), K))
    for k, p in enumerate(principal):
        pad = np.r_[np.arange(p.n_spheres), np.zeros(K - p.n_spheres, dtype=int)]
        off[k], rad[k] = p.offsets[pad], p.radii[pad]
    return off[material] * diameter[:, None, None], rad[material] * diameter[:, None]


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
