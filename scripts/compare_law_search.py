"""Gradient through the loop against a derivative-free search, on the same task and budget of
simulated descent-steps: the ``div_gs`` law's constants (lambda_per_s, d_final_per_s) on
``paper_montecarlo`` D-G with the oracle, loss as ``dvsland train-loop --what law`` (landing speed,
failures, fuel), then both results flown on the dispersed descents of an unseen seed.

    OMP_NUM_THREADS=1 python scripts/compare_law_search.py --windows 12 --out logs/law_search.json

- gradient: ``--windows`` whole-descent windows of Adam (lr 2e-2 in log space), each on new
  dispersed starts (:func:`dvsland.learn.loop_train.train_windows`);
- derivative-free: scipy's Nelder-Mead on the same log-constants, each evaluation one whole-descent
  flight of the same batch (fixed dispersed starts), stopped when it has simulated as many
  descent-steps as the gradient did.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
from scipy.optimize import minimize

from dvsland.config import load_config
from dvsland.learn.loop_loss import LossWeights, window_loss
from dvsland.learn.loop_train import TrainLoopRun, TrainLoopSettings, restart_ended, train_windows, validate
from dvsland.learn.loop_trainables import make_trainable
from dvsland.report.stats import wilson_interval
from dvsland.sim import init_state
from dvsland.stages import build_stages

COMMON = ["estimator.name=oracle", "dispersion.terrain_variants=1", "render.threads=1", "controller.name=div_gs"]
LOSS = LossWeights(track=0.0, landing=1.0, fail=25.0, fuel=0.05)


def stages_of(seeds: int, seed: int):
    return build_stages(load_config("paper_montecarlo", COMMON + [f"simulation.n_seeds={seeds}",
                                                                  f"simulation.seed={seed}"]), "D,E,F,G")


def gradient(windows: int, seeds: int) -> dict:
    st = stages_of(seeds, 0)
    tr = make_trainable(st, "law")
    opt = torch.optim.Adam(tr.parameters(), lr=2e-2)
    run = TrainLoopRun()
    s = TrainLoopSettings(what="law", window=0, lr=2e-2, cpu_minutes=1e5, max_windows=windows, loss=LOSS).check()
    c0 = time.process_time()
    train_windows(st, tr, opt, s, run, torch.zeros(st.batch_size, dtype=torch.int64))
    return {"trainable": tr, "steps": run.steps, "cpu_s": time.process_time() - c0, "values": tr.describe()}


def derivative_free(step_budget: int, seeds: int) -> dict:
    st = stages_of(seeds, 0)
    tr = make_trainable(st, "law")
    start = init_state(st)
    start, _ = restart_ended(st, start._replace(active=torch.zeros_like(start.active)),
                             torch.zeros(st.batch_size, dtype=torch.int64), 0, 0.05)
    used = {"steps": 0, "evals": 0, "best": (float("inf"), None)}

    class Budget(Exception):
        pass

    def f(x):
        if used["steps"] >= step_budget:
            raise Budget
        with torch.no_grad():
            for name, v in zip(tr.names, x):
                tr.raw[name].fill_(float(v))
            tr.apply(st.controller)
            loss, terms, _ = window_loss(st, start, 0, LOSS)
        used["steps"] += terms["steps"]
        used["evals"] += 1
        if float(loss) < used["best"][0]:
            used["best"] = (float(loss), np.array(x, dtype=float))
        return float(loss)

    x0 = np.array([float(tr.raw[n].detach()) for n in tr.names])
    c0 = time.process_time()
    try:
        minimize(f, x0, method="Nelder-Mead", options={"initial_simplex": x0 + 0.3 * np.vstack([np.zeros(2),
                                                                                              np.eye(2)])})
    except Budget:
        pass
    with torch.no_grad():  # the search's answer: the best point it evaluated
        for name, v in zip(tr.names, used["best"][1]):
            tr.raw[name].fill_(float(v))
    return {"trainable": tr, "steps": used["steps"], "evals": used["evals"], "cpu_s": time.process_time() - c0,
            "values": tr.describe()}


@torch.no_grad()
def test_loss(test, trainable) -> float:
    """The loss of whole descents of the test batch with the trained values."""
    trainable.apply(test.controller)
    return round(float(window_loss(test, init_state(test), 0, LOSS)[0]), 4)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--windows", type=int, default=12)
    ap.add_argument("--seeds", type=int, default=2, help="training seeds per site and setting")
    ap.add_argument("--test-seed", type=int, default=999)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    test = stages_of(8, a.test_seed)
    rows_trainables = {"config (lambda 1, d_final 0.03)": make_trainable(test, "law")}
    base = validate(test, rows_trainables["config (lambda 1, d_final 0.03)"])
    rows = {"config (lambda 1, d_final 0.03)": {"steps": 0, "cpu_s": 0.0, "values": make_trainable(test, "law").describe(),
                                               "test": base}}
    g = gradient(a.windows, a.seeds)
    rows_trainables["gradient through the loop"] = g["trainable"]
    rows["gradient through the loop"] = {**{k: g[k] for k in ("steps", "cpu_s", "values")},
                                         "test": validate(test, g["trainable"])}
    d = derivative_free(g["steps"], a.seeds)
    rows_trainables["Nelder-Mead (scipy)"] = d["trainable"]
    rows["Nelder-Mead (scipy)"] = {**{k: d[k] for k in ("steps", "evals", "cpu_s", "values")},
                                   "test": validate(test, d["trainable"])}
    for name, r in rows.items():
        r["test_loss"] = test_loss(test, rows_trainables[name])
        r["test"].pop("outcomes", None)
        r["test"]["wilson95"] = [round(x, 3) for x in wilson_interval(r["test"]["landed"], r["test"]["n"])]
        r["cpu_s"] = round(r["cpu_s"], 1)
    text = json.dumps(rows, indent=1)
    print(text)
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
