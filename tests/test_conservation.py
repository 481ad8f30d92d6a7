"""Conservation laws.

- Frictionless elastic spheres in a closed box (no gravity): kinetic + Hertz elastic energy
  conserved within 0.5% over 10^4 steps.
- A free clump spinning about a non-principal axis: world angular momentum conserved to
  round-off, rotational kinetic energy within 1e-6, and the body-frame angular velocity
  follows Euler's equations (reference: scipy's solve_ivp at 1e-12 tolerance) within 1e-3.
- Two clumps colliding off-centre (no gravity, no walls): total linear momentum and total
  angular momentum about the origin conserved within 1e-9 relative.
"""

import numpy as np
import torch
from scipy.integrate import solve_ivp

from conftest import F64, elastic_spheres_in_a_box, glass, steel
from torchdem.clumps import ClumpTemplate
from torchdem.materials import interaction_table
from torchdem.rigid import quat_rotate_inverse
from torchdem.simulation import GuardSettings, Simulation, elastic_energy, kinetic_energy
from torchdem.system import build_system

SINTER_LIKE = ClumpTemplate(
    "tri3", np.array([[0.0, 0.0, 0.0], [0.007, 0.001, 0.0], [0.002, 0.006, 0.003]]),
    np.array([0.005, 0.004, 0.0035]))


def test_frictionless_elastic_spheres_conserve_energy_over_1e4_steps():
    sim = elastic_spheres_in_a_box()
    e0 = (kinetic_energy(sim.system, sim.state) + elastic_energy(sim.system, sim.state)).item()
    collisions_seen = 0
    for _ in range(20):
        sim.advance(500)
        collisions_seen += int(sim.state.pairs.n > 0)
    e1 = (kinetic_energy(sim.system, sim.state) + elastic_energy(sim.system, sim.state)).item()
    assert sim.state.step == 10_000
    assert collisions_seen > 10
    assert abs(e1 - e0) / e0 < 0.005, (e0, e1)


def _free_clump(omega0, steps, fraction=0.15):
    mats = [glass(), steel()]
    table = interaction_table(mats, {("glass", "glass"): dict(mu_s=0.5, mu_r=0.05, restitution=0.5)})
    system, state = build_system(
        torch.zeros(1, 1, 3, dtype=F64), torch.zeros(1, 1, dtype=torch.long), mats, table,
        templates=[SINTER_LIKE], template_index=torch.zeros(1, 1, dtype=torch.long),
        scale=torch.ones(1, 1, dtype=F64), angular_velocity=torch.tensor([[omega0]], dtype=F64),
        gravity=(0, 0, 0), time_step_fraction=fraction, domain=((-1, -1, -1), (1, 1, 1)))
    return Simulation(system, state, GuardSettings(check_every=10_000))


def test_free_clump_conserves_angular_momentum_and_follows_euler_equations():
    sim = _free_clump([3.0, -2.0, 5.0], 0)
    I = sim.system.inertia[0, 0].numpy()
    L0 = sim.state.bodies.angular_momentum.clone()
    ke0 = kinetic_energy(sim.system, sim.state).item()
    q0 = sim.state.bodies.orientation[0, 0]
    w_body0 = quat_rotate_inverse(q0, torch.tensor([3.0, -2.0, 5.0], dtype=F64)).numpy()
    steps = 4000
    sim.advance(steps)
    t_end = sim.time
    assert torch.allclose(sim.state.bodies.angular_momentum, L0, rtol=1e-12, atol=0)
    assert abs(kinetic_energy(sim.system, sim.state).item() - ke0) / ke0 < 1e-6

    def euler(t, w):
        return [(I[1] - I[2]) * w[1] * w[2] / I[0], (I[2] - I[0]) * w[2] * w[0] / I[1],
                (I[0] - I[1]) * w[0] * w[1] / I[2]]

    ref = solve_ivp(euler, (0, t_end), w_body0, rtol=1e-12, atol=1e-12).y[:, -1]
    q = sim.state.bodies.orientation[0, 0]
    from torchdem.integrate import body_angular_velocity
    w_world = body_angular_velocity(sim.system, sim.state.bodies)[0]
    w_body = quat_rotate_inverse(q, w_world).numpy()
    assert np.linalg.norm(w_body - ref) / np.linalg.norm(ref) < 1e-3, (w_body, ref)
    assert np.linalg.norm(w_body - w_body0) > 0.1  # the body really tumbled


def test_colliding_clumps_conserve_linear_and_angular_momentum():
    mats = [glass(), steel()]
    table = interaction_table(mats, {("glass", "glass"): dict(mu_s=0.4, mu_r=0.1, restitution=0.6,
                                                            rolling_damping=0.3)})
    pos = torch.tensor([[[0.0, 0.0, 0.0], [0.03, 0.004, -0.002]]], dtype=F64)
    vel = torch.tensor([[[0.8, 0.0, 0.1], [-0.8, 0.05, 0.0]]], dtype=F64)
    omega = torch.tensor([[[0.0, 10.0, 0.0], [5.0, 0.0, -3.0]]], dtype=F64)
    system, state = build_system(pos, torch.zeros(1, 2, dtype=torch.long), mats, table,
                                 templates=[SINTER_LIKE], template_index=torch.zeros(1, 2, dtype=torch.long),
                                 scale=torch.ones(1, 2, dtype=F64), velocity=vel, angular_velocity=omega,
                                 gravity=(0, 0, 0), time_step_fraction=0.1, domain=((-1, -1, -1), (1, 1, 1)))
    sim = Simulation(system, state)

    def momenta():
        b = sim.state.bodies
        p = (system.mass[..., None] * b.velocity).sum(1)[0]
        L = (torch.linalg.cross(b.position, system.mass[..., None] * b.velocity, dim=-1)
             + b.angular_momentum).sum(1)[0]
        return p, L

    p0, L0 = momenta()
    touched = 0
    for _ in range(60):
        sim.advance(50)
        touched += int(sim.state.pairs.n > 0 and elastic_energy(system, sim.state).item() > 0)
    p1, L1 = momenta()
    assert touched > 0
    assert torch.allclose(p1, p0, rtol=0, atol=1e-9 * p0.norm().item())
    assert torch.allclose(L1, L0, rtol=0, atol=1e-9 * L0.norm().item())
