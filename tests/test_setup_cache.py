"""Set-up that does not scale with the seeds: a dispersed scene's terrain fields are cached on disk,
so another sun re-shades them; the result equals a preparation from scratch bit for bit."""

from __future__ import annotations

from pathlib import Path

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


def test_cached_levels_are_mapped_from_their_file_and_equal(cache):
    ref = prepare_scene_levels(load_scene("D~3@el15"), PARAMS, "D~3@el15")
    _forget()
    again = prepare_scene_levels(load_scene("D~3@el15"), PARAMS, "D~3@el15")
    assert again.source == "disk"
    assert torch.equal(ref.irradiance, again.irradiance) and torch.equal(ref.height_m, again.height_m)
    (path,) = cache.glob("*.pt")
    # mapped, not copied into process memory (lod.load_cached)
    assert _mapped_from(again.irradiance.data_ptr()) == str(path)


def _mapped_from(address: int):
    """The file whose mapping holds ``address`` in this process (Linux ``/proc/self/maps``), or None."""
    maps = Path("/proc/self/maps")
    if not maps.exists():
        pytest.skip("no /proc/self/maps on this platform")
    for line in maps.read_text().splitlines():
        parts = line.split(maxsplit=5)
        lo, hi = (int(v, 16) for v in parts[0].split("-"))
        if lo <= address < hi:
            return parts[5] if len(parts) == 6 else None
    return None


@pytest.mark.parametrize("body", ["legacy", "broken"])
def test_load_cached_reads_legacy_files_and_raises_for_broken_ones(tmp_path, body):
    path = tmp_path / "levels.pt"
    data = {"irradiance": torch.arange(6.0).view(2, 3)}
    if body == "legacy":  # torch's pre-zip format: no mmap, read the plain way
        torch.save(data, path, _use_new_zipfile_serialization=False)
        assert torch.equal(lod.load_cached(path)["irradiance"], data["irradiance"])
    else:
        path.write_bytes(b"not a torch file")
        with pytest.raises(Exception):
            lod.load_cached(path)
