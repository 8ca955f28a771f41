"""``LoopStream``: event windows straight from the loop, for training on the fly.

It plans the same shards as :func:`dvsland.data.build_dataset` for the same arguments, flies them
with the same stages and cuts the steps the same way (:mod:`dvsland.data.collect`), so it yields
exactly the samples, in the same order, that ``EventWindowDataset(built folder, split=...)``
holds: deterministic for a config, its ``simulation.seed`` and the seeds.

DataLoader workers: with ``num_workers=0`` (the default) the process flies every shard in
order. With ``num_workers=K`` worker ``w`` flies shards ``w, w + K, ...`` (each shard once over
all workers, each worker building its own stages and renderer), so the loader yields every
sample once per epoch, interleaved by the loader in worker order rather than in shard order.
Each epoch flies the shards again (the same samples: the stream is not randomised; shuffle with a
buffer if needed).
"""

from __future__ import annotations

from typing import Callable, Iterator, Optional, Sequence

import numpy as np
import torch

from .build import resolve_config
from .collect import Flight, descent_table, recording_stages
from .represent import check_representation, represent, targets_of
from .splits import SplitRule, check_split


class LoopStream(torch.utils.data.IterableDataset):
    """Samples ``(input, targets)`` flown live (see the module doc).

    Args:
        config: a :class:`~dvsland.config.Config`, YAML path or shipped name.
        n_seeds, sites, shard_size, estimator, overrides: as for :func:`dvsland.data.build_dataset`.
        representation, split, n_bins, valid_only, split_rule, transform, target_transform: as for
            :class:`dvsland.data.EventWindowDataset`.
        device: torch device the loop flies on (default ``simulation.device``).
    """

    def __init__(self, config=None, n_seeds: int = 1, sites=None, shard_size: int = 5,
                 estimator: Optional[str] = "oracle", overrides: Sequence[str] = (), representation: str = "count",
                 split: str = "all", n_bins: int = 5, valid_only: bool = True, split_rule: Optional[SplitRule] = None,
                 transform: Optional[Callable] = None, target_transform: Optional[Callable] = None, device=None):
        from dvsland.campaign import make_plan

        check_representation(representation, n_bins)
        check_split(split)
        self.cfg = resolve_config(config, overrides, sites, estimator)
        self.plan = make_plan(self.cfg, (), n_seeds, shard_size)
        self.representation, self.split, self.n_bins, self.valid_only = representation, split, int(n_bins), valid_only
        self.rule = split_rule or SplitRule()
        self.transform, self.target_transform = transform, target_transform
        self.device = device or self.cfg.simulation.device
        self.sites = [s.name for s in self.cfg.simulation.sites]
        self.sensor_size = (int(self.cfg.camera.width_px), int(self.cfg.camera.height_px))
        disp = self.cfg.dispersion
        self.n_variants = int(disp.terrain_variants) if disp.enabled else 1

    def _my_shards(self) -> list:
        info = torch.utils.data.get_worker_info()
        shards = list(self.plan.shards)
        return shards if info is None else shards[info.id::info.num_workers]

    def __iter__(self) -> Iterator:
        for sh in self._my_shards():
            yield from self._shard_samples(sh)

    def _shard_samples(self, sh) -> Iterator:
        from dvsland.campaign.plan import config_from_dict

        cfg = config_from_dict(self.plan.config, sh.overrides())
        if cfg.simulation.torch_threads > 0:
            torch.set_num_threads(int(cfg.simulation.torch_threads))
        stages, crop = recording_stages(cfg, self.device)
        desc = descent_table(stages.layout)
        split = self.rule.assign(desc["site"], desc["variant"], self.n_variants)
        site_index = [self.sites.index(str(s)) for s in desc["site"]]
        for st in Flight(stages, crop=crop):
            ends = np.cumsum(st.counts)
            for j, d in enumerate(st.samples["descent"]):
                if (self.valid_only and not st.samples["valid"][j]) or (self.split not in ("all", split[d])):
                    continue
                a, b = int(ends[j] - st.counts[j]), int(ends[j])
                ev = {k: v[a:b] for k, v in st.events.items()}
                x = represent(ev, int(st.samples["t0_us"][j]), int(st.samples["t_us"][j]), self.sensor_size,
                              self.representation, self.n_bins)
                y = targets_of(st.samples, j, desc, site_index[d], b - a)
                yield (x if self.transform is None else self.transform(x),
                       y if self.target_transform is None else self.target_transform(y))
