"""Validation of the ``dispersion`` config section (no torch: the config package stays light).

The sampling itself lives in :mod:`dvsland.layout.dispersion`."""

from __future__ import annotations

KINDS = ("off", "fixed", "uniform", "normal")


def check_distribution(dist, path: str) -> None:
    """ValueError naming ``path`` when ``dist`` (a Dispersion) is inconsistent."""
    kind = dist.kind
    if kind not in KINDS:
        raise ValueError(f"{path}.kind: {kind!r} is not allowed; choose one of {list(KINDS)}")
    if kind == "uniform" and not (dist.low <= dist.high):
        raise ValueError(f"{path}: uniform needs low <= high, got low={dist.low}, high={dist.high}")
    if kind == "normal":
        if not dist.std >= 0:
            raise ValueError(f"{path}.std: must be >= 0, got {dist.std}")
        if not (dist.low <= dist.high):
            raise ValueError(f"{path}: normal is clipped to [low, high]; needs low <= high, "
                             f"got low={dist.low}, high={dist.high}")


def check_dispersion_config(dcfg, source: str = "") -> None:
    """Cross-field checks of a :class:`~dvsland.config.schema.DispersionConfig`: every enabled
    distribution is consistent and its possible draws lie in the parameter's allowed range.
    ValueError naming the parameter (``dispersion.<name>``) and the range."""
    from .schema import DISPERSION_RANGES

    where = f" (in {source})" if source else ""
    for name, (lo, hi) in DISPERSION_RANGES.items():
        dist = getattr(dcfg, name)
        path = f"dispersion.{name}"
        try:
            check_distribution(dist, path)
        except ValueError as exc:
            raise ValueError(f"{exc}{where}") from None
        if dist.kind == "off":
            continue
        vals = {"fixed": [dist.value], "uniform": [dist.low, dist.high], "normal": [dist.low, dist.high, dist.mean]}
        for v in vals[dist.kind]:
            if not (lo <= v <= hi):
                raise ValueError(f"{path}{where}: {dist.kind} draws must lie in [{lo}, {hi}], got {v}")
