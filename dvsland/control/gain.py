"""Loop-gain maths of the built-in laws, in one place (the summaries and the docs use these).

Two loops, two gains:

- ``tau_p`` (Eq. 2 read in tau-space): near the ideal descent d(tau)/dt = -1 + lambda (tau* - tau)
  with lambda = Kp z0 / (m v0^2), 1/s (z / v^2 stays z0 / v0^2 along the ideal descent).
- ``div_p`` (the released implementation's law, u = Kp (D* - mean D_hat)): a thrust change du
  changes dv/dt by du/m, hence dD/dt by du/(m z); the divergence loop's gain is
  lambda_D = Kp / (m z), 1/s. It grows as the craft descends and loses mass.

Sampled at dt with the error averaged over the last n_bin estimates, the divergence loop is
  D[k+1] = D[k] - g (D[k-d] + ... + D[k-d-n_bin+1]) / n_bin,   g = lambda_D dt,
(d = whole steps of estimator lag). It is stable while g < g_crit(n_bin, d)
(:func:`critical_step_gain`: 2 for n_bin = 1, d = 0). :func:`gain_limit_altitude_m` is the altitude
below which Kp / (m z) dt passes g_crit: the descent's "unstable near the end".
"""

from __future__ import annotations

import functools

import numpy as np
import torch

Tensor = torch.Tensor


def tau_loop_gain(kp, z0_m, v0_mps, mass_kg):
    """lambda = Kp z0 / (m v0^2), 1/s (tau-space gain of Eq. 2). Tensors or floats, broadcast
    (the same formula as :func:`dvsland.dynamics.loop_gain`, which takes floats)."""
    if not any(isinstance(x, Tensor) for x in (kp, z0_m, v0_mps, mass_kg)):
        from dvsland.dynamics import loop_gain

        return loop_gain(kp, z0_m, v0_mps, mass_kg)
    return kp * z0_m / (mass_kg * v0_mps ** 2)


def div_loop_gain(kp, mass_kg, altitude_m):
    """lambda_D = Kp / (m z), 1/s (divergence-space gain of u = Kp (D* - D)). Tensors or floats."""
    return kp / (mass_kg * altitude_m)


def _spectral_radius(g: float, n_bin: int, delay_steps: int) -> float:
    # z^(n+d) - z^(n+d-1) + (g/n) (z^(n-1) + ... + 1) = 0
    deg = n_bin + delay_steps
    coeffs = np.zeros(deg + 1)
    coeffs[0] = 1.0
    coeffs[1] -= 1.0
    coeffs[deg - n_bin + 1:] += g / n_bin
    return float(np.max(np.abs(np.roots(coeffs))))


#: above this n_bin, :func:`critical_step_gain` uses the long-average limit (the exact roots of a
#: degree-n polynomial cost O(n^3) per bisection step: 20 s at n_bin = 200, hours at 10 000)
EXACT_MAX_N_BIN = 64


def long_average_step_gain(n_bin: int, delay_steps: int = 0) -> float:
    """g_crit of a long moving average, from the continuous loop x'(t) = -(lambda / T) times the
    integral of x over [t - delta - T, t - delta] (T = n_bin dt, delta = delay_steps dt): with
    r = delta / T it is stable while lambda T < w^2 / (2 sin(w / 2)), w = pi / (2 r + 1)
    (pi^2 / 2 without lag). Agrees with the exact sampled loop to 4e-4 relative at n_bin = 50 and
    better above (tested)."""
    w = np.pi / (2.0 * delay_steps / n_bin + 1.0)
    return float(w * w / (2.0 * np.sin(w / 2.0)) / n_bin)


@functools.lru_cache(maxsize=256)
def critical_step_gain(n_bin: int = 1, delay_steps: int = 0) -> float:
    """Largest g = lambda_D dt for which the sampled divergence loop with an n_bin moving average
    and ``delay_steps`` whole steps of lag is stable: bisection on the characteristic roots for
    n_bin <= :data:`EXACT_MAX_N_BIN`, the long-average limit (:func:`long_average_step_gain`) above.

    Args:
        n_bin: moving-average length, >= 1.
        delay_steps: estimator lag in control steps, >= 0.

    Returns:
        g_crit (float): 2.0 for n_bin = 1 without lag; smaller for longer averages / more lag.
    """
    n_bin, delay_steps = int(n_bin), int(delay_steps)
    if n_bin < 1:
        raise ValueError(f"n_bin must be >= 1, got {n_bin}")
    if delay_steps < 0:
        raise ValueError(f"delay_steps must be >= 0, got {delay_steps}")
    if n_bin > EXACT_MAX_N_BIN:
        return long_average_step_gain(n_bin, delay_steps)
    lo, hi = 0.0, 2.0
    if _spectral_radius(hi, n_bin, delay_steps) < 1.0:  # cannot happen: g = 2 always unstable or marginal
        return hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if _spectral_radius(mid, n_bin, delay_steps) < 1.0 - 1e-12:
            lo = mid
        else:
            hi = mid
    return lo


def gain_limit_altitude_m(kp, mass_kg, dt_s: float, n_bin, delay_steps: int = 0):
    """Altitude (m) below which the div_p loop's Kp / (m z) dt exceeds g_crit(n_bin, delay).

    Args:
        kp: (B,) or float gain, N s.
        mass_kg: (B,) or float mass, kg (the current or final mass).
        dt_s: control interval, s.
        n_bin: (B,) int or int moving-average lengths.
        delay_steps: estimator lag, whole steps.

    Returns:
        z_limit = Kp dt / (m g_crit), same type/shape as ``kp`` (tensor in, tensor out).
    """
    if isinstance(n_bin, Tensor):
        gc = torch.tensor([critical_step_gain(int(n), delay_steps) for n in n_bin.reshape(-1).tolist()],
                          dtype=torch.float64, device=n_bin.device).reshape(n_bin.shape)
    else:
        gc = critical_step_gain(int(n_bin), delay_steps)
    return kp * dt_s / (mass_kg * gc)





def loop_gain_fields(controller, mass_kg: Tensor, altitude_m: Tensor) -> dict:
    """The summary's loop-gain fields of ``controller`` at the given (final) state.

    Returns a dict with ``loop_gain`` ((B,) tensor, 1/s, or None), ``loop_gain_kind`` (``"tau"``:
    Eq. 2's lambda = Kp z0 / (m0 v0^2); ``"div"``: the divergence loop's Kp / (m z) at the end; None)
    and ``gain_limit_altitude_m`` ((B,) tensor or None: where Kp / (m z) dt crosses the sampled
    loop's limit, ``div_p`` only). A law without ``loop_gain_fields`` reports None for all three.
    """
    out = {"loop_gain": None, "loop_gain_kind": None, "gain_limit_altitude_m": None}
    fn = getattr(controller, "loop_gain_fields", None)
    if fn is not None:
        out.update(fn(mass_kg.to(torch.float64), altitude_m.to(torch.float64)))
    return out
__all__ = ["tau_loop_gain", "div_loop_gain", "critical_step_gain", "gain_limit_altitude_m", "loop_gain_fields"]
