"""NIR export and re-import of the spiking model :class:`~.models.SpikingVoxelNet`.

:func:`to_nir` writes one time step of the network as a NIR graph (packages ``nir``, ``nirtorch``:
the optional extra ``dvsland[nir]``)::

    input (3, h, w) -> Conv2d 3x3 stride 2 -> CubaLIF (width, h1, w1)
                    -> Conv2d 3x3 stride 2 -> CubaLIF (2 width, h2, w2)
                    [-> Conv2d 3x3 stride 2 -> CubaLIF (2 width, h3, w3) when depth = 3] -> output (spikes)

The per-time-step input (the normalised voxel bin and the two coordinate channels,
:meth:`~.models.SpikingVoxelNet.slice_inputs`) and the read-out of the summed layer-2 spikes
(:meth:`~.models.SpikingVoxelNet.readout`, a linear map or small MLP to mu and log_var) stay outside the
graph, as the input encoding does for ``snn``. Neurons use NIR's CubaLIF with the forward-Euler
step of :mod:`dvsland.estimators.snn.nir_export` (w_in = tau_syn / dt).
:func:`run_nir` runs a re-imported graph over a window and returns what the model returns.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..snn.nir_export import _Euler, _require
from .models import SpikingVoxelNet


def to_nir(net: SpikingVoxelNet, grid_hw):
    """One time step of ``net`` for an input grid ``grid_hw`` (h, w) as a :class:`nir.NIRGraph`."""
    _require()
    import nir

    f32 = lambda t: t.detach().cpu().numpy().astype(np.float32)  # noqa: E731
    h, w = (int(v) for v in grid_hw)
    with torch.no_grad():
        shapes = [tuple(net.conv1(torch.zeros(1, net.in_channels, h, w)).shape[1:])]
        for m in net._layers():
            shapes.append(tuple(m(torch.zeros(1, *shapes[-1])).shape[1:]))
    p, dt = net.p, net.slice_dt_s

    def lif(shape):
        full = lambda v: np.full(shape, v, np.float32)  # noqa: E731
        return nir.CubaLIF(tau_syn=full(p.tau_syn_s), tau_mem=full(p.tau_mem_s), r=full(1.0), v_leak=full(p.v_leak),
                           v_threshold=full(p.v_th), v_reset=full(0.0), w_in=full(p.tau_syn_s / dt))

    def conv(m, shape_in):
        return nir.Conv2d(input_shape=shape_in, weight=f32(m.weight), stride=tuple(m.stride), padding=tuple(m.padding),
                          dilation=(1, 1), groups=1, bias=f32(m.bias))

    nodes = {"input": nir.Input(input_type={"input": np.array([net.in_channels, h, w])}),
             "conv1": conv(net.conv1, (h, w)), "lif1": lif(shapes[0])}
    for k, m in enumerate(net._layers(), start=2):
        nodes.update({f"conv{k}": conv(m, shapes[k - 2][1:]), f"lif{k}": lif(shapes[k - 1])})
    nodes["output"] = nir.Output(output_type={"output": np.array(shapes[-1])})
    order = list(nodes)
    return nir.NIRGraph(nodes=nodes, edges=list(zip(order[:-1], order[1:])),
                        metadata={"dt_s": dt, "producer": "dvsland learned spiking",
                                  "input": "[voxel bin / mean |voxel|, (delay) earlier bins, x, y coordinate channels]",
                                  "output": "last layer's spikes; summed over the window into SpikingVoxelNet.readout"})


def export_nir(net: SpikingVoxelNet, grid_hw, path) -> Path:
    """Write :func:`to_nir` to ``path`` (HDF5, ``nir.write``); returns the path."""
    _require()
    import nir

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    nir.write(str(path), to_nir(net, grid_hw))
    return path


def from_nir(graph, dt_s=None) -> torch.nn.Module:
    """A torch module of a graph of :func:`to_nir` (a NIRGraph or a file); call it per time step as
    ``spikes, state = module(x, state)`` (state None first)."""
    _require()
    import nir
    import nirtorch

    if isinstance(graph, (str, Path)):
        graph = nir.read(str(graph))
    dt = float(dt_s if dt_s is not None else graph.metadata["dt_s"])
    return nirtorch.nir_to_torch(graph, {nir.CubaLIF: lambda n: _Euler(n, dt, True)})


@torch.no_grad()
def run_nir(module, net: SpikingVoxelNet, vox: torch.Tensor, coords: torch.Tensor, log_count: torch.Tensor):
    """(mu, log_var) (B,) of a window through the re-imported graph ``module`` and ``net``'s
    input and read-out (the same call as ``net(vox, coords, log_count)``)."""
    x = net.slice_inputs(vox, coords)
    state, count2, outs = None, 0.0, []
    for k in range(net.n_bins):
        z, state = module(x[:, k], state)
        count2 = count2 + z
        outs.append(z)
    return net.readout(count2, coords, log_count, torch.stack(outs, dim=1) if net.per_step else None)
