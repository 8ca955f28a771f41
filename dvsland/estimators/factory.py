"""Build the configured estimator for a batch (the simulator's and the evaluator's one way in)."""

from __future__ import annotations

import dataclasses
from typing import Any

from dvsland.config import Config

from .abstain import DEFAULT_ABSTAIN, AbstainParams, check_abstain_params
from .calibrate import (SHIPPED_SETS, calibration_off, checkpoint_sha256, params_to, resolve_calibration,
                        shipped_calibrations)
from .fused import member_names
from .registry import get_estimator, split_alias


def estimator_params(cfg: Config, name: str | None = None) -> dict:
    """Keyword parameters of estimator ``name`` (default ``cfg.estimator.name``) from the config.

    Built-ins take their section (``estimator.dpr``, ``estimator.cmax``, ``estimator.oracle``)
    without the keys the factory reads itself (``estimator.fused.tables``); any other estimator
    takes the free-form ``estimator.params``.
    """
    name = name or cfg.estimator.name
    _, spec = split_alias(name)  # 'fast=dpr' takes estimator.dpr
    section = getattr(cfg.estimator, spec, None)
    if dataclasses.is_dataclass(section):
        params = dataclasses.asdict(section)
        for key in FACTORY_KEYS.get(spec, ()):  # a section is found for a plain name only
            params.pop(key, None)
        return params
    return dict(cfg.estimator.params)


#: keys of an estimator's config section that the factory reads, not the estimator's constructor
FACTORY_KEYS = {"fused": ("tables",)}


def make_estimator(cfg: Config, batch_size: int, device: Any = "cpu", name: str | None = None, seed: int | None = None):
    """Instantiate the configured estimator for ``batch_size`` descents on ``device``.

    The estimator receives ``dt_s`` (the frame interval), ``seed`` and ``principal_point_px`` (the
    camera's focus of expansion, None = the sensor centre) in addition to its params (each only
    where its constructor takes it; see :func:`get_estimator`). ``fused`` gets its members built
    here, each from its own section with its own motion-evidence test, and is calibrated by
    :func:`calibrate_fused`.
    """
    return _build(cfg, batch_size, device, name or cfg.estimator.name, seed, calibrate=True)


def _build(cfg: Config, batch_size: int, device: Any, name: str, seed: int | None, calibrate: bool):
    params = estimator_params(cfg, name)
    params.setdefault("dt_s", cfg.dt_s)
    params.setdefault("seed", cfg.simulation.seed if seed is None else seed)
    params.setdefault("principal_point_px", cfg.camera.principal_point_px)
    fused = _is_fused(name)
    if fused:  # each member from its own section, with its own motion-evidence test; calibrated below
        params["members"] = [(m, _build(cfg, batch_size, device, m, seed, calibrate=False))
                             for m in member_names(params["members"])]
    est = get_estimator(name, batch_size, (cfg.camera.width_px, cfg.camera.height_px), device, **params)
    if fused:
        if calibrate:
            calibrate_fused(est, cfg, name, cfg.estimator.fused.tables)
    else:
        apply_abstain(est, getattr(cfg.estimator, "abstain", None))
        if calibrate:
            apply_calibration(est, cfg, name)
    return est


def _is_fused(name: str) -> bool:
    """Whether estimator ``name`` (an alias ``A=fused`` and options ``fused[...]`` included) is ``fused``."""
    return split_alias(name)[1].split("[", 1)[0].strip() == "fused"


def _fused_set_table(cfg: Config, checkpoint=False) -> bool:
    """Whether ``estimator.calibration`` is a shipped set (``ideal``, ``realistic``) whose
    ``fused_<set>.json`` ships for these members (``estimator.fused.members``) and, unless
    ``checkpoint`` is False (not known yet), for this checkpoint (the text of
    :func:`~.calibrate.checkpoint_sha256`, None where no member reads one): a ``fused`` table
    describes one combination."""
    v = str(getattr(cfg.estimator, "calibration", "none")).strip()
    if v not in SHIPPED_SETS or f"fused_{v}" not in shipped_calibrations():
        return False
    try:
        _, obj = resolve_calibration(v, "fused", checkpoint or None)
    except ValueError:  # fitted on another checkpoint
        return False
    fit = obj.get("fit") or {}
    try:
        same = member_names((fit.get("estimator_params") or {}).get("members", "")) == member_names(
            cfg.estimator.fused.members)
    except ValueError:  # a table without (valid) members, or invalid configured ones: not this combination
        same = False
    if not same:
        return False
    return checkpoint is False or (checkpoint is None) == (fit.get("checkpoint") is None)


