"""The batched env as a stable-baselines3 ``VecEnv``: :func:`sb3_vec_env`.

stable-baselines3 expects same-step autoreset: on the step an episode ends, ``step_wait`` returns
the next episode's first observation and puts the end's own in ``info["terminal_observation"]``.
That is :class:`~dvsland.envs.LandingVectorEnv` with ``autoreset_mode="same_step"``, so the adapter
only renames: no copy of the loop, no Python loop over the batch beyond the ended envs' infos.
stable-baselines3 is optional (the ``rl`` extra); it is imported when the adapter is made.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode


def sb3_vec_env(env: Any):
    """A stable-baselines3 ``VecEnv`` over ``env`` (a :class:`~dvsland.envs.LandingVectorEnv` made
    with ``autoreset_mode="same_step"``). ``infos[i]`` of an ended env holds
    ``terminal_observation``, ``TimeLimit.truncated``, ``episode`` (``r`` return, ``l`` length) and
    ``outcome``.

    Raises:
        ValueError: ``env`` does not autoreset in the same step (names ``autoreset_mode``).
        ImportError: stable-baselines3 is not installed (``pip install 'dvsland[rl]'``).
    """
    if getattr(env, "autoreset_mode", None) != AutoresetMode.SAME_STEP:
        raise ValueError("sb3_vec_env needs LandingVectorEnv(..., autoreset_mode='same_step'), got "
                         f"autoreset_mode={getattr(env, 'autoreset_mode', None)!r}")
    from stable_baselines3.common.vec_env import VecEnv

    class LandingSB3(VecEnv):
        """stable-baselines3's view of one :class:`~dvsland.envs.LandingVectorEnv`."""

        def __init__(self):
            super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)
            self.env, self._seed, self._actions = env, None, None
            self._ret, self._len = np.zeros(env.num_envs), np.zeros(env.num_envs, int)

        def seed(self, seed=None):
            if seed is not None and (not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0):
                raise ValueError(f"seed must be None or an int >= 0 (env i gets seed + i), got {seed!r}")
            self._seed = None if seed is None else int(seed)
            return [None if seed is None else self._seed + i for i in range(self.num_envs)]

        def reset(self):
            obs, _ = self.env.reset(seed=self._seed)
            self._seed = None  # later resets replay from the current env seeds' episodes on
            self._ret[:], self._len[:] = 0, 0
            return obs

        def step_async(self, actions):
            self._actions = np.clip(actions, self.action_space.low, self.action_space.high)

        def step_wait(self):
            obs, rew, term, trunc, info = self.env.step(self._actions)
            self._ret += rew
            self._len += 1
            infos = [{} for _ in range(self.num_envs)]
            done = term | trunc
            for i in np.flatnonzero(done):
                infos[i] = {"terminal_observation": info["final_obs"][i], "TimeLimit.truncated": bool(trunc[i]),
                            "episode": {"r": float(self._ret[i]), "l": int(self._len[i])},
                            "outcome": info["outcome"][i]}
                self._ret[i], self._len[i] = 0.0, 0
            return obs, rew.astype(np.float32), done, infos

        def close(self):
            self.env.close()

        # the batch is one env object: an attribute or a method is the batch's, once per index
        def get_attr(self, name, indices=None):
            return [getattr(self.env, name)] * len(self._indices(indices))

        def set_attr(self, name, value, indices=None):
            if len(set(self._indices(indices))) != self.num_envs:
                raise ValueError(f"set_attr({name!r}): the {self.num_envs} envs are one batch; an attribute is set "
                                 f"for all of them (indices=None), got indices={indices!r}")
            setattr(self.env, name, value)

        def env_method(self, name, *args, indices=None, **kwargs):
            return [getattr(self.env, name)(*args, **kwargs)] * len(self._indices(indices))

        def env_is_wrapped(self, wrapper_class, indices=None):
            return [False] * len(self._indices(indices))

        def _indices(self, indices) -> list:
            """SB3's ``indices`` (None, an int or ints) as a checked list of env indices."""
            idx = list(range(self.num_envs)) if indices is None else (
                [indices] if isinstance(indices, (int, np.integer)) else list(indices))
            bad = [i for i in idx if not isinstance(i, (int, np.integer)) or not 0 <= i < self.num_envs]
            if bad:
                raise ValueError(f"indices must be env indices in [0, {self.num_envs}), got {bad}")
            return idx

    return LandingSB3()


__all__ = ["sb3_vec_env"]
