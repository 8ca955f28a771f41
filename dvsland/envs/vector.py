"""``LandingVectorEnv``: B closed-loop descents as one gymnasium ``VectorEnv``.

The env flies the batched loop of :mod:`dvsland.sim` in its two halves,
:func:`~dvsland.sim.sense_step` and :func:`~dvsland.sim.act_step`, with the agent's thrust instead
of the controller's. Each env step:

1. the action (checked, :mod:`dvsland.envs.actions`) becomes a thrust u (B,) N;
2. the descents fly [t_k, t_k + dt) with u (the step whose sensing the agent saw);
3. reward and episode ends are judged at t_{k+1} (:mod:`dvsland.envs.reward`);
4. descents whose episode is over restart (:func:`~dvsland.sim.reset_where`), as the autoreset
   mode says, while the others fly on;
5. the loop senses at t_{k+1} (render, emulate, estimate, filter, and the shipped law's command,
   reported as ``info["controller_thrust_n"]``): the next observation.

Autoreset (``autoreset_mode=``, gymnasium's :class:`~gymnasium.vector.AutoresetMode`; the default is
``metadata["autoreset_mode"]``, NEXT_STEP):

- ``NEXT_STEP``: the step after an end returns that descent's first observation of its next episode
  (reward 0, both flags False; its action is ignored), and it flies on from there;
- ``SAME_STEP``: the step of an end returns the next episode's first observation, the end's own in
  ``info["final_obs"]`` (and its info in ``info["final_info"]``), masked by ``info["_final_obs"]``;
- ``DISABLED``: an ended descent stays frozen (reward 0, action ignored) until
  ``reset(options={"reset_mask": mask})`` restarts it.

No descent ever waits for its batch-mates. Episodes are seeded per env: ``reset(seed=s)`` gives env
i the seed s + i (or ``seed=[s_0, ..., s_{B-1}]``), and each episode of an env draws its start
(altitude and velocity dispersed by ``start_dispersion``, relative) and its sensor-noise seed from
(env seed, episode index) by counter-based draws: ``reset(seed=1)`` flies other descents than
``reset(seed=0)``, and ``reset()`` without a seed replays the current seeds' episodes.
"""

from __future__ import annotations

import copy
import math
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from dvsland.config import Config, ConfigError, load_config, validate_config
from dvsland.config.validate import check_memory
from dvsland.layout import build_layout
from dvsland.checks import check_choice, check_device, check_keys, check_range
from dvsland.pytree import hash_bits
from dvsland.sim import OUTCOMES, act_step, dispersed_start, init_state, reset_where, sense_step
from dvsland.stages import build_stages, check_names

from . import observations as obs_mod
from .actions import SETPOINT_GAIN_NS, action_spec, check_action, hover_fraction, to_thrust
from .layout import fit_layout
from .reward import RewardConfig, divergence_target, episode_ends, step_reward


#: the largest batch an env takes (its layout holds a few Python values per descent)
MAX_NUM_ENVS = 1_000_000