def calibrate_fused(est, cfg: Config, name: str, tables: str = "members") -> None:
    """Calibrate a built ``fused``: its combined output by ``fused``'s own table (its members then
    fly raw) where ``estimator.calibration`` names one (a shipped name or a path: it must have been
    fitted for ``fused``) or, with ``tables="own"`` (``estimator.fused.tables``), is a set whose
    ``fused_<set>.json`` ships for these members and their checkpoint (:func:`_fused_set_table`);
    else each member by its own table."""
    value = getattr(cfg.estimator, "calibration", "none")
    if calibration_off(value):
        return
    if str(value).strip() not in SHIPPED_SETS or (tables == "own" and _fused_set_table(cfg, checkpoint_sha256(est))):
        apply_calibration(est, cfg, name)
        return
    for label, member in zip(est.member_labels, est.members):
        apply_calibration(member, cfg, label)


def calibration_names(cfg: Config, name: str) -> tuple:
    """The estimators whose calibration tables ``name`` flies with (checked before a run): ``fused``
    its own where ``estimator.calibration`` is a name or path, or a set with a shipped ``fused``
    table for its members; else its members' (``estimator.fused.members``); any other is itself."""
    if not _is_fused(name) or str(getattr(cfg.estimator, "calibration", "none")).strip() not in SHIPPED_SETS:
        return (name,)
    if cfg.estimator.fused.tables == "own" and _fused_set_table(cfg):
        return (name,)
    return member_names(cfg.estimator.fused.members)


def apply_calibration(est, cfg: Config, name: str) -> None:
    """Set ``est.calibration`` from ``estimator.calibration`` (``none``, a shipped set or name, or a
    path to a table fitted for this estimator and its checkpoint:
    :func:`~.calibrate.resolve_calibration`, whose errors name the key). ``none`` leaves the
    estimator's own setting."""
    value = getattr(cfg.estimator, "calibration", "none")
    if calibration_off(value):  # the default: no checkpoint is hashed
        return
    _, spec = split_alias(name)
    found = resolve_calibration(value, name, checkpoint_sha256(est))
    if found is None:
        return
    est.calibration = params_to(found[0], getattr(est, "device", "cpu"))  # on the estimator's device: no copy per step
    fitted = (found[1].get("fit") or {}).get("estimator_params") or {}
    own = estimator_params(cfg, name)
    diff = sorted(k for k in fitted if k in own and _differs(fitted[k], own[k]))
    if diff:
        import warnings

        warnings.warn(f"estimator.calibration: {value!r} was fitted with "
                      + ", ".join(f"{k}={fitted[k]!r}" for k in diff) + f"; this {spec} runs with "
                      + ", ".join(f"{k}={own[k]!r}" for k in diff) + ": its coverage may not hold (refit it)",
                      RuntimeWarning, stacklevel=2)


def _differs(a, b) -> bool:
    """Whether two parameter values differ (numbers compared as floats, as JSON stores them)."""
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool) and not isinstance(b, bool):
        return float(a) != float(b)
    return a != b


def apply_abstain(est, section) -> None:
    """Set ``est.abstain`` from the ``estimator.abstain`` section (:class:`AbstainParams`, or None when
    ``enabled`` is false). A class that opts out (``abstain = None``) stays out; a section equal to the
    defaults leaves the class's own setting."""
    if section is None or getattr(est, "abstain", None) is None:
        return
    params = AbstainParams(**{k: getattr(section, k) for k in AbstainParams._fields})
    if not section.enabled:
        est.abstain = None
    elif params != DEFAULT_ABSTAIN:
        try:
            check_abstain_params(params)
        except ValueError as exc:
            raise ValueError(f"estimator.{exc}") from None
        est.abstain = params
