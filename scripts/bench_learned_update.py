"""CPU time of one ``learned`` update at B rows, one thread, and where it goes.

    python scripts/bench_learned_update.py --batch 18 --d -0.1,-0.3 --modes ",ring,bf16" --repeat 5

Events: random textures zoomed at divergence D (the generalisation check's scene,
scripts/measure_learned_zoom.py), through the config's emulator. For each mode of
``estimator.learned.fast`` (``""`` = the model as trained) the update is timed after its ring is
full (the best of --repeat passes of --steps updates each: the machine is shared, the best pass is
the least disturbed), with the parts: the estimators' shared input check (``events/validate.py``,
run by every estimator's update), the shared motion-evidence test (``estimators/abstain.py``, run
on every estimator's output), the voxel grid, the network, and the rest (the update less those:
the ring's copy and write, the estimate, confidence and gating, per-call overhead, and the caches
the other parts leave cold; each part is timed on its own, so on a busy machine the rest moves by
the others' noise and can even read below 0).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __name__ == "__main__":  # keep freed memory as the dvsland command does (before torch allocates)
    from dvsland.allocator import tune_allocator

    tune_allocator()

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _best(fn, steps: int, repeat: int) -> float:
    """Least CPU ms per call over ``repeat`` passes of ``steps`` calls."""
    best = float("inf")
    for _ in range(repeat):
        c = time.process_time()
        for _ in range(steps):
            fn()
        best = min(best, 1e3 * (time.process_time() - c) / steps)
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="montecarlo_efference")
    ap.add_argument("--batch", type=int, default=18)
    ap.add_argument("--d", default="-0.1,-0.3")
    ap.add_argument("--modes", default=",ring,bf16")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--checkpoint", default="")
    ap.add_argument("--donate", type=int, default=1, help="1: the object API's default (the ring written in place); "
                    "0: a new ring per update, as the pure step builds it in the loop")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    from measure_learned_zoom import _events, _frames

    from dvsland.config import load_config
    from dvsland.estimators import get_estimator
    from dvsland.estimators.abstain import motion_evidence
    from dvsland.estimators.learned.estimator import ordered_ring
    from dvsland.estimators.learned.inputs import events_voxel_grid
    from dvsland.events.validate import checked_for_estimator

    cfg = load_config(a.config)
    B, W, H = a.batch, cfg.camera.width_px, cfg.camera.height_px
    for d in (float(v) for v in a.d.split(",")):
        evs = _events(cfg, _frames(cfg.camera, d, B, 12, 1000.0, 7))
        ev = evs[-1]
        for mode in a.modes.split(","):
            est = get_estimator("learned", B, (W, H), checkpoint=a.checkpoint, fast=mode,
                                donate=bool(a.donate))
            for k, e in enumerate(evs[:-1], start=1):
                est.update(e, 100_000 * k)
            t = [100_000 * len(evs)]

            def step():
                t[0] += 100_000
                est.update(ev, t[0])

            total = _best(step, a.steps, a.repeat)
            gate = _best(lambda: checked_for_estimator(ev, B, W, H), a.steps, a.repeat)
            evc = checked_for_estimator(ev, B, W, H)
            evid = _best(lambda: motion_evidence(evc, B, (W, H), t[0], est.abstain), a.steps, a.repeat)
            grid = _best(lambda: events_voxel_grid(ev, 0, 100_000, B, est.spec, est.cmap), a.steps, a.repeat)
            st, lc = est.state, torch.full((B,), 9.0)
            with torch.no_grad():
                if est.ring_net is not None:
                    net = _best(lambda: est.ring_net(st.ring, st.ring_abs, st.newest, lc), a.steps, a.repeat)
                else:
                    net = _best(lambda: est.model(ordered_ring(st, est.spec), est.coords, lc), a.steps, a.repeat)
            rest = total - gate - evid - grid - net
            print(f"D = {d:+.2f} 1/s, {len(ev) / B:7.0f} events/row, fast={mode!r:7s}: update {total:5.2f} ms CPU "
                  f"(input check {gate:4.2f}, motion evidence {evid:4.2f}, voxel grid {grid:4.2f}, "
                  f"network {net:4.2f}, rest {rest:4.2f}) at B = {B}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
