"""Train / val / test splits by site type and terrain variant.

The rule (:class:`SplitRule`, decided per descent from its site and terrain variant, at read
time, so one build serves any rule):

- **test**: every descent on an evaluation terrain, i.e. terrain variant 0 (the shipped sites
  A-I that ``dvsland evaluate``, the campaigns and the paper's table fly, whatever their sun or
  sensor dispersion), and every descent of the held-out site type ``hold_out_type`` (default
  ``craters_rocks``: sites D and E, at every variant), so test measures generalisation to a kind of
  terrain never trained on;
- **val**: the remaining descents on the last terrain variant (``n_variants - 1``: ``X~4`` with
  the Monte Carlo presets' five variants), a terrain never trained on; none when there are fewer
  than three variants;
- **train**: everything else (variants ``1 .. n_variants - 2`` of the other site types).

So no evaluation scene (a site at variant 0) is ever in train or val. Site types are those of
the spiking estimator's training data (:data:`dvsland.estimators.snn.data.SITE_TYPES`:
craters ABC, craters_rocks DE, rocky FG, featureless HI); ``hold_out_type=None`` holds none out.
A site name that is not one of A-I belongs to no type (never held out by type).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

#: split names accepted by the datasets ("all" = every sample)
SPLITS = ("train", "val", "test", "all")


def site_types() -> dict:
    """{type name: site letters}, the one definition of :mod:`dvsland.estimators.snn.data`."""
    from dvsland.estimators.snn.data import SITE_TYPES

    return dict(SITE_TYPES)


@dataclass(frozen=True)
class SplitRule:
    """Which descents go to which split (see the module doc).

    Attributes:
        hold_out_type: a key of :func:`site_types` whose sites are test only, or None.
    """

    hold_out_type: Optional[str] = "craters_rocks"

    def __post_init__(self):
        if self.hold_out_type is not None and self.hold_out_type not in site_types():
            raise ValueError(f"split_rule.hold_out_type must be one of {sorted(site_types())} or None, "
                             f"got {self.hold_out_type!r}")

    def assign(self, sites: Sequence[str], variants: Sequence[int], n_variants: int) -> np.ndarray:
        """The split of each descent: (n,) array of ``"train" | "val" | "test"``.

        Args:
            sites: (n,) base site names (``"A"``; a variant name ``"A~2"`` is reduced to ``"A"``).
            variants: (n,) int terrain variant (0 = the shipped evaluation terrain).
            n_variants: ``dispersion.terrain_variants`` of the build (1 without dispersion).
        """
        held = set(site_types()[self.hold_out_type]) if self.hold_out_type is not None else set()
        base = np.asarray([str(s).split("~")[0] for s in sites], dtype=object)
        var = np.asarray(variants, dtype=np.int64)
        out = np.full(len(base), "train", dtype=object)
        if int(n_variants) >= 3:
            out[var == int(n_variants) - 1] = "val"
        out[np.asarray([b in held for b in base], dtype=bool) | (var == 0)] = "test"
        return out


def check_split(split: str, param: str = "split") -> str:
    """``split`` if it is one of :data:`SPLITS`, else ValueError naming ``param``."""
    if split not in SPLITS:
        raise ValueError(f"{param} must be one of {list(SPLITS)}, got {split!r}")
    return split
