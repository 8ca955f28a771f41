"""Abstention: one shared, cheap test of whether a window of events shows motion at all.

Every estimator that takes events runs behind it (:class:`dvsland.estimators.base.DivergenceEstimator`
applies it to whatever the estimator's step returns, plug-ins included): where the window holds
no evidence of a moving scene (uniform sensor noise on a static scene, a global flicker) the
estimate becomes NaN and its confidence 0; where the evidence is weak the confidence is scaled
down. Where a scene moves, the factor is exactly 1 and the estimator's output passes unchanged.

What is measured per descent, on the events of one step (all descents at once, no loop):

- ``clustering``: the index of dispersion of the *active pixels* (pixels with at least one event)
  counted over ``cell_px`` x ``cell_px`` cells, divided by its value for pixels active at random
  (a binomial count: mean m, variance m (1 - m / cell_px^2)). 1 +- 0.09 for uniform noise, whatever
  its rate; a scene's events lie on its edges and texture: >= 3.2 on every judged window of the
  shipped sites (ideal pixel).
- ``neighbours``: the share of active pixels with an active 8-neighbour, minus its value for
  pixels active at random, 1 - (1 - q)^8 with q the share of active pixels, in standard errors of
  that share: 0 +- 1 for noise, >= 6.8 on the shipped sites (events of an edge have neighbours:
  the background-activity filter's idea).
- ``flicker``: |correlation of polarity and time| over the window: about 0.87 for a global
  flicker (every pixel ON, then OFF), <= 0.18 on the shipped sites (ON and OFF interleave).

Through the realistic pixel either of the first two can fall to noise level on a window, but not
both (measured on every step of the nine evaluation descents; docs/estimators.md).

The factor: ``clamp(max(ramp(clustering), ramp(neighbours)), 0, 1)``, times the flicker ramp, and
judged only on windows with enough events: below ``min_events`` the window is not judged (factor
1: the estimators' own rules on few events hold, e.g. ``cmax``'s ``min_events`` over its longer
window), from ``full_events`` on it is judged fully, linear between.

Where most pixels are active (a dense window: a recording binned to large pixels, 10-20 events per
pixel and step) neither active-pixel statistic can show structure: every pixel is active whether
the scene moves or not. From an active share ``saturated_from`` (0.6) to ``saturated_full`` (0.75)
the two fade out of the test (the flicker test stays). Uniform noise reaches that share only at
about one noise event per pixel per step, 5x the densest noise the test is tuned on.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Tuple

import torch

from dvsland.events import native


class AbstainParams(NamedTuple):
    """Thresholds of the motion-evidence test (the defaults are the shipped behaviour).

    Attributes:
        cell_px: side of the cells of the clustering index, px (>= 2).
        clustering_none / clustering_full: clustering index at or below which the window shows no
            structure (factor 0) / at or above which it does (factor 1); linear between.
        neighbours_none / neighbours_full: the same for the neighbour excess.
        flicker_full / flicker_none: |corr(polarity, time)| at or below which the window is no
            flicker (factor 1) / at or above which it is one (factor 0).
        min_events / full_events: events of one descent in the window below which it is not judged
            (factor 1) / from which it is judged fully.
        saturated_from / saturated_full: share of active pixels from which the clustering and
            neighbour tests fade out / at which they no longer judge (module doc).
    """

    cell_px: int = 8
    clustering_none: float = 1.4
    clustering_full: float = 1.6
    neighbours_none: float = 3.25
    neighbours_full: float = 4.25
    flicker_full: float = 0.5
    flicker_none: float = 0.7
    min_events: int = 200
    full_events: int = 300
    saturated_from: float = 0.6
    saturated_full: float = 0.75


#: the shipped thresholds; ``DivergenceEstimator.abstain = None`` turns the test off for a class or
#: an instance, another :class:`AbstainParams` tunes it.
DEFAULT_ABSTAIN = AbstainParams()

#: the key of the factor in every gated estimator's diagnostics
EVIDENCE_KEY = "motion_evidence"


class MotionEvidence(NamedTuple):
    """The test's result for B descents.

    Attributes:
        factor: (B,) float32 in [0, 1], what the confidence is multiplied by (0: D_hat becomes NaN).
        clustering: (B,) float32 clustering index (1 = random), 0 where not measurable.
        neighbours: (B,) float32 neighbour excess (0 = random).
        flicker: (B,) float32 |corr(polarity, time)| in [0, 1].
        n_events: (B,) int64 events of each descent in the window.
    """

    factor: torch.Tensor
    clustering: torch.Tensor
    neighbours: torch.Tensor
    flicker: torch.Tensor
    n_events: torch.Tensor


#: the neighbour share's spread under random activity, measured, over its binomial standard error
NEIGHBOUR_SD_INFLATION = 1.3


def _ramp(v: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    """0 at or below ``lo``, 1 at or above ``hi``, linear between (``lo > hi`` falls instead)."""
    return ((v - lo) / (hi - lo)).clamp(0.0, 1.0)


def _occupancy(events, B: int, W: int, H: int, dev) -> torch.Tensor:
    """(B, H + 2, W + 2) uint8 occupancy images with a zero border: 1 where a pixel holds at least
    one event (events checked to lie on the sensor and in the batch; no host sync). The flat index
    b (H + 2)(W + 2) + y (W + 2) + x is two fused multiply-adds, offset by the border (W + 3)."""
    b, x, y = events.b.to(dev), events.x.to(dev), events.y.to(dev)
    P = (H + 2) * (W + 2)
    occ = torch.zeros(B * P, dtype=torch.uint8, device=dev)
    occ[W + 3:].index_fill_(0, torch.add(torch.add(x, y, alpha=W + 2), b, alpha=P), 1)
    return occ.view(B, H + 2, W + 2)


def _clustering(img: torch.Tensor, cell: int) -> torch.Tensor:
    """Clustering index (B,) float32 of the active pixels of ``img`` (B, H, W) uint8 over ``cell``
    px cells (module doc). The cell counts are integers: summed over the cell's rows first (whole
    image rows, vectorised), then over its columns."""
    B, H, W = img.shape
    Hc, Wc = H // cell, W // cell
    if Hc * Wc < 2:  # too small a sensor to count cells: no clustering evidence either way
        return torch.zeros(B, dtype=torch.float32, device=img.device)
    acc = torch.uint8 if cell * cell <= 255 else torch.int32
    c = img[:, :Hc * cell, :Wc * cell].reshape(B, Hc, cell, Wc * cell).sum(dim=2, dtype=acc)
    return _clustering_of_counts(c.view(B, Hc * Wc, cell).sum(dim=2, dtype=acc).to(torch.float32), cell)


def _clustering_of_counts(c: torch.Tensor, cell: int) -> torch.Tensor:
    """Clustering index (B,) float32 of the active pixels per cell ``c`` (B, cells) float32 (integers)."""
    m = c.mean(dim=1)
    den = m * (1.0 - m / (cell * cell))
    return torch.where(den > 1e-6, c.var(dim=1) / den.clamp_min(1e-6), torch.zeros_like(m))


def _neighbour_counts(padded: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """(active pixels, active pixels with an active 8-neighbour), (B,) float32 each (integers, exact),
    of the occupancy images ``padded`` (B, H + 2, W + 2) uint8 with a zero border.

    The 3 x 3 box sums run on the flat images (every shift a contiguous slice: a pixel's
    neighbours are +-1 and +-(W + 2) away, and the zero borders keep images and rows apart);
    the counts are float32 sums (exact below 2^24, and several times faster than integer ones)."""
    B, o, L = padded.shape[0], padded.shape[2], padded.numel()
    f = padded.view(-1)
    r = f[:L - 2] + f[1:L - 1]  # r[i]: the row sum of the 3 pixels centred at i + 1 (uint8: <= 3)
    r += f[2:]
    box = r[:L - 2 - 2 * o] + r[o:L - 2 - o]  # box[k]: the 3 x 3 sum centred at k + 1 + o (<= 9)
    box += r[2 * o:]
    centre = f[1 + o:L - 1 - o]
    has = torch.zeros(L, dtype=torch.uint8, device=f.device)  # read as bool (0/1 bytes): no conversions
    inner = has[1 + o:L - 1 - o].view(torch.bool)
    torch.gt(box, centre, out=inner)  # an active neighbour (the box holds the centre)
    inner.logical_and_(centre.view(torch.bool))
    with_nb = has.view(B, -1).to(torch.float32).sum(dim=1)
    active = padded.view(B, -1).to(torch.float32).sum(dim=1)  # the border is 0
    return active, with_nb


def _neighbours_of_counts(active: torch.Tensor, with_nb: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """Neighbour excess (B,) float32 in standard errors (module doc) of the active pixels ``active``
    (B,) and those of them with an active 8-neighbour ``with_nb`` (B,), float32 integers, on an
    H x W sensor: the share with a neighbour against 1 - (1 - q)^8 for pixels active at random."""
    obs = with_nb / active.clamp_min(1.0)
    q = active / float(H * W)
    exp = 1.0 - (1.0 - q) ** 8
    # in standard errors of the share under random activity (binomial over the active pixels,
    # times NEIGHBOUR_SD_INFLATION for the pairs a neighbourhood shares)
    se = NEIGHBOUR_SD_INFLATION * torch.sqrt(exp * (1.0 - exp) / active.clamp_min(1.0))
    return torch.where((active > 0) & (se > 0), (obs - exp) / se.clamp_min(1e-9), torch.zeros_like(q))


def _row_sums(src: torch.Tensor, b: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """(k, B) float32 per-row sums of ``src`` (k, N) float32 over events of rows ``b`` (N,) int64
    sorted ascending with ``n`` (B,) int64 events per row: each row's events added in their order
    (the sums of ``zeros(k, B).index_add_(1, b, src)``, bit for bit, on a CPU). A CPU runs one
    segment reduction per row (about 1.5x faster than the scatter); other devices scatter."""
    if src.device.type != "cpu":
        return torch.zeros(src.shape[0], n.shape[0], dtype=src.dtype, device=src.device).index_add_(1, b, src)
    # lengths checked (>= 0, summing to N; read on the host, where they are): rows out of order
    # (against the events' contract) give wrong sums or an error, never a read outside ``src``
    return torch.segment_reduce(src, "sum", lengths=n.expand(src.shape[0], -1), axis=1, unsafe=False)


def _flicker(events, B: int, t_us: int, n: torch.Tensor, dev) -> torch.Tensor:
    """|corr(polarity, time)| per descent, (B,) float32 (0 where undefined); ``n`` (B,) int64 the
    events of each descent (events sorted by b)."""
    b = events.b.to(dev)
    src = torch.empty(4, b.shape[0], dtype=torch.float32, device=dev)  # rows t, p, t^2, p t
    t, p = src[0], src[1]
    torch.sub(events.t.to(dev), int(t_us), out=t)  # int64 difference, rounded once to float32
    t.div_(t.abs().max().clamp_min(1.0))  # in [-1, 0]: float32 sums keep their precision
    p.copy_(events.p.to(dev))
    torch.mul(t, t, out=src[2])
    torch.mul(p, t, out=src[3])
    return _flicker_of_sums(_row_sums(src, b, n), n)


def _flicker_of_sums(sums: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """|corr(polarity, time)| (B,) float32 from the per-descent sums (4, B) float32 of (t, p, t^2, p t)
    and the event counts ``n`` (B,) int64."""
    nn = n.to(torch.float32).clamp_min(1.0)
    mt, mp = sums[0] / nn, sums[1] / nn
    vt, vp = sums[2] / nn - mt ** 2, 1.0 - mp ** 2  # p = +-1: E[p^2] = 1
    cov = sums[3] / nn - mt * mp
    ok = (vt > 1e-6) & (vp > 1e-6)
    r = cov.abs() / torch.sqrt((vt * vp).clamp_min(1e-12))
    return torch.where(ok, r, torch.zeros_like(r)).clamp(0.0, 1.0).to(torch.float32)


def _statistics(events, B: int, W: int, H: int, t_us: int, n: torch.Tensor, cell: int, dev):
    """(clustering, neighbours, flicker, active pixels), each (B,) float32, of the checked events
    sorted by b: their counts and sums from the compiled kernel where it runs (CPU;
    :mod:`dvsland.events.native`, the same integers and the same float32 sums in the same order), else
    from torch; the statistics from torch."""
    mod = native.kernels() if dev.type == "cpu" and events.b.device.type == "cpu" else None
    if mod is None:
        padded = _occupancy(events, B, W, H, dev)
        active, with_nb = _neighbour_counts(padded)
        return (_clustering(padded[:, 1:-1, 1:-1], cell), _neighbours_of_counts(active, with_nb, H, W),
                _flicker(events, B, t_us, n, dev), active)
    with_cells = (H // cell) * (W // cell) >= 2
    cells, active, with_nb, sums = mod.motion_counts(
        *(v.to(torch.int64).contiguous() for v in (events.b, events.x, events.y, events.t)),
        events.p.to(torch.int8).contiguous(), B, H, W, cell if with_cells else 0, int(t_us))
    clus = _clustering_of_counts(cells, cell) if with_cells else torch.zeros(B, dtype=torch.float32)
    return clus, _neighbours_of_counts(active, with_nb, H, W), _flicker_of_sums(sums, n), active


def check_abstain_params(p: AbstainParams) -> None:
    """Raise ValueError naming the field when ``p`` is no usable :class:`AbstainParams`."""
    if not isinstance(p, AbstainParams):
        raise ValueError(f"abstain must be an AbstainParams or None, got {type(p).__name__}")
    if not 2 <= p.cell_px <= 1024:
        raise ValueError(f"abstain.cell_px must be in [2, 1024] px, got {p.cell_px}")
    for lo, hi in (("clustering_none", "clustering_full"), ("neighbours_none", "neighbours_full"),
                   ("flicker_full", "flicker_none"), ("min_events", "full_events"),
                   ("saturated_from", "saturated_full")):
        if not getattr(p, lo) < getattr(p, hi):
            raise ValueError(f"abstain.{lo} must be < abstain.{hi}, got {getattr(p, lo)} and {getattr(p, hi)}")
    if p.min_events < 0:
        raise ValueError(f"abstain.min_events must be >= 0, got {p.min_events}")


def motion_evidence(events, batch_size: int, sensor_size: Tuple[int, int], t_us: int,
                    params: AbstainParams = DEFAULT_ABSTAIN, device=None) -> MotionEvidence:
    """The motion-evidence test of the events of one step (module doc), all descents at once.

    Args:
        events: :class:`dvsland.events.Events` of the step, checked and sorted by (b, t) (b in
            [0, B), x, y on the sensor: :func:`dvsland.events.validate.checked_for_estimator`,
            which every estimator's input passes; the per-row counts and sums read each row's
            events as one contiguous run), or None / empty (then nothing is judged: factor 1).
        batch_size: B.
        sensor_size: (W, H) px.
        t_us: end of the window, int µs (times are taken relative to it).
        params: :class:`AbstainParams`.
        device: where the result lives (default the events').

    Returns:
        :class:`MotionEvidence`, each field (B,).
    """
    check_abstain_params(params)
    B, (W, H) = int(batch_size), (int(sensor_size[0]), int(sensor_size[1]))
    dev = torch.device(device) if device is not None else (events.b.device if events is not None else "cpu")
    if events is None or events.b.numel() == 0:
        zf = torch.zeros(B, dtype=torch.float32, device=dev)
        return MotionEvidence(torch.ones_like(zf), zf, zf.clone(), zf.clone(),
                              torch.zeros(B, dtype=torch.int64, device=dev))
    b = events.b.to(dev).contiguous()  # sorted: the events of a row are contiguous
    edges = torch.searchsorted(b, torch.arange(B + 1, dtype=b.dtype, device=dev))
    n = edges[1:] - edges[:-1]
    clus, nbx, flick, active = _statistics(events, B, W, H, t_us, n, max(2, int(params.cell_px)), dev)
    motion = torch.maximum(_ramp(clus, params.clustering_none, params.clustering_full),
                           _ramp(nbx, params.neighbours_none, params.neighbours_full))
    # most pixels active: the two cannot show structure and fade out (module doc)
    saturated = _ramp(active / float(H * W), params.saturated_from, params.saturated_full)
    motion = torch.maximum(motion, saturated)
    motion = motion * _ramp(flick, params.flicker_none, params.flicker_full)
    judged = _ramp(n.to(torch.float32), float(params.min_events), float(params.full_events))
    factor = (1.0 - judged * (1.0 - motion)).clamp(0.0, 1.0)
    return MotionEvidence(factor, clus.to(torch.float32), nbx.to(torch.float32), flick, n)


def apply_evidence(out, factor: torch.Tensor):
    """``out`` (:class:`~dvsland.estimators.base.EstimateOut`) with its confidence times ``factor``
    (B,) float32, D_hat NaN (and confidence 0) where the factor is 0, and ``factor`` in its
    diagnostics under :data:`EVIDENCE_KEY`. Where the factor is 1 D_hat and confidence are unchanged."""
    d = out.d_hat
    f = factor.to(device=d.device)
    d = torch.where(f > 0, d, torch.full_like(d, float("nan")))
    conf = out.confidence * f.to(out.confidence.dtype)
    conf = torch.where(torch.isfinite(d), conf, torch.zeros_like(conf))
    diag = dict(out.diagnostics)
    diag[EVIDENCE_KEY] = f
    if "confidence" in diag:
        diag["confidence"] = conf
    return out._replace(d_hat=d, confidence=conf, diagnostics=diag)


def gate_output(out, events, batch_size: int, sensor_size, t_us: int, params: Optional[AbstainParams]):
    """``out`` gated by the motion evidence of ``events`` (unchanged when ``params`` is None or
    ``out`` was gated already)."""
    if params is None or EVIDENCE_KEY in out.diagnostics:
        return out
    ev = motion_evidence(events, batch_size, sensor_size, t_us, params, device=out.d_hat.device)
    return apply_evidence(out, ev.factor)


__all__ = ["AbstainParams", "DEFAULT_ABSTAIN", "EVIDENCE_KEY", "MotionEvidence", "motion_evidence", "check_abstain_params",
           "apply_evidence", "gate_output"]
