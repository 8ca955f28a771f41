"""The estimator extension point: registry, entry points, factory from the config."""

from __future__ import annotations

import sys
import textwrap

import pytest
import torch

from dvsland.config import load_config
from dvsland.estimators import (DivergenceEstimator, available_estimators, get_estimator, make_estimator,
                                refresh_entry_points, register_estimator)
from dvsland.estimators import registry


def test_builtins_registered():
    names = available_estimators()
    for n in ("dpr", "cmax", "oracle"):
        assert n in names


def test_unknown_name_lists_known():
    with pytest.raises(ValueError) as err:
        get_estimator("no-such-estimator", 2, (8, 8))
    msg = str(err.value)
    assert "no-such-estimator" in msg and "dpr" in msg and "cmax" in msg and "oracle" in msg


def test_register_decorator_and_bad_name():
    @register_estimator("test-const")
    class Const(DivergenceEstimator):
        def reset(self, mask=None):
            pass

        def update(self, events, t_us, truth=None):
            return torch.full((self.batch_size,), -0.1)

    try:
        est = get_estimator("test-const", 3, (8, 8))
        assert isinstance(est, Const) and est.update(None, 0).shape == (3,)
    finally:
        registry._REGISTRY.pop("test-const", None)
    with pytest.raises(ValueError, match="name"):
        register_estimator("")


def test_entry_point_plugin_found_by_name(tmp_path, monkeypatch):
    """A third-party package that declares a 'dvsland.estimators' entry point (no network)."""
    pkg = tmp_path / "mylander_est"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(textwrap.dedent('''
        import torch
        from dvsland.estimators import DivergenceEstimator

        class Half(DivergenceEstimator):
            def reset(self, mask=None):
                pass

            def update(self, events, t_us, truth=None):
                return torch.full((self.batch_size,), -0.5)
    '''))
    dist = tmp_path / "mylander_est-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: mylander-est\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[dvsland.estimators]\nhalf-plugin = mylander_est:Half\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        assert "half-plugin" not in registry._REGISTRY
        refresh_entry_points()
        assert "half-plugin" in available_estimators()
        est = get_estimator("half-plugin", 2, (16, 16))
        assert est.update(None, 100_000).tolist() == [-0.5, -0.5]
    finally:
        registry._REGISTRY.pop("half-plugin", None)
        sys.modules.pop("mylander_est", None)


def test_broken_entry_point_warns_not_crashes(tmp_path, monkeypatch):
    dist = tmp_path / "broken_est-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-est\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[dvsland.estimators]\nbroken-plugin = no_such_module_xyz:Nope\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.warns(UserWarning, match="broken-plugin"):
        refresh_entry_points()
    assert "broken-plugin" not in available_estimators()


@pytest.mark.parametrize("name", ["dpr", "cmax", "oracle"])
def test_make_estimator_from_paper_config(paper_yaml, name):
    cfg = load_config(paper_yaml)
    est = make_estimator(cfg, 4, name=name)
    assert est.batch_size == 4 and est.sensor_size == (cfg.camera.width_px, cfg.camera.height_px)
    assert est.dt_s == pytest.approx(cfg.dt_s)
