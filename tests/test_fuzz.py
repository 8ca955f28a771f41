"""Fuzzing (hypothesis) of every public entry point: config fields, ``--set``, event files and
arrays, Events, frames given to the emulator, CLI arguments and the Python API.

The property everywhere: a bad input gets one clear error of the documented type (ConfigError,
EventDataError, ValueError) that names the parameter; never a traceback from deep inside numpy
or torch, and never a silent success. Examples are few per test (the suite stays fast); the
strategies aim at the edges (range limits, NaN, inf, wrong types)."""

from __future__ import annotations

import dataclasses
import math
import typing

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import dvsland
from dvsland.cli.main import main
from dvsland.config import Config, ConfigError, config_to_dict, validate_config
from dvsland.config.schema import LIST_ITEM_TYPES
from dvsland.config.validate import _strip_optional
from dvsland.events import EventDataError, EventEmulator, Events, load_events, save_events

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


# ------------------------------------------------------------------ the config schema
def _leaves(cls=Config, prefix=(), owner=None):
    """(path tuple, field metadata, field type) of every scalar field; lists by their item 0."""
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp, _ = _strip_optional(hints[f.name])
        path = prefix + (f.name,)
        if dataclasses.is_dataclass(tp):
            out += _leaves(tp, path)
        elif tp is list:
            item = LIST_ITEM_TYPES.get((cls, f.name))
            if item is not None:
                out += _leaves(item, path + (0,))
        else:
            out.append((path, f.metadata, tp))
    return out


LEAVES = _leaves()


def _bad_values(md, tp):
    """Values the field must refuse: outside its range, NaN, inf, wrong types."""
    bad = []
    wrong_type = [[1, 2], {"a": 1}]
    if tp in (int, float):
        bad += [float("nan"), float("inf"), float("-inf"), "abc", True] + wrong_type
        if md.get("rng"):
            lo, hi = md["rng"]
            if math.isfinite(lo):
                bad.append(lo if md.get("open_lo") else lo - max(1.0, abs(lo)) * 0.5)
            if math.isfinite(hi):
                bad.append(hi if md.get("open_hi") else hi + max(1.0, abs(hi)) * 0.5)
        if tp is int:
            bad.append(1.5)
    elif tp is bool:
        bad += ["maybe", 2, 0.5] + wrong_type
    elif tp is str:
        bad += wrong_type
        if md.get("choices"):
            bad += ["bogus-choice", ""]
    elif tp is dict:
        bad += [[1, 2], "text", 3]
    return bad


CASES = [(path, v) for path, md, tp in LEAVES for v in _bad_values(md, tp)]


def _set_in(data, path, value):
    node = data
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value


def _dotted(path):
    return ".".join(str(p) for p in path if not isinstance(p, int))


def test_every_field_has_bad_values():
    assert len(LEAVES) > 60
    fields_with_cases = {p for p, _ in CASES}
    uncovered = [p for p, md, tp in LEAVES if p not in fields_with_cases]
    # only free-text strings have no bad value of their own (any text is a valid label / path)
    assert all(tp is str for p, md, tp in LEAVES if p in uncovered)


@FUZZ
@given(case=st.sampled_from(CASES))
def test_config_field_fuzz_file_path(case):
    """As from a YAML file or --set: a mapping."""
    path, value = case
    data = config_to_dict(Config())
    _set_in(data, path, value)
    with pytest.raises(ConfigError) as ei:
        validate_config(data)
    assert path[-1] in str(ei.value), str(ei.value)


@FUZZ
@given(case=st.sampled_from(CASES))
def test_config_field_fuzz_python_path(case):
    """As a Config object edited in Python and given to the API: the same check."""
    path, value = case
    cfg = Config()
    obj = cfg
    for k in path[:-1]:
        obj = obj[k] if isinstance(k, int) else getattr(obj, k)
    setattr(obj, path[-1], value)
    with pytest.raises(ConfigError) as ei:
        validate_config(cfg)
    assert path[-1] in str(ei.value), str(ei.value)


_KEYS = st.sampled_from([_dotted(p) if 0 not in p else
                         ".".join(str(x) for x in p) for p, _, _ in LEAVES] + ["simulation.sites.99.z0_m",
                                                                              "nope", "camera.nope", "a.b.c",
                                                                              "simulation.sites.x", "simulation.sites.9",
                                                                              "controller.settings.5"])
_VALS = st.one_of(st.text(max_size=12), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                  st.integers(-10**12, 10**12).map(str), st.sampled_from(["[1, 2]", "{a: 1}", "null", "-.inf", ".nan",
                                                                          "", "[", "true"]))


