"""Fusion across levels of maplets (METHOD.md 6): the sums of each level of node spacing
(pwm.tiling.level_of) kept apart, each at its own voxel size, and composed from the coarsest
level to the finest, so that each place takes the finest level that covers it.

The coarsest level is fused over the base: one closed surface of the body where its lattice is
affordable, else kept as points and laid onto the base (pwm.volume.grid_for chooses). A finer
level is kept as points (pwm.fusion.VoxelGrid) and laid onto the surface made so far
(`displace`): that surface's faces about the level's region are split until they are as fine as its voxels
(pwm.mesh.refine_faces, conforming) and each vertex there is moved along the level's vertical
(the direction its surface is a height field along) to the level's own surface, fully inside
the region and fading to nothing over BLEND_VOXELS inside its border. So a site's centimetre
maplets sit in the survey's closed surface without a step, and the result stays closed,
manifold and consistently wound: a closed base stays closed, with no site patched beside it (a
base of a body with holes and patches over them is sealed into one closed surface first,
`sealed`). (A level made while it was the coarsest, and later under a coarser one, may be a
DistanceGrid: its closed surface is then made over the surface below, which fills where its
maplets do not reach.) A maplet's revision is subtracted from its own level's sums exactly as
it was added.

The laid levels are laid place by place: the places ("regions") are the connected parts of the
ground within a margin of their sums, far enough apart that laying one cannot touch another's
faces. So a composition can start from the previous one (`Composition`): while the surface
below the laid levels is the same, a region that no added or subtracted maplet touched keeps
the previous composition's faces and vertices as they were, the rest of the body the surface
below's, and only the touched regions are laid again; the result is the one laying everything
would make. Lengths in km.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from pwm.fusion import VoxelGrid, border_vertices
from pwm.maplets import MapletGrid
from pwm.mesh import Mesh, border_edges, compact, edge_keys, largest_piece, pieces, refine_faces
from pwm.raytrace import Hits, RayTracer
from pwm.tiling import level_of
from pwm.volume import DistanceGrid, grid_for
from pwm.voxels import find, pack, unpack
from pwm.weights import raised_cosine

Grid = VoxelGrid | DistanceGrid
BATCH = 64
"""Maplets of one level held at a time while they are added."""
BLEND_VOXELS = 12.0
"""Width, in a finer level's voxels, of the band inside its border over which it fades into the
surface below it."""
MAX_EDGE_VOXELS = float(np.sqrt(2.0))
"""Longest edge, in a finer level's voxels, of the faces laid onto it: about as many vertices as
the level has lattice points over the same ground."""
REACH_VOXELS = 4.0
"""How far, in the next coarser level's voxels, a finer level's surface is looked for either way
along its vertical from the surface below it: about how far the coarser level may be off."""
MARGIN_EDGES = 3.0
"""Rings of the surface below's faces, beyond a laid level's reach, that a region's margin
holds: the conforming splits about the laid faces stay inside it."""

SEAL_OVER_EDGES = 4.0
"""How far (in its mean edges) along its normal a patch's vertex may lie from the body under it
and be taken as over it (`sealed`)."""

_NEIGHBOURS = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], dtype=np.int64)
_REACH = np.array([[i, j, k] for i in range(-2, 3) for j in range(-2, 3) for k in range(-2, 3)], dtype=np.int64)


@dataclass(frozen=True)
class Composition:
    """What a composed surface keeps for the next composition (`LevelGrids.compose`).

    below: the surface that the closed levels (and those laid between them) make over the base,
    onto which the rest are laid; digest: of what made `below` (the base and those levels' sums);
    vertex_origin: per vertex of the composed surface, the vertex of `below` it is (moved or
    not), -1 for a vertex the laying made; face_origin: per face, the face of `below` it is or
    was split from; below_region: per face of `below`, the laid levels' region it lies in, -1
    for none (the part of the body that only the closed levels make)."""

    below: Mesh
    digest: str
    vertex_origin: np.ndarray
    face_origin: np.ndarray
    below_region: np.ndarray

    def face_region(self) -> np.ndarray:
        """Per face of the composed surface, its region (-1: none)."""
        return self.below_region[self.face_origin]


@dataclass(frozen=True)
class Laid:
    """How a composition was made: regions laid again and carried over from the previous one,
    and whether the surface below the laid levels was made again."""

    regions_laid: int
    regions_carried: int
    below_made: bool


@dataclass
class LevelGrids:
    """The fusion sums of each level, by level. taper_fraction: the maplets' overlap.
    changed: the (level, centre, radius) of each maplet added or subtracted since these sums
    were made or read, which a composition lays again."""

    taper_fraction: float
    grids: dict[int, Grid] = field(default_factory=dict)
    changed: list[tuple[int, np.ndarray, float]] = field(default_factory=list, repr=False, compare=False)

    def add_all(self, maplets: Iterable[MapletGrid], *, base: Mesh) -> None:
        """Add the maplets to their levels' sums, a batch of each level at a time, so that they
        need not be held together. A level's first maplet sets its voxel size, and `base` (the
        body) whether the level is one closed surface or laid onto it."""
        pending: dict[int, list[MapletGrid]] = {}
        for maplet in maplets:
            level = self._note(maplet)
            if level not in self.grids:
                coarsest = level > max(self.grids, default=level - 1)
                self.grids[level] = (grid_for(base, voxel_km=maplet.spacing_km, taper_fraction=self.taper_fraction)
                                     if coarsest else VoxelGrid(maplet.spacing_km, taper_fraction=self.taper_fraction))
            pending.setdefault(level, []).append(maplet)
            if len(pending[level]) >= BATCH:
                self.grids[level].add_all(pending.pop(level))
        for level, batch in pending.items():
            self.grids[level].add_all(batch)

    def subtract(self, maplet: MapletGrid) -> None:
        """Take a maplet's contribution out of its level's sums, exactly as it was added."""
        level = int(level_of(maplet.spacing_km))
        if level not in self.grids:
            raise ValueError(f"maplet {maplet.name} is of level {level}, which these sums do not hold")
        self.grids[level].subtract(maplet)
        self._note(maplet)

    def _note(self, maplet: MapletGrid) -> int:
        nodes = maplet.nodes_body().reshape(-1, 3)
        centre = nodes.mean(axis=0)
        level = int(level_of(maplet.spacing_km))
        self.changed.append((level, centre, float(np.linalg.norm(nodes - centre, axis=1).max())))
        return level

    def mesh(self, base: Mesh) -> Mesh:
        """The fused surface: `base` with each level fused over it, coarsest first (see the
        module docstring)."""
        return self.compose(base)[0]

    def compose(self, base: Mesh, *, previous: tuple[Mesh, Composition] | None = None,
                close: Callable[[DistanceGrid, Mesh], Mesh] | None = None) -> tuple[Mesh, Composition, Laid]:
        """The fused surface over `base` (as `mesh`), what the next composition needs of it, and
        how it was made. previous: the surface composed from these sums before the changes
        since (`changed`) and its composition; the regions the changes do not touch are carried
        over from it while the surface below the laid levels is the same. A base of a body and
        patches beside it is made one closed surface first (`sealed`). close: makes a closed
        level's surface over the one below (DistanceGrid.mesh by default; pwm.blocks
        .mesh_in_blocks fuses a large one in blocks)."""
        base = sealed(base)
        order = self.held
        closed = [i for i, k in enumerate(order) if isinstance(self.grids[k], DistanceGrid)]
        made = order[: max(closed, default=0) + 1]
        digest = _digest(base, [(k, self.grids[k]) for k in made])
        if previous is not None and previous[1].digest == digest:
            below, carried = previous[1].below, previous
        else:
            below, carried = self._below(base, made, close), None
        laid = order[len(made):]
        reach = {k: REACH_VOXELS * self.grids[coarser].voxel_km for coarser, k in zip(order, order[1:], strict=False)}
        identity = np.arange(len(below.vertices)), np.arange(len(below.faces))
        if not laid:
            return below, Composition(below, digest, *identity, np.full(len(below.faces), -1)), Laid(
                0, 0, carried is None)
        margin = max(reach[k] + 2.0 * self.grids[k].voxel_km for k in laid) + MARGIN_EDGES * _longest_edge(below)
        regions = _regions([self.grids[k] for k in laid], margin, below)
        dirty = (np.ones(regions.count, dtype=bool) if carried is None
                 else regions.touched([(c, r) for k, c, r in self.changed if k in laid]))
        face_region = regions.of(below.vertices)[below.faces].max(axis=1)
        pieces = [_Piece.of(below, face_region < 0)]
        if carried is not None:
            pieces.append(_Piece.carried(*carried, keep=~dirty[np.maximum(face_region, 0)] & (face_region >= 0)))
        outer = border_edges(below.faces, len(below.vertices))
        for r in np.flatnonzero(dirty):
            pieces.append(self._lay(below, face_region == r, regions=regions, r=int(r), laid=laid, reach=reach,
                                    outer=outer))
        mesh, vertex_origin, face_origin = _weld(pieces)
        return mesh, Composition(below, digest, vertex_origin, face_origin, face_region), Laid(
            int(dirty.sum()), int((~dirty).sum()), carried is None)

    def _below(self, base: Mesh, made: list[int], close: Callable[[DistanceGrid, Mesh], Mesh] | None) -> Mesh:
        """The surface of the levels `made` (coarsest first) over `base`: a DistanceGrid closes
        its own (with `close`, as `compose`); a VoxelGrid is laid onto the surface below it, the
        base for the first."""
        surface = base
        for i, k in enumerate(made):
            grid = self.grids[k]
            if isinstance(grid, DistanceGrid):
                surface = grid.mesh(surface) if close is None else close(grid, surface)
            else:
                # the first level laid onto the base, as a finer level onto a coarser one, keeps the
                # base's surface one piece; how far off the base may be, its faces' size tells
                coarser = self.grids[made[i - 1]].voxel_km if i else base.mean_edge_length()
                albedo = grid.points().albedo
                if surface.albedo is None and not np.isnan(albedo).all():
                    # a base without albedo takes the level's mean, which the laid level's own
                    # albedo fades into
                    surface = Mesh(surface.vertices, surface.faces, np.full(len(surface.vertices),
                                                                            float(np.nanmean(albedo))))
                surface = displace(surface, grid, reach_km=REACH_VOXELS * coarser)[0]
        return surface

    def _lay(self, below: Mesh, faces: np.ndarray, *, regions: _Regions, r: int, laid: list[int],
             reach: dict[int, float], outer: np.ndarray) -> _Piece:
        """The laid levels' part of region r laid onto its faces of `below`. outer: the edges
        where `below` is open (`pwm.mesh.border_edges`)."""
        used, sub_faces = compact(len(below.vertices), below.faces[faces])
        origin_vertex = np.flatnonzero(used)
        surface = Mesh(below.vertices[used], sub_faces, None if below.albedo is None else below.albedo[used])
        origin_face = np.flatnonzero(faces)
        for k in laid:
            grid = _part(self.grids[k], regions, r)
            if grid is not None:
                surface, parent = displace(surface, grid, reach_km=reach[k])
                origin_face = origin_face[parent]
        n, m = len(origin_vertex), len(surface.vertices)
        # where the region's faces meet the rest of `below` (not where `below` itself is open),
        # the laying must have left every edge and corner as it was
        border = border_edges(sub_faces, m)
        a, b = origin_vertex[border // m], origin_vertex[border % m]
        cut = border[~np.isin(a * len(below.vertices) + b, outer)]
        ends = np.unique(np.concatenate([cut // m, cut % m]))
        if not (np.array_equal(surface.vertices[ends], below.vertices[origin_vertex[ends]])
                and np.isin(cut, border_edges(surface.faces, m)).all()):
            raise RuntimeError(f"laying region {r} reached its margin: MARGIN_EDGES is too small")
        vertex_origin = np.concatenate([origin_vertex, np.full(m - n, -1)])
        return _Piece(surface, vertex_origin, origin_face)

    @property
    def held(self) -> list[int]:
        """The levels that hold points, coarsest first: the order they are composed in."""
        return [k for k in sorted(self.grids, reverse=True) if len(self.grids[k].keys)]

    @property
    def voxels(self) -> int:
        """The lattice points of all levels."""
        return sum(len(grid.keys) for grid in self.grids.values())

    def describe(self) -> dict[str, dict]:
        """Per level (as text), coarsest first: how it makes the surface ("closed"; "laid" onto
        the levels below, or the base), its voxel size (m) and lattice points."""
        out: dict[str, dict] = {}
        for level, grid in sorted(self.grids.items(), reverse=True):
            surface = "closed" if isinstance(grid, DistanceGrid) else "laid"
            out[str(level)] = {"surface": surface, "voxel_m": grid.voxel_km * 1e3, "voxels": len(grid.keys)}
        return out


def displace(surface: Mesh, grid: VoxelGrid, *, reach_km: float) -> tuple[Mesh, np.ndarray]:
    """`surface` with the finer level of `grid` laid onto it (see the module docstring): the
    faces with a vertex that finds the level's surface along its vertical within reach_km either
    way split to MAX_EDGE_VOXELS; the vertices that find it moved to it, in full at BLEND_VOXELS
    and more inside its border, fading to nothing at it; albedo likewise. A face of `surface`
    across the level's border with no vertex over the level stays whole, and the level is laid
    only up to it: its edges shared with split faces are split too, so it ramps from them to its
    own corners, without a step. Also returns each face's face of `surface`."""
    level = grid.mesh()
    tracer = RayTracer(level)
    over = _crossing(tracer, surface.vertices, grid.vertical(surface.vertices), reach_km)[0]
    selected = over[surface.faces].any(axis=1)
    refined, parent = refine_faces(surface, selected, max_edge_km=MAX_EDGE_VOXELS * grid.voxel_km)
    chosen = selected[parent]
    moved = np.unique(refined.faces[chosen])
    up = grid.vertical(refined.vertices[moved])
    found, shift, hits = _crossing(tracer, refined.vertices[moved], up, reach_km)
    at = refined.vertices[moved[found]] + shift[found, None] * up[found]
    edge = level.vertices[border_vertices(level.faces)]
    inside = cKDTree(edge).query(at)[0] if len(edge) else np.full(len(at), np.inf)
    share = raised_cosine(inside / (BLEND_VOXELS * grid.voxel_km))
    vertices = refined.vertices.copy()
    index = moved[found]
    vertices[index] += (share * shift[found])[:, None] * up[found]
    albedo = refined.albedo
    if albedo is not None and level.albedo is not None:
        albedo = albedo.copy()
        albedo[index] += share * (tracer.interpolate(level.albedo, hits)[found] - albedo[index])
    return Mesh(vertices, refined.faces, albedo), parent


