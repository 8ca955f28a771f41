"""Count the host synchronisations of the loop's step: ``python -m dvsland.bench.syncs``.

A host synchronisation is a call that needs a tensor's value on the host: ``item``, ``tolist``,
``bool(t)``, ``int(t)``, ``float(t)``, ``nonzero``, ``cpu``, ``numpy``, ``repeat_interleave``
without ``output_size``, and indexing with a bool mask (its result's size depends on the values).
On CUDA each one stalls the stream; on CPU they are counted the same way (:class:`SyncCounter`, a
:class:`torch.overrides.TorchFunctionMode`), so the count can be checked without a GPU. On CUDA,
``torch.cuda.set_sync_debug_mode("warn")`` shows the same calls.

    python -m dvsland.bench.syncs --estimators oracle,dpr,cmax,snn,learned --steps 5

prints the syncs per step of each estimator's loop (paper, sites D, one torch thread), by call.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from typing import Dict

import torch
from torch.overrides import TorchFunctionMode

#: the tensor calls that read a value on the host
SYNC_CALLS = frozenset({"item", "tolist", "__bool__", "__int__", "__float__", "__index__", "nonzero", "cpu",
                        "numpy", "argwhere", "masked_select", "unique", "unique_consecutive", "repeat_interleave"})


class SyncCounter(TorchFunctionMode):
    """Counts :data:`SYNC_CALLS` (and bool-mask indexing) made inside the ``with`` block.

    Attributes:
        calls: Counter of call names.
    """

    def __init__(self):
        super().__init__()
        self.calls: Counter = Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name == "repeat_interleave" and (kwargs or {}).get("output_size") is not None:
            pass  # sized by the caller: no sync
        elif name in SYNC_CALLS:
            self.calls[name] += 1
        elif name == "__getitem__" and len(args) > 1 and _has_bool_mask(args[1]):
            self.calls["bool_index"] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return int(sum(self.calls.values()))


def _has_bool_mask(index) -> bool:
    items = index if isinstance(index, tuple) else (index,)
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in items)


def loop_syncs(estimator: str, steps: int = 5, preset: str = "paper", sites: str = "D", warmup: int = 3,
               overrides=()) -> Dict:
    """Host syncs per ``loop_step`` of ``preset`` with ``estimator`` (after ``warmup`` steps)."""
    from dvsland.config import load_config
    from dvsland.sim import init_state, loop_step
    from dvsland.stages import build_stages

    stages = build_stages(load_config(preset, [f"estimator.name={estimator}", "render.threads=1", *overrides]), sites)
    state = init_state(stages)
    for _ in range(warmup):
        state, _ = loop_step(stages, state)
    with SyncCounter() as c:
        for _ in range(steps):
            state, _ = loop_step(stages, state)
    return {"estimator": estimator, "preset": preset, "B": stages.batch_size, "steps": steps,
            "syncs_per_step": c.total / steps, "by_call": {k: v / steps for k, v in sorted(c.calls.items())}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--estimators", default="oracle,dpr,cmax,snn,learned")
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--preset", default="paper")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    for est in a.estimators.split(","):
        print(json.dumps(loop_syncs(est, a.steps, a.preset)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
