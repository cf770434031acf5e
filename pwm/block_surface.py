"""The surface fused in blocks (pwm.blocks) as pieces, one per block, never held whole: each
block's marching-cubes piece welded by the lattice edge each vertex lies on (so that a vertex
has the same name in every block that makes it), the body's piece found across the seams (the
largest, as pwm.volume.body_surface keeps), and the checks of a closed surface gathered over
the seams. What one process holds grows with the seams between blocks, not with the surface:
a body too big for one process still fuses (issue 50). Vertices in lattice steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from pwm.mesh import compact, edge_keys, pieces, uncollapsed
from pwm.voxels import pack, unpack

# a vertex this close (in lattice steps) to a lattice point is at it: both blocks about it agree
_AT_POINT = 1e-9
_ID = np.dtype([("key", "<i8"), ("axis", "<i8")])


def lattice_edges(vertices: np.ndarray) -> np.ndarray:
    """(N, 2) the lattice edge each marching-cubes vertex (in lattice steps) lies on: the key of
    its lower end and its axis (0-2), or the key of the lattice point it is at and 3."""
    nearest = np.round(vertices)
    at_point = (np.abs(vertices - nearest) <= _AT_POINT).all(axis=1)
    lower = np.floor(vertices)
    axis = np.argmax(vertices - lower, axis=1)
    lower = np.where(at_point[:, None], nearest, lower).astype(np.int64)
    return np.column_stack([pack(lower), np.where(at_point, 3, axis)])


def named(ids: np.ndarray) -> np.ndarray:
    """(N,) vertex names, one comparable value per (N, 2) lattice edge of `lattice_edges`."""
    return np.ascontiguousarray(ids, dtype=np.int64).view(_ID).reshape(-1)


@dataclass(frozen=True)
class Piece:
    """A block's piece welded: ids (V, 2) the lattice edge of each vertex (`lattice_edges`, one
    vertex per edge), vertices (V, 3) in lattice steps, albedo (V,) (nan without), faces (F, 3),
    part (F,) the edge-connected part of the piece each face is in (0, 1, ...)."""

    ids: np.ndarray
    vertices: np.ndarray
    albedo: np.ndarray
    faces: np.ndarray
    part: np.ndarray


def welded(vertices: np.ndarray, faces: np.ndarray, albedo: np.ndarray) -> Piece:
    """Marching cubes' vertices (lattice steps), faces and albedo as one vertex per lattice edge
    (the first of each), the faces that weld leaves with two corners one vertex dropped."""
    ids = lattice_edges(vertices)
    _, first, inverse = np.unique(named(ids), return_index=True, return_inverse=True)
    used, faces = compact(len(first), uncollapsed(inverse.reshape(-1)[faces]))
    keep = first[used]
    return Piece(ids=ids[keep], vertices=vertices[keep], albedo=albedo[keep], faces=faces,
                 part=pieces(len(keep), faces))


@dataclass(frozen=True)
class Seams:
    """What a block's piece shares with the others and what the checks of a closed surface
    need of it, per part: shell (S, 2) the ids of its vertices on the block's faces (the only
    ones another block can make) and shell_part (S,); faces (P,) and volume (P,) (signed, in
    cubic lattice steps) per part; open (E, 4) its directed edges in one face only (from id,
    to id) and open_part (E,); nonmanifold (P,) its edges in more than two faces; inconsistent
    (P,) its edges in two faces wound the same way."""

    shell: np.ndarray
    shell_part: np.ndarray
    faces: np.ndarray
    volume: np.ndarray
    open: np.ndarray
    open_part: np.ndarray
    nonmanifold: np.ndarray
    inconsistent: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Seams:
        return cls(**{name: arrays[name] for name in cls.__dataclass_fields__})


def seams(piece: Piece, *, origin: np.ndarray, cells: int) -> Seams:
    """The seams of a block's piece, the block's lowest lattice point at `origin`, `cells`
    steps a side."""
    parts = int(piece.part.max(initial=-1)) + 1
    rel = unpack(piece.ids[:, 0]) - origin
    shell = ((rel == 0) | (rel == cells)).any(axis=1)
    vertex_part = np.zeros(len(piece.ids), dtype=np.int64)
    vertex_part[piece.faces.reshape(-1)] = np.repeat(piece.part, 3)
    tri = piece.vertices[piece.faces]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    # edge k of a face joins its corners k and k + 1 (pwm.mesh.edge_keys), face by face
    directed = np.stack([piece.faces, np.roll(piece.faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    edge_part = np.repeat(piece.part, 3)
    _, first, where, count = np.unique(edge_keys(piece.faces, len(piece.ids)).reshape(-1), return_index=True,
                                       return_inverse=True, return_counts=True)
    uses = count[where.reshape(-1)]
    # an edge in two faces wound the same way: its two uses are one directed edge
    _, first_way, ways = np.unique(directed @ np.array([len(piece.ids), 1]), return_index=True, return_counts=True)
    same_way = first_way[(ways == 2) & (uses[first_way] == 2)]
    one = uses == 1
    return Seams(shell=piece.ids[shell], shell_part=vertex_part[shell],
                 faces=np.bincount(piece.part, minlength=parts), volume=np.bincount(piece.part, volume, parts),
                 open=np.column_stack([piece.ids[directed[one, 0]], piece.ids[directed[one, 1]]]),
                 open_part=edge_part[one],
                 nonmanifold=np.bincount(edge_part[first[count > 2]], minlength=parts),
                 inconsistent=np.bincount(edge_part[same_way], minlength=parts))


def body_parts(held: dict[int, Seams]) -> dict[int, np.ndarray]:
    """The parts of each block's piece that make the body: the parts joined across the seams
    (by a vertex two blocks make) into the largest whole, by faces. Blocks of none: left out."""
    blocks = sorted(held)
    if not sum(int(held[b].faces.sum()) for b in blocks):
        raise ValueError("the fused distances have no zero crossing")
    offset = np.cumsum([0] + [len(held[b].faces) for b in blocks])
    shell = np.concatenate([named(held[b].shell) for b in blocks])
    node = np.concatenate([held[b].shell_part + o for b, o in zip(blocks, offset, strict=False)])
    order = np.argsort(shell, kind="stable")
    same = np.flatnonzero(shell[order][1:] == shell[order][:-1])
    graph = coo_matrix((np.ones(len(same)), (node[order][same], node[order][same + 1])), shape=(int(offset[-1]),) * 2)
    _, label = connected_components(graph, directed=False)
    body = np.bincount(label, np.concatenate([held[b].faces for b in blocks])).argmax()
    kept = {b: np.flatnonzero(label[offset[k]:offset[k + 1]] == body) for k, b in enumerate(blocks)}
    return {b: parts for b, parts in kept.items() if len(parts)}


@dataclass(frozen=True)
class SeamChecks:
    """The checks of a closed surface over the body's parts in all blocks (see
    pwm.evaluate.closure.Closure): boundary_edges: edges in one face of the whole; nonmanifold
    and inconsistent edges (in more than two faces; in two wound the same way); volume in cubic
    lattice steps."""

    boundary_edges: int
    nonmanifold_edges: int
    inconsistent_edges: int
    volume: float


def seam_checks(held: dict[int, Seams], body: dict[int, np.ndarray]) -> SeamChecks:
    """The body's checks: each block's own, and its open edges met by the other blocks'. An
    edge open in one block is closed by the same edge, the other way round, open in another."""
    opened, counts = [], {"nonmanifold": 0, "inconsistent": 0}
    volume = 0.0
    for block, parts in body.items():
        s = held[block]
        opened.append(s.open[np.isin(s.open_part, parts)])
        counts["nonmanifold"] += int(s.nonmanifold[parts].sum())
        counts["inconsistent"] += int(s.inconsistent[parts].sum())
        volume += float(s.volume[parts].sum())
    edges = np.vstack(opened) if opened else np.empty((0, 4), dtype=np.int64)
    start, end = edges[:, :2], edges[:, 2:]
    forward = (start[:, 0] < end[:, 0]) | ((start[:, 0] == end[:, 0]) & (start[:, 1] < end[:, 1]))
    pair = np.where(forward[:, None], edges, np.column_stack([end, start]))
    _, where, uses = np.unique(pair, axis=0, return_inverse=True, return_counts=True)
    turns = np.bincount(where.reshape(-1), np.where(forward, 1, -1), len(uses))
    return SeamChecks(boundary_edges=int((uses == 1).sum()),
                      nonmanifold_edges=counts["nonmanifold"] + int((uses > 2).sum()),
                      inconsistent_edges=counts["inconsistent"] + int(((uses == 2) & (turns != 0)).sum()),
                      volume=volume)