def sealed(base: Mesh) -> Mesh:
    """`base` made one closed surface where it is a body with holes and patches over them, each
    overlapping its hole's rim (as a start model made of a site's patch on the body it was cut
    from comes): each patch less its faces over the body (SEAL_OVER_EDGES of its edges within)
    and a band beyond them as wide as the rim's edges are long, its border zipped to its hole's
    by a ring of faces in the patch's plane. Any other mesh, or one whose pieces are not so,
    comes back as it is."""
    n = len(base.vertices)
    piece = pieces(n, base.faces)
    if piece.max(initial=0) == 0:
        return base
    body = np.bincount(piece).argmax()
    faces = [base.faces[piece == body]]
    holes = _loops(faces[0], n)
    if holes is None:
        return base
    tracer = RayTracer(Mesh(base.vertices, faces[0]))
    for k in np.setdiff1d(np.unique(piece), [body]):
        patch = base.faces[piece == k]
        if not holes:
            return base
        centre = base.vertices[np.unique(patch)].mean(axis=0)
        hole = holes.pop(int(np.argmin([np.linalg.norm(base.vertices[h].mean(axis=0) - centre) for h in holes])))
        tri = base.vertices[patch]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).sum(axis=0)
        normal /= max(float(np.linalg.norm(normal)), 1e-300)
        edge = float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).mean())
        used = np.unique(patch)
        hits = tracer.intersect(base.vertices[used] + SEAL_OVER_EDGES * edge * normal,
                                np.broadcast_to(-normal, (len(used), 3)))
        over = np.zeros(n, dtype=bool)
        over[used] = hits.hit & (hits.t <= 2.0 * SEAL_OVER_EDGES * edge)
        # and as many rings of the patch's faces beyond as the rim's edges are long, so that no
        # kept face reaches over a notch of the rim, which the ring's faces would cross
        rim = float(np.linalg.norm(base.vertices[np.roll(hole, -1)] - base.vertices[hole], axis=1).mean())
        for _ in range(int(np.ceil(rim / edge))):
            over[patch[over[patch].any(axis=1)]] = True
        kept = patch[~over[patch].any(axis=1)]
        if not len(kept):
            return base
        kept = kept[largest_piece(n, kept)]
        inner = _loops(kept, n)
        if inner is None or len(inner) != 1:
            return base
        faces += [kept, _zip(base.vertices, outer=hole[::-1], inner=inner[0], centre=centre, normal=normal)]
    used_mask, joined = compact(n, np.vstack(faces))
    out = Mesh(base.vertices[used_mask], joined, None if base.albedo is None else base.albedo[used_mask])
    check = trimesh.Trimesh(out.vertices, out.faces, process=False)
    return out if check.is_watertight and check.is_winding_consistent and check.volume > 0 else base


