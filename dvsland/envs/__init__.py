"""Gymnasium environments over the batched closed loop (docs/envs.md).

- :class:`LandingVectorEnv`: B descents as one ``gymnasium.vector.VectorEnv`` (NEXT_STEP
  autoreset; the batch restarts together once every descent has ended).
- :class:`LandingEnv`: one descent as a ``gymnasium.Env``.

Importing this package registers ``dvsland/Landing-v0``::

    import gymnasium as gym
    import dvsland.envs  # noqa: F401 - registers the id

    envs = gym.make_vec("dvsland/Landing-v0", num_envs=8, vectorization_mode="vector_entry_point",
                        config="paper", sites="D,E,F,G", estimator="oracle", observation="oracle")
    env = gym.make("dvsland/Landing-v0", sites="D", estimator="oracle", observation="oracle")
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

from .actions import ACTIONS, UNBOUNDED_HIGH_HOVERS, ActionSpec
from .observations import DIVERGENCE_FIELDS, OBSERVATIONS, ORACLE_FIELDS
from .reward import RewardConfig
from .single import LandingEnv
from .vector import LandingVectorEnv

#: the registered id of the environment
ENV_ID = "dvsland/Landing-v0"

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="dvsland.envs.single:LandingEnv",
             vector_entry_point="dvsland.envs.vector:LandingVectorEnv")

__all__ = ["LandingVectorEnv", "LandingEnv", "RewardConfig", "ActionSpec", "ENV_ID", "OBSERVATIONS", "ACTIONS",
           "DIVERGENCE_FIELDS", "ORACLE_FIELDS", "UNBOUNDED_HIGH_HOVERS"]
