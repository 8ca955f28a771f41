"""Aliases for estimators: ``--estimator mine=pkg.mod:Class`` (or ``estimator.name:
mine=...``, ``fast=dpr[baseline_steps=5]`` in ``evaluate --estimators``) builds the estimator after
``=`` and shows it as ``mine`` in tables, JSON keys, figures and TensorBoard."""

from __future__ import annotations

import json

import pytest
import yaml

from dvsland.cli.main import main
from dvsland.config import ConfigError, load_config
from dvsland.estimators import estimator_label, get_estimator
from dvsland.estimators.factory import estimator_params
from dvsland.estimators.registry import estimator_class, split_alias

SMALL = ["--set", "camera.width_px=32", "--set", "camera.height_px=32"]


@pytest.fixture
def user_module(tmp_path, monkeypatch, half_estimator_source):
    (tmp_path / "alias_user_estimators.py").write_text(half_estimator_source)
    monkeypatch.chdir(tmp_path)  # found in the current directory, as a user's own module
    return "alias_user_estimators:Half"


class TestSplitAlias:
    @pytest.mark.parametrize("text,expected", [
        ("mine=pkg.mod:Class", ("mine", "pkg.mod:Class")),
        ("fast=dpr[baseline_steps=5]", ("fast", "dpr[baseline_steps=5]")),
        ("cmax[window_ms=300]", (None, "cmax[window_ms=300]")),
        ("dpr", (None, "dpr")),
        ("my-est.v2 = path/to/file.py:Cls", ("my-est.v2", "path/to/file.py:Cls")),
        ("dpr=dpr", ("dpr", "dpr")),
    ])
    def test_smoke(self, text, expected):
        assert split_alias(text) == expected
        assert estimator_label(text) == (expected[0] or text)

    @pytest.mark.parametrize("text,needle", [("1x=dpr", "plain name"), ("my est=dpr", "plain name"),
                                             ("=dpr", "plain name"), ("mine=", "nothing after"),
                                             ("cmax=dpr", "already a registered estimator")])
    def test_refused(self, text, needle):
        with pytest.raises(ValueError, match=needle):
            split_alias(text)
        assert estimator_label(text) == text  # display never raises

    def test_builds_what_follows(self, user_module):
        assert estimator_class(f"half={user_module}") is estimator_class(user_module)
        est = get_estimator(f"half={user_module}", 2, (32, 32))
        assert type(est).__name__ == "Half" and est.batch_size == 2
        cfg = load_config("paper", ["estimator.dpr.baseline_steps=5"])
        assert estimator_params(cfg, "fast=dpr") == estimator_params(cfg, "dpr")  # an alias of a built-in keeps its section


def test_config_name_with_alias_is_checked(tmp_path, user_module):
    from dvsland.stages import check_names

    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump({"extends": "paper", "estimator": {"name": f"half={user_module}"}}))
    check_names(load_config(p))
    with pytest.raises(ConfigError, match=r"estimator\.name.*plain name"):
        check_names(load_config("paper", ["estimator.name=9lives=dpr"]))


def test_evaluate_shows_the_alias_everywhere(tmp_path, user_module, capsys):
    out = tmp_path / "ev"
    rc = main(["evaluate", "--estimators", f"half={user_module},fast=dpr[baseline_steps=5],oracle",
               "--sites", "D", "--max-steps", "4", "--warmup-steps", "0", "--no-figures", "--out", str(out),
               *SMALL])
    assert rc == 0
    printed = capsys.readouterr().out
    res = json.loads((out / "evaluation.json").read_text())
    assert set(res["estimators"]) == {"half", "fast", "oracle"}
    assert "alias_user_estimators" not in json.dumps(res["estimators"])
    assert "half" in printed and "alias_user_estimators:Half" not in printed
    folders = {p.name for p in (out / "tb").rglob("*") if p.is_dir()}
    assert {"half", "fast", "oracle"} <= folders, folders
    # the alias' estimate is the one of the class it names: half of the oracle's
    import numpy as np

    tr = np.load(out / "traces.npz")
    np.testing.assert_allclose(tr["d_hat_half"][:, 1:], 0.5 * tr["d_hat_oracle"][:, 1:], rtol=1e-6)


def test_evaluate_refuses_two_equal_labels_before_the_folder(tmp_path, capsys):
    out = tmp_path / "ev"
    assert main(["evaluate", "--estimators", "a=dpr,a=cmax", "--out", str(out)]) == 2
    assert "a named twice" in capsys.readouterr().err and not out.exists()


def test_simulate_and_campaign_groups_show_the_alias(tmp_path, user_module):
    from dvsland.report.stats import group_stats
    from dvsland.report.tensorboard import _estimator_label

    out = tmp_path / "sim"
    spec = f"half={user_module}"
    assert main(["simulate", "--sites", "D", "--estimator", spec, "--out", str(out), *SMALL,
                 "--set", "simulation.t_max_s=0.3", "--set", "logging.figures=false", "--quiet"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["status"] == "complete" and res["estimator"] == spec  # the file records what was built
    runs = res["runs"]
    groups = group_stats(runs, ["site", "estimator"])
    assert {g["estimator"] for g in groups} == {"half"}
    assert _estimator_label(runs[0]["estimator"]) == "half"
    swept = [dict(r, sweep={"estimator.name": spec}) for r in runs]
    assert {g["sweep.estimator.name"] for g in group_stats(swept, ["sweep.estimator.name"])} == {"half"}
