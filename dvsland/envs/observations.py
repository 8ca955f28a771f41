"""What a :class:`~dvsland.envs.LandingVectorEnv` shows its agent: observation spaces and values.

Three observations, chosen by name (``observation="divergence"``) or several at once as a
:class:`gymnasium.spaces.Dict` (``observation=("events", "divergence")``):

- ``"events"``: (2, H, W) float32 event counts of the last control interval (channel 0 ON,
  channel 1 OFF; zero at the first step), H x W = ``camera.height_px`` x ``camera.width_px``.
- ``"divergence"``: (7,) float32 ``[d_est, d_conf, d_filtered, z_est_m, d_target, hover_frac,
  t_frac]``: the estimator's D_hat (1/s, 0 where it has none), its confidence in [0, 1] (0 where
  none), the loop filter's output (1/s, 0 where none), the filter's altitude estimate (m; the
  efference-copy filters give one, 0 otherwise), and the context below.
- ``"oracle"``: (4,) float32 ``[d_true, d_target, hover_frac, t_frac]``: the true divergence
  v/z (1/s, negative while descending) and the context.

Context (in both vectors): ``d_target`` = D*(t) = -1 / max(tau0 - c2 t, tau_min) (1/s), the
paper's time-to-contact target of the descent (see :mod:`dvsland.envs.reward`); ``hover_frac`` =
m g / thrust_high, the hover thrust as a fraction of the upper bound of the normalised
``"thrust"`` action; ``t_frac`` = t / ``simulation.t_max_s``.

Everything describes the same instant t_k: the frames rendered at t_k, the events of
(t_{k-1}, t_k], the estimate and filter output at t_k and the true state at t_k; the action chosen
from it flies over [t_k, t_k + dt) (as the shipped controller's command does).
"""

from __future__ import annotations

from typing import Dict, Sequence, Tuple, Union

import numpy as np
import torch
from gymnasium import spaces

#: the observation names, in the order of a Dict space's keys
OBSERVATIONS = ("events", "divergence", "oracle")
#: the fields of the "divergence" and "oracle" vectors
DIVERGENCE_FIELDS = ("d_est", "d_conf", "d_filtered", "z_est_m", "d_target", "hover_frac", "t_frac")
ORACLE_FIELDS = ("d_true", "d_target", "hover_frac", "t_frac")
#: the true divergence is shown clipped to +-this, 1/s (the loop's bound on an estimate; at z <= 0
#: after a crash v/z is not finite)
D_ABS_MAX = 10.0


def parse_observation(observation: Union[str, Sequence[str]]) -> Tuple[str, ...]:
    """The observation name(s) as a tuple; ValueError naming ``observation`` and the allowed names."""
    names = (observation,) if isinstance(observation, str) else tuple(observation or ())
    bad = [n for n in names if n not in OBSERVATIONS]
    if not names or bad or len(set(names)) != len(names):
        raise ValueError(f"observation must be one of {list(OBSERVATIONS)} or a list of distinct ones, "
                         f"got {observation!r}")
    return names


def single_space(names: Tuple[str, ...], height: int, width: int) -> spaces.Space:
    """The space of one element: a Box for one name, a Dict keyed by name for several."""
    boxes = {
        "events": spaces.Box(0.0, np.inf, (2, height, width), np.float32),
        "divergence": spaces.Box(-np.inf, np.inf, (len(DIVERGENCE_FIELDS),), np.float32),
        "oracle": spaces.Box(-np.inf, np.inf, (len(ORACLE_FIELDS),), np.float32),
    }
    if len(names) == 1:
        return boxes[names[0]]
    return spaces.Dict({n: boxes[n] for n in names})


def context(out, d_target: torch.Tensor, hover_frac: torch.Tensor, t_max_s: float) -> torch.Tensor:
    """(B, 3) float64 ``[d_target, hover_frac, t_frac]`` at the step of ``out`` (a StepOutput)."""
    t_frac = torch.full_like(d_target, out.t_s / t_max_s)
    return torch.stack((d_target, hover_frac, t_frac), dim=1)


def observe(names: Tuple[str, ...], out, ctx: torch.Tensor, hw: Tuple[int, int]) -> Dict[str, torch.Tensor]:
    """Every requested observation of all B elements from one :class:`~dvsland.sim.StepOutput`.

    Args:
        names: observation names (:func:`parse_observation`).
        out: the StepOutput sensed at t_k (its ``events``, ``d_est``, ... and true ``d_true``).
        ctx: (B, 3) float64 from :func:`context`.
        hw: (H, W) of the event images.

    Returns:
        {name: (B, ...) float32 tensor on ``ctx``'s device}; NaN estimates are 0 (with confidence 0).
    """
    B, dev = ctx.shape[0], ctx.device
    res = {}
    for n in names:
        if n == "events":
            ev = out.events
            img = (torch.zeros(B, 2, *hw, device=dev) if ev is None or len(ev) == 0 else ev.to_count_image(B, *hw))
            res[n] = img.to(device=dev, dtype=torch.float32)
        elif n == "divergence":
            z_est = out.z_est_m if out.z_est_m is not None else torch.zeros_like(out.d_est)
            cols = [out.d_est, out.d_conf, out.d_filtered, z_est.to(out.d_est.dtype)]
            v = torch.cat((torch.stack(cols, dim=1), ctx), dim=1)
            res[n] = torch.nan_to_num(v, nan=0.0).to(torch.float32)
        else:  # oracle
            d = torch.nan_to_num(out.d_true, nan=0.0).clamp(-D_ABS_MAX, D_ABS_MAX)  # z <= 0 at a crash
            v = torch.cat((d.unsqueeze(1), ctx), dim=1)
            res[n] = v.to(torch.float32)
    return res


def pack(names: Tuple[str, ...], obs: Dict):
    """The observation in the space's layout: the array itself for one name, the dict for several."""
    return obs[names[0]] if len(names) == 1 else obs


def to_numpy(obs: Dict[str, torch.Tensor]) -> Dict[str, np.ndarray]:
    """The observation dict as numpy arrays (copies on the host)."""
    return {n: v.detach().cpu().numpy() for n, v in obs.items()}


def _rows(rows: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return rows.to(like.device).view((-1,) + (1,) * (like.dim() - 1))


def hold_sensing(obs: Dict[str, torch.Tensor], prev: Dict[str, torch.Tensor], rows: torch.Tensor) -> Dict:
    """``obs`` with the sensed parts of ``rows`` (B,) bool taken from ``prev`` (a new dict; no host
    sync): the event image and the first four ``divergence`` fields (estimate, confidence, filter
    output, altitude estimate). A finished descent's camera is frozen, so its last observation keeps
    the last sensing it had while flying; its true divergence and context are those of its end."""
    if prev is None:
        return obs
    res = dict(obs)
    if "events" in obs:
        res["events"] = torch.where(_rows(rows, obs["events"]), prev["events"], obs["events"])
    if "divergence" in obs:
        d = obs["divergence"]
        held = torch.cat((prev["divergence"][:, :4], d[:, 4:]), dim=1)
        res["divergence"] = torch.where(_rows(rows, d), held, d)
    return res


def take_rows(obs: Dict[str, torch.Tensor], src: Dict[str, torch.Tensor], rows: torch.Tensor) -> Dict:
    """``obs`` with every part of ``rows`` (B,) bool taken from ``src`` (a new dict; no host sync)."""
    if src is None:
        return obs
    return {n: torch.where(_rows(rows, v), src[n], v) for n, v in obs.items()}
