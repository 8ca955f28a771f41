"""Moon-like landing sites: continuous, seeded, multi-scale terrain (docs/render.md).

Public names: :func:`load_site`, :class:`Terrain`, :class:`SiteSpec`, :func:`load_spec`,
:func:`available_sites`, :class:`Grid`, :func:`shade`, :func:`cast_shadow`,
:func:`shaded_sun_grid`, :func:`lunar_lambert_l`.

Conventions: world frame x east, y north, z up, metres; the landing point is (0, 0).
Map-view images (``Terrain.heightmap``, ``Terrain.irradiance`` and the renderers' frames):
row 0 is the north edge (row i -> y decreasing), column j -> x increasing (east to the right).
"""

from .grid import Grid
from .photometry import cast_shadow, lunar_lambert_l, shade, shaded_sun_grid
from .spec import SiteSpec, available_sites, is_site_name, load_spec, spec_from_dict, split_site_name
from .terrain import Terrain, load_site

__all__ = ["load_site", "Terrain", "SiteSpec", "load_spec", "spec_from_dict", "available_sites", "Grid",
           "split_site_name", "is_site_name",
           "shade", "cast_shadow", "shaded_sun_grid", "lunar_lambert_l"]
