"""Env steps per second of the gymnasium vector env at B = 64, with and without per-descent resets.

Both runs fly ``paper`` D-G x 2 settings x 8 seeds (B = 64) with the oracle, the agent sending the
shipped law's commands (``action="thrust_n"``), one torch thread:

- ``no reset``: ``autoreset_mode="disabled"``, the first ``--steps`` steps of one batch episode
  (every descent flies from step 0; no restart happens before the first end at ~97 s);
- ``per-descent reset``: ``autoreset_mode="next_step"`` over ``--steps`` steps from ~96 s into the
  episode on, where the 64 descents end at different steps and each restarts on its own (the count
  of restarts is printed).

    python scripts/bench_env_reset.py --steps 600
    python scripts/bench_env_reset.py --steps 300 --estimator learned   # with the event camera

Prints one JSON line per mode: steps, wall s, CPU s, env steps/s, descent-steps/s, restarts.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from dvsland.envs import LandingVectorEnv

OVERRIDES = ["simulation.n_seeds=8", "render.threads=1", "logging.tensorboard=false", "logging.figures=false"]


def fly(env, n: int, info) -> tuple:
    """``n`` env steps with the law's commands; (steps, wall s, CPU s, restarts, info)."""
    restarts = 0
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(n):
        _, _, _, _, info = env.step(np.nan_to_num(info["controller_thrust_n"]))
        restarts += int((info["outcome"] == "reset").sum())
    return n, time.perf_counter() - t0, time.process_time() - c0, restarts, info


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--estimator", default="oracle", help="an event estimator makes the env render and "
                    "emulate (its restarts restart the event camera too)")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    for mode in ("disabled", "next_step"):
        env = LandingVectorEnv(config="paper", sites="D,E,F,G", estimator=a.estimator, observation="oracle",
                               action="thrust_n", overrides=OVERRIDES, autoreset_mode=mode)
        _, info = env.reset(seed=0)
        if mode == "next_step":  # fly to the region where descents end and restart
            _, _, _, _, info = fly(env, 960, info)
        n, wall, cpu, restarts, _ = fly(env, a.steps, info)
        print(json.dumps({"mode": "no reset" if mode == "disabled" else "per-descent reset", "B": env.num_envs,
                          "estimator": a.estimator,
                          "steps": n, "wall_s": round(wall, 3), "cpu_s": round(cpu, 3),
                          "env_steps_per_s": round(n / wall, 1), "descent_steps_per_s": round(n * env.num_envs / wall),
                          "restarts": restarts}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
