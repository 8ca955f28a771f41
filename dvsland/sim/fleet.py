"""A fleet: many more descents than the batch holds, flown through B slots that never wait.

:func:`dvsland.simulate` and the campaigns fly B descents that start together and end with the last
of them: near the end a few slow descents (a time-out flies every one of its steps) hold the whole
batch, and each of their steps pays the batch's fixed cost. :func:`fly_fleet` instead keeps every
slot busy. When a descent ends, its result is recorded and its slot restarts at once
(:func:`dvsland.sim.reset_where`) with the slot's next descent, until ``n_descents`` have been
flown. That is the way to count whole descents per minute on a large batch.

Which descents fly:

- slot b is layout element b (its site, scene, sensor and controller setting; the dispersed values of
  the layout that are built into the stages stay the slot's);
- the slot's first descent (restart 0) is the layout's own: the same descent as in
  :func:`dvsland.simulate`, bit for bit;
- its restart r >= 1 draws a new start (altitude and velocity from the config's ``dispersion.z0_scale``
  and ``dispersion.v0_scale`` around the site's nominal start; nominal where a dispersion is off) and a
  new sensor-noise seed, by counter-based draws of (the slot's seed, its site, r). A restart's
  conditions therefore depend on its slot and r only, never on when it started, the batch size or
  the device. Its flight is that of a new descent with those conditions up to rounding: the filter's
  sums run over the batch's longer history (with the ``oracle``, within 1e-12 relative: tested).
  With event estimators it is the same descent in distribution, not to the bit: ``cmax`` dithers
  its events by a hash of their time, and the learned ring keeps its slot position (the
  convolution sums its channels in another order).

Slots are restarted in slot order at a check (every ``check_every`` steps: a check is one host
synchronisation); once ``n_descents`` have started, finished slots stay finished (frozen, and off
the hot path as in any batch).
"""

from __future__ import annotations

import time
from typing import Callable, Dict, List, NamedTuple, Optional

import torch

from dvsland.layout.dispersion import site_key
from dvsland.pytree import hash_bits, hash_normal, hash_uniform

from .reset import init_state, reset_where
from .state import LoopState
from .step import loop_step
from .termination import OUTCOMES

#: per-descent fields of a :class:`FleetResult` (each (N,) in the order the descents ended)
FLEET_FIELDS = ("slot", "restart", "outcome", "t_end_s", "z_end_m", "v_end_mps", "lowest_m", "fuel_used_kg",
                "max_thrust_n", "z0_m", "v0_mps", "noise_seed", "missing_estimates", "end_step")

#: stream tags of a restart's draws (the altitude's and velocity's scales, the noise seed's halves)
_TAG_Z, _TAG_V, _TAG_SEED_HI, _TAG_SEED_LO = 11, 12, 13, 14


class FleetResult(NamedTuple):
    """What a fleet flew.

    Attributes:
        descents: {field: (N,) CPU tensor} for the N descents that ended, in the order they ended
            (:data:`FLEET_FIELDS`: ``slot`` int64 layout element, ``restart`` int64 (0 = the layout's
            own descent), ``outcome`` int8 code of :data:`dvsland.sim.OUTCOMES`, ``t_end_s`` float64
            flight time s, ``z_end_m``, ``v_end_mps``, ``lowest_m``, ``fuel_used_kg``,
            ``max_thrust_n``, ``z0_m``, ``v0_mps`` float64, ``noise_seed`` int64,
            ``missing_estimates`` int64, ``end_step`` int64 the fleet's step at which it was
            recorded).
        steps: control steps the fleet flew.
        wall_s: wall seconds of the flight (set-up excluded).
        n_started: descents started (== N unless ``max_steps`` stopped the fleet first).
    """

    descents: Dict[str, torch.Tensor]
    steps: int
    wall_s: float
    n_started: int

    @property
    def n_ended(self) -> int:
        return int(self.descents["slot"].numel())

    @property
    def complete(self) -> bool:
        """Every started descent ended."""
        return self.n_ended >= self.n_started

    def descents_per_minute(self) -> float:
        """Whole descents ended per minute of wall time."""
        return 60.0 * self.n_ended / self.wall_s if self.wall_s > 0 else float("nan")

    def outcome_counts(self) -> Dict[str, int]:
        """{outcome name: count} over the ended descents."""
        codes = self.descents["outcome"].to(torch.int64)
        counts = torch.bincount(codes, minlength=len(OUTCOMES)).tolist()
        return {name: int(c) for name, c in zip(OUTCOMES, counts) if c}


