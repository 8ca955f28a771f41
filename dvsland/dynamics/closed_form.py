"""Closed-form constant-TTC-decrease descent (Izzo & de Croon 2012): the one place it is written.

With perfect sensing and tau(t) = tau0 - c^2 t exactly tracked:
s = 1 + c^2 v0 t / z0,  z = z0 s^(1/c^2),  v = v0 s^(1/c^2 - 1).
"""

from __future__ import annotations

import numpy as np


def _check(z0_m: float, v0_mps: float, c2: float) -> None:
    if not z0_m > 0:
        raise ValueError(f"z0_m must be > 0, got {z0_m}")
    if not v0_mps < 0:
        raise ValueError(f"v0_mps must be < 0 (descending), got {v0_mps}")
    if not 0 < c2 < 1:
        raise ValueError(f"c2 must be in (0, 1), got {c2}")


def closed_form_state(t_s, z0_m: float, v0_mps: float, c2: float = 0.5):
    """Altitude and velocity of the ideal descent at times ``t_s``.

    Args:
        t_s: array-like of times, s (>= 0); after touchdown (s <= 0) z = v = 0.
        z0_m: initial altitude, m (> 0).
        v0_mps: initial velocity, m/s (< 0).
        c2: c^2 of tau*(t) = tau0 - c^2 t, in (0, 1).

    Returns:
        (z_m, v_mps): float64 numpy arrays shaped like ``t_s``.
    """
    _check(z0_m, v0_mps, c2)
    t = np.asarray(t_s, dtype=np.float64)
    s = np.clip(1.0 + c2 * v0_mps * t / z0_m, 0.0, None)
    return z0_m * s ** (1.0 / c2), v0_mps * s ** (1.0 / c2 - 1.0)


def closed_form_time_to_altitude(z_m: float, z0_m: float, v0_mps: float, c2: float = 0.5) -> float:
    """Time (s) at which the ideal descent reaches altitude ``z_m`` (0 < z_m <= z0_m)."""
    _check(z0_m, v0_mps, c2)
    if not 0 <= z_m <= z0_m:
        raise ValueError(f"z_m must be in [0, z0_m={z0_m}], got {z_m}")
    s = (z_m / z0_m) ** c2
    return (s - 1.0) * z0_m / (c2 * v0_mps)


def closed_form_descent(z0_m: float, v0_mps: float, c2: float = 0.5, *, to_m: float, from_m: float | None = None,
                        dt_s: float | None = None, n: int | None = None):
    """Samples of the ideal descent from ``from_m`` (default ``z0_m``) down to ``to_m``.

    Give exactly one of:
        dt_s: a sample every ``dt_s`` s from ``from_m`` until the altitude is <= ``to_m`` (the frame
            clock of a descent: the last sample is the first at or below ``to_m``);
        n: ``n`` samples uniform in time, the first at ``from_m``, the last at ``to_m``.

    Returns:
        (t_s, z_m, v_mps): float64 numpy arrays (K,), t_s the flight time since z = z0_m, s.

    Raises:
        ValueError: not ``z0_m >= from_m > to_m > 0``, or not exactly one of ``dt_s`` / ``n``
            (``dt_s > 0``, ``n >= 2``).
    """
    from_m = float(z0_m if from_m is None else from_m)
    if not (z0_m >= from_m > to_m > 0):
        raise ValueError(f"need z0_m >= from_m > to_m > 0, got z0_m={z0_m}, from_m={from_m}, to_m={to_m}")
    if (dt_s is None) == (n is None):
        raise ValueError("give exactly one of dt_s (a sample every dt_s s) and n (n samples)")
    t0 = closed_form_time_to_altitude(from_m, z0_m, v0_mps, c2)
    t1 = closed_form_time_to_altitude(to_m, z0_m, v0_mps, c2)
    if dt_s is not None:
        if not dt_s > 0:
            raise ValueError(f"dt_s must be > 0, got {dt_s}")
        k = int(np.ceil((t1 - t0) / dt_s - 1e-9)) + 1
        t = t0 + dt_s * np.arange(k)
    else:
        if int(n) < 2:
            raise ValueError(f"n must be >= 2, got {n}")
        t = np.linspace(t0, t1, int(n))
    z, v = closed_form_state(t, z0_m, v0_mps, c2)
    return t, z, v


def closed_form_thrust(t_s, z0_m: float, v0_mps: float, mass_kg, g_mps2: float = 1.62, c2: float = 0.5):
    """Thrust (N) the ideal descent needs: m (a + g), a = dv/dt = c^2 (1/c^2 - 1) v0^2/z0 s^(1/c^2 - 2)."""
    _check(z0_m, v0_mps, c2)
    t = np.asarray(t_s, dtype=np.float64)
    s = np.clip(1.0 + c2 * v0_mps * t / z0_m, 0.0, None)
    a = (1.0 - c2) * v0_mps ** 2 / z0_m * s ** (1.0 / c2 - 2.0)
    return np.asarray(mass_kg, dtype=np.float64) * (a + g_mps2)


def loop_gain(kp: float, z0_m: float, v0_mps: float, mass_kg: float) -> float:
    """Loop gain lambda = Kp z0 / (m v0^2), 1/s: d(tau)/dt = -1 + lambda (tau* - tau) near the ideal
    descent (z / v^2 stays z0 / v0^2 along it); lambda dt >~ 2 makes the sampled loop relay-like."""
    return float(kp) * float(z0_m) / (float(mass_kg) * float(v0_mps) ** 2)


__all__ = ["closed_form_state", "closed_form_time_to_altitude", "closed_form_descent", "closed_form_thrust",
           "loop_gain"]