def _loops(faces: np.ndarray, n_vertices: int) -> list[np.ndarray] | None:
    """The border loops of `faces`, each its vertices in the order its faces run along it; None
    where a border is not simple (a vertex on it twice)."""
    directed = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    directed = directed[np.isin(edge_keys(faces, n_vertices).ravel(), border_edges(faces, n_vertices))]
    if len(np.unique(directed[:, 0])) != len(directed):
        return None
    following = dict(zip(directed[:, 0].tolist(), directed[:, 1].tolist(), strict=True))
    loops = []
    while following:
        start = next(iter(following))
        loop = [start]
        while (step := following.pop(loop[-1], None)) is not None and step != start:
            loop.append(step)
        if step != start:
            return None
        loops.append(np.array(loop, dtype=np.int64))
    return loops


def _zip(vertices: np.ndarray, *, outer: np.ndarray, inner: np.ndarray, centre: np.ndarray,
         normal: np.ndarray) -> np.ndarray:
    """Faces joining two loops about `centre`, both running counter-clockwise seen along -normal,
    `outer` round `inner`: each step takes the next vertex of the loop whose next vertex comes
    first in angle, so the ring's faces are wound outwards (along normal)."""
    e1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)

    def angles(loop: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = vertices[loop] - centre
        a = np.mod(np.arctan2(d @ e2, d @ e1), 2 * np.pi)
        first = int(np.argmin(a))
        loop = np.roll(loop, -first)
        a = np.unwrap(np.roll(a, -first))
        return np.append(loop, loop[0]), np.append(a, a[0] + 2 * np.pi)

    (o, ao), (i, ai) = angles(outer), angles(inner)
    faces, p, q = [], 0, 0
    while p < len(o) - 1 or q < len(i) - 1:
        if q == len(i) - 1 or (p < len(o) - 1 and ao[p + 1] <= ai[q + 1]):
            faces.append((o[p], o[p + 1], i[q]))
            p += 1
        else:
            faces.append((o[p], i[q + 1], i[q]))
            q += 1
    return np.array(faces, dtype=np.int64)


def _crossing(tracer: RayTracer, points: np.ndarray, directions: np.ndarray,
              reach_km: float) -> tuple[np.ndarray, np.ndarray, Hits]:
    """Where the tracer's surface crosses the line through each point along its direction
    within reach_km either way (the first crossing from below): whether it does, the signed
    shift along the direction (km), and the hits."""
    hits = tracer.intersect(points - reach_km * directions, directions)
    return hits.hit & (hits.t <= 2.0 * reach_km), hits.t - reach_km, hits


@dataclass(frozen=True)
class _Piece:
    """Part of a composed surface: its mesh, and per vertex and face their origin in `below`."""

    mesh: Mesh
    vertex_origin: np.ndarray
    face_origin: np.ndarray

    @classmethod
    def of(cls, below: Mesh, faces: np.ndarray) -> _Piece:
        """The faces of `below` as they are."""
        return cls(Mesh(below.vertices, below.faces[faces], below.albedo), np.arange(len(below.vertices)),
                   np.flatnonzero(faces))

    @classmethod
    def carried(cls, mesh: Mesh, composition: Composition, *, keep: np.ndarray) -> _Piece:
        """The faces of a previous composition that came from the faces `keep` of its `below`."""
        chosen = keep[composition.face_origin]
        return cls(Mesh(mesh.vertices, mesh.faces[chosen], mesh.albedo), composition.vertex_origin,
                   composition.face_origin[chosen])


def _weld(pieces: list[_Piece]) -> tuple[Mesh, np.ndarray, np.ndarray]:
    """The pieces as one mesh, a vertex of `below` shared by several pieces made one (it must lie
    where each piece has it), the vertices no face uses dropped; with the vertices' and faces'
    origins."""
    vertices = np.vstack([p.mesh.vertices for p in pieces])
    origin = np.concatenate([p.vertex_origin for p in pieces])
    offsets = np.cumsum([0] + [len(p.mesh.vertices) for p in pieces])
    faces = np.vstack([p.mesh.faces + o for p, o in zip(pieces, offsets[:-1], strict=True)])
    used = np.zeros(len(vertices), dtype=bool)
    used[faces] = True
    target = np.arange(len(vertices))
    shared = np.flatnonzero(used & (origin >= 0))
    _, first, inverse = np.unique(origin[shared], return_index=True, return_inverse=True)
    target[shared] = shared[first][inverse]
    if not np.array_equal(vertices[shared], vertices[target[shared]]):
        raise RuntimeError("pieces of a composition disagree where they meet")
    faces = target[faces]
    kept, faces = compact(len(vertices), faces)
    albedo = None
    if all(p.mesh.albedo is not None for p in pieces):
        albedo = np.concatenate([p.mesh.require_albedo() for p in pieces])[kept]
    return (Mesh(vertices[kept], faces, albedo), origin[kept],
            np.concatenate([p.face_origin for p in pieces]))


@dataclass(frozen=True)
class _Regions:
    """The laid levels' regions: the cells (of side margin_km, packed, sorted) that hold their
    sums or lie next to one that does, and each cell's region."""

    margin_km: float
    cells: np.ndarray
    label: np.ndarray

    @property
    def count(self) -> int:
        return int(self.label.max()) + 1

    def of(self, points: np.ndarray) -> np.ndarray:
        """The region of each point (N, 3), -1 for none."""
        found = find(self.cells, pack(np.floor(points / self.margin_km).astype(np.int64)))
        return np.where(found >= 0, self.label[found], -1)

    def touched(self, spheres: list[tuple[np.ndarray, float]]) -> np.ndarray:
        """Which regions reach within one cell of the spheres (centre, radius)."""
        out = np.zeros(self.count, dtype=bool)
        for centre, radius in spheres:
            lo = np.floor((centre - radius) / self.margin_km).astype(np.int64) - 1
            hi = np.floor((centre + radius) / self.margin_km).astype(np.int64) + 1
            box = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi, strict=True)], indexing="ij"), -1)
            found = find(self.cells, pack(box.reshape(-1, 3)))
            out[self.label[found[found >= 0]]] = True
        return out


