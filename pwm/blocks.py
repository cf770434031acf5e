"""Volumetric fusion (pwm.volume) in blocks of the lattice, each on its own with bounded memory,
into one closed surface held as a piece per block: that of the whole lattice but where the base's samples about a
block's edge differ from the whole body's (a thousandth of a voxel RMS in tests/test_blocks.py;
bench/RESULTS.md for Bennu).

A block is the cube of `cells` lattice steps a side whose points have index // cells equal to
its own index (named by that index packed as a lattice key, pwm.voxels.pack); it keeps the sums
of its own points, so that a maplet changes only the blocks its band reaches (`BlockedSums`).
Fusing takes three passes over the blocks, each block a job of its own (`fuse_in_blocks`):

1. the reach of the base's band from the block's own samples (the base's distances are
   clipped at the body's widest, the largest of the blocks');
2. closing: a block reads its own sums and its neighbours' within `margin` lattice steps, adds
   the base's distances where no maplet reached (pwm.volume.DistanceGrid.closed, from the base's
   faces about it, made only where they reach the block's own points) and keeps the result at
   its own points only: every lattice point's value is made once, by its own block, and the
   margin gives it nearly what the whole body would (the base's bend reaches FADE_VOXELS and its
   band the maplets' disagreement: FusionBlocks.margin);
3. marching cubes over the cells whose lowest corner is the block's own, from its closed values
   and the first layer of its upper neighbours'. Two blocks sharing a face see the same values on
   it, so they make the same vertices there, named by the lattice edge each lies on
   (pwm.block_surface): the pieces meet with no crack and no vertex twice. The body's parts of
   the pieces are then found across their seams (`choose_body`); the surface stays in the
   blocks, made one mesh where it fits one process (`body_mesh`) and checked there without
   (`closure_in_blocks`).

Each block's reach, closed values and piece are kept with its sums, so that the next fusion over
the same base remakes only the blocks about those whose sums changed: the others' files stay
as they were, byte for byte, and the surface is the one a fusion from the start would make.

The blocks' files are kept by a `BlockStore` (pwm.io.fusion_state.BlockFiles); jobs run on
pwm.parallel.map_processes. Lengths in km, lattice indices along the body axes.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import partial
from typing import Protocol

import numpy as np

from pwm.block_surface import Seams, body_parts, named, seam_checks, seams, welded
from pwm.config import FusionBlocks
from pwm.evaluate.closure import Closure, self_intersections
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh
from pwm.parallel import map_processes
from pwm.volume import FADE_VOXELS, TRUNCATION_VOXELS, DistanceGrid, extract, in_box, surface_mesh
from pwm.voxels import SparseSums, pack, sum_by_key, unpack

FILES = 2
"""The form of the files a fusion in blocks keeps (1: pieces as marching cubes made them; 2:
pieces welded by lattice edge, with their seams and the body's parts): a fusion over a store
of another form makes every block afresh (service.fusion_blocks.Layout)."""

_UPPER = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)
_AROUND = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], dtype=np.int64)
# two faces of marching cubes cross only within this many lattice steps of each other's centres
_CROSSING_STEPS = 2


class BlockStore(Protocol):
    """Where the blocks' sums ("sums") and closed values ("closed") are kept, with what a fusion
    made of them per block: its mesh piece ("pieces") and the base's reach ("reach"); picklable,
    so that each job opens it itself."""

    def blocks(self, kind: str) -> list[int]:
        """The blocks of this kind held, by key."""
        ...

    def read(self, kind: str, block: int) -> DistanceGrid | None:
        """A block's sums of this kind, None where it has none."""
        ...

    def write(self, kind: str, block: int, grid: DistanceGrid) -> None:
        """Keep a block's sums of this kind (a grid without points: drop them)."""
        ...

    def read_arrays(self, kind: str, block: int) -> dict[str, np.ndarray] | None:
        """A block's arrays of this kind, None where it has none."""
        ...

    def write_arrays(self, kind: str, block: int, arrays: dict[str, np.ndarray]) -> None:
        """Keep a block's arrays of this kind (none: drop them)."""
        ...

    def clear(self, kind: str) -> None:
        """Drop every block's files of this kind."""
        ...


def block_of(keys: np.ndarray, cells: int) -> np.ndarray:
    """The block key of each lattice key."""
    return pack(np.floor_divide(unpack(keys), cells))


def split(grid: DistanceGrid, cells: int) -> dict[int, DistanceGrid]:
    """The sums of each block (by key) that the grid's points fall in, each still sorted."""
    if not len(grid.keys):
        return {}
    blocks = block_of(grid.keys, cells)
    order = np.argsort(blocks, kind="stable")
    names, starts = np.unique(blocks[order], return_index=True)
    ends = np.r_[starts[1:], len(order)]
    return {int(b): DistanceGrid(grid.voxel_km, grid.keys[order[a:z]], grid.sums[order[a:z]],
                                 grid.count[order[a:z]], taper_fraction=grid.taper_fraction)
            for b, a, z in zip(names, starts, ends, strict=True)}


def spanned(lo: np.ndarray, hi: np.ndarray, cells: int) -> np.ndarray:
    """Keys of the blocks that the box of lattice indices lo..hi (inclusive) meets."""
    first, last = np.floor_divide(lo, cells), np.floor_divide(hi, cells)
    axes = [np.arange(a, b + 1) for a, b in zip(first, last, strict=True)]
    return pack(np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3))