class LandingVectorEnv(VectorEnv):
    """B = ``num_envs`` descents of one config, as a gymnasium (>= 1.1) vector env.

    Args:
        num_envs: B; None = every element of the config's layout (sites x settings x seeds). Other
            values take ``simulation.n_seeds`` = ceil(B / (sites x settings)) and the first B
            elements in seed-major order (every site once before any site twice).
        config: a :class:`~dvsland.config.Config`, a shipped config name or YAML path, or None
            (``paper``).
        sites: subset of the configured sites, ``"D,E"`` or a list (None = all).
        estimator: estimator name (overrides ``estimator.name``; ``"oracle"`` needs no rendering).
        observation: ``"events"``, ``"divergence"``, ``"oracle"`` or a list of them (a Dict
            space); see :mod:`dvsland.envs.observations`.
        action: ``"thrust"``, ``"thrust_n"`` or ``"divergence_setpoint"``
            (:mod:`dvsland.envs.actions`).
        device: torch device of the loop.
        overrides: ``section.key=value`` strings applied to a config name or path.
        reward: a :class:`RewardConfig` or a dict of its fields.
        clip_actions: clip out-of-range actions instead of raising ValueError.
        setpoint_gain_ns: K of the ``divergence_setpoint`` law, N s.
        autoreset_mode: an :class:`~gymnasium.vector.AutoresetMode` or its name (``"next_step"``,
            ``"same_step"``, ``"disabled"``); default ``metadata["autoreset_mode"]``.
        start_dispersion: relative 1-sigma dispersion of each episode's initial altitude and
            velocity around the layout's, in [0, 0.3]; 0 flies the layout's starts (the descents of
            :func:`dvsland.simulate`) with the layout's sensor-noise seeds.
        array_api: ``"numpy"`` (gymnasium's default: observations, rewards, flags and info as numpy
            arrays on the host) or ``"torch"`` (all of them torch tensors on ``device``, nothing copied
            to the host: for torch RL libraries and a CUDA loop; ``info["outcome_code"]`` holds the
            outcome codes of :data:`dvsland.sim.OUTCOMES` instead of names, ``info["restarted"]``
            marks the restarts).

    Raises:
        ValueError: an unknown ``observation``, ``action`` or ``autoreset_mode`` (naming the allowed
            ones), bad ``num_envs``, ``sites`` or ``start_dispersion``; ConfigError: an invalid
            config or unknown stage name.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs: Optional[int] = None, config: Union[Config, str, None] = None,
                 sites: Union[str, Sequence[str], None] = None, estimator: Optional[str] = None,
                 observation: Union[str, Sequence[str]] = "divergence", action: str = "thrust",
                 device: Any = "cpu", overrides: Sequence[str] = (), reward: Any = None,
                 clip_actions: bool = False, setpoint_gain_ns: float = SETPOINT_GAIN_NS,
                 autoreset_mode: Union[AutoresetMode, str, None] = None, start_dispersion: float = 0.05,
                 array_api: str = "numpy"):
        self._names = obs_mod.parse_observation(observation)
        self.autoreset_mode = _autoreset_mode(autoreset_mode)
        check_device(device, "device")
        if num_envs is not None and not (isinstance(num_envs, (int, np.integer)) and not isinstance(num_envs, bool)
                                         and 1 <= num_envs <= MAX_NUM_ENVS):
            raise ValueError(f"num_envs must be an integer in [1, {MAX_NUM_ENVS}] or None, got {num_envs!r}")
        self.metadata = {**type(self).metadata, "autoreset_mode": self.autoreset_mode}
        self._dispersion = check_range("start_dispersion", start_dispersion, 0.0, 0.3)
        self.array_api = check_choice("array_api", array_api, ("numpy", "torch"))
        self.cfg = _resolve_config(config, overrides, estimator, device)
        if num_envs is not None:  # the memory estimate of the batch, before anything is built
            try:
                check_memory(self.cfg, batch_size=int(num_envs))
            except ConfigError as exc:
                raise ValueError(f"num_envs={num_envs}: {exc}") from None
        if not isinstance(clip_actions, (bool, np.bool_)):  # a string 'no' is truthy: it clipped
            raise ValueError(f"clip_actions must be True or False, got {clip_actions!r}")
        self._spec = action_spec(action, self.cfg, bool(clip_actions), setpoint_gain_ns)
        self._reward = _reward_config(reward)
        self._sites = _sites_arg(sites)
        self._num_envs_arg = None if num_envs is None else int(num_envs)
        self._device = torch.device(device)
        self._seed = int(self.cfg.simulation.seed)
        self._build(self._seed)
        self.num_envs = self.stages.batch_size
        hw = (int(self.cfg.camera.height_px), int(self.cfg.camera.width_px))
        self._hw = hw
        self.single_observation_space = obs_mod.single_space(self._names, *hw)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.single_action_space = self._spec.space()
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        B, dev = self.num_envs, self._device
        self._env_seed = torch.arange(B, dtype=torch.int64, device=dev) + self._seed
        self._episode = torch.zeros(B, dtype=torch.int64, device=dev)
        self._autoreset = torch.zeros(B, dtype=torch.bool, device=dev)
        self._state = self._sensed = self._obs = None

    # ------------------------------------------------------------------ building
    def _build(self, seed: int) -> None:
        """(Re)build the stages for master seed ``seed`` (the layout's dispersions depend on it)."""
        cfg = copy.deepcopy(self.cfg)
        cfg.simulation.seed = int(seed)
        layout = fit_layout(cfg, self._sites, self._num_envs_arg)
        old = getattr(self, "stages", None)
        reuse = old is not None and old.renderer is not None and old.layout.scene_names == layout.scene_names
        self.stages = build_stages(cfg, layout, self._device, renderer=old.renderer if reuse else None)
        self._seed = int(seed)
        p = self.stages.params
        self._tau0 = p.tau0_s.to(self._device)
        self._c2 = float(p.c2)
        rc = self._reward
        self._tau_min = float(rc.tau_min_s) if rc.tau_min_s is not None else 2.0 / cfg.simulation.crash_divergence

    @property
    def layout(self):
        """The :class:`~dvsland.layout.BatchLayout` flown (site, seed, ... of each element)."""
        return self.stages.layout

    @property
    def action_spec(self):
        """The :class:`~dvsland.envs.actions.ActionSpec` (mode, range, thrust range)."""
        return self._spec

    @property
    def state(self):
        """The loop's current :class:`~dvsland.sim.LoopState` (None before :meth:`reset`)."""
        return self._state

    # ------------------------------------------------------------------ reset
    def reset(self, *, seed: Union[int, Sequence[int], None] = None, options: Optional[dict] = None):
        """Restart every descent, or those of ``options["reset_mask"]``.

        Args:
            seed: None (the current seeds' episodes again, from episode 0), an int s (env i gets
                s + i; a new s also rebuilds the layout's dispersions for master seed s) or one int
                per env.
            options: None, or ``{"reset_mask": (B,) bool}``: restart only those envs (the others'
                state and observation are unchanged; ``seed`` then seeds only those).

        Returns:
            (observation batch, info dict of (B,) arrays).
        """
        mask = _reset_mask(options, self.num_envs)
        if mask is not None and self._state is None:
            raise RuntimeError("reset(options={'reset_mask': ...}) needs a first reset() of every env")
        seeds = self._seeds(seed)  # checked before anything changes
        if isinstance(seed, (int, np.integer)) and mask is None:
            super().reset(seed=int(seed))
            if int(seed) != self._seed:
                self._build(int(seed))
        if mask is None:
            self._env_seed, self._episode = seeds, torch.zeros_like(self._episode)
            z0, v0, noise = self._starts()
            self._state = init_state(self.stages, z_m=z0, v_mps=v0)._replace(noise_seed=noise)
            self._autoreset = torch.zeros_like(self._autoreset)
            return self._sense_all(None)
        m = mask.to(self._device)
        self._env_seed = torch.where(m, seeds, self._env_seed)
        self._episode = torch.where(m, torch.zeros_like(self._episode), self._episode)
        self._state = self._restart(self._state, m)
        self._autoreset = self._autoreset & ~m
        return self._sense_all(m)

    def _seeds(self, seed) -> torch.Tensor:
        """(B,) int64 env seeds for ``seed`` (None: the current ones)."""
        B = self.num_envs
        if seed is None:
            return self._env_seed
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            if not 0 <= int(seed) < 2 ** 62 - B:
                raise ValueError(f"seed must be an int in [0, 2**62 - num_envs), got {seed!r}")
            return (torch.arange(B, dtype=torch.int64) + int(seed)).to(self._device)
        try:
            vals = [int(v) for v in seed] if len(seed) == B and all(
                isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in seed) else None
        except TypeError:
            vals = None
        if vals is None:
            raise ValueError(f"seed must be None, an int or {B} ints (one per env), got {seed!r}")
        if not all(0 <= v < 2 ** 62 for v in vals):
            raise ValueError(f"seed must lie in [0, 2**62) per env, got {vals}")
        return torch.as_tensor(vals, dtype=torch.int64).to(self._device)

    def _starts(self):
        """(z0_m, v0_mps, noise_seed) (B,) of each env's current episode: the layout's start
        dispersed by counter-based draws of (env seed, episode) (:func:`dvsland.sim.dispersed_start`)."""
        L, dev, f64 = self.stages.layout, self._device, torch.float64
        sig = self._dispersion
        if sig == 0:
            return L.tensor("z0_m", dev, f64), L.tensor("v0_mps", dev, f64), L.tensor("seed", dev, torch.int64)
        keys = (self._env_seed, self._episode)
        z0, v0 = dispersed_start(self.stages, keys, sig, sig)
        return z0, v0, (hash_bits(*keys, 3) << 31) ^ hash_bits(*keys, 4)

    def _restart(self, state, mask: torch.Tensor):
        """``state`` with the envs of ``mask`` at the start of their next episode."""
        z0, v0, noise = self._starts()
        return reset_where(self.stages, state, mask, z_m=z0, v_mps=v0, seed=noise)

    def _sense_all(self, mask: Optional[torch.Tensor]):
        """Sense the current state; the observation (of ``mask``'s envs; all when None) and info."""
        self._sensed = sense_step(self.stages, self._state)
        out = self._sensed.out
        obs = self._observe(out, out.t_flight_s, out.m_kg)
        if mask is not None and self._obs is not None:
            obs = obs_mod.take_rows(obs, self._obs, ~mask)
        self._obs = obs
        none = torch.zeros_like(self._autoreset)
        info = self._info(self._state, out.thrust_n, none, out.t_flight_s, ended=none, restart=none)
        return self._export_obs(obs), self._export_info(info)

    # ------------------------------------------------------------------ step
    def step(self, actions):
        """Fly one control step of every flying descent with ``actions``.

        Args:
            actions: (B, 1) or (B,) in the action mode's units and range.

        Returns:
            (observations, rewards (B,) float64, terminated (B,) bool, truncated (B,) bool, info):
            info holds (B,) arrays ``outcome`` (str: ``running``, the outcome name on the step a
            descent ends, ``reset`` on a NEXT_STEP restart, ``ended`` while a DISABLED env waits for
            its reset), ``z_m``, ``v_mps``, ``m_kg``, ``t_s`` (flight time after the step),
            ``thrust_n`` (what flew; 0 where the action was ignored), ``controller_thrust_n`` (the
            shipped law's command for the returned observation; NaN where none), ``d_target`` (1/s),
            ``ignored`` (bool: this step ignored the action), ``episode`` (int) and, in SAME_STEP
            mode, ``final_obs`` / ``final_info`` / ``_final_obs``.

        Raises:
            RuntimeError: before :meth:`reset`. ValueError: an invalid action (see
            :func:`~dvsland.envs.actions.check_action`).
        """
        if self._state is None:
            raise RuntimeError("LandingVectorEnv.step called before reset()")
        B = self.num_envs
        a = check_action(self._spec, actions, B)
        state, out = self._state, self._sensed.out
        g = self.stages.settings.g_mps2
        u = to_thrust(self._spec, a.to(self._device), state.m_kg, g, out.d_filtered)
        flying = state.active
        u = torch.where(flying, u, torch.zeros_like(u))
        nxt, _ = act_step(self.stages, self._sensed, thrust=u)
        return self._finish(state, nxt, u, flying)

    def _finish(self, state, nxt, u, flying):
        """Reward, ends, restarts, the next sensing and observation after ``state`` -> ``nxt``."""
        ended = flying & ~nxt.active
        t1 = nxt.flight_step.to(torch.float64) * self.stages.settings.dt_s
        d_true = nxt.v_mps / nxt.z_m
        d_tgt = divergence_target(t1, self._tau0, self._c2, self._tau_min)
        reward = step_reward(self._reward, self.stages.settings.dt_s, d_true, d_tgt, nxt.v_mps, flying, ended,
                             nxt.outcome)
        term, trunc = episode_ends(ended, nxt.outcome)
        mode = self.autoreset_mode
        restart = self._autoreset if mode == AutoresetMode.NEXT_STEP else (
            ended if mode == AutoresetMode.SAME_STEP else torch.zeros_like(ended))
        final = None
        if mode == AutoresetMode.SAME_STEP and bool(ended.any()):  # one host sync per step in this mode
            final = self._final(nxt, ended, d_true, t1, u, d_tgt)
        codes = nxt.outcome  # how the ended descents ended (before a same-step restart clears it)
        if bool(restart.any()):  # one host sync per step: restart only when some episode is over
            self._episode = self._episode + restart.to(torch.int64)
            nxt = self._restart(nxt, restart)
        self._autoreset = ended if mode == AutoresetMode.NEXT_STEP else torch.zeros_like(ended)
        self._state = nxt
        ignored = ~flying
        obs, ctl = self._next_obs(nxt, ended, restart, d_true, t1, ignored)
        t_info = torch.where(restart, torch.zeros_like(t1), t1)
        info = self._info(nxt, ctl, ignored, t_info, thrust=u, d_target=d_tgt, ended=ended, restart=restart,
                          outcome=codes)
        info = self._export_info(info)
        if final is not None:
            info.update(final)
        return (self._export_obs(obs), self._export(reward), self._export(term), self._export(trunc), info)

    def _next_obs(self, nxt, ended, restart, d_true, t1, ignored: torch.Tensor):
        """Sense ``nxt`` (when anything flies) and build the observation batch; (obs, law's thrust).
        A descent that ended at this step keeps the last sensing it had while flying; one that had
        ended before (DISABLED mode, waiting for its reset) keeps its whole last observation."""
        if bool(nxt.active.any()):
            self._sensed = sense_step(self.stages, nxt)
            out = self._sensed.out
            obs = self._observe(out, out.t_flight_s, nxt.m_kg)
            ctl = torch.where(nxt.active, out.thrust_n, torch.full_like(out.thrust_n, math.nan))
        else:  # nothing flies on: no sensing; the final observation needs only the true state
            out = self._sensed.out._replace(t_s=float(t1.max()), d_true=d_true, m_kg=nxt.m_kg)
            self._sensed = self._sensed._replace(state=nxt, out=out)
            obs = self._observe(out, t1, nxt.m_kg)
            ctl = torch.full_like(d_true, math.nan)
        obs = obs_mod.hold_sensing(obs, self._obs, ended & ~restart)  # a finished camera is frozen
        obs = obs_mod.take_rows(obs, self._obs, ignored & ~restart)
        self._obs = obs
        return obs, ctl

    def _final(self, nxt, ended, d_true, t1, u, d_tgt) -> dict:
        """SAME_STEP: the ended envs' own last observation and info, before their restart."""
        out = self._sensed.out._replace(d_true=d_true, m_kg=nxt.m_kg)
        obs = obs_mod.hold_sensing(self._observe(out, t1, nxt.m_kg), self._obs, torch.ones_like(ended))
        none = torch.zeros_like(ended)
        info = self._info(nxt, torch.full_like(d_true, math.nan), none, t1, thrust=u, d_target=d_tgt, ended=ended,
                          restart=none)
        if self.array_api == "torch":
            return {"final_obs": obs_mod.pack(self._names, obs), "final_info": info, "_final_obs": ended,
                    "_final_info": ended}
        info = self._export_info(info)
        packed = obs_mod.pack(self._names, obs_mod.to_numpy(obs))
        e = ended.cpu().numpy()
        final_obs = np.empty(self.num_envs, dtype=object)
        final_info = np.empty(self.num_envs, dtype=object)
        for i in np.flatnonzero(e):
            final_obs[i] = _row(packed, i)
            final_info[i] = {k: v[i] for k, v in info.items()}
        return {"final_obs": final_obs, "final_info": final_info, "_final_obs": e.copy(), "_final_info": e.copy()}

    # ------------------------------------------------------------------ helpers
    def _observe(self, out, t_s: torch.Tensor, m_kg: torch.Tensor):
        d_tgt = divergence_target(t_s, self._tau0, self._c2, self._tau_min)
        hover = hover_fraction(self._spec, m_kg, self.stages.settings.g_mps2)
        t_frac = torch.as_tensor(t_s, dtype=torch.float64, device=d_tgt.device).expand_as(d_tgt)
        ctx = torch.stack((d_tgt, hover, t_frac / self.stages.settings.t_max_s), dim=1)
        return obs_mod.observe(self._names, out, ctx, self._hw)

    def _info(self, state, ctl, ignored, t_s, thrust=None, d_target=None, ended=None, restart=None,
              outcome=None) -> dict:
        """The info of a step as (B,) tensors on the loop's device (no host sync)."""
        B = self.num_envs
        outcome = state.outcome if outcome is None else outcome
        if d_target is None:
            d_target = divergence_target(t_s, self._tau0, self._c2, self._tau_min)
        f64 = torch.float64
        return {"outcome_code": torch.where(ended, outcome, torch.zeros_like(outcome)),
                "z_m": state.z_m, "v_mps": state.v_mps, "m_kg": state.m_kg,
                "t_s": torch.as_tensor(t_s, dtype=f64, device=state.z_m.device).expand(B),
                "thrust_n": torch.zeros_like(state.z_m) if thrust is None else thrust.to(f64),
                "controller_thrust_n": ctl.to(f64), "d_target": d_target.to(f64), "ignored": ignored,
                "restarted": restart, "episode": self._episode}

    def _export_info(self, info: dict) -> dict:
        """The info as the API returns it: tensors (``array_api="torch"``) or numpy arrays with the
        outcome's name per env (``running``, the outcome's name on its end, ``reset``, ``ended``)."""
        if self.array_api == "torch":
            return dict(info)
        out = {k: v.detach().cpu().numpy().copy() for k, v in info.items() if k not in ("outcome_code", "restarted")}
        code, restart = info["outcome_code"].cpu().numpy(), info["restarted"].cpu().numpy()
        names = np.array([OUTCOMES[int(c)] for c in code], dtype=object)
        names[out["ignored"]] = "ended"
        names[restart & out["ignored"]] = "reset"
        out["outcome"] = names
        return out

    def _export(self, t: torch.Tensor):
        return t if self.array_api == "torch" else t.detach().cpu().numpy()

    def _export_obs(self, obs: dict):
        """The observation batch as the API returns it (tensors stay on the device in torch mode)."""
        return obs_mod.pack(self._names, dict(obs) if self.array_api == "torch" else obs_mod.to_numpy(obs))

    def close_extras(self, **kwargs) -> None:
        self._state = self._sensed = self._obs = None


def _autoreset_mode(mode) -> AutoresetMode:
    if mode is None:
        return LandingVectorEnv.metadata["autoreset_mode"]
    if isinstance(mode, AutoresetMode):
        return mode
    known = {k: m for m in AutoresetMode for k in (m.name.lower(), m.value.lower())}
    if isinstance(mode, str) and mode.lower() in known:
        return known[mode.lower()]
    names = [m.name.lower() for m in AutoresetMode]
    raise ValueError(f"autoreset_mode must be one of {names} (or a gymnasium AutoresetMode), got {mode!r}")


def _reward_config(reward) -> RewardConfig:
    """``reward`` (None, a RewardConfig or a mapping of its fields) as a RewardConfig; ValueError
    naming ``reward`` and the allowed keys otherwise."""
    if isinstance(reward, RewardConfig):
        return reward
    if reward is None:
        return RewardConfig()
    if not isinstance(reward, Mapping):
        raise ValueError(f"reward must be None, a RewardConfig or a mapping of its fields, got {type(reward).__name__}")
    check_keys("reward", reward, RewardConfig.__dataclass_fields__)
    return RewardConfig(**reward)


def _sites_arg(sites):
    """``sites`` (None, ``"A,D"`` or a sequence of site names) as a list of names or None."""
    if sites is None:
        return None
    if isinstance(sites, str):
        return sites.split(",")
    if not isinstance(sites, (list, tuple)) or not all(isinstance(s, str) for s in sites):
        raise ValueError(f"sites must be None, 'A,D' or a list of site names, got {sites!r}")
    return list(sites)


def _reset_mask(options, B: int) -> Optional[torch.Tensor]:
    """``options["reset_mask"]`` as a (B,) bool tensor, or None (every env)."""
    if not options:
        return None
    if not isinstance(options, Mapping):
        raise ValueError(f"options must be None or a dict such as {{'reset_mask': ...}}, got {options!r}")
    unknown = sorted(set(options) - {"reset_mask"})
    if unknown:
        raise ValueError(f"options: unknown keys {unknown}; supported: ['reset_mask']")
    m = np.asarray(options["reset_mask"])
    if m.shape != (B,) or m.dtype != np.bool_:
        raise ValueError(f"options['reset_mask'] must be a ({B},) bool array (one entry per env), got shape "
                         f"{m.shape} dtype {m.dtype}")
    return torch.as_tensor(m)


def _row(obs, i: int):
    return {k: v[i].copy() for k, v in obs.items()} if isinstance(obs, dict) else obs[i].copy()


def _resolve_config(config, overrides, estimator, device) -> Config:
    """A checked private copy of the config, with ``estimator`` and ``device`` applied
    (``overrides``: a ``section.key=value`` string or a sequence of them)."""
    if isinstance(overrides, str):
        overrides = [overrides]
    elif not isinstance(overrides, (list, tuple)) or not all(isinstance(o, str) for o in overrides):
        raise ValueError(f"overrides must be 'section.key=value' strings, got {overrides!r}")
    if isinstance(config, Config):
        if overrides:
            raise ValueError("overrides apply to a config name or path; edit the Config object instead")
        cfg = copy.deepcopy(config)
    elif config is None or isinstance(config, str) or hasattr(config, "__fspath__"):
        cfg = load_config(config or "paper", list(overrides))
    else:
        raise ValueError(f"config must be a Config, a config name or path, or None, got {type(config).__name__}")
    if estimator is not None:
        if not isinstance(estimator, str):
            raise ValueError(f"estimator must be an estimator name, got {type(estimator).__name__}")
        cfg.estimator.name = estimator
    cfg.simulation.device = str(torch.device(device))
    cfg = validate_config(cfg)
    check_names(cfg)
    return cfg