def _regions(grids: list[Grid], margin_km: float, below: Mesh) -> _Regions:
    """The regions of the laid levels' sums (see `_Regions`): cells holding sums are joined where
    the cells next to them overlap, and regions that one face of `below` spans are one."""
    occupied = unpack(np.unique(np.concatenate(
        [pack(np.floor(unpack(g.keys) * (g.voxel_km / margin_km)).astype(np.int64)) for g in grids])))
    label = _components(occupied, _REACH)
    cells = (occupied[:, None, :] + _NEIGHBOURS[None]).reshape(-1, 3)
    keys, first = np.unique(pack(cells), return_index=True)
    regions = _Regions(margin_km, keys, np.repeat(label, len(_NEIGHBOURS))[first])
    # a face with corners in two regions' cells (cells next to each other) joins them
    corner = regions.of(below.vertices)[below.faces]
    corner = np.where(corner < 0, corner.max(axis=1, keepdims=True), corner)
    joined = corner[corner.min(axis=1) >= 0]
    graph = coo_matrix((np.ones(2 * len(joined)), (np.concatenate([joined[:, 0], joined[:, 1]]),
                                                    np.concatenate([joined[:, 1], joined[:, 2]]))),
                       shape=(regions.count, regions.count))
    _, merged = connected_components(graph, directed=False)
    return _Regions(margin_km, keys, merged[regions.label])


