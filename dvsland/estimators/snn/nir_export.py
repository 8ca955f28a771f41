"""Export of the spiking network to NIR (the Neuromorphic Intermediate Representation) and back.

NIR (packages ``nir`` and ``nirtorch``, the optional extra ``dvsland[nir]``) is read by the
neuromorphic frameworks and chips (snnTorch, Norse, Lava / Loihi, SpiNNaker2, Speck, Xylo, ...).
:func:`to_nir` writes one time slice of :class:`~.model.SpikingDivergenceNet` as a graph:

    input (2, n_rho, n_phi + 8)
      -> Conv2d 5x5, padding (2, 0)            -> CubaLIF (c1, n_rho, n_phi + 4)
      -> Conv2d 5x5, stride (2, 1), pad (2, 0) -> CubaLIF (c2, n_rho2, n_phi)
      -> SumPool2d (1, n_phi) -> Flatten -> Affine -> CubaLI (1,) = D_hat, 1/s

Two parts of the network stay outside the graph, in :func:`nir_input` (as the log-polar encoding
does): the input compression log1p(gain * x), and the circular padding in phi, which NIR has no
node for. Circular padding is made exact by feeding the graph two wrapped columns on each side
of phi and using valid convolutions in phi: the layer-1 neurons of the two extra columns get the
same input as the columns they copy, so they spike alike, and layer 2 sees exactly the circularly
padded layer-1 spikes. The read-out scale ``d_scale`` and the mean over phi are folded into the
Affine weights.

Neuron parameters follow NIR's continuous-time CubaLIF / CubaLI (tau_syn dI/dt = -I + w_in S,
tau_mem dv/dt = v_leak - v + R I, spike and reset to v_reset at v_threshold); the network's
discrete step of length dt (stored as graph metadata ``dt_s``) is their forward-Euler step with
the input added to the current as a jump: w_in = tau_syn / dt. :func:`from_nir` maps the graph
back to torch with :func:`nirtorch.nir_to_torch` and modules that run exactly that step, so
``from_nir(to_nir(model))`` reproduces the model (tests/test_estimators_snn.py checks it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import torch
import torch.nn as nn

from .model import SpikingDivergenceNet

#: columns of wrapped input on each side of phi (two valid 5-wide convolutions)
HALO = 4


def _require():
    try:
        import nir  # noqa: F401
        import nirtorch  # noqa: F401
    except ImportError as exc:  # pragma: no cover - exercised only without the extra
        raise ImportError("NIR export needs the optional packages nir and nirtorch: "
                          "pip install 'dvsland[nir]'") from exc


def nir_input(x: torch.Tensor, model: SpikingDivergenceNet) -> torch.Tensor:
    """The graph's input for event rates x (B, 2, n_rho, n_phi) of one slice: log1p(gain x) with
    ``HALO`` wrapped columns on each side of phi -> (B, 2, n_rho, n_phi + 2 HALO) float32."""
    c = torch.log1p(x * model.log_in_gain.exp())
    return torch.cat([c[..., -HALO:], c, c[..., :HALO]], dim=-1).to(torch.float32)


def _time_constants(model: SpikingDivergenceNet) -> dict:
    """Per-channel (tau_mem, tau_syn) in seconds of both layers, and the read-out's, as numpy."""
    dt = model.dt_s
    c1, c2 = model.channels
    if model.learn_tau:
        k = {n: v.detach().flatten().double().cpu().numpy() for n, v in model._time_constants().items()}
        return {"l1": (dt / k["mem1"], dt / k["syn1"]), "l2": (dt / k["mem2"], dt / k["syn2"]),
                "out": (np.array([model.po.tau_mem_s]), np.array([model.po.tau_syn_s]))}
    return {"l1": (np.full(c1, model.p1.tau_mem_s), np.full(c1, model.p1.tau_syn_s)),
            "l2": (np.full(c2, model.p2.tau_mem_s), np.full(c2, model.p2.tau_syn_s)),
            "out": (np.array([model.po.tau_mem_s]), np.array([model.po.tau_syn_s]))}