@FUZZ
@given(key=_KEYS, value=_VALS)
def test_set_override_fuzz(key, value):
    """``--set key=value`` with any text: a valid config or a ConfigError, nothing else."""
    from dvsland.config import load_config

    try:
        load_config(None, [f"{key}={value}"])
    except ConfigError as exc:
        assert str(exc)


@FUZZ
@given(argv=st.lists(st.sampled_from(["--set", "camera.fov_deg=nan", "simulation.sites.20=A", "--bogus", "x",
                                      "estimator.name=", "=", "camera=3", "paper", "nonexistent.yaml",
                                      "logging.root=", "name=../x", "--quiet"]), max_size=5))
def test_cli_config_show_fuzz(argv, capsys):
    """Random CLI arguments: exit code 0 or 2 with a message, never an exception."""
    try:
        rc = main(["config", "show", *argv])
    except SystemExit as exc:  # argparse's own usage errors
        rc = exc.code
    assert rc in (0, 2)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    if rc == 2:
        assert err.strip()


# ------------------------------------------------------------------ the Python API
@FUZZ
@given(kw=st.one_of(
    st.fixed_dictionaries({"sites": st.one_of(st.just("Z"), st.just(""), st.integers(), st.just([1, 2]))}),
    st.fixed_dictionaries({"estimator": st.one_of(st.just(""), st.just("bogus"), st.integers(), st.just(object()))}),
    st.fixed_dictionaries({"device": st.sampled_from(["mps", "bogus", "", "cuda:x", "cpu:0:1"])}),
    st.fixed_dictionaries({"renderer": st.sampled_from(["", "bogus", "FAST"])}),
    st.fixed_dictionaries({"config": st.one_of(st.integers(), st.just("no/such/file.yaml"), st.just([1]))}),
    st.fixed_dictionaries({"out": st.sampled_from(["", "/proc/dvsland/x"])}),
))
def test_simulate_bad_kwargs(kw, tmp_path):
    kw = dict(kw)
    kw.setdefault("estimator", "oracle")
    with pytest.raises(ValueError):
        dvsland.simulate(kw.pop("config", None), quiet=True,
                         overrides=[f"logging.root={tmp_path / 'logs'}", "simulation.t_max_s=0.2"], **kw)


# ------------------------------------------------------------------ Events and the emulator
_INTS = st.integers(-2 ** 63, 2 ** 63 - 1)


@FUZZ
@given(n=st.integers(0, 6), data=st.data())
def test_events_construction_fuzz(n, data):
    """Events(...) with any integer values: built, and validate() either passes or names a field."""
    fields = {k: torch.tensor(data.draw(st.lists(_INTS, min_size=n, max_size=n)), dtype=torch.int64)
              for k in ("b", "x", "y", "t")}
    p = torch.tensor(data.draw(st.lists(st.integers(-128, 127), min_size=n, max_size=n)), dtype=torch.int8)
    ev = Events(**fields, p=p, sort=data.draw(st.booleans()))
    ev.is_sorted()  # never overflows
    try:
        ev.validate(batch_size=4, height=8, width=8)
    except EventDataError as exc:
        assert "'" in str(exc) or "sorted" in str(exc)


@FUZZ
@given(kind=st.sampled_from(["float", "2d", "len", "complex"]))
def test_events_bad_tensors(kind):
    z = torch.zeros(3, dtype=torch.int64)
    f = {"b": z, "x": z, "y": z, "t": z, "p": z.to(torch.int8)}
    if kind == "float":
        f["t"] = torch.tensor([0.0, float("nan"), 1.0])
    elif kind == "2d":
        f["x"] = torch.zeros(3, 1, dtype=torch.int64)
    elif kind == "len":
        f["y"] = torch.zeros(2, dtype=torch.int64)
    else:
        f["t"] = torch.zeros(3, dtype=torch.complex64)
    with pytest.raises(ValueError):
        Events(**f)


@FUZZ
@given(kind=st.sampled_from(["nan", "inf", "neg", "shape", "int", "batch", "sensor", "1d", "empty"]),
       where=st.integers(0, 63))
def test_emulator_frames_fuzz(kind, where):
    emu = EventEmulator()
    good = torch.full((2, 4, 8), 0.3)
    emu.reset(good, 0)
    f = good.clone()
    if kind == "nan":
        f.view(-1)[where] = float("nan")
    elif kind == "inf":
        f.view(-1)[where] = float("inf")
    elif kind == "neg":
        f.view(-1)[where] = -1e-3
    elif kind == "shape":
        f = f.reshape(2, 8, 4)
    elif kind == "int":
        f = f.to(torch.int32)
    elif kind == "batch":
        f = f[:1]
    elif kind == "sensor":
        f = f[:, :3]
    elif kind == "1d":
        f = f.reshape(-1)
    else:
        f = torch.empty(0, 4, 8)
    with pytest.raises(ValueError):
        emu.step(f, 100_000)


