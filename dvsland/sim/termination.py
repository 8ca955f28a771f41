"""How a descent ends: success (z <= success altitude), ascent (v > 0), crash (|D| too large or z <= 0), timeout."""

from __future__ import annotations

import torch

Tensor = torch.Tensor

#: Outcome codes; index = code stored in the int8 outcome tensor.
OUTCOMES = ("running", "success", "ascent", "crash", "timeout", "interrupted")
RUNNING, SUCCESS, ASCENT, CRASH, TIMEOUT, INTERRUPTED = range(6)


def termination_code(z_m: Tensor, v_mps: Tensor, t_s, success_altitude_m: float, crash_divergence: float,
                     t_max_s: float) -> Tensor:
    """Outcome code per element after a step (0 = still flying).

    Precedence: z <= 0 crash; z <= success altitude success; |D| = -v/z >= crash_divergence
    crash; v > 0 ascent; t >= t_max timeout.

    Args:
        z_m, v_mps: (B,) float64 state after the step.
        t_s: scalar or (B,) float64 time after the step, s.
        success_altitude_m, crash_divergence, t_max_s: thresholds.

    Returns:
        (B,) int8 codes (see :data:`OUTCOMES`).
    """
    if crash_divergence <= 0:
        raise ValueError(f"crash_divergence must be > 0, got {crash_divergence}")
    if t_max_s <= 0:
        raise ValueError(f"t_max_s must be > 0, got {t_max_s}")
    if isinstance(t_s, torch.Tensor):
        code = torch.where(t_s >= t_max_s - 1e-9, TIMEOUT, RUNNING).to(torch.int8).expand_as(z_m)
    else:
        code = torch.full(z_m.shape, TIMEOUT if t_s >= t_max_s - 1e-9 else RUNNING, dtype=torch.int8,
                          device=z_m.device)
    code = torch.where(v_mps > 0, ASCENT, code)
    # |D| = -v/z >= c  <=>  -v >= c z  (z > 0 here; z <= 0 is a crash anyway)
    code = torch.where(-v_mps >= crash_divergence * z_m, CRASH, code)
    code = torch.where(z_m <= success_altitude_m, SUCCESS, code)
    return torch.where(z_m <= 0, CRASH, code).to(torch.int8)