def slot_keys(stages) -> tuple:
    """The two keys of each slot's restart draws: (its seed, its site's key), (B,) int64 each on the
    stages' device (made once per fleet: a host loop over the slots' site names)."""
    L, dev = stages.layout, torch.device(stages.device)
    return L.tensor("seed", dev, torch.int64), torch.as_tensor([site_key(s) for s in L.site], dtype=torch.int64,
                                                                device=dev)


def restart_conditions(stages, restart: torch.Tensor, keys: Optional[tuple] = None):
    """The start and noise seed of each slot's restart ``restart`` ((B,) int64, >= 1 where used);
    ``keys``: :func:`slot_keys` (made here when None).

    Returns:
        (z0_m, v0_mps, noise_seed): (B,) float64 m, float64 m/s and int64, on the stages' device.
    """
    L, dev, f64 = stages.layout, torch.device(stages.device), torch.float64
    keys = (*(slot_keys(stages) if keys is None else keys), restart.to(dev))
    disp = stages.cfg.dispersion
    z0 = _nominal(L, "z0_m", "z0_scale", dev) * _scale(disp, "z0_scale", keys, _TAG_Z)
    v0 = _nominal(L, "v0_mps", "v0_scale", dev) * _scale(disp, "v0_scale", keys, _TAG_V)
    seed = (hash_bits(*keys, _TAG_SEED_HI) << 31) ^ hash_bits(*keys, _TAG_SEED_LO)
    return z0.to(f64), v0.to(f64), seed


def _nominal(L, field: str, scale_name: str, dev) -> torch.Tensor:
    """The layout's start ``field`` without its dispersed scale."""
    value = L.tensor(field, dev, torch.float64)
    scale = L.dispersed.get(scale_name)
    return value if scale is None else value / torch.as_tensor(scale, dtype=torch.float64, device=dev)


def _scale(disp, name: str, keys, tag: int):
    """Counter-based draws of dispersion ``name`` (1.0 where it, or the dispersions, are off)."""
    dist = getattr(disp, name)
    kind = dist.kind if disp.enabled else "off"
    if kind == "off":
        return 1.0
    if kind == "fixed":
        return float(dist.value)
    if kind == "uniform":
        return dist.low + (dist.high - dist.low) * hash_uniform(*keys, tag)
    return (dist.mean + dist.std * hash_normal(*keys, tag)).clamp(dist.low, dist.high)


def _take(state: LoopState, idx: torch.Tensor, restart, z0, v0, mass0: float, step: int) -> Dict[str, torch.Tensor]:
    """The results of the descents in slots ``idx`` (just ended)."""
    return {"slot": idx, "restart": restart[idx], "outcome": state.outcome[idx], "t_end_s": state.t_end_s[idx],
            "z_end_m": state.z_m[idx], "v_end_mps": state.v_mps[idx], "lowest_m": state.lowest_m[idx],
            "fuel_used_kg": mass0 - state.m_kg[idx], "max_thrust_n": state.max_thrust_n[idx], "z0_m": z0[idx],
            "v0_mps": v0[idx], "noise_seed": state.noise_seed[idx], "missing_estimates": state.n_missing[idx],
            "end_step": torch.full_like(idx, step)}


