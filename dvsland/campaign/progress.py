"""Progress inside shards: a bar that moves with every loop step of every shard in flight.

A shard (a campaign's batch, a dataset build's shard) is flown in one call, here or in a pool
worker, for minutes. A bar counting shards sits at ``0/1`` for the whole of a one-shard job;
this one counts loop steps.

- The driver makes a :class:`StepBar` with each shard's most steps (``simulation.t_max_s / dt``)
  and a *slot* per shard: a shared-memory ``int64`` array (one entry per shard) that the pool's
  workers get when they start (:func:`dvsland.campaign.executors.make_pool`), or a plain list when
  the shards are flown in this process.
- The shard's flight calls :func:`report` once per loop step with its slot and the steps flown
  (one write into the array: no loop over descents, no lock, no message).
- The driver polls the slots (:meth:`StepBar.refresh`, from its wait loop, or from :func:`report`
  itself when the shard is flown here) and counts a finished shard as all its steps, so a job whose
  descents all end before ``t_max`` still ends at 100 %. tqdm gives the rate and the ETA.
"""

from __future__ import annotations

import sys
import time
from typing import List, Optional, Sequence

#: the slots of this process: the pool's shared array in a worker, the driver's list when it flies
_SLOTS: dict = {"slots": None, "notify": None}


def install(slots, notify=None) -> None:
    """Make :func:`report` write into ``slots`` (an indexable of ints; None = report nothing) and
    call ``notify(slot)`` after each write (the driver's :meth:`StepBar.refresh` when it flies the
    shard itself)."""
    _SLOTS["slots"], _SLOTS["notify"] = slots, notify


def report(slot: Optional[int], steps: int) -> None:
    """Say that the shard in ``slot`` has flown ``steps`` loop steps (None or no slots: nothing)."""
    slots = _SLOTS["slots"]
    if slot is None or slots is None:
        return
    slots[slot] = int(steps)
    notify = _SLOTS["notify"]
    if notify is not None:
        notify(slot)


def shard_steps(plan_config: dict, shards: Sequence[dict]) -> List[int]:
    """Each shard's most loop steps (``ceil(simulation.t_max_s / dt)`` of its grid point's config;
    one config built per grid point, not per shard)."""
    import json

    from dvsland.stages import LoopSettings

    from .plan import config_from_dict

    by_point: dict = {}
    out = []
    for sh in shards:
        key = json.dumps(sh.get("sweep", {}), sort_keys=True)
        if key not in by_point:
            sets = [f"{k}={v}" for k, v in sh.get("sweep", {}).items()]
            by_point[key] = LoopSettings.from_config(config_from_dict(plan_config, sets)).n_steps_max
        out.append(by_point[key])
    return out


class StepBar:
    """The driver's bar over the steps of the shards ``steps`` (one int per shard still to fly),
    after ``steps_before`` steps of shards finished earlier.

    Args:
        steps: most loop steps of each shard to fly, in slot order.
        desc: the bar's label.
        shards_total, shards_before: shards of the whole job and those finished earlier (postfix).
        steps_before: steps of the shards finished earlier (the bar starts there).
        shared: slots in shared memory for a process pool (else a list for this process).
    """

    def __init__(self, steps: Sequence[int], desc: str, shards_total: int, shards_before: int = 0,
                 steps_before: int = 0, shared: bool = False):
        from tqdm.auto import tqdm

        self.steps = [int(s) for s in steps]
        self.finished = [False] * len(self.steps)
        if shared:
            import multiprocessing as mp

            self.slots = mp.get_context("spawn").RawArray("q", max(1, len(self.steps)))
        else:
            self.slots = [0] * max(1, len(self.steps))
        self.before, self.shards_total, self.shards_done = int(steps_before), int(shards_total), int(shards_before)
        self.bar = tqdm(total=self.before + sum(self.steps), initial=self.before, unit="step", desc=desc,
                        file=sys.stderr, dynamic_ncols=True)
        self.bar.set_postfix_str(self._postfix(), refresh=False)
        self._drawn = time.monotonic()
        self._done_steps = self.before  # steps of the shards finished, earlier and now

    def _postfix(self) -> str:
        return f"shards {self.shards_done}/{self.shards_total}"

    def refresh(self, slot: Optional[int] = None) -> None:
        """Move the bar to the steps flown so far (tqdm redraws at most ~10 times a second); with
        no new step (workers starting, terrain being prepared) redraw its clock once a second.
        ``slot``: only that shard is in flight (flown here: O(1) per step, no loop over shards)."""
        # a shard in flight stops one step short: its file is written after its last step
        if slot is not None:
            n = self._done_steps + (0 if self.finished[slot] else min(int(self.slots[slot]), self.steps[slot] - 1))
        else:
            n = self._done_steps + sum(min(int(v), s - 1) for s, f, v in zip(self.steps, self.finished, self.slots)
                                       if not f)
        if n > self.bar.n:
            self.bar.update(n - self.bar.n)
        elif time.monotonic() - self._drawn > 1.0:
            self.bar.refresh()
        else:
            return
        self._drawn = time.monotonic()

    def shard_done(self, slot: int, postfix: str = "") -> None:
        """Count the shard in ``slot`` as all its steps (its descents may have ended before t_max)."""
        if 0 <= slot < len(self.finished) and not self.finished[slot]:
            self.finished[slot] = True
            self.shards_done += 1
            self._done_steps += self.steps[slot]
        self.bar.set_postfix_str(self._postfix() + (f", {postfix}" if postfix else ""), refresh=False)
        self.refresh()

    def close(self) -> None:
        self.bar.close()


__all__ = ["StepBar", "install", "report", "shard_steps"]
