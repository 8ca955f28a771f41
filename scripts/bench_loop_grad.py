"""The cost of differentiating through the closed loop: CPU time per descent-step of the plain step
(no graph) against a window flown with ``grad=True`` plus its backward pass, and the autograd
graph's saved tensors per descent-step (the memory a window holds until its backward).

    OMP_NUM_THREADS=1 python scripts/bench_loop_grad.py --controller div_gs --steps 200

The batch is ``paper_montecarlo`` with the oracle on sites D-G (``--seeds`` seeds x 2 settings x 4
sites), flown from the planned starts; one torch thread. Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from dvsland.config import load_config
from dvsland.learn.loop_loss import LossWeights, window_loss
from dvsland.learn.loop_trainables import make_trainable
from dvsland.sim import init_state, loop_step
from dvsland.stages import build_stages


def plain_cpu_s(stages, steps: int) -> float:
    """CPU s of ``steps`` plain loop steps (no graph)."""
    state = init_state(stages)
    with torch.no_grad():
        c0 = time.process_time()
        for _ in range(steps):
            state, _ = loop_step(stages, state)
        return time.process_time() - c0


def grad_cpu_s(stages, trainable, steps: int):
    """(CPU s of a ``steps``-step window with grad=True and its backward, bytes the graph saved)."""
    saved = [0]

    def pack(t):
        saved[0] += t.numel() * t.element_size()
        return t

    c0 = time.process_time()
    trainable.apply(stages.controller)
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        loss, _, _ = window_loss(stages, init_state(stages), steps, LossWeights(fuel=0.05))
    loss.backward()
    return time.process_time() - c0, saved[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--controller", default="div_gs", choices=("div_gs", "tau_p", "policy"))
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = load_config("paper_montecarlo", ["estimator.name=oracle", "dispersion.terrain_variants=1",
                                           f"simulation.n_seeds={a.seeds}", f"controller.name={a.controller}"])
    stages = build_stages(cfg, "D,E,F,G")
    trainable = make_trainable(stages, "policy" if a.controller == "policy" else "law")
    plain_cpu_s(stages, 5)  # warm-up
    plain = min(plain_cpu_s(stages, a.steps) for _ in range(a.repeats))
    runs = [grad_cpu_s(stages, trainable, a.steps) for _ in range(a.repeats)]
    grad, saved = min(r[0] for r in runs), runs[0][1]
    ds = a.steps * stages.batch_size
    print(json.dumps({"controller": a.controller, "batch": stages.batch_size, "steps": a.steps,
                      "plain_us_per_descent_step": round(plain / ds * 1e6, 2),
                      "grad_fwd_bwd_us_per_descent_step": round(grad / ds * 1e6, 2),
                      "ratio": round(grad / plain, 2), "graph_bytes_per_descent_step": round(saved / ds)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
