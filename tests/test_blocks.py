"""Fusion in blocks (pwm.blocks): the same closed surface as one process, exact seams, per-block
sums that a revision changes only where it reaches, and jobs that hold a block, not the body."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from pwm.block_surface import Seams, body_parts, seams, welded
from pwm.blocks import (
    _UPPER,
    BlockedSums,
    Shape,
    around,
    block_crossings,
    body_mesh,
    closure_in_blocks,
    context,
    fuse_in_blocks,
    maplet_blocks,
    mesh_in_blocks,
    split,
)
from pwm.config import FusionBlocks
from pwm.evaluate.closure import closure
from pwm.evaluate.distance import ClosestPoint
from pwm.io.fusion_state import BlockFiles, build_blocks, write_maplet
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.tiling import sample_surface, tile
from pwm.volume import DistanceGrid
from pwm.voxels import pack, unpack
from tests.conftest import LONG_BLOCK, LONG_VOXEL

VOXEL, NODES, CELLS, MARGIN = 0.006, 11, 32, 16
AXES = np.array([0.10, 0.075, 0.06])


def _ellipsoid(subdivisions: int, grow_km: float = 0.0) -> Mesh:
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = np.asarray(s.vertices) * (AXES + grow_km)
    # a bump, so that the maplets and the base disagree by more than a voxel in places
    v *= 1.0 + 0.08 * np.exp(-np.sum((np.asarray(s.vertices) - [0, 1, 0]) ** 2, axis=1) / 0.1)[:, None]
    return Mesh(v, np.asarray(s.faces))


@pytest.fixture(scope="module")
def body() -> tuple[Mesh, list[MapletGrid]]:
    """The base (a coarse ellipsoid without the bump, 3 m larger) and maplets over the truth
    (with the bump) everywhere but a cap at +x, which the base closes, each with albedo."""
    truth = _ellipsoid(4)
    tracer = RayTracer(truth)
    maplets = []
    for m in tile(truth, spacing_km=VOXEL, nodes=NODES, overlap=0.25):
        if m.frame.origin[0] > 0.07:
            continue
        m.heights, _ = sample_surface(tracer, m)
        m.albedo = np.full_like(m.heights, 0.05 + 0.2 * m.frame.origin[1])
        maplets.append(m)
    base = Mesh(np.asarray(trimesh.creation.icosphere(subdivisions=3, radius=1.0).vertices) * (AXES + 0.003),
                np.asarray(trimesh.creation.icosphere(subdivisions=3, radius=1.0).faces))
    return base, maplets


def _store(path: Path, maplets: list[MapletGrid]) -> BlockFiles:
    store = BlockFiles(path)
    sums = BlockedSums(store, VOXEL, 0.25, CELLS)
    for start in range(0, len(maplets), 64):
        sums.add_batch(maplets[start:start + 64])
    sums.save()
    return store


def test_blocks_make_the_one_process_surface_with_exact_seams(body, tmp_path):
    base, maplets = body
    whole = DistanceGrid(VOXEL, taper_fraction=0.25)
    whole.add_all(maplets)
    one = whole.mesh(base)
    # a lattice that a block spans is fused whole, as before: the same mesh, bit for bit
    small = mesh_in_blocks(whole, base, store=BlockFiles(tmp_path / "whole"), blocks=FusionBlocks(cells=64))
    assert np.array_equal(small.vertices, one.vertices) and np.array_equal(small.faces, one.faces)
    assert small.albedo is not None and np.array_equal(small.albedo, one.albedo)
    assert not (tmp_path / "whole").exists()
    store = _store(tmp_path, maplets)
    # the blocks hold the whole grid's sums, bit for bit
    parts = split(whole, CELLS)
    assert store.blocks("sums") == sorted(parts) and len(parts) >= 8
    for block, part in parts.items():
        held = store.read("sums", block)
        assert held is not None
        assert np.array_equal(held.keys, part.keys) and np.array_equal(held.sums, part.sums)
    # made block by block from the maplets' files, each job making only its own block's points
    paths = []
    (tmp_path / "maplets").mkdir()
    for k, m in enumerate(maplets):
        paths.append(tmp_path / "maplets" / f"{k}.npz")
        write_maplet(paths[-1], m)
    jobs = BlockFiles(tmp_path / "jobs")
    build_blocks(jobs, paths, voxel_km=VOXEL, taper_fraction=0.25, cells=CELLS, workers=1)
    assert jobs.blocks("sums") == sorted(parts)
    assert split(DistanceGrid(VOXEL), CELLS) == {}  # a maplet whose box, not band, reaches a block
    for block, part in parts.items():
        held = jobs.read("sums", block)
        assert held is not None and np.array_equal(held.keys, part.keys)
        assert np.array_equal(held.count, part.count)
        assert np.allclose(held.sums, part.sums, rtol=0, atol=1e-12)
    body = fuse_in_blocks(store, base=base, blocks=FusionBlocks(cells=CELLS, margin=MARGIN))
    blocked = body_mesh(store, voxel_km=VOXEL)
    assert (body.faces, body.parts_left_out) == (len(blocked.faces), 0)
    checks = closure(blocked)
    assert checks.closed and checks.components == 1, checks
    # welded: no two vertices at one place
    assert len(np.unique(blocked.vertices, axis=0)) == len(blocked.vertices)
    assert abs(len(blocked.faces) - len(one.faces)) <= 0.001 * len(one.faces)
    off = ClosestPoint(one).query(blocked.vertices)[0]
    assert np.sqrt(np.mean(off ** 2)) < 1e-3 * VOXEL and off.max() < 0.1 * VOXEL
    assert blocked.albedo is not None and one.albedo is not None
    assert abs(blocked.albedo.mean() - one.albedo.mean()) < 1e-3


def test_a_revision_changes_only_the_blocks_it_reaches(body, tmp_path):
    base, maplets = body
    store = _store(tmp_path, maplets)
    before = {b: store.path("sums", b).read_bytes() for b in store.blocks("sums")}
    old = maplets[len(maplets) // 2]
    new = MapletGrid(name=old.name, frame=old.frame, spacing_km=old.spacing_km, heights=old.heights + 0.002,
                     albedo=old.albedo)
    sums = BlockedSums(store, VOXEL, 0.25, CELLS)
    sums.subtract(old)
    sums.add_batch([new])
    touched = set(sums.save())
    reach = set(maplet_blocks(old, voxel_km=VOXEL, cells=CELLS).tolist())
    assert touched and touched <= reach and len(touched) < len(before)
    for block, content in before.items():
        if block not in touched:
            assert store.path("sums", block).read_bytes() == content
    # the touched blocks hold what fusing the new revision from the start would
    whole = DistanceGrid(VOXEL, taper_fraction=0.25)
    whole.add_all([new if m is old else m for m in maplets])
    for block in touched:
        held, part = store.read("sums", block), split(whole, CELLS)[block]
        assert held is not None and np.array_equal(held.keys, part.keys)
        assert np.allclose(held.sums, part.sums, rtol=0, atol=1e-12)


def test_a_block_holds_its_own_points_and_its_margin_not_the_body(body, tmp_path):
    _, maplets = body
    store = _store(tmp_path, maplets)
    whole = DistanceGrid(VOXEL, taper_fraction=0.25)
    whole.add_all(maplets)
    index = unpack(whole.keys)
    shape = Shape(cells=CELLS, margin=MARGIN // 2, voxel_km=VOXEL, taper_fraction=0.25)
    counts = []
    for block in store.blocks("sums"):
        origin = unpack(np.array([block]))[0] * CELLS
        held = store.read("sums", block)
        assert held is not None
        own = unpack(held.keys) - origin
        assert own.min() >= 0 and own.max() < CELLS
        # a job reads its block's points and its neighbours' within the margin, no others
        counts.append(len(context(store, block, shape=shape).keys))
        about = ((index >= origin - shape.margin) & (index < origin + CELLS + shape.margin)).all(axis=1).sum()
        assert counts[-1] == about
    assert sum(len(store.read("sums", b).keys) for b in store.blocks("sums")) == len(whole.keys)
    assert max(counts) < 0.8 * len(whole.keys)


def test_a_fusion_over_an_earlier_one_remakes_only_the_blocks_about_the_change(long_body, tmp_path):
    # the maplets enclose the body: no base (the service's test, with one, checks its reach too)
    _, maplets = long_body
    blocks = FusionBlocks(cells=LONG_BLOCK, margin=4)
    whole = DistanceGrid(LONG_VOXEL, taper_fraction=0.25)
    whole.add_all(maplets)
    store = BlockFiles(tmp_path / "kept")
    mesh_in_blocks(whole, None, store=store, blocks=blocks)
    files = {p: p.read_bytes() for p in (tmp_path / "kept").rglob("*.npz")}
    assert {p.parent.name for p in files} == {"sums", "closed", "pieces", "seams", "body"}
    old = max(maplets, key=lambda m: m.frame.origin[0])
    new = MapletGrid(name=old.name, frame=old.frame, spacing_km=old.spacing_km, heights=old.heights + 0.002,
                     albedo=old.albedo)
    whole.subtract(old)
    whole.add_all([new])
    again = mesh_in_blocks(whole, None, store=store, blocks=blocks)
    # the surface a fusion from the start makes, bit for bit
    fresh = mesh_in_blocks(whole, None, store=BlockFiles(tmp_path / "fresh"), blocks=blocks)
    assert np.array_equal(again.vertices, fresh.vertices) and np.array_equal(again.faces, fresh.faces)
    assert again.albedo is not None and fresh.albedo is not None and np.array_equal(again.albedo, fresh.albedo)
    # the sums changed where the maplet reaches; the values about them were closed again, and
    # the pieces those reach meshed again; no other file was written
    changed = {_key(p) for p in files if p.parent.name == "sums" and p.read_bytes() != files[p]}
    assert changed and changed <= set(maplet_blocks(old, voxel_km=LONG_VOXEL, cells=blocks.cells).tolist())
    closed = around(changed)
    meshed = around(closed, steps=-_UPPER)
    remade = {"sums": changed, "closed": closed, "pieces": meshed, "seams": meshed, "body": meshed}
    kept = [p for p in files if _key(p) not in remade[p.parent.name]]
    # of each kind, some blocks' files are left as they were
    assert {p.parent.name for p in kept} == set(remade)
    for path in kept:
        assert path.read_bytes() == files[path], path


def test_a_change_that_widens_the_bases_reach_closes_every_block_again(body, tmp_path):
    base, maplets = body
    blocks = FusionBlocks(cells=CELLS, margin=MARGIN)
    whole = DistanceGrid(VOXEL, taper_fraction=0.25)
    whole.add_all(maplets)
    store = BlockFiles(tmp_path / "kept")
    mesh_in_blocks(whole, base, store=store, blocks=blocks)
    reach = {b: float(store.read_arrays("reach", b)["reach_km"]) for b in store.blocks("reach")}
    # a maplet 10 m under the others: the base, 3 m out, now disagrees with it by 13 m
    old = maplets[len(maplets) // 2]
    whole.subtract(old)
    whole.add_all([MapletGrid(name=old.name, frame=old.frame, spacing_km=old.spacing_km,
                              heights=old.heights - 0.010, albedo=old.albedo)])
    again = mesh_in_blocks(whole, base, store=store, blocks=blocks)
    assert max(float(store.read_arrays("reach", b)["reach_km"]) for b in reach) > max(reach.values())
    fresh = mesh_in_blocks(whole, base, store=BlockFiles(tmp_path / "fresh"), blocks=blocks)
    assert np.array_equal(again.vertices, fresh.vertices) and np.array_equal(again.faces, fresh.faces)


def test_the_blocks_check_their_surface_as_the_whole_mesh_is_checked(body, tmp_path):
    """pwm.blocks.closure_in_blocks, which never makes the surface one mesh, finds what
    pwm.evaluate.closure finds on it: a closed surface, a face missing, a face turned, and
    faces folded through the body across the blocks' seams (each crossing pair counted once)."""
    base, maplets = body
    store = _store(tmp_path, maplets)
    fuse_in_blocks(store, base=base, blocks=FusionBlocks(cells=CELLS, margin=MARGIN))

    def both() -> tuple:
        return (closure_in_blocks(store, voxel_km=VOXEL, cells=CELLS, workers=1),
                closure(body_mesh(store, voxel_km=VOXEL)))

    in_blocks, at_once = both()
    assert in_blocks.closed and at_once.closed
    assert abs(in_blocks.volume_km3 - at_once.volume_km3) < 1e-9 * at_once.volume_km3
    # a block's piece at a seam, edited as marching cubes never would
    block = store.blocks("body")[0]
    piece = store.read_arrays("pieces", block)
    shell = {tuple(i) for i in store.read_arrays("seams", block)["shell"]}
    at_seam = next(k for k, f in enumerate(piece["faces"]) if any(tuple(piece["ids"][v]) in shell for v in f))
    origin = unpack(np.array([block]))[0] * CELLS

    def rewrite(faces: np.ndarray, vertices: np.ndarray = piece["vertices"]) -> None:
        edited = welded(vertices, faces, piece["albedo"])
        assert len(edited.faces) == len(faces)
        store.write_arrays("pieces", block, {"ids": edited.ids, "vertices": edited.vertices, "albedo": edited.albedo,
                                             "faces": edited.faces, "part": edited.part})
        store.write_arrays("seams", block, seams(edited, origin=origin, cells=CELLS).arrays())

    rewrite(np.delete(piece["faces"], at_seam, axis=0))
    in_blocks, at_once = both()
    assert not in_blocks.watertight and in_blocks.boundary_edges == at_once.boundary_edges == 3
    turned = piece["faces"].copy()
    turned[at_seam] = turned[at_seam, ::-1]
    rewrite(turned)
    in_blocks, at_once = both()
    assert in_blocks.watertight and not in_blocks.winding_consistent and not at_once.winding_consistent
    rewrite(piece["faces"])
    # the top of the body folded down through it and widened: the same map on every block's
    # vertices, so the pieces still meet
    for b in store.blocks("pieces"):
        held = store.read_arrays("pieces", b)
        v = held["vertices"].copy()
        up = np.clip(v[:, 2] - 5.0, 0.0, None)
        v[:, 2] -= 4.0 * up
        v[:, :2] *= 1.0 + 0.3 * up[:, None]
        store.write_arrays("pieces", b, {**held, "vertices": v})
    in_blocks, at_once = both()
    assert in_blocks.self_intersections == at_once.self_intersections > 0