# ------------------------------------------------------------------ event files
@pytest.fixture(scope="module")
def good_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("ev")
    g = torch.Generator().manual_seed(0)
    n = 300
    ev = Events(b=torch.randint(0, 2, (n,), generator=g), x=torch.randint(0, 32, (n,), generator=g),
                y=torch.randint(0, 24, (n,), generator=g), t=torch.randint(0, 10**6, (n,), generator=g),
                p=(torch.randint(0, 2, (n,), generator=g) * 2 - 1).to(torch.int8), sort=True)
    out = {"npz": save_events(d / "e.npz", ev, sensor_size=(32, 24), batch_size=2).read_bytes()}
    try:
        import h5py  # noqa: F401

        out["h5"] = save_events(d / "e.h5", ev, sensor_size=(32, 24), batch_size=2).read_bytes()
    except ImportError:
        pass
    return out


def _load_or_clear_error(path):
    try:
        ev = load_events(path)
    except EventDataError as exc:
        assert str(exc)
        return None
    ev.validate()  # whatever loads is usable
    return ev


@FUZZ
@given(data=st.data())
def test_event_file_corruption_fuzz(good_files, tmp_path, data):
    """Truncated files and flipped bytes: the events load (and are valid) or one EventDataError."""
    fmt = data.draw(st.sampled_from(sorted(good_files)))
    raw = bytearray(good_files[fmt])
    if data.draw(st.booleans()):
        raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
    else:
        for _ in range(data.draw(st.integers(1, 8))):
            i = data.draw(st.integers(0, len(raw) - 1))
            raw[i] = data.draw(st.integers(0, 255))
    path = tmp_path / f"fuzz.{fmt}"
    path.write_bytes(bytes(raw))
    _load_or_clear_error(path)


_ARR = st.one_of(
    st.lists(st.integers(-2 ** 63, 2 ** 63 - 1), max_size=5).map(lambda v: np.array(v, dtype=np.int64)),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=5).map(lambda v: np.array(v, dtype=np.float64)),
    st.lists(st.integers(0, 2 ** 64 - 1), max_size=5).map(lambda v: np.array(v, dtype=np.uint64)),
    st.lists(st.booleans(), max_size=5).map(np.array),
    st.just(np.zeros((2, 2), np.int64)),
    st.just(np.array(["a", "b"])),
)


@FUZZ
@given(arrs=st.fixed_dictionaries({k: _ARR for k in ("b", "x", "y", "t", "p")}),
       sensor=st.sampled_from([None, np.array([8, 8, 2]), np.array([-1, 3, 2]), np.array([np.nan, 1, 2]),
                               np.array([1, 2])]))
def test_event_arrays_fuzz(arrs, sensor, tmp_path):
    """Random arrays in an npz: valid events or one EventDataError."""
    path = tmp_path / "a.npz"
    extra = {} if sensor is None else {"meta_sensor_size": sensor}
    with open(path, "wb") as fh:
        np.savez(fh, **arrs, **extra)
    _load_or_clear_error(path)


@FUZZ
@given(arrs=st.fixed_dictionaries({k: _ARR for k in ("x", "y", "t", "p")}))
def test_tonic_arrays_fuzz(arrs):
    n = min(len(a) for a in arrs.values())
    try:
        arr = np.zeros(n, dtype=[(k, arrs[k].dtype) for k in ("x", "y", "t", "p")])
        for k in arrs:
            arr[k] = arrs[k][:n]
    except (ValueError, TypeError):
        return  # numpy itself refuses to build this structured array: nothing reaches dvsland
    try:
        Events.from_tonic(arr)
    except EventDataError as exc:
        assert str(exc)


# ------------------------------------------------------------------ checkpoints
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_snn_checkpoint_corruption_fuzz(tmp_path, data):
    """A truncated or byte-flipped checkpoint: the shipped weights load or one ValueError naming
    estimator.snn.checkpoint; never torch's unpickling advice."""
    from dvsland.estimators import get_estimator
    from dvsland.estimators.snn.estimator import DEFAULT_CHECKPOINT

    raw = bytearray(DEFAULT_CHECKPOINT.read_bytes())
    if data.draw(st.booleans()):
        raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
    else:
        for _ in range(data.draw(st.integers(1, 16))):
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    path = tmp_path / "ck.pt"
    path.write_bytes(bytes(raw))
    try:
        get_estimator("snn", 1, (128, 128), checkpoint=str(path))
    except ValueError as exc:
        assert "estimator.snn.checkpoint" in str(exc)
