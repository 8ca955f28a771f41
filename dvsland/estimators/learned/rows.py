"""A network run on the rows of a batch that give an estimate only, with the whole batch's bits.

The closed loop keeps finished descents in the batch (their events are dropped: their windows are
empty), so a network run on every row pays for descents that have ended. :func:`run_rows` runs it
on the rows that need an estimate only, padded to :data:`MIN_ROWS`. A convolution may round a
smaller batch differently (oneDNN picks its code path by the batch's shape): on an AMD EPYC with
AVX-512, rows taken out of a batch of 45 gave the whole batch's bits from 5 rows on, not for 1 to
3. So each (batch, rows) size is checked once, on the step's own data, against the whole batch,
bit for bit, and the whole batch runs where they differ. The verdicts are kept in a dict owned by
the network's holder (a property of this machine's convolution code, not of the data).

Meant for a CPU batch: reading which rows are needed is a host read.
"""

from __future__ import annotations

from typing import Callable, Dict, Sequence, Tuple

import torch

#: the fewest rows :func:`run_rows` runs (fewer are padded with rows not needed): the smallest
#: batches take other convolution code paths, whose sums round differently
MIN_ROWS = 8
#: above this share of the batch needed, :func:`run_rows` runs the whole batch
ROWS_SHARE = 0.75
#: the rows path on (a CPU's only: reading the rows is a host sync on a GPU; the sync-count test
#: switches it off to count the path a GPU runs)
CPU_ROWS = True


def rows_path(t: torch.Tensor) -> bool:
    """Whether a network's input ``t`` takes the rows path (:data:`CPU_ROWS`, on a CPU)."""
    return CPU_ROWS and t.device.type == "cpu"


def run_rows(call: Callable[..., Tuple[torch.Tensor, ...]], inputs: Sequence[torch.Tensor], need: torch.Tensor,
             exact: Dict[Tuple[int, int], bool]) -> Tuple[torch.Tensor, ...]:
    """``call(*inputs)``, a tuple of batch-first outputs, computed for the rows where ``need`` is
    True (and the padding rows): the whole batch's bits at those rows, 0 at the rows not computed.

    Args:
        call: the network, a pure function of ``inputs`` row by row.
        inputs: batch-first tensors (B, ...), on the CPU.
        need: (B,) bool, the rows whose outputs are used.
        exact: (B, rows run) -> whether the rows give the whole batch's bits (filled on first use).
    """
    B = need.shape[0]
    rows = need.nonzero().squeeze(1)
    k = max(rows.numel(), min(MIN_ROWS, B))
    if k > ROWS_SHARE * B or exact.get((B, k)) is False:
        return call(*inputs)
    if rows.numel() < k:  # padded with the first rows not needed (sorted: the batch's order)
        rows = torch.cat([rows, (~need).nonzero().squeeze(1)[:k - rows.numel()]]).sort().values
    part = call(*(t.index_select(0, rows) for t in inputs))
    if (B, k) not in exact:  # once: the rows' bits against the whole batch's
        whole = call(*inputs)
        exact[(B, k)] = all(torch.equal(a, w.index_select(0, rows)) for a, w in zip(part, whole))
        return whole
    return tuple(a.new_zeros((B,) + tuple(a.shape[1:])).index_copy_(0, rows, a) for a in part)


__all__ = ["CPU_ROWS", "MIN_ROWS", "ROWS_SHARE", "rows_path", "run_rows"]