def maplet_blocks(maplet: MapletGrid, *, voxel_km: float, cells: int) -> np.ndarray:
    """Keys of the blocks a maplet's band of lattice points may reach (its nodes' box widened by
    the truncation and a cell's corners)."""
    nodes = maplet.nodes_body().reshape(-1, 3) / voxel_km
    reach = TRUNCATION_VOXELS + 2.0
    return spanned(np.floor(nodes.min(axis=0) - reach).astype(np.int64),
                   np.ceil(nodes.max(axis=0) + reach).astype(np.int64), cells)


def base_blocks(base: Mesh, *, voxel_km: float, cells: int, margin: int) -> np.ndarray:
    """Keys of the blocks within `margin` lattice steps of the base's faces' boxes."""
    tri = base.vertices[base.faces] / voxel_km
    lo = np.floor(tri.min(axis=1)).astype(np.int64) - margin
    hi = np.ceil(tri.max(axis=1)).astype(np.int64) + margin
    return np.unique(np.concatenate([spanned(a, b, cells) for a, b in zip(lo, hi, strict=True)]))


def span(grid: SparseSums) -> int:
    """The most lattice steps the grid's points span along an axis (0 without points)."""
    if not len(grid.keys):
        return 0
    index = unpack(grid.keys)
    return int((index.max(axis=0) - index.min(axis=0)).max())


