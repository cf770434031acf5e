"""Fusion across levels (pwm.levels): a survey's closed surface with a site's finer maplets laid
onto it, each place from the finest level that covers it, without a step at the site's border; a
base of a body and a patch over its hole sealed into one closed surface."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pwm.evaluate.closure import closure
from pwm.frames import latlon_to_unit
from pwm.fusion import VoxelGrid
from pwm.io.fusion_state import read_composition, read_levels, write_composition, write_levels
from pwm.levels import Laid, LevelGrids, sealed
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh, grid_faces, refine_faces
from pwm.raytrace import RayTracer
from pwm.tiling import level_of, tile
from pwm.volume import DistanceGrid

R = 0.25
SITE = (10.0, 40.0)
SITE_B = (-30.0, 220.0)
BUMP_KM, BUMP_SIGMA_KM, OFFSET_KM = 2e-3, 3e-3, 0.5e-3


@pytest.fixture(scope="module")
def sphere() -> Mesh:
    s = trimesh.creation.icosphere(subdivisions=5, radius=R)
    return Mesh(np.asarray(s.vertices), np.asarray(s.faces), np.full(len(s.vertices), 0.1))


def _site(maplet: MapletGrid, site: tuple[float, float] = SITE, bump_km: float = BUMP_KM) -> MapletGrid:
    """The maplet raised by a hill at the site and by OFFSET_KM everywhere: the site level
    disagrees with the survey at its border, which must fade, not step."""
    centre = R * latlon_to_unit(*site)
    r = np.linalg.norm(maplet.nodes_body() - centre, axis=-1)
    maplet.heights = maplet.heights + OFFSET_KM + bump_km * np.exp(-0.5 * (r / BUMP_SIGMA_KM) ** 2)
    return maplet


def _site_b(sphere: Mesh, bump_km: float) -> list[MapletGrid]:
    return [_site(m, SITE_B, bump_km) for m in tile(sphere, spacing_km=5e-4, nodes=21, overlap=0.25,
                                                     centre_lat_deg=SITE_B[0], centre_lon_deg=SITE_B[1],
                                                     radius_km=0.008)]


def _faces(mesh: Mesh, keep: np.ndarray | None = None) -> set[tuple[float, ...]]:
    """The faces (those kept) as their corners' coordinates, each from its least corner on, so
    that two meshes of the same faces compare equal whatever their numbering."""
    out = set()
    for tri in mesh.vertices[mesh.faces if keep is None else mesh.faces[keep]]:
        corners = [tuple(c) for c in tri]
        first = corners.index(min(corners))
        out.add(tuple(x for c in corners[first:] + corners[:first] for x in c))
    return out


@pytest.fixture(scope="module")
def levels(sphere) -> tuple[list[MapletGrid], list[MapletGrid]]:
    survey = tile(sphere, spacing_km=0.01, nodes=12, overlap=0.25)
    site = [_site(m) for m in tile(sphere, spacing_km=5e-4, nodes=21, overlap=0.25, centre_lat_deg=SITE[0],
                                    centre_lon_deg=SITE[1], radius_km=0.008)]
    return survey, site


def _radius(mesh: Mesh, directions: np.ndarray) -> np.ndarray:
    """Radius of the surface along unit directions from the centre (first hit from outside)."""
    hits = RayTracer(mesh).intersect(2 * R * directions, -directions)
    assert hits.hit.all()
    return 2 * R - hits.t


def test_refining_faces_keeps_a_closed_mesh_closed(sphere):
    top = sphere.vertices[sphere.faces].mean(axis=1)[:, 2] > 0.2
    refined, origin = refine_faces(sphere, top, max_edge_km=0.004)
    chosen = top[origin]
    mesh = trimesh.Trimesh(refined.vertices, refined.faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    corners = refined.vertices[refined.faces[chosen]]
    assert np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max() <= 0.004
    # the selected faces split, the rest only where they meet them (halved, to conform)
    assert chosen.sum() >= 4 * top.sum() and (~chosen).sum() - (~top).sum() < 0.05 * len(sphere.faces)
    assert np.array_equal(refined.vertices[: len(sphere.vertices)], sphere.vertices)
    assert refined.albedo is not None and np.allclose(refined.albedo, 0.1)


def test_a_site_level_is_laid_into_the_survey_without_a_step(sphere, levels, tmp_path):
    survey, site = levels
    assert int(level_of(survey[0].spacing_km)) == 3 and int(level_of(site[0].spacing_km)) == -1
    fusion = LevelGrids(taper_fraction=0.25)
    fusion.add_all(survey + site, base=sphere)
    assert isinstance(fusion.grids[3], DistanceGrid) and isinstance(fusion.grids[-1], VoxelGrid)
    assert {k: d["surface"] for k, d in fusion.describe().items()} == {"3": "closed", "-1": "laid"}
    mesh = fusion.mesh(sphere)
    closed = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert closed.is_watertight and closed.is_winding_consistent and closed.volume > 0

    # the site from its level: the hill's top, and the survey's sphere away from it
    centre = latlon_to_unit(*SITE)
    assert _radius(mesh, centre[None])[0] == pytest.approx(R + OFFSET_KM + BUMP_KM, abs=1e-4)
    far = latlon_to_unit(np.array([-40.0, 60.0, 10.0]), np.array([200.0, 100.0, 80.0]))
    assert np.allclose(_radius(mesh, far), R, atol=5e-4)

    # across the site's border, 1 cm apart along a meridian: no slope steeper than 0.6, where
    # the hill's steepest is 0.4 and the level's 0.5 m offset, laid without the blend, makes a
    # step of slope 2.3 over one fine edge
    lat = SITE[0] + np.degrees(np.arange(0.0, 0.016, 1e-5) / R)
    profile = _radius(mesh, latlon_to_unit(lat, np.full(len(lat), SITE[1])))
    assert profile[0] - profile[-1] > OFFSET_KM + 0.9 * BUMP_KM  # from the site onto the survey
    assert np.abs(np.diff(profile)).max() < 0.6 * 1e-5

    # the sums round trip through a file, and taking the site out leaves the survey's surface
    write_levels(tmp_path / "levels.npz", fusion)
    again = read_levels(tmp_path / "levels.npz")
    assert np.array_equal(again.mesh(sphere).vertices, mesh.vertices)
    site_alone = read_levels(tmp_path / "levels.npz")
    for m in survey:
        site_alone.subtract(m)
    # with the survey's sums empty, the site is laid onto the base itself, which stays closed
    assert {k: d["surface"] for k, d in site_alone.describe().items()} == {"3": "closed", "-1": "laid"}
    assert closure(site_alone.mesh(sphere)).closed
    for m in site:
        again.subtract(m)
    alone = LevelGrids(taper_fraction=0.25)
    alone.add_all(survey, base=sphere)
    assert np.array_equal(again.mesh(sphere).vertices, alone.mesh(sphere).vertices)
    with pytest.raises(ValueError, match="level -2"):
        again.subtract(tile(sphere, spacing_km=2.5e-4, nodes=5, centre_lat_deg=0.0, centre_lon_deg=0.0,
                            radius_km=1e-4)[0])


def test_a_changed_site_is_laid_again_and_the_rest_carried_over(sphere, levels, tmp_path):
    survey, site = levels
    fusion = LevelGrids(taper_fraction=0.25)
    fusion.add_all(survey + site + _site_b(sphere, BUMP_KM), base=sphere)
    first, composition, laid = fusion.compose(sphere)
    assert laid == Laid(regions_laid=2, regions_carried=0, below_made=True)
    write_levels(tmp_path / "levels.npz", fusion)
    write_composition(tmp_path / "composition.npz", composition)

    # the next version: site B's maplets revised (its hill twice as high), site A's untouched
    fusion = read_levels(tmp_path / "levels.npz")
    for m in _site_b(sphere, BUMP_KM):
        fusion.subtract(m)
    revised = _site_b(sphere, 2 * BUMP_KM)
    fusion.add_all(revised, base=sphere)
    previous = (first, read_composition(tmp_path / "composition.npz"))
    second, _, laid = fusion.compose(sphere, previous=previous)
    assert laid == Laid(regions_laid=1, regions_carried=1, below_made=False)
    # the surface that composing it all again makes, closed
    again = LevelGrids(taper_fraction=0.25)
    again.add_all(survey + site + revised, base=sphere)
    assert _faces(second) == _faces(again.mesh(sphere))
    closed = trimesh.Trimesh(second.vertices, second.faces, process=False)
    assert closed.is_watertight and closed.is_winding_consistent
    # the hill is twice as high; away from site B every face is the first version's, site A's too
    centre_b = latlon_to_unit(*SITE_B)
    assert _radius(second, centre_b[None])[0] == pytest.approx(R + OFFSET_KM + 2 * BUMP_KM, abs=1e-4)
    away = [np.linalg.norm(m.vertices[m.faces].mean(axis=1) - R * centre_b, axis=1) > 0.2 for m in (first, second)]
    kept = _faces(first, away[0])
    assert kept == _faces(second, away[1])
    assert len(kept) > len(sphere.faces) // 2 and _radius(second, latlon_to_unit(*SITE)[None])[0] > R + BUMP_KM

    # site B gone: its place is the survey's surface again, the rest still carried over
    fusion = read_levels(tmp_path / "levels.npz")
    for m in _site_b(sphere, BUMP_KM):
        fusion.subtract(m)
    third, _, laid = fusion.compose(sphere, previous=previous)
    assert laid == Laid(regions_laid=0, regions_carried=1, below_made=False)
    alone = LevelGrids(taper_fraction=0.25)
    alone.add_all(survey + site, base=sphere)
    assert _faces(third) == _faces(alone.mesh(sphere))
    assert _radius(third, centre_b[None])[0] == pytest.approx(R, abs=5e-4)


def test_a_body_with_a_patch_over_its_hole_is_sealed_into_one_closed_surface(sphere):
    # as a site's start model comes: the body less the faces under the site, and the site's
    # grid over the hole, overlapping its rim
    cap = sphere.vertices[sphere.faces].mean(axis=1)[:, 2] > 0.9 * R
    axis = np.linspace(-0.5 * R, 0.5 * R, 41)
    x, y = np.meshgrid(axis, axis)
    grid = np.column_stack([x.ravel(), y.ravel(), np.sqrt(R**2 - x.ravel() ** 2 - y.ravel() ** 2)])
    body = Mesh(np.vstack([sphere.vertices, grid]),
                np.vstack([sphere.faces[~cap], grid_faces(41, 41) + len(sphere.vertices)]))
    checks = closure(body)
    assert (checks.components, checks.boundary_edges) == (2, closure(Mesh(sphere.vertices,
                                                                          sphere.faces[~cap])).boundary_edges + 160)
    sealed_body = sealed(body)
    assert closure(sealed_body).closed
    assert closure(sealed_body).volume_km3 == pytest.approx(closure(sphere).volume_km3, rel=1e-3)
    # the site's surface is kept where it covers the hole: the top is the grid's
    assert _radius(sealed_body, np.array([[0.0, 0.0, 1.0]]))[0] == pytest.approx(R, abs=1e-9)
    # a hole with nothing over it is left as it is, for the checks to tell
    holed = Mesh(sphere.vertices, sphere.faces[~cap])
    assert sealed(holed) is holed and sealed(sphere) is sphere
