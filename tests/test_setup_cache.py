"""Set-up that does not scale with the seeds: a dispersed scene's terrain fields are cached on disk,
so another sun re-shades them; the result equals a preparation from scratch bit for bit."""

from __future__ import annotations

import pytest
import torch

import dvsland.render.lod as lod
import dvsland.render.scenes as scenes
from dvsland.render.lod import LevelParams
from dvsland.render.scenes import fields_path, load_scene, prepare_scene_levels

PARAMS = LevelParams(level_size=40, gutter=2, base_texel_m=0.5, n_levels=3)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("DVSLAND_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(scenes, "_FIELDS", {})
    monkeypatch.setattr(scenes, "_MEMORY", {})
    monkeypatch.setattr(lod, "_MEMORY", scenes._MEMORY)
    return tmp_path / "cache"


def _forget():
    scenes._FIELDS.clear()
    scenes._MEMORY.clear()


def test_fields_are_written_once_and_reused_bit_identically(cache, monkeypatch):
    first = prepare_scene_levels(load_scene("E~2@el12"), PARAMS, "E~2@el12")
    assert first.source == "computed"
    files = sorted((cache / "fields").glob("*.pt"))
    assert len(files) == PARAMS.n_levels
    _forget()
    calls = []
    real = scenes.Terrain.fields
    monkeypatch.setattr(scenes.Terrain, "fields", lambda self, g: calls.append(g) or real(self, g))
    other = prepare_scene_levels(load_scene("E~2@el17"), PARAMS, "E~2@el17")  # new sun: shading only
    assert other.source == "computed" and calls == []
    _forget()
    monkeypatch.setenv("DVSLAND_CACHE_DIR", "off")
    scratch = prepare_scene_levels(load_scene("E~2@el17"), PARAMS, "E~2@el17", disk_cache=False)
    assert len(calls) == PARAMS.n_levels  # from scratch: the fields were computed
    assert torch.equal(other.irradiance, scratch.irradiance) and torch.equal(other.height_m, scratch.height_m)
    assert other.h0_m == scratch.h0_m


def test_broken_fields_file_is_recomputed(cache):
    ref = prepare_scene_levels(load_scene("B~1@el14"), PARAMS, "B~1@el14")
    _forget()
    for f in (cache / "fields").glob("*.pt"):
        f.write_bytes(b"not a torch file")
    for f in cache.glob("*.pt"):
        f.unlink()  # the scene itself is prepared again
    again = prepare_scene_levels(load_scene("B~1@el14"), PARAMS, "B~1@el14")
    assert torch.equal(ref.irradiance, again.irradiance)


def test_cache_off_writes_nothing(cache, monkeypatch):
    monkeypatch.setenv("DVSLAND_CACHE_DIR", "off")
    assert fields_path("x") is None
    prepare_scene_levels(load_scene("C@el13"), PARAMS, "C@el13")
    assert not cache.exists()