@dataclass
class BlockedSums:
    """The sums of a DistanceGrid kept per block: a maplet added or subtracted changes only the
    blocks its band reaches (`touched`), each read from `store` when first needed. The sums are
    those the whole grid would hold, bit for bit: each maplet's contribution is made whole
    (pwm.volume.DistanceGrid) and split, and a batch is summed as SparseSums.add_all sums it.
    only: the blocks kept (None: all), for a job that makes one block's sums."""

    store: BlockStore
    voxel_km: float
    taper_fraction: float
    cells: int
    only: set[int] | None = None
    grids: dict[int, DistanceGrid] = field(default_factory=dict)
    touched: set[int] = field(default_factory=set)

    def add_batch(self, maplets: Iterable[MapletGrid]) -> None:
        """Add maplets as one batch (as SparseSums.add_all does a batch)."""
        shape, box = DistanceGrid(self.voxel_km, taper_fraction=self.taper_fraction), self._box()
        parts = [shape._contribution(m, box) for m in maplets]
        if parts:
            self._merge(*sum_by_key(np.concatenate([p[0] for p in parts]), np.vstack([p[1] for p in parts]),
                                    np.concatenate([p[2] for p in parts])), sign=+1, name="a batch of maplets")

    def subtract(self, maplet: MapletGrid) -> None:
        """Take a maplet's revision out, exactly as it was added."""
        shape = DistanceGrid(self.voxel_km, taper_fraction=self.taper_fraction)
        self._merge(*shape._contribution(maplet, self._box()), sign=-1, name=f"maplet {maplet.name}")

    def _box(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The lattice box (lowest, highest index) about the blocks kept (None: all)."""
        if self.only is None:
            return None
        index = unpack(np.array(sorted(self.only), dtype=np.int64))
        return index.min(axis=0) * self.cells, (index.max(axis=0) + 1) * self.cells - 1

    def _merge(self, keys: np.ndarray, sums: np.ndarray, count: np.ndarray, *, sign: int, name: str) -> None:
        part = DistanceGrid(self.voxel_km, keys, sums, count, taper_fraction=self.taper_fraction)
        for block, piece in split(part, self.cells).items():
            if self.only is not None and block not in self.only:
                continue
            if block not in self.grids:
                stored = self.store.read("sums", block)
                self.grids[block] = stored if stored is not None else DistanceGrid(
                    self.voxel_km, taper_fraction=self.taper_fraction)
            self.grids[block].merge(piece.keys, piece.sums, piece.count, sign=sign, name=name)
            self.touched.add(block)

    def save(self) -> list[int]:
        """Write the touched blocks to the store; their keys."""
        for block in sorted(self.touched):
            self.store.write("sums", block, self.grids[block])
        return sorted(self.touched)


def mesh_in_blocks(grid: DistanceGrid, base: Mesh | None, *, store: BlockStore, blocks: FusionBlocks) -> Mesh:
    """grid.mesh(base), in blocks kept by `store` when its lattice spans more than a block: a
    smaller one is fused whole, as it always was. The store is empty, or holds an earlier fusion
    in blocks over the same base with the same `blocks`: then only the blocks whose sums differ
    from the grid's are written, and only they and those about them fused again (`fuse_in_blocks`)."""
    if span(grid) <= blocks.cells:
        return grid.mesh(base)
    parts = split(grid, blocks.cells)
    changed = set()
    for block in sorted(set(parts) | set(store.blocks("sums"))):
        held, part = store.read("sums", block), parts.get(block)
        if part is None:
            store.write("sums", block, DistanceGrid(grid.voxel_km, taper_fraction=grid.taper_fraction))
        elif held is None or not (np.array_equal(held.keys, part.keys) and np.array_equal(held.sums, part.sums)
                                  and np.array_equal(held.count, part.count)):
            store.write("sums", block, part)
        else:
            continue
        changed.add(block)
    fuse_in_blocks(store, base=base, blocks=blocks, changed=changed if store.blocks("pieces") else None)
    return body_mesh(store, voxel_km=grid.voxel_km)


def fuse_in_blocks(store: BlockStore, *, base: Mesh | None, blocks: FusionBlocks,
                   changed: set[int] | None = None) -> Body:
    """The closed surface of the sums the store holds per block (with `base` closing where no
    maplet reached, as pwm.volume.DistanceGrid.mesh), fused block by block on blocks.workers
    processes (see the module docstring); each block's closed values, mesh piece (with its
    seams), base reach and part of the body are kept in the store, and the surface is left
    there (`body_mesh` makes it one mesh, `closure_in_blocks` checks it).

    changed: the blocks whose sums changed since the store's pieces were made over the same
    base (None: make them all). A block's closed values depend only on the sums of the blocks
    about it (the margin is at most a block) and on the base's reach over the whole body, and
    its piece only on its own and its upper neighbours' closed values: while that reach stays
    as it was, only the blocks about the changed ones are closed again and only the pieces
    those reach meshed again; the other blocks' files are left as they were, byte for byte,
    and the surface is the one making them all would give (the body's parts are chosen again
    over all blocks' seams, a block's file written only where its parts changed)."""
    held = store.blocks("sums")
    if not held:
        raise ValueError("nothing fused")
    sample = store.read("sums", held[0])
    assert sample is not None  # listed by the store
    names = np.asarray(held, dtype=np.int64)
    shape = Shape(cells=blocks.cells, margin=blocks.margin, voxel_km=sample.voxel_km,
                  taper_fraction=sample.taper_fraction)
    if changed is None:
        store.clear("reach")
    about = None if changed is None else around(changed)
    clip_km = None
    if base is not None:
        # the base's distances are clipped at its widest band's reach over the whole body: the
        # largest of the blocks that hold its samples
        sampled = base_blocks(base, voxel_km=sample.voxel_km, cells=blocks.cells, margin=1).tolist()
        before = _clip(store, sampled)
        again = [b for b in sampled if about is None or b in about or store.read_arrays("reach", b) is None]
        reaches = map_processes(partial(block_reach, store, base=base, shape=shape), again, workers=blocks.workers)
        for block, reach in zip(again, reaches, strict=True):
            store.write_arrays("reach", block, {"reach_km": np.array(reach)})
        clip_km = _clip(store, sampled)
        assert clip_km is not None  # each of the base's blocks was just reached
        if clip_km != before:
            about = None
        # its band reaches that far from its faces (and the rings about its bend follow the
        # surface, which its bend moves no further)
        names = np.union1d(names, base_blocks(base, voxel_km=sample.voxel_km, cells=blocks.cells,
                                              margin=int(np.ceil(clip_km / sample.voxel_km)) + 2))
    if about is None:
        store.clear("closed")
        store.clear("pieces")
        closing = names.tolist()
    else:
        closing = sorted(set(names.tolist()) & about)
        # a block about the change that is no longer fused drops what it held
        for block in about - set(closing):
            store.write("closed", block, DistanceGrid(shape.voxel_km, taper_fraction=shape.taper_fraction))
    list(map_processes(partial(close_block, store, base=base, clip_km=clip_km, shape=shape), closing,
                       workers=blocks.workers))
    # a block's piece reads its own closed values and its upper neighbours'
    meshing = store.blocks("closed") if about is None else sorted(around(about, steps=-_UPPER))
    list(map_processes(partial(mesh_block, store, cells=blocks.cells), meshing, workers=blocks.workers))
    return choose_body(store)


def around(blocks: Iterable[int], *, steps: np.ndarray = _AROUND) -> set[int]:
    """The keys of the blocks at `steps` (block indices) from the given ones: by default each
    block and the 26 about it."""
    index = unpack(np.asarray(list(blocks), dtype=np.int64).reshape(-1))
    if not len(index):
        return set()
    return set(pack((index[:, None, :] + steps[None, :, :]).reshape(-1, 3)).tolist())


def _clip(store: BlockStore, sampled: list[int]) -> float | None:
    """The largest base reach the store holds of these blocks (None: none held)."""
    held = [store.read_arrays("reach", b) for b in sampled]
    return max((float(h["reach_km"]) for h in held if h is not None), default=None)


@dataclass(frozen=True)
class Shape:
    """The blocks' layout (pwm.config.FusionBlocks' cells and margin) and the lattice's voxel
    and taper."""

    cells: int
    margin: int
    voxel_km: float
    taper_fraction: float


def context(store: BlockStore, block: int, *, shape: Shape) -> DistanceGrid:
    """The sums of a block and of its neighbours' points within `margin` lattice steps of it."""
    origin = unpack(np.array([block]))[0] * shape.cells
    lo, hi = origin - shape.margin, origin + shape.cells + shape.margin
    keys, sums, count = [], [], []
    for step in _AROUND:
        grid = store.read("sums", int(pack((unpack(np.array([block]))[0] + step)[None])[0]))
        if grid is None:
            continue
        index = unpack(grid.keys)
        inside = ((index >= lo) & (index < hi)).all(axis=1)
        keys.append(grid.keys[inside])
        sums.append(grid.sums[inside])
        count.append(grid.count[inside])
    out = DistanceGrid(shape.voxel_km, taper_fraction=shape.taper_fraction)
    if keys:
        all_keys = np.concatenate(keys)
        order = np.argsort(all_keys)
        out.keys, out.sums, out.count = all_keys[order], np.vstack(sums)[order], np.concatenate(count)[order]
    return out


def block_reach(store: BlockStore, block: int, *, base: Mesh, shape: Shape) -> float:
    """How far the base's band reaches from the block's own samples (pwm.volume
    .DistanceGrid.base_reach): the body's widest is the largest of its blocks'."""
    origin = unpack(np.array([block]))[0] * shape.cells
    return context(store, block, shape=shape).base_reach(base, _faces_about(base, block, shape=shape),
                                                         within=(origin, origin + shape.cells - 1))


def close_block(store: BlockStore, block: int, *, base: Mesh | None, clip_km: float | None, shape: Shape) -> int:
    """Close a block's own points (step 1 of the module docstring), the base's distances clipped
    at clip_km, and keep them as its "closed" sums; the lattice points its context held then
    (the most one job holds at a time)."""
    grid = context(store, block, shape=shape)
    faces = None if base is None else _faces_about(base, block, shape=shape)
    if not len(grid.keys) and (faces is None or not faces.any()):
        store.write("closed", block, grid)
        return 0
    origin = unpack(np.array([block]))[0] * shape.cells
    closed = grid.closed(base, faces, clip_km, within=(origin, origin + shape.cells - 1))
    own = block_of(closed.keys, shape.cells) == block
    store.write("closed", block, DistanceGrid(shape.voxel_km, closed.keys[own], closed.sums[own],
                                              closed.count[own], taper_fraction=shape.taper_fraction))
    return len(closed.keys)


def _faces_about(base: Mesh, block: int, *, shape: Shape) -> np.ndarray:
    """Mask of the base's faces about a block's context: the samples its points are nearest to,
    and those whose band reaches it."""
    origin = unpack(np.array([block]))[0] * shape.cells
    tri = base.vertices[base.faces] / shape.voxel_km
    # the context's points' nearest samples, and the bands that reach them, lie within this
    reach = shape.margin + int(TRUNCATION_VOXELS + FADE_VOXELS)
    lo, hi = origin - reach, origin + shape.cells + reach
    return ((tri.max(axis=1) >= lo) & (tri.min(axis=1) <= hi)).all(axis=1)


def mesh_block(store: BlockStore, block: int, *, cells: int) -> int:
    """Marching cubes over the cells whose lowest corner is the block's (step 3 of the module
    docstring), welded (pwm.block_surface.welded) and kept as its piece (vertices in lattice
    steps) with its seams; its faces (a block without closed values of its own has none)."""
    index = unpack(np.array([block]))[0]
    origin = index * cells
    own = store.read("closed", block)
    if own is None:  # no cell has its lowest corner here
        store.write_arrays("pieces", block, {})
        store.write_arrays("seams", block, {})
        return 0
    # _UPPER starts at the block itself
    parts = []
    for grid in [own] + [store.read("closed", int(pack((index + step)[None])[0])) for step in _UPPER[1:]]:
        if grid is None:
            continue
        rel = unpack(grid.keys) - origin
        # the first layer of an upper neighbour closes the block's last cells
        keep = (rel <= cells).all(axis=1)
        parts.append((grid.keys[keep], grid.sums[keep], grid.count[keep]))
    keys = np.concatenate([p[0] for p in parts])
    order = np.argsort(keys)
    voxel_km = 1.0  # marching cubes work in lattice steps
    piece = welded(*extract(SparseSums(voxel_km, keys[order], np.vstack([p[1] for p in parts])[order],
                                       np.concatenate([p[2] for p in parts])[order])))
    if not len(piece.faces):
        store.write_arrays("pieces", block, {})
        store.write_arrays("seams", block, {})
        return 0
    store.write_arrays("pieces", block, {"ids": piece.ids, "vertices": piece.vertices, "albedo": piece.albedo,
                                         "faces": piece.faces, "part": piece.part})
    store.write_arrays("seams", block, seams(piece, origin=origin, cells=cells).arrays())
    return len(piece.faces)


@dataclass(frozen=True)
class Body:
    """The body's surface as the blocks hold it: its faces in all, and the parts of pieces apart
    from it left out (specks that marching cubes make off the surface)."""

    faces: int
    parts_left_out: int


def _seams(store: BlockStore) -> dict[int, Seams]:
    return {b: Seams.from_arrays(a) for b in store.blocks("seams") if (a := store.read_arrays("seams", b))}


def _body(store: BlockStore, block: int) -> np.ndarray:
    held = store.read_arrays("body", block)
    return np.empty(0, dtype=np.int64) if held is None else held["parts"]


def choose_body(store: BlockStore) -> Body:
    """Find the body's parts of the blocks' pieces across their seams (pwm.block_surface
    .body_parts) and keep them as each block's "body"; a block's file is written only where
    they changed."""
    held = _seams(store)
    body = body_parts(held)
    for block in sorted(set(body) | set(store.blocks("body"))):
        parts = body.get(block)
        if parts is None:
            store.write_arrays("body", block, {})
        elif not np.array_equal(_body(store, block), parts):
            store.write_arrays("body", block, {"parts": parts})
    faces = sum(int(held[b].faces[parts].sum()) for b, parts in body.items())
    return Body(faces=faces, parts_left_out=sum(len(s.faces) for s in held.values()) - sum(map(len, body.values())))


def _body_piece(store: BlockStore, block: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """A block's part of the body: its piece's ids, vertices, albedo, and the faces the body
    holds; None where the block holds none of it."""
    parts = store.read_arrays("body", block)
    if parts is None:
        return None
    piece = store.read_arrays("pieces", block)
    assert piece is not None  # a block of the body has a piece
    return piece["ids"], piece["vertices"], piece["albedo"], piece["faces"][np.isin(piece["part"], parts["parts"])]


def _joined(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Pieces (ids, vertices, faces) welded by the lattice edge each vertex lies on
    (pwm.block_surface.named): the index of each vertex kept (the first of each edge) in the
    pieces' vertices one after the other, and the faces over those kept."""
    offsets = np.cumsum([0] + [len(p[0]) for p in parts])
    _, first, inverse = np.unique(named(np.vstack([p[0] for p in parts])), return_index=True, return_inverse=True)
    return first, inverse.reshape(-1)[np.vstack([p[2] + o for p, o in zip(parts, offsets, strict=False)])]


def body_mesh(store: BlockStore, *, voxel_km: float) -> Mesh:
    """The body's surface as one mesh (km): each block's part of it, welded by the lattice edge
    each vertex lies on, which leaves no crack and no vertex twice."""
    parts = [p for b in store.blocks("body") if (p := _body_piece(store, b)) is not None]
    if not parts:
        raise ValueError("the fused distances have no zero crossing")
    first, faces = _joined([(ids, vertices, faces) for ids, vertices, _, faces in parts])
    return surface_mesh(np.vstack([p[1] for p in parts])[first], faces, np.concatenate([p[2] for p in parts])[first],
                        voxel_km=voxel_km)


def closure_in_blocks(store: BlockStore, *, voxel_km: float, cells: int, workers: int,
                      count_intersections: bool = True) -> Closure:
    """The checks of a closed surface (pwm.evaluate.closure) on the body the blocks hold,
    without making it one mesh: each block's own and its open edges met across the seams
    (pwm.block_surface.seam_checks), and the self-intersections counted block by block
    (`block_crossings`) on `workers` processes."""
    body = {b: _body(store, b) for b in store.blocks("body")}
    checks = seam_checks(_seams(store), body)
    watertight = checks.boundary_edges == 0 and checks.nonmanifold_edges == 0
    counted = watertight and count_intersections
    crossings = sum(map_processes(partial(block_crossings, store, cells=cells), sorted(body), workers=workers)
                    ) if counted else None
    return Closure(watertight=watertight, winding_consistent=checks.inconsistent_edges == 0,
                   outward=checks.volume > 0, self_intersections=crossings, intersections_counted=counted,
                   volume_km3=checks.volume * voxel_km ** 3, boundary_edges=checks.boundary_edges,
                   nonmanifold_edges=checks.nonmanifold_edges, components=1 if body else 0)


def block_crossings(store: BlockStore, block: int, *, cells: int) -> int:
    """The pairs of the body's faces that cross (pwm.evaluate.closure.self_intersections) with
    at least one face in this block and none in a block of a lower key: each pair is counted by
    one block. The faces of the blocks about it are taken where they can reach its own."""
    index = unpack(np.array([block]))[0]
    lo, hi = index * cells - _CROSSING_STEPS, (index + 1) * cells + _CROSSING_STEPS
    parts, owned = [], []
    for step in _AROUND:
        other = int(pack((index + step)[None])[0])
        held = None if other < block else _body_piece(store, other)
        if held is None:
            continue
        ids, vertices, _, faces = held
        faces = faces[in_box(vertices[faces].mean(axis=1), lo, hi)]
        parts.append((ids, vertices, faces))
        owned.append(np.full(len(faces), other == block))
    first, faces = _joined(parts)
    return self_intersections(Mesh(np.vstack([p[1] for p in parts])[first], faces), owned=np.concatenate(owned))
