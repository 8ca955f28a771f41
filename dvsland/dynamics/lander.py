"""Vertical 1-D lander of paper Eq. 1, batched, float64, thrust held over each control step.

    dz/dt = v,    dv/dt = u/m - g,    dm/dt = -u / (Isp g0)

z is up (z = 0 the surface), v < 0 while descending. Between control steps the thrust u is
held (zero-order hold). :func:`step_exact` advances the state in closed form (rocket
equation), splitting the step at burnout when the tank empties (mass never falls below the
dry mass; after burnout the craft falls freely). :func:`step_euler` takes one explicit Euler
step (the paper's released implementation). :func:`step_substeps` integrates the same
ODE with classic RK4 sub-steps (a reference for the exact step, and a template for laws whose
thrust is not held).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import torch

Tensor = torch.Tensor

#: Integrator names of :class:`LanderDynamics` (``dynamics.integrator``).
INTEGRATORS = ("exact", "euler", "substeps")


@dataclass
class LanderParams:
    """Physical constants of the lander.

    Attributes:
        g_mps2: gravity, m/s^2.
        g0_mps2: standard gravity used with Isp, m/s^2.
        isp_s: specific impulse, s.
        dry_mass_kg: mass below which no thrust is produced, kg.
    """

    g_mps2: float = 1.62
    g0_mps2: float = 9.81
    isp_s: float = 600.0
    dry_mass_kg: float = 1000.0

    def __post_init__(self):
        for name in ("g_mps2", "g0_mps2", "isp_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.dry_mass_kg >= 0:
            raise ValueError(f"dry_mass_kg must be >= 0, got {self.dry_mass_kg}")

    @property
    def exhaust_velocity_mps(self) -> float:
        """Effective exhaust velocity c_e = Isp g0, m/s."""
        return self.isp_s * self.g0_mps2

    @classmethod
    def from_config(cls, dyn) -> "LanderParams":
        """From a :class:`dvsland.config.DynamicsConfig`."""
        return cls(g_mps2=dyn.g_mps2, g0_mps2=dyn.g0_mps2, isp_s=dyn.isp_s, dry_mass_kg=dyn.dry_mass_kg)


def _check(z_m: Tensor, v_mps: Tensor, m_kg: Tensor, thrust_n: Tensor, dt_s: float) -> None:
    if not dt_s > 0:
        raise ValueError(f"dt_s must be > 0, got {dt_s}")
    if not (z_m.shape == v_mps.shape == m_kg.shape == thrust_n.shape):
        raise ValueError(f"z_m, v_mps, m_kg, thrust_n must share one shape (B,), got {tuple(z_m.shape)}, "
                         f"{tuple(v_mps.shape)}, {tuple(m_kg.shape)}, {tuple(thrust_n.shape)}")


def _log1p_neg_integral_over_x(x: Tensor, log1p_neg_x: Tensor) -> Tensor:
    """((1 - x) ln(1 - x) + x) / x for x in [0, 1), given ln(1 - x); the series
    x/2 + x^2/6 + x^3/12 below x = 1e-4 (exact at x = 0, no 0/0)."""
    small = x < 1e-4
    series = x * (0.5 + x * (1.0 / 6.0 + x * (1.0 / 12.0)))
    exact = ((1 - x) * log1p_neg_x + x) / torch.where(small, 1.0, x)
    return torch.where(small, series, exact)


def step_exact(z_m: Tensor, v_mps: Tensor, m_kg: Tensor, thrust_n: Tensor, dt_s: float,
               params: LanderParams) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Advance the lander by ``dt_s`` with constant thrust, exactly (rocket equation).

    With constant thrust u and c_e = Isp g0, m(t) = m0 - u t / c_e and, writing
    x = u t / (c_e m0):  v(t) = v0 - g t - c_e ln(1 - x),
    z(t) = z0 + v0 t - g t^2 / 2 + c_e t ((1 - x) ln(1 - x) + x) / x.
    If the tank empties (m reaches ``params.dry_mass_kg``) during the step, the step is split
    at burnout and the rest is free fall.

    Args:
        z_m, v_mps, m_kg: (B,) float64 state: altitude m, velocity m/s, mass kg.
        thrust_n: (B,) commanded thrust, N, >= 0 (negative values are treated as 0).
        dt_s: step length, s (> 0).
        params: :class:`LanderParams`.

    Returns:
        (z_m, v_mps, m_kg, burn_s): new state (B,) float64 and the time each element actually
        burned during the step (B,) float64, s (< dt_s where the tank ran dry).
    """
    _check(z_m, v_mps, m_kg, thrust_n, dt_s)
    dtype = torch.float64
    z0, v0, m0 = z_m.to(dtype), v_mps.to(dtype), m_kg.to(dtype)
    u = thrust_n.to(dtype).clamp_min(0.0)
    ce, g, dry = params.exhaust_velocity_mps, params.g_mps2, params.dry_mass_kg
    fuel = (m0 - dry).clamp_min(0.0)
    mdot = u * (1.0 / ce)
    # burn time inside this step: dt unless the tank empties first (u = 0 -> dt; no fuel -> 0)
    full = mdot * dt_s <= fuel
    h1 = torch.where(full, dt_s, fuel / torch.where(full, 1.0, mdot))  # no 0/0 in the branch not taken (its gradient)
    x = (mdot * h1 / m0).clamp_max(1.0 - 1e-15)
    log_ratio = torch.log1p(-x)  # ln(m1 / m0)
    v1 = v0 - g * h1 - ce * log_ratio
    z1 = z0 + h1 * (v0 - 0.5 * g * h1 + ce * _log1p_neg_integral_over_x(x, log_ratio))
    m1 = torch.where(full, m0 - mdot * h1, torch.clamp(m0, max=dry))  # never below dry (nor above m0)
    h2 = dt_s - h1  # free fall after burnout (0 unless the tank ran dry)
    z2 = z1 + h2 * (v1 - 0.5 * g * h2)
    v2 = v1 - g * h2
    return z2, v2, m1, torch.where(u > 0, h1, 0.0)


