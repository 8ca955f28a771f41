"""The CNN's update without copying its input: a circular ring, folded normalisation and coordinates.

:class:`~.models.VoxelCNN` reads ``cat([vox / mean|vox|, coords])`` through a first convolution.
That convolution is linear in its input channels, so for the K-step ring of the estimator

    conv1(cat([vox / s, coords])) = conv(vox, W_vox) / s + conv(coords, W_xy) + bias,

where ``conv(coords, W_xy) + bias`` is one constant (1, C, h/2, w/2) map (computed once) and s is
the mean |vox| per row, the sum of the ring's per-window |sums| (kept beside the ring). The ring
itself stays circular (slot ``newest`` holds the latest window; no shift, no copy): the weights
are permuted instead of the data, W_vox[:, slot] = W[:, age of the slot]. The remaining layers run
as they are, with the scaling, the shift and every ReLU done in place on the convolutions' outputs
(the bits of ``addcdiv`` and ``nn.ReLU``, tested; a frozen TorchScript graph measured no faster,
mkldnn's fused convolution + ReLU gave the same bits and no time). Same numbers as the model up to
float32 rounding (tested). In bfloat16 (``dtype``) the convolutions run channels-last.

:meth:`RingCNN.forward_rows` runs the network on the rows that will give an estimate only
(:func:`~.rows.run_rows`: a finished descent's empty window costs nothing, with the whole batch's bits).
"""

from __future__ import annotations

from typing import Dict, Tuple

import torch
from torch import nn
from torch.nn import functional as F

from .models import VoxelCNN
from .rows import run_rows


def _conv_relu_layers(rest: nn.Sequential) -> Tuple[nn.Conv2d, ...]:
    """The convolutions of ``rest`` = (ReLU, Conv2d, ReLU, ..., Conv2d, ReLU), the features of a
    :class:`VoxelCNN` after its first convolution (ValueError for another layout)."""
    layers = list(rest)
    convs = layers[1::2]
    if (len(layers) % 2 != 1 or not all(type(m) is nn.ReLU for m in layers[0::2])
            or not all(isinstance(m, nn.Conv2d) for m in convs)):
        raise ValueError(f"RingCNN: expected (ReLU, Conv2d, ReLU, ...) after the first layer, got {rest}")
    return tuple(convs)