def fly_fleet(stages, n_descents: int, check_every: int = 4, max_steps: Optional[int] = None,
              on_check: Optional[Callable[[int, int, int], None]] = None,
              on_ended: Optional[Callable[[Dict[str, torch.Tensor]], None]] = None) -> FleetResult:
    """Fly ``n_descents`` whole descents through the B slots of ``stages`` (see the module's text).

    Args:
        stages: :class:`dvsland.stages.Stages` of B slots.
        n_descents: descents to fly, >= 1 (fewer than B flies the first ``n_descents`` slots' own
            descents, the others' descents are ended unrecorded at the start).
        check_every: steps between two checks for ended descents (1 to 1000). A slot waits up to
            ``check_every - 1`` steps for its restart; each check is one host synchronisation.
        max_steps: stop after this many steps even if descents still fly (None: until all ended).
        on_check: optional ``on_check(step, n_ended, n_started)`` after each check (progress).
        on_ended: optional ``on_ended(descents)`` with the descents that ended since the last check
            ({field: (n,) CPU tensor}, as :attr:`FleetResult.descents`): to write them as they come,
            so that a fleet stopped half-way keeps what it flew.

    Returns:
        :class:`FleetResult`.

    Raises:
        ValueError: ``n_descents``, ``check_every`` or ``max_steps`` out of range (names it).
    """
    n_descents, check_every = _count("n_descents", n_descents, 1, 10 ** 9), _count("check_every", check_every, 1, 1000)
    max_steps = None if max_steps is None else _count("max_steps", max_steps, 1, 10 ** 9)
    B, dev = stages.batch_size, torch.device(stages.device)
    state = init_state(stages)
    restart = torch.zeros(B, dtype=torch.int64, device=dev)
    z0, v0 = state.z_m.clone(), state.v_mps.clone()
    pending = torch.arange(B, device=dev) < n_descents  # slots holding a descent not yet recorded
    if n_descents < B:
        state = state._replace(active=state.active & pending)
    n_started, n_ended, parts, mass0 = min(B, n_descents), 0, [], float(stages.settings.mass_kg)
    keys = slot_keys(stages)
    t0, steps = time.perf_counter(), 0
    while True:
        state, _ = loop_step(stages, state, donate=True)  # the fleet's own state
        steps += 1
        last = max_steps is not None and steps >= max_steps
        if steps % check_every and not last:
            continue
        idx = torch.nonzero(pending & ~state.active).squeeze(1)  # the check's one sync
        if idx.numel():
            parts.append(_take(state, idx, restart, z0, v0, mass0, steps))
            n_ended += int(idx.numel())
            if on_ended is not None:
                on_ended({k: v.cpu() for k, v in parts[-1].items()})
            n_new = min(int(idx.numel()), n_descents - n_started)
            pending[idx[n_new:]] = False
            if n_new:
                state, restart, z0, v0 = _restart(stages, state, idx[:n_new], restart, z0, v0, keys)
                n_started += n_new
        if on_check is not None:
            on_check(steps, n_ended, n_started)
        if n_ended >= n_started or last:
            break
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
    wall = time.perf_counter() - t0
    descents = {k: torch.cat([p[k] for p in parts]).cpu() if parts else torch.zeros(0) for k in FLEET_FIELDS}
    return FleetResult(descents, steps, wall, n_started)


def _restart(stages, state: LoopState, idx: torch.Tensor, restart, z0, v0, keys):
    """Restart slots ``idx`` with their next descents: (state, restart, z0, v0) updated."""
    mask = torch.zeros_like(state.active)
    mask[idx] = True
    restart = torch.where(mask, restart + 1, restart)
    z_new, v_new, seed_new = restart_conditions(stages, restart, keys)
    state = reset_where(stages, state, mask, z_m=z_new, v_mps=v_new, seed=seed_new)
    return state, restart, torch.where(mask, z_new, z0), torch.where(mask, v_new, v0)


def _count(name: str, value, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return int(value)


def fleet_rows(stages, result) -> List[dict]:
    """One dict per ended descent, with the keys of a campaign's runs where they mean the same
    (``site``, ``scene``, ``label``, ``estimator``, ``outcome``, ``t_end_s``, ``lowest_altitude_m``,
    ``v_end_mps``, ``fuel_used_kg``, ...; no ``v_at_50m_mps``: a fleet keeps no traces), plus
    ``slot``, ``restart``, ``noise_seed`` and ``end_step``: for :func:`dvsland.report.stats.group_stats`.
    ``result``: a :class:`FleetResult` or its ``descents`` dict (what ``on_ended`` is given)."""
    from dvsland.estimators.registry import estimator_label

    L = stages.layout
    d = result.descents if isinstance(result, FleetResult) else result
    est = estimator_label(stages.cfg.estimator.name)
    renamed = {"lowest_m": "lowest_altitude_m"}
    cols = {k: d[k].tolist() for k in FLEET_FIELDS}
    rows = []
    for i in range(len(cols["slot"])):
        b = cols["slot"][i]
        row = {"slot": b, "site": L.site[b], "scene": L.scene[b], "label": L.label[b], "estimator": est,
               "restart": cols["restart"][i], "outcome": OUTCOMES[cols["outcome"][i]]}
        row.update({renamed.get(k, k): cols[k][i] for k in FLEET_FIELDS if k not in ("slot", "restart", "outcome")})
        rows.append(row)
    return rows


__all__ = ["fly_fleet", "FleetResult", "FLEET_FIELDS", "restart_conditions", "slot_keys", "fleet_rows"]
