"""``LandingVectorEnv``: B closed-loop descents as one gymnasium ``VectorEnv``.

The env flies the batched loop of :mod:`dvsland.sim` (:func:`~dvsland.sim.init_state` and
:func:`~dvsland.sim.loop_step` in its two halves, :func:`~dvsland.sim.sense_step` and
:func:`~dvsland.sim.act_step`) with the agent's thrust instead of the controller's. Each env step:

1. the action (checked, :mod:`dvsland.envs.actions`) becomes a thrust u (B,) N;
2. the descents fly [t_k, t_k + dt) with u (the step whose sensing the agent saw);
3. reward and episode ends are judged at t_{k+1} (:mod:`dvsland.envs.reward`);
4. the loop senses at t_{k+1} (render, emulate, estimate, filter, and the shipped law's command,
   reported as ``info["controller_thrust_n"]``): the next observation.

The loop senses before the agent acts (``sense_step``) and flies the agent's thrust after it
(``act_step(thrust=u)``); ``loop_step`` is the same two halves with the law's thrust, so an agent
that sends the controller's commands flies exactly the descents of :func:`dvsland.simulate`.

Episodes: all B descents start together. A descent that ends reports ``terminated`` or
``truncated`` once; the loop keeps it frozen. Autoreset is gymnasium's NEXT_STEP mode: the step
after an end returns that element's initial observation (reward 0, both flags False), and the
element then *waits*, its actions ignored and its observation its initial one, with reward 0,
until every descent of the batch has ended; the step after the last end restarts the whole batch
(the stages' state included, from a clone of the initial state: every episode of a seed is the
same batch of descents). ``info["waiting"]`` marks the steps whose action was ignored.
"""

from __future__ import annotations

import copy
import math
from typing import Any, Optional, Sequence, Union

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from dvsland.config import Config, load_config, validate_config
from dvsland.layout import build_layout
from dvsland.sim import OUTCOMES, act_step, clone_state, init_state, sense_step
from dvsland.stages import build_stages, check_names

from . import observations as obs_mod
from .actions import SETPOINT_GAIN_NS, action_spec, check_action, hover_fraction, to_thrust
from .layout import fit_layout
from .reward import RewardConfig, divergence_target, episode_ends, step_reward


