"""``LandingEnv``: one descent as a plain ``gymnasium.Env`` (a :class:`LandingVectorEnv` with B = 1)."""

from __future__ import annotations

from typing import Optional

import gymnasium as gym
import numpy as np

from .vector import LandingVectorEnv


class LandingEnv(gym.Env):
    """One descent: the first element of the config's layout (choose it with ``sites="D"``).

    Takes the keyword arguments of :class:`LandingVectorEnv` except ``num_envs``. Observations,
    actions, reward and ends are those of one element; ``info`` holds its values as scalars. After
    ``terminated`` or ``truncated``, call :meth:`reset`.
    """

    metadata = {"render_modes": []}

    def __init__(self, **kwargs):
        if "num_envs" in kwargs:
            raise ValueError("LandingEnv flies one descent; use LandingVectorEnv for num_envs")
        self.vec = LandingVectorEnv(num_envs=1, **kwargs)
        self.observation_space = self.vec.single_observation_space
        self.action_space = self.vec.single_action_space

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        """Restart the descent (``seed``: see :meth:`LandingVectorEnv.reset`); (observation, info)."""
        super().reset(seed=seed)
        obs, info = self.vec.reset(seed=seed, options=options)
        return _first(obs), _first(info)

    def step(self, action):
        """(observation, reward, terminated, truncated, info) of one control step; ``action``
        shape (1,) (or a scalar) in the action mode's units."""
        obs, rew, term, trunc, info = self.vec.step(np.reshape(np.asarray(action, dtype=np.float64), (1,)))
        return _first(obs), float(rew[0]), bool(term[0]), bool(trunc[0]), _first(info)

    def close(self):
        self.vec.close()


def _first(x):
    """Element 0 of a batched observation or info (dicts recursively; numpy scalars to Python)."""
    if isinstance(x, dict):
        return {k: _first(v) for k, v in x.items()}
    v = x[0]
    if isinstance(v, np.ndarray):
        return v
    return v.item() if isinstance(v, np.generic) else v
