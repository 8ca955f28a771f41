"""The training terrains of the spiking estimator: held-out site variants ``<site>~<k>`` (never the
nine evaluation sites), grouped by kind so that one kind can be left out entirely.

Only names live here (no import beyond the standard library): the sequences themselves are
flown on the loop by :mod:`dvsland.data.snn_sequences` (the estimators layer renders and
emulates nothing), and ``scripts/train_snn.py`` wires them to :mod:`.train`.
"""

from __future__ import annotations

from typing import Optional, Sequence

#: the site types of the nine evaluation sites (configs/sites/)
SITE_TYPES = {"craters": "ABC", "craters_rocks": "DE", "rocky": "FG", "featureless": "HI"}


def training_sites(variants: Sequence[int] = (1, 2), sites: str = "ABCDEFGHI",
                   hold_out_type: Optional[str] = None) -> list:
    """Names of the held-out training terrains, e.g. ["A~1", ..., "I~2"], without the sites of
    ``hold_out_type`` (a key of :data:`SITE_TYPES`) when given."""
    if hold_out_type is not None:
        if hold_out_type not in SITE_TYPES:
            raise ValueError(f"hold_out_type must be one of {sorted(SITE_TYPES)}, got {hold_out_type!r}")
        sites = "".join(c for c in sites if c not in SITE_TYPES[hold_out_type])
    return [f"{s}~{k}" for k in variants for s in sites]


__all__ = ["SITE_TYPES", "training_sites"]