def to_nir(model: SpikingDivergenceNet):
    """One time slice of ``model`` as a :class:`nir.NIRGraph` (see module doc)."""
    _require()
    import nir

    f32 = lambda t: t.detach().cpu().numpy().astype(np.float32)  # noqa: E731
    dt = float(model.dt_s)
    n_rho, n_phi, n_rho2 = model.n_rho, model.n_phi, model.n_rho2
    c1, c2 = model.channels
    tc = _time_constants(model)

    def lif(shape, taus, p):
        tau_mem = np.broadcast_to(taus[0].reshape(-1, 1, 1), shape).astype(np.float32)
        tau_syn = np.broadcast_to(taus[1].reshape(-1, 1, 1), shape).astype(np.float32)
        return nir.CubaLIF(tau_syn=tau_syn.copy(), tau_mem=tau_mem.copy(), r=np.ones(shape, np.float32),
                           v_leak=np.full(shape, p.v_leak, np.float32), v_threshold=np.full(shape, p.v_th, np.float32),
                           v_reset=np.zeros(shape, np.float32), w_in=(tau_syn / dt).astype(np.float32))

    s1 = (c1, n_rho, n_phi + 2 * HALO - 4)

    def square(w):  # (C_out, C_in, 5, 3) -> (C_out, C_in, 5, 5), zero outer columns
        w = f32(w)
        kh, kw = w.shape[-2:]
        if kh != 5 or kw != 3:
            raise ValueError(f"NIR export expects 5x3 kernels, got {kh}x{kw}")
        return np.pad(w, ((0, 0), (0, 0), (0, 0), (1, 1)))

    s2 = (c2, n_rho2, n_phi)
    w_out = f32(model.readout.weight) * (model.d_scale / n_phi)
    b_out = f32(model.readout.bias) * model.d_scale
    t_out = tc["out"]
    nodes = {
        "input": nir.Input(input_type={"input": np.array([2, n_rho, n_phi + 2 * HALO])}),
        "conv1": nir.Conv2d(input_shape=(n_rho, n_phi + 2 * HALO), weight=square(model.conv1.weight), stride=(1, 1),
                            padding=(2, 0), dilation=(1, 1), groups=1, bias=f32(model.conv1.bias)),
        "lif1": lif(s1, tc["l1"], model.p1),
        "conv2": nir.Conv2d(input_shape=s1[1:], weight=square(model.conv2.weight), stride=tuple(model.conv2.stride),
                            padding=(2, 0), dilation=(1, 1), groups=1, bias=f32(model.conv2.bias)),
        "lif2": lif(s2, tc["l2"], model.p2),
        "pool": nir.SumPool2d(kernel_size=np.array([1, n_phi]), stride=np.array([1, n_phi]), padding=np.array([0, 0])),
        "flatten": nir.Flatten(input_type={"input": np.array([c2, n_rho2, 1])}, start_dim=0, end_dim=-1),
        "readout": nir.Affine(weight=w_out, bias=b_out),
        "li": nir.CubaLI(tau_syn=t_out[1].astype(np.float32), tau_mem=t_out[0].astype(np.float32),
                         r=np.ones(1, np.float32), v_leak=np.full(1, model.po.v_leak, np.float32),
                         w_in=(t_out[1] / dt).astype(np.float32)),
        "output": nir.Output(output_type={"output": np.array([1])}),
    }
    order = list(nodes)
    edges = [(a, b) for a, b in zip(order[:-1], order[1:])]
    return nir.NIRGraph(nodes=nodes, edges=edges, metadata={"dt_s": dt, "producer": "dvsland snn",
                                                              "input": f"log1p(gain * events per pixel), phi halo {HALO}",
                                                              "output": "D_hat, 1/s"})


def export_nir(model: SpikingDivergenceNet, path) -> Path:
    """Write :func:`to_nir` of ``model`` to ``path`` (HDF5, ``nir.write``); returns the path."""
    _require()
    import nir

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    nir.write(str(path), to_nir(model))
    return path


class _Euler(nn.Module):
    """Forward-Euler step of a NIR CubaLIF (``spiking``) or CubaLI node at step ``dt_s``, with the
    network's update order: v from the previous current, then the current takes the input."""

    def __init__(self, node, dt_s: float, spiking: bool):
        super().__init__()
        t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32))  # noqa: E731
        self.register_buffer("k_mem", dt_s / t(node.tau_mem))
        self.register_buffer("k_syn", dt_s / t(node.tau_syn))
        self.register_buffer("r", t(node.r))
        self.register_buffer("v_leak", t(node.v_leak))
        self.register_buffer("w_in", t(node.w_in))
        self.spiking = spiking
        if spiking:
            self.register_buffer("v_th", t(node.v_threshold))
            self.register_buffer("v_reset", t(node.v_reset))

    def forward(self, x: torch.Tensor, state: Optional[Tuple[torch.Tensor, torch.Tensor]] = None):
        if state is None:
            state = (torch.zeros_like(x), torch.zeros_like(x))
        v, i = state
        v = v + self.k_mem * (self.v_leak - v + self.r * i)
        i = i * (1.0 - self.k_syn) + self.k_syn * self.w_in * x
        if not self.spiking:
            return v, (v, i)
        z = (v - self.v_th > 0).to(v.dtype)
        v = v * (1.0 - z) + z * self.v_reset
        return z, (v, i)


def from_nir(graph, dt_s: Optional[float] = None) -> torch.nn.Module:
    """A torch module of a NIR graph of this network (a :class:`nir.NIRGraph` or a file path).
    Call it per slice as ``out, state = module(nir_input(x, model), state)`` (state None first);
    ``out`` (B, 1) is D_hat in 1/s. ``dt_s`` defaults to the graph's metadata."""
    _require()
    import nir
    import nirtorch

    if isinstance(graph, (str, Path)):
        graph = nir.read(str(graph))
    dt = float(dt_s if dt_s is not None else graph.metadata["dt_s"])

    def affine(node):  # nirtorch 2.6's default Affine mapping leaves the bias unset
        m = nn.Linear(node.weight.shape[-1], node.weight.shape[-2], bias=True)
        m.weight.data = torch.as_tensor(np.asarray(node.weight, dtype=np.float32))
        m.bias.data = torch.as_tensor(np.asarray(node.bias, dtype=np.float32))
        return m

    def sumpool(node):
        k = tuple(int(v) for v in node.kernel_size)
        return _SumPool(k)

    node_map = {nir.CubaLIF: lambda n: _Euler(n, dt, True), nir.CubaLI: lambda n: _Euler(n, dt, False),
                nir.Affine: affine, nir.SumPool2d: sumpool,
                nir.Flatten: lambda n: nn.Flatten(start_dim=n.start_dim + 1, end_dim=n.end_dim)}
    return nirtorch.nir_to_torch(graph, node_map)


class _SumPool(nn.Module):
    def __init__(self, kernel):
        super().__init__()
        self.kernel = kernel

    def forward(self, x):
        return torch.nn.functional.avg_pool2d(x, self.kernel, self.kernel) * float(self.kernel[0] * self.kernel[1])