def test_a_crossing_across_a_seam_is_counted_by_one_block(tmp_path):
    """Two faces that cross, each in its own block on either side of a seam (at 32 steps up):
    the lower block counts the pair, the upper one does not count it again."""
    store = BlockFiles(tmp_path)
    lower, upper = (int(pack(np.array([[0, 0, k]]))[0]) for k in (0, 1))
    flat = np.array([[10, 10, 31.8], [16, 10, 31.8], [10, 16, 31.8]])
    through = np.array([[11, 11, 30.5], [12, 11, 33.5], [11, 12, 33.5]])
    for block, vertices, first in ((lower, flat, 1), (upper, through, 4)):
        store.write_arrays("pieces", block, {"ids": np.column_stack([np.arange(first, first + 3), np.zeros(3, int)]),
                                             "vertices": vertices, "albedo": np.full(3, np.nan),
                                             "faces": np.array([[0, 1, 2]]), "part": np.array([0])})
        store.write_arrays("body", block, {"parts": np.array([0])})
    assert [block_crossings(store, b, cells=32) for b in (lower, upper)] == [1, 0]


def test_the_body_is_the_largest_whole_joined_across_the_seams():
    def held(faces: list[int], shell: list[tuple[int, int]]) -> Seams:
        parts = len(faces)
        return Seams(shell=np.array([[k, 0] for k, _ in shell]).reshape(-1, 2),
                     shell_part=np.array([p for _, p in shell], dtype=np.int64), faces=np.array(faces),
                     volume=np.zeros(parts), open=np.empty((0, 4), dtype=np.int64),
                     open_part=np.empty(0, dtype=np.int64), nonmanifold=np.zeros(parts, dtype=np.int64),
                     inconsistent=np.zeros(parts, dtype=np.int64))

    # block 1's part 1 meets block 2's only part (vertex 7): 5 + 50 faces, less than block 1's part 0
    a = held([100, 5], [(3, 0), (7, 1)])
    b = held([50], [(7, 0), (9, 0)])
    assert {k: v.tolist() for k, v in body_parts({1: a, 2: b}).items()} == {1: [0]}
    # once block 2 also meets part 0 (vertex 3), all of it is one whole
    b = held([50], [(7, 0), (3, 0)])
    assert {k: v.tolist() for k, v in body_parts({1: a, 2: b}).items()} == {1: [0, 1], 2: [0]}


def _key(path: Path) -> int:
    return int(pack(np.array([[int(v) for v in path.stem.split("_")]]))[0])