class RingCNN(nn.Module):
    """A :class:`VoxelCNN` evaluated on a circular ring (module doc).

    Args:
        net: the trained network (eval mode; its weights are read, not copied).
        coords: (1, 2, h, w) float32 coordinate channels of its input.
        n_windows: K, the windows (slots) of the ring; ``net.n_bins`` must be a multiple.
        dtype: ``torch.float32`` (default) or ``torch.bfloat16``: the convolutions in bfloat16,
            channels-last (about twice as fast on a CPU with AVX512-BF16; the head stays float32;
            mu moves by about 1e-2, see docs/learning.md).
        channels_last: run the float32 convolutions channels-last too (on a GPU: cuDNN's kernels
            want that layout and would otherwise transpose every input and output; the same numbers
            up to the convolution's own rounding). Always on in bfloat16.
    """

    def __init__(self, net: VoxelCNN, coords: torch.Tensor, n_windows: int,
                 dtype: torch.dtype = torch.float32, channels_last: bool = False):
        super().__init__()
        conv1 = net.features[0]
        nb, K = net.n_bins, int(n_windows)
        self.K, self.bpw, self.stride, self.padding = K, nb // K, conv1.stride, conv1.padding
        with torch.no_grad():
            w = conv1.weight.detach()
            self.w_vox = w[:, :nb].reshape(w.shape[0], K, self.bpw, *w.shape[2:]).clone()
            self.const = F.conv2d(coords.to(w), w[:, nb:], conv1.bias, conv1.stride, conv1.padding)
        self.dtype = dtype
        self.channels_last = bool(channels_last) or dtype != torch.float32
        self.rest = net.features[1:]
        if self.channels_last:
            import copy

            self.rest = copy.deepcopy(self.rest).to(dtype).to(memory_format=torch.channels_last)
            self.w_vox = self.w_vox.to(dtype)
            self.const = self.const.to(dtype).contiguous(memory_format=torch.channels_last)
        self.head = net.head
        #: the convolutions of ``rest`` (each followed by a ReLU, applied in place: same numbers; a
        #: tuple, not submodules: ``rest`` holds them)
        self.convs = _conv_relu_layers(self.rest)
        # the first layer's vox weights for each position of the newest slot (K small tensors)
        self.w_by_newest = [self.w_vox[:, (torch.arange(K) - q - 1) % K].flatten(1, 2).contiguous() for q in range(K)]
        #: the same, stacked (K, C, K * bpw, kh, kw): picked on the device by a tensor ``newest``
        self.w_stack = torch.stack(self.w_by_newest)
        #: (batch size, rows run) -> whether :meth:`forward_rows` gives the whole batch's bits (a
        #: property of this machine's convolution code paths, checked once per size)
        self._rows_exact: Dict[Tuple[int, int], bool] = {}

    def forward_rows(self, ring: torch.Tensor, abs_sums: torch.Tensor, newest: torch.Tensor,
                     log_count: torch.Tensor, need: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward` of the rows where ``need`` (B,) bool is True (:func:`~.rows.run_rows`):
        (mu, log_var) (B,) float32, the whole batch's bits at those rows, 0 at the others (rows not
        needed may be computed too). ``newest`` is (B,) int64 here. Meant for a CPU batch."""
        if not bool(need.any()):  # no row gives an estimate: nothing to run
            return tuple(torch.zeros(ring.shape[0], dtype=torch.float32, device=ring.device) for _ in range(2))
        return run_rows(self, (ring, abs_sums, newest, log_count), need, self._rows_exact)

    def forward(self, ring: torch.Tensor, abs_sums: torch.Tensor, newest,
                log_count: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """(mu, log_var) (B,) float32.

        Args:
            ring: (B, K * bpw, h, w) float32, slot q = channels q bpw .. (q + 1) bpw - 1.
            abs_sums: (B, K) float32 sum of |values| of each slot.
            newest: the slot of the latest window (slot newest + 1 mod K is the oldest): an int,
                or a (B,) int64 tensor whose rows all hold the same slot (row 0's is used, picked
                on the device: no host read).
            log_count: (B,) float32.
        """
        B, nb, h, w = ring.shape
        # [:, slot q] = the weights of the window's age (q - newest - 1) mod K
        if isinstance(newest, torch.Tensor):
            wq = self.w_stack.index_select(0, newest.reshape(-1)[:1].to(self.w_stack.device)).squeeze(0)
        else:
            wq = self.w_by_newest[int(newest)]
        s = (abs_sums.sum(1) / float(nb * h * w)).clamp_min(1e-3)
        if self.channels_last:
            ring = ring.to(self.dtype).contiguous(memory_format=torch.channels_last)
        y = F.conv2d(ring, wq, None, self.stride, self.padding)
        if self.dtype == torch.float32:  # addcdiv into y (one pass: the bits of div then add) and ReLU
            y = torch.addcdiv(self.const, y, s.view(B, 1, 1, 1), out=y).relu_()
        else:  # one rounding to bfloat16 of the sum (in place would round twice)
            y = torch.addcdiv(self.const, y, s.view(B, 1, 1, 1).to(self.dtype)).relu_()
        for conv in self.convs:
            y = conv(y).relu_()
        f = y.float()
        f = torch.cat([f.mean(dim=(2, 3)), f.amax(dim=(2, 3)), log_count[:, None]], dim=1)
        mu, log_var = self.head(f).unbind(1)
        return mu, log_var.clamp(-12.0, 6.0)