def step_substeps(z_m: Tensor, v_mps: Tensor, m_kg: Tensor, thrust_n: Tensor, dt_s: float,
                  params: LanderParams, substeps: int = 100) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Advance by ``dt_s`` with ``substeps`` classic RK4 sub-steps of the held thrust.

    Thrust is cut (set to 0) in a sub-step that starts at or below the dry mass, and the mass
    is clamped at the dry mass; so burnout is resolved to one sub-step.

    Args and returns as :func:`step_exact`.
    """
    _check(z_m, v_mps, m_kg, thrust_n, dt_s)
    if int(substeps) < 1:
        raise ValueError(f"substeps must be >= 1, got {substeps}")
    dtype = torch.float64
    z, v, m = z_m.to(dtype).clone(), v_mps.to(dtype).clone(), m_kg.to(dtype).clone()
    u_cmd = thrust_n.to(dtype).clamp_min(0.0)
    ce, g, dry = params.exhaust_velocity_mps, params.g_mps2, params.dry_mass_kg
    h = dt_s / int(substeps)
    burn = torch.zeros_like(z)

    for _ in range(int(substeps)):
        u = torch.where(m > dry, u_cmd, torch.zeros_like(u_cmd))

        def f(zz, vv, mm):
            return vv, u / mm - g, -u / ce

        k1 = f(z, v, m)
        k2 = f(z + 0.5 * h * k1[0], v + 0.5 * h * k1[1], m + 0.5 * h * k1[2])
        k3 = f(z + 0.5 * h * k2[0], v + 0.5 * h * k2[1], m + 0.5 * h * k2[2])
        k4 = f(z + h * k3[0], v + h * k3[1], m + h * k3[2])
        z = z + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        v = v + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        m_new = m + h / 6 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
        m = torch.where(m > dry, m_new.clamp_min(dry), m)
        burn = burn + torch.where(u > 0, torch.full_like(burn, h), torch.zeros_like(burn))
    return z, v, m, burn


def step_euler(z_m: Tensor, v_mps: Tensor, m_kg: Tensor, thrust_n: Tensor, dt_s: float,
               params: LanderParams) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Advance by ``dt_s`` with one explicit Euler step (the paper's released implementation):

        z += v dt,  v += (u/m - g) dt,  m -= u / (Isp g0) dt      (all rates at the start state)

    First order: its error per step is O(dt^2) (about g dt^2 / 2 = 8 mm in z at dt = 0.1 s with
    no thrust). Thrust is cut (0) where the mass is at or below the dry mass; the mass never
    falls below it (the burn time is then shortened to what the fuel allowed).

    Args and returns as :func:`step_exact`.
    """
    _check(z_m, v_mps, m_kg, thrust_n, dt_s)
    dtype = torch.float64
    z0, v0, m0 = z_m.to(dtype), v_mps.to(dtype), m_kg.to(dtype)
    ce, g, dry = params.exhaust_velocity_mps, params.g_mps2, params.dry_mass_kg
    u = torch.where(m0 > dry, thrust_n.to(dtype).clamp_min(0.0), 0.0)
    fuel = (m0 - dry).clamp_min(0.0)
    mdot = u / ce
    burn = torch.where(mdot * dt_s <= fuel, dt_s, fuel / torch.where(mdot > 0, mdot, 1.0))
    z1 = z0 + v0 * dt_s
    v1 = v0 + (u / m0) * burn - g * dt_s
    m1 = torch.maximum(m0 - mdot * burn, torch.minimum(m0, torch.full_like(m0, dry)))
    return z1, v1, m1, torch.where(u > 0, burn, 0.0)


class LanderDynamics:
    """Module form: ``dyn.step(z, v, m, thrust, dt_s)`` with the configured integrator.

    Args:
        params: :class:`LanderParams`.
        integrator: ``"exact"`` (rocket equation, zero-order hold), ``"euler"`` (one explicit Euler
            step, the paper's released code) or ``"substeps"`` (RK4).
        substeps: sub-steps per step for ``"substeps"``.
    """

    def __init__(self, params: LanderParams, integrator: str = "exact", substeps: int = 100):
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {list(INTEGRATORS)}, got {integrator!r}")
        if int(substeps) < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        self.params = params
        self.integrator = integrator
        self.substeps = int(substeps)

    @classmethod
    def from_config(cls, dyn) -> "LanderDynamics":
        """From a :class:`dvsland.config.DynamicsConfig`."""
        return cls(LanderParams.from_config(dyn), dyn.integrator, dyn.substeps)

    def step(self, z_m: Tensor, v_mps: Tensor, m_kg: Tensor, thrust_n: Tensor, dt_s: float):
        """See :func:`step_exact`; returns (z_m, v_mps, m_kg, burn_s)."""
        if self.integrator == "exact":
            return step_exact(z_m, v_mps, m_kg, thrust_n, dt_s, self.params)
        if self.integrator == "euler":
            return step_euler(z_m, v_mps, m_kg, thrust_n, dt_s, self.params)
        return step_substeps(z_m, v_mps, m_kg, thrust_n, dt_s, self.params, self.substeps)