def _components(cells: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Component of each of the unique integer cells (N, 3), two cells joined when one is a
    step (of `steps`) from the other."""
    keys = pack(cells)
    order = np.argsort(keys)
    rows, cols = [], []
    for step in steps:
        found = find(keys[order], pack(cells + step))
        rows.append(np.flatnonzero(found >= 0))
        cols.append(order[found[found >= 0]])
    n = len(keys)
    graph = coo_matrix((np.ones(sum(len(r) for r in rows)), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _part(grid: Grid, regions: _Regions, r: int) -> VoxelGrid | None:
    """The part of a laid level's sums in region r, None if it has none there."""
    if not isinstance(grid, VoxelGrid):
        raise TypeError("a laid level is a VoxelGrid")
    inside = regions.of(unpack(grid.keys) * grid.voxel_km) == r
    if not inside.any():
        return None
    return VoxelGrid(grid.voxel_km, taper_fraction=grid.taper_fraction, keys=grid.keys[inside],
                     sums=grid.sums[inside], count=grid.count[inside])


def _longest_edge(mesh: Mesh) -> float:
    tri = mesh.vertices[mesh.faces]
    return float(np.linalg.norm(np.roll(tri, -1, axis=1) - tri, axis=2).max())


def _digest(base: Mesh, grids: list[tuple[int, Grid]]) -> str:
    """sha256 of the base and the levels' sums."""
    h = hashlib.sha256()
    for array in (base.vertices, base.faces, base.albedo if base.albedo is not None else np.empty(0)):
        h.update(np.ascontiguousarray(array).tobytes())
    for level, grid in grids:
        h.update(f"{level} {type(grid).__name__} {grid.voxel_km!r} {grid.taper_fraction!r}".encode())
        for array in (grid.keys, grid.sums, grid.count):
            h.update(np.ascontiguousarray(array).tobytes())
    return h.hexdigest()
