"""Train a thrust policy by gradients through the closed loop (dvsland.learn.loop_policy) and
evaluate it on dispersed descents of a seed it never trained on.

    python scripts/train_policy_grad.py --cpu-seconds 30 --out logs/policy_grad

Trains on ``paper_montecarlo`` sites D-G (oracle estimate, B = 32: 4 seeds x 2 settings x 4 sites,
every descent restarting with a new dispersed start when it ends) for ``--cpu-seconds`` of process
CPU time, one torch thread; then flies the 64 descents of ``paper_montecarlo`` D-G x 2 settings x 8
seeds of ``--test-seed`` once and writes ``policy.pt`` and ``results.json`` (successes, landing
speeds, simulated steps, CPU time) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from dvsland.config import load_config
from dvsland.learn.loop_policy import evaluate_policy, train_policy
from dvsland.stages import build_stages

SITES = "D,E,F,G"
COMMON = ["estimator.name=oracle", "dispersion.terrain_variants=1", "render.threads=1"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cpu-seconds", type=float, default=30.0)
    ap.add_argument("--window", type=int, default=40, help="steps per truncated-backpropagation window")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--test-seed", type=int, default=999)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    train = build_stages(load_config("paper_montecarlo", COMMON + ["simulation.n_seeds=4",
                                                                   f"simulation.seed={a.seed}"]), SITES)
    run = train_policy(train, seconds=a.cpu_seconds, window=a.window, seed=a.seed, log=print)
    test = build_stages(load_config("paper_montecarlo", COMMON + ["simulation.n_seeds=8",
                                                                  f"simulation.seed={a.test_seed}"]), SITES)
    ev = evaluate_policy(test, run["net"])
    res = {"train_batch": train.batch_size, "windows": run["windows"], "simulated_steps": run["steps"],
           "cpu_s": round(run["cpu_s"], 1), "train_episodes_ended": run["ends"],
           "train_successes": run["successes"], "test_seed": a.test_seed, **ev}
    print(json.dumps({k: v for k, v in res.items() if k not in ("outcomes", "landing_speed_mps")}))
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        torch.save({"kind": "dvsland-loop-policy", "state_dict": run["net"].state_dict()}, out / "policy.pt")
        (out / "results.json").write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