class LandingVectorEnv(VectorEnv):
    """B = ``num_envs`` descents of one config, as a gymnasium (>= 1.0) vector env.

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

    Raises:
        ValueError: an unknown ``observation`` or ``action`` (naming the allowed ones), bad
            ``num_envs`` or ``sites``; ConfigError: an invalid config or unknown stage name.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs: Optional[int] = None, config: Union[Config, str, None] = None,
                 sites: Union[str, Sequence[str], None] = None, estimator: Optional[str] = None,
                 observation: Union[str, Sequence[str]] = "divergence", action: str = "thrust",
                 device: Any = "cpu", overrides: Sequence[str] = (), reward: Any = None,
                 clip_actions: bool = False, setpoint_gain_ns: float = SETPOINT_GAIN_NS):
        self._names = obs_mod.parse_observation(observation)
        self.cfg = _resolve_config(config, overrides, estimator, device)
        self._spec = action_spec(action, self.cfg, clip_actions, setpoint_gain_ns)
        self._reward = reward if isinstance(reward, RewardConfig) else RewardConfig(**(reward or {}))
        if num_envs is not None and not (isinstance(num_envs, (int, np.integer)) and num_envs >= 1):
            raise ValueError(f"num_envs must be an integer >= 1 or None, got {num_envs!r}")
        self._sites = sites.split(",") if isinstance(sites, str) else sites
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
        self._state = None
        self._all_done = False

    # ------------------------------------------------------------------ building
    def _build(self, seed: int) -> None:
        """(Re)build the stages for master seed ``seed`` and clone their initial state."""
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
        self._init = clone_state(self.stages, init_state(self.stages))
        self._obs0 = None

    @property
    def layout(self):
        """The :class:`~dvsland.layout.BatchLayout` flown (site, seed, ... of each element)."""
        return self.stages.layout

    @property
    def action_spec(self):
        """The :class:`~dvsland.envs.actions.ActionSpec` (mode, range, thrust range)."""
        return self._spec

    @property
    def reset_observation(self):
        """The initial observation batch of the current seed (what an element shows from the step
        after its end until the batch restarts); None before the first :meth:`reset`. A copy."""
        return None if self._obs0 is None else obs_mod.pack(self._names, copy.deepcopy(self._obs0))

    # ------------------------------------------------------------------ reset
    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        """Restart every descent.

        Args:
            seed: None (the descents of the current seed again, bit for bit) or a master seed:
                ``simulation.seed`` of the layout's element seeds, dispersions and sensor noise
                (the stages are rebuilt when it changes).
            options: not supported (only None or an empty dict).

        Returns:
            (observation batch, info dict of (B,) arrays).
        """
        if options:
            raise ValueError(f"options are not supported (all descents restart together), got {options!r}")
        super().reset(seed=seed)
        if seed is not None and int(seed) != self._seed:
            self._build(int(seed))
        return self._begin()

    def _begin(self):
        """Start the batch from a clone of the initial state and sense its first step."""
        self._state = clone_state(self.stages, self._init)
        self._sensed = sense_step(self.stages, self._state)
        self._out = self._sensed.out
        self._all_done = False
        obs = self._observe(self._out, self._out.t_s, self._out.m_kg)
        if self._obs0 is None:
            self._obs0 = copy.deepcopy(obs)
        self._obs = obs
        B = self.num_envs
        info = self._info(self._state, ["running"] * B, self._out.thrust_n, np.zeros(B, bool), self._out.t_s)
        return obs_mod.pack(self._names, obs), info

    # ------------------------------------------------------------------ step
    def step(self, actions):
        """Fly one control step of every flying descent with ``actions``.

        Args:
            actions: (B, 1) or (B,) in the action mode's units and range.

        Returns:
            (observations, rewards (B,) float64, terminated (B,) bool, truncated (B,) bool, info):
            info holds (B,) arrays ``outcome`` (str: ``running``, the outcome name on the step a
            descent ends, ``waiting`` while it waits for the batch to restart), ``z_m``, ``v_mps``,
            ``m_kg``, ``t_s`` (after the step), ``thrust_n`` (what flew; 0 where waiting),
            ``controller_thrust_n`` (the shipped law's command for the returned observation; NaN
            where none), ``d_target`` (1/s) and ``waiting`` (bool: this step ignored the action).

        Raises:
            RuntimeError: before :meth:`reset`. ValueError: an invalid action (see
            :func:`~dvsland.envs.actions.check_action`).
        """
        if self._state is None:
            raise RuntimeError("LandingVectorEnv.step called before reset()")
        B = self.num_envs
        if self._all_done:  # the step after the last descent ended: restart the batch
            obs, info = self._begin()
            info["waiting"][:] = True
            info["outcome"][:] = "waiting"
            return obs, np.zeros(B), np.zeros(B, bool), np.zeros(B, bool), info
        a = check_action(self._spec, actions, B)
        state, out = self._state, self._out
        g = self.stages.settings.g_mps2
        u = to_thrust(self._spec, a.to(self._device), state.m_kg, g, out.d_filtered)
        u = torch.where(state.active, u, torch.zeros_like(u))
        nxt = self._fly(state, out, u)
        return self._finish(state, nxt, u)

    def _fly(self, state, out, u):
        """The state after this step flown with thrust ``u`` (B,) N (0 where not flying)."""
        nxt, _ = act_step(self.stages, self._sensed, thrust=u)
        return nxt

    def _finish(self, state, nxt, u):
        """Reward, ends, the next sensing and observation after flying ``state`` -> ``nxt``."""
        flying, t1 = state.active, nxt.step * self.stages.settings.dt_s
        ended = flying & ~nxt.active
        d_true = nxt.v_mps / nxt.z_m
        d_tgt = divergence_target(t1, self._tau0, self._c2, self._tau_min)
        reward = step_reward(self._reward, self.stages.settings.dt_s, d_true, d_tgt, nxt.v_mps, flying, ended,
                             nxt.outcome)
        term, trunc = episode_ends(ended, nxt.outcome)
        self._state = nxt
        if bool(nxt.active.any()):
            self._sensed = sense_step(self.stages, nxt)
            self._out = self._sensed.out
            sensed, ctl = self._out, self._out.thrust_n
        else:  # nothing flies on: no sensing; the final observation needs only the true state
            self._all_done = True
            sensed = self._out._replace(t_s=t1, d_true=d_true, m_kg=nxt.m_kg)
            ctl = torch.full_like(u, math.nan)
        obs = self._observe(sensed, t1, nxt.m_kg)
        ended_np, waiting = ended.cpu().numpy(), (~flying).cpu().numpy()
        obs = obs_mod.hold_sensing(obs, self._obs, ended_np)
        obs = obs_mod.take_rows(obs, self._obs0, waiting)
        self._obs = obs
        names = np.array([OUTCOMES[int(c)] if e else "running" for c, e in zip(nxt.outcome.tolist(), ended_np)],
                         dtype=object)
        names[waiting] = "waiting"
        info = self._info(nxt, names, ctl, waiting, t1, thrust=u, d_target=d_tgt)
        return (obs_mod.pack(self._names, obs), reward.cpu().numpy(), term.cpu().numpy(), trunc.cpu().numpy(),
                info)

    # ------------------------------------------------------------------ helpers
    def _observe(self, out, t_s: float, m_kg: torch.Tensor):
        d_tgt = divergence_target(t_s, self._tau0, self._c2, self._tau_min)
        hover = hover_fraction(self._spec, m_kg, self.stages.settings.g_mps2)
        ctx = torch.stack((d_tgt, hover, torch.full_like(d_tgt, t_s / self.stages.settings.t_max_s)), dim=1)
        return obs_mod.observe(self._names, out, ctx, self._hw)

    def _info(self, state, outcome, ctl, waiting, t_s: float, thrust=None, d_target=None) -> dict:
        B = self.num_envs
        f = (lambda t: t.detach().to(torch.float64).cpu().numpy())
        if d_target is None:
            d_target = divergence_target(t_s, self._tau0, self._c2, self._tau_min)
        return {"outcome": np.asarray(outcome, dtype=object), "z_m": f(state.z_m), "v_mps": f(state.v_mps),
                "m_kg": f(state.m_kg), "t_s": np.full(B, float(t_s)),
                "thrust_n": np.zeros(B) if thrust is None else f(thrust), "controller_thrust_n": f(ctl),
                "d_target": f(d_target), "waiting": np.asarray(waiting, dtype=bool)}

    def close_extras(self, **kwargs) -> None:
        self._state = self._sensed = self._out = None


def _resolve_config(config, overrides, estimator, device) -> Config:
    """A checked private copy of the config, with ``estimator`` and ``device`` applied."""
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
