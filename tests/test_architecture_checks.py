"""One range-check helper, one range per parameter, unknown keys rejected with the allowed ones,
one override syntax."""

from __future__ import annotations

import math

import pytest

from dvsland.checks import check_choice, check_fields, check_keys, check_range, field_bounds
from dvsland.config import ConfigError, DPRConfig, load_config


@pytest.mark.parametrize("value,kw,ok", [
    (0.5, dict(lo=0.5, hi=64.0), True),
    (64.0, dict(lo=0.5, hi=64.0), True),
    (0.49, dict(lo=0.5, hi=64.0), False),
    (0.0, dict(lo=0.0, hi=1.0, open_lo=True), False),
    (1.0, dict(lo=0.0, hi=1.0, open_hi=True), False),
    (math.nan, dict(lo=0.0, hi=1.0), False),
    (math.inf, dict(lo=0.0, hi=1.0), False),
    (math.inf, dict(lo=0.0, hi=math.inf), True),
    ("3", dict(lo=0.0, hi=5.0), True),
    ("x", dict(lo=0.0, hi=5.0), False),
    (7, dict(lo=0), True),
])
def test_check_range(value, kw, ok):
    lo, hi = kw.pop("lo", None), kw.pop("hi", None)
    if ok:
        assert check_range("p", value, lo, hi, **kw) is value
    else:
        with pytest.raises(ValueError, match=r"^p: .* is out of range; allowed [\[(]"):
            check_range("p", value, lo, hi, **kw)


def test_check_range_custom_error_and_where():
    with pytest.raises(ConfigError, match=r"emulator.threshold \(in c.yaml\): 0 is out of range; allowed \(0.0, 10.0\]"):
        check_range("emulator.threshold", 0, 0.0, 10.0, open_lo=True, where=" (in c.yaml)", error=ConfigError)


def test_check_choice_and_keys():
    assert check_choice("mode", "a", ("a", "b")) == "a"
    with pytest.raises(ValueError, match=r"mode: 'c' is not allowed; choose one of \['a', 'b'\]"):
        check_choice("mode", "c", ("a", "b"))
    check_keys("thing", ["a"], ["a", "b"])
    with pytest.raises(ValueError, match=r"thing: unknown keys \['x', 'y'\]; allowed: \['a', 'b'\]"):
        check_keys("thing", ["a", "y", "x"], ["b", "a"])


def test_radius_px_has_one_range():
    """The schema's range is the class's range (it used to accept 0.001 px in the class)."""
    from dvsland.estimators import get_estimator

    b = field_bounds(DPRConfig, "radius_px")
    assert (b["lo"], b["hi"]) == (0.5, 64.0)
    get_estimator("dpr", 1, (32, 32), radius_px=0.5)
    with pytest.raises(ValueError, match=r"radius_px: 0.1 is out of range; allowed \[0.5, 64.0\]"):
        get_estimator("dpr", 1, (32, 32), radius_px=0.1)
    with pytest.raises(ConfigError, match=r"estimator.dpr.radius_px.*allowed \[0.5, 64.0\]"):
        load_config("paper", ["estimator.dpr.radius_px=0.1"])
    with pytest.raises(ValueError, match="pair_weighting"):
        check_fields(DPRConfig, pair_weighting="area")


@pytest.mark.parametrize("name,params,needle", [
    ("cmax", {"window_ms": 0.5}, r"window_ms: 0.5 is out of range; allowed \[1.0, 10000.0\]"),
    ("cmax", {"blur_sigma_px": 20.0}, r"blur_sigma_px: 20.0 is out of range; allowed \[0.0, 16.0\]"),
    ("oracle", {"noise_abs": -1.0}, r"noise_abs: -1.0 is out of range; allowed \[0.0, 100.0\]"),
    ("snn", {"warmup_steps": -1}, r"warmup_steps: -1 is out of range; allowed \[0, 10000\]"),
])
def test_constructors_use_the_schema_ranges(name, params, needle):
    from dvsland.estimators import get_estimator

    with pytest.raises(ValueError, match=needle):
        get_estimator(name, 1, (32, 32), **params)


@pytest.mark.parametrize("name,params", [
    ("dpr", {"radiuss_px": 3.0}),
    ("cmax", {"window": 300}),
    ("oracle", {"noise": 0.1}),
    ("snn", {"check_point": "x.pt"}),
])
def test_misspelt_estimator_keys_are_rejected(name, params):
    from dvsland.estimators import get_estimator

    with pytest.raises(ValueError, match=rf"estimator '{name}': unknown key \['{list(params)[0]}'\]; allowed: \["):
        get_estimator(name, 1, (32, 32), **params)


def test_context_params_pass_only_where_taken():
    from dvsland.estimators import get_estimator

    est = get_estimator("dpr", 1, (32, 32), dt_s=0.05, seed=3)  # dpr takes no seed: not passed
    assert est.dt_s == 0.05


def test_estimator_variant_maps_onto_set():
    from dvsland.evaluate.run import parse_estimator_spec, variant_config

    cfg = load_config("paper")
    label, name, over = parse_estimator_spec("cmax[window_ms=300;n_grid=7]")
    v = variant_config(cfg, name, over, label)
    assert v.estimator.cmax.window_ms == 300.0 and isinstance(v.estimator.cmax.window_ms, float)
    assert v == load_config("paper", ["estimator.cmax.window_ms=300", "estimator.cmax.n_grid=7"])
    assert cfg.estimator.cmax.window_ms == 1000.0  # the base config is untouched
    with pytest.raises(ConfigError, match=r"estimator.cmax.window_ms \(in estimator spec cmax\[window_ms=0\]\)"
                                          r": 0.0 is out of range; allowed \[1.0, 10000.0\]"):
        variant_config(cfg, "cmax", {"window_ms": 0}, "cmax[window_ms=0]")
    with pytest.raises(ConfigError, match=r"unknown key 'estimator.cmax.windw_ms'.*known keys here: \["):
        variant_config(cfg, "cmax", {"windw_ms": 5})


def test_site_specs_use_the_config_validation():
    from dvsland.terrain.spec import spec_from_dict

    with pytest.raises(ConfigError, match=r"craters.density \(in s.yaml\): 20.0 is out of range; allowed \[0.0, 10.0\]"):
        spec_from_dict({"craters": {"density": 20}}, "s.yaml")
    with pytest.raises(ConfigError, match=r"unknown key 'boulders.size'.*known keys here: \['d_max_m'"):
        spec_from_dict({"boulders": {"size": 1}}, "s.yaml")
    with pytest.raises(ValueError, match=r"craters.d_max_m.*must be >= craters.d_min_m"):
        spec_from_dict({"craters": {"d_min_m": 10, "d_max_m": 5}}, "s.yaml")
