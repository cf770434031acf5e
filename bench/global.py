"""Scale of a whole-body model: tiling, fusion and refinement of about 100, 400 and 1300 maplets
of 100 x 100 nodes over the whole of Bennu, on the cores given (issue 15.5).

    .venv/bin/python bench/global.py [--maplets 100 400 1300] [--survey SIM] [--sample 8] [--workers 2]
    .venv/bin/python bench/global.py --maplets 100 400 --blocks 1 2 [--cells 256] [--compare] [--downlink 5]
        [--no-check]

Fusion, per size: the whole shape (pwm's Bennu radar model) is tiled at the spacing that gives
about N maplets, each maplet's heights get 1 cm of noise (so that fusion has disagreements to
average), and they are fused, streamed from disk one at a time as the catalog's fusion does, into
one closed surface (pwm.volume.DistanceGrid) closed by the shape; each size runs in a process of
its own, whose peak resident memory up to the mesh is reported (the closed-surface checks after
it cost their own), with the size of the sums a version keeps. Refinement: `--sample` maplets of a survey
simulation (SIM, e.g. `pwm simulate SIM --scenario global-coarse --with-start-model`), at its
images' pixel scale, are refined from its images against its start model on `--workers`
processes; a maplet's cost depends on its nodes and images, not on how many others there are,
so maplets per hour carry over to every size. The table gives the hours for each size and for
the PWM paper's 1300-maplet Bennu model.

With --blocks, the fusion runs in blocks (pwm.blocks) on each process count given: each
block's sums made from the maplet files that reach it, then closed and meshed, the body's
parts of the pieces found across their seams, the surface left in the blocks; the peak memory
of the parent and of the largest worker, whether the surface is closed (pwm.blocks
.closure_in_blocks, block by block, with the parent's peak then; but with --no-check), and with
--compare (in a process of its own, after) the distance of the blocks' vertices to the
one-process vertices on the same lattice edges; with --downlink K, a downlink that changes the
K maplets nearest one of them (heights 1 m up) fused over the first fusion's blocks (pwm.blocks
.fuse_in_blocks' changed): its seconds and how many of the blocks' files it wrote; then the
extrapolation to Bennu at 5 cm.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pwm.config import BLOCKS, DEFAULTS  # noqa: E402
from pwm.mesh import Mesh  # noqa: E402

CHECK_MAX_FACES = 30_000_000  # about 0.55 GiB a million faces (pwm.evaluate.closure, in slabs)
BENNU_FINE_M = 0.05
CLOSED = {True: "yes", False: "no", None: "not checked"}
VERTICES = "blocks_vertices.npy"
SHAPE = Path(__file__).resolve().parents[1] / "pwm" / "data" / "shapes" / "bennu_radar_nolan2013_sbgat.obj"


def _tiled(scratch: Path, maplets: int, nodes: int) -> tuple[Mesh, float, list[Path], float]:
    """The shape, the spacing (km) that tiles it with about `maplets` maplets, their files under
    `scratch` (1 cm of noise on the heights) and the seconds the tiling took."""
    from pwm.io.fusion_state import write_maplet
    from pwm.io.meshio import read_obj
    from pwm.tiling import tile

    shape = read_obj(SHAPE)
    spacing = np.sqrt(shape.face_areas().sum() / maplets) / ((1 - DEFAULTS.overlap) * (nodes - 1))
    clock = time.perf_counter()
    tiled = tile(shape, spacing_km=spacing, nodes=nodes, overlap=DEFAULTS.overlap)
    tiling_s = time.perf_counter() - clock
    rng = np.random.default_rng(0)
    paths = []
    for k, m in enumerate(tiled):
        m.heights = m.heights + 1e-5 * rng.standard_normal(m.heights.shape)
        paths.append(scratch / f"{k}.npz")
        write_maplet(paths[-1], m)
    return shape, spacing, paths, tiling_s


def fuse_once(maplets: int, nodes: int) -> dict:
    """Tile, store and fuse about `maplets` maplets over the whole shape; figures as a dict."""
    from pwm.evaluate.closure import closure
    from pwm.io.fusion_state import read_maplet, write_levels
    from pwm.levels import LevelGrids
    from pwm.tiling import level_of
    from pwm.volume import DistanceGrid

    with tempfile.TemporaryDirectory() as scratch:
        shape, spacing, paths, tiling_s = _tiled(Path(scratch), maplets, nodes)
        count = len(paths)
        clock = time.perf_counter()
        grid = DistanceGrid(voxel_km=spacing, taper_fraction=DEFAULTS.overlap)
        grid.add_all(read_maplet(p) for p in paths)
        add_s = time.perf_counter() - clock
    clock = time.perf_counter()
    mesh = grid.mesh(shape)
    mesh_s = time.perf_counter() - clock
    peak_gib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # before the checks' own
    with tempfile.TemporaryDirectory() as scratch:
        write_levels(Path(scratch) / "grid.npz", LevelGrids(DEFAULTS.overlap, {int(level_of(spacing)): grid}))
        grid_mib = (Path(scratch) / "grid.npz").stat().st_size / 2**20
    clock = time.perf_counter()
    # the self-intersection test holds every nearby pair of faces: beyond this, not checked here
    closed = closure(mesh).closed if len(mesh.faces) <= CHECK_MAX_FACES else None
    return {"maplets": count, "spacing_m": spacing * 1e3, "tiling_s": tiling_s, "add_s": add_s, "mesh_s": mesh_s,
            "lattice_points": len(grid.keys), "grid_mib": grid_mib, "faces": len(mesh.faces),
            "closed": closed, "check_s": time.perf_counter() - clock, "peak_gib": peak_gib}


def fuse_blocks_once(maplets: int, nodes: int, workers: int, cells: int, compare: bool, downlink: int,
                     check: bool) -> dict:
    """As `fuse_once`, in blocks of `cells` lattice steps (pwm.blocks) on `workers` processes:
    each block's sums made from the maplet files that reach it, then closed and meshed, the
    surface left in the blocks; the peak resident memory of this process and of the largest worker (with one
    worker the blocks run here), and with `compare` the RMS and largest distance of the
    blocks' vertices to the one-process vertices on their lattice edges (made after the peaks are
    read); with `downlink` maplets changed (`_downlink`), the seconds and files written of their fusion."""
    from pwm.blocks import body_mesh, closure_in_blocks, fuse_in_blocks
    from pwm.config import FusionBlocks
    from pwm.io.fusion_state import BlockFiles, build_blocks

    blocks = FusionBlocks(cells=cells, workers=workers)
    with tempfile.TemporaryDirectory() as scratch:
        shape, spacing, paths, _ = _tiled(Path(scratch), maplets, nodes)
        count = len(paths)
        store = BlockFiles(Path(scratch) / "blocks")
        clock = time.perf_counter()
        build_blocks(store, paths, voxel_km=spacing, taper_fraction=DEFAULTS.overlap, cells=cells, workers=workers)
        add_s = time.perf_counter() - clock
        points = [len(g.keys) for b in store.blocks("sums") if (g := store.read("sums", b)) is not None]
        clock = time.perf_counter()
        body = fuse_in_blocks(store, base=shape, blocks=blocks)
        mesh_s = time.perf_counter() - clock
        figures = {"maplets": count, "spacing_m": spacing * 1e3, "spacing_km": float(spacing), "workers": workers,
                   "blocks": len(points),
                   "lattice_points": sum(points), "largest_block_points": max(points), "add_s": add_s,
                   "mesh_s": mesh_s, "peak_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
                   "worker_gib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2**20,
                   "sums_mib": sum(store.path("sums", b).stat().st_size for b in store.blocks("sums")) / 2**20,
                   "faces": body.faces, "closed": None, "check_s": 0.0, "check_peak_gib": None, "rms_mm": None,
                   "max_mm": None,
                   "downlink": None}
        _report(figures)  # what a later step that fails (memory) would lose
        if downlink:
            figures["downlink"] = _downlink(store, paths, blocks=blocks, spacing=spacing, base=shape, count=downlink)
        if check:
            clock = time.perf_counter()
            checks = closure_in_blocks(store, voxel_km=spacing, cells=cells, workers=workers)
            figures["closed"] = checks.closed
            figures["check_s"] = time.perf_counter() - clock
            figures["check_peak_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
            _report(figures)
        if compare:
            # kept for a process of its own, once this one has ended: the one-process sums are
            # the largest thing the comparison holds, and nothing of this process may hold beside them
            kept = Path(tempfile.mkdtemp(prefix="pwm-compare-"))
            for path in paths:
                shutil.move(path, kept / path.name)
            np.save(kept / VERTICES, body_mesh(store, voxel_km=spacing).vertices)
            figures["compare_dir"] = str(kept)
    return figures


def _report(figures: dict) -> None:
    print(json.dumps(figures), flush=True)


def compare_one(scratch: Path, spacing: float) -> dict:
    """The maplet files under `scratch` fused in one process (pwm.volume.DistanceGrid) over the
    shape, and the RMS and largest distance (mm) of the blocks' vertices saved there to the
    one-process vertex on the same lattice edge (pwm.block_surface.lattice_edges): each lies on the
    other's surface only if they are the same point, so this bounds the distance to the surface
    from above, with no distance structure over the whole mesh (at 22.5M faces ClosestPoint's
    would need about 30 GiB); the vertices that have no partner, in each mesh, are counted."""
    from pwm.block_surface import lattice_edges, named
    from pwm.io.fusion_state import read_maplet
    from pwm.io.meshio import read_obj
    from pwm.volume import DistanceGrid

    paths = sorted(scratch.glob("*.npz"), key=lambda p: int(p.stem))
    grid = DistanceGrid(voxel_km=spacing, taper_fraction=DEFAULTS.overlap)
    grid.add_all(read_maplet(p) for p in paths)
    one = grid.mesh(read_obj(SHAPE))
    del grid
    blocks = np.load(scratch / VERTICES)
    edge = [named(lattice_edges(_steps(v, spacing))) for v in (one.vertices, blocks)]
    order = np.argsort(edge[0])
    at = np.minimum(np.searchsorted(edge[0], edge[1], sorter=order), len(order) - 1)
    partner = order[at]
    found = edge[0][partner] == edge[1]
    off = np.linalg.norm(blocks[found] - one.vertices[partner[found]], axis=1)
    return {"rms_mm": float(np.sqrt(np.mean(off ** 2)) * 1e6), "max_mm": float(off.max() * 1e6),
            "blocks_unpaired": int((~found).sum()),
            "one_unpaired": int(len(one.vertices) - len(np.unique(partner[found]))),
            "one_faces": len(one.faces), "one_peak_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def _steps(vertices: np.ndarray, spacing: float) -> np.ndarray:
    """Vertices (km) in lattice steps, the coordinates off their edge's axis made whole again
    (dividing by the spacing leaves them a rounding error off, which would put a vertex on
    another edge)."""
    steps = vertices / spacing
    whole = np.round(steps)
    return np.where(np.abs(steps - whole) < 1e-6, whole, steps)


def _downlink(store, paths: list[Path], *, blocks, spacing: float, base: Mesh, count: int) -> dict:
    """The `count` maplets nearest the first one raised 1 m, their old revisions taken out of
    the blocks' sums and the new ones added, and fused over the blocks as they are: seconds
    (sums and fusion), the blocks whose sums changed, and the files written of all."""
    from pwm.blocks import BlockedSums, fuse_in_blocks
    from pwm.io.fusion_state import read_maplet

    maplets = [read_maplet(p) for p in paths]
    origin = maplets[0].frame.origin
    chosen = sorted(maplets, key=lambda m: float(np.linalg.norm(m.frame.origin - origin)))[:count]
    files = {p: p.stat().st_mtime_ns for p in store.directory.rglob("*.npz")}
    clock = time.perf_counter()
    sums = BlockedSums(store, spacing, DEFAULTS.overlap, blocks.cells)
    for old in chosen:
        sums.subtract(old)
        old.heights = old.heights + 0.001
        sums.add_batch([old])
    changed = set(sums.save())
    fuse_in_blocks(store, base=base, blocks=blocks, changed=changed)
    seconds = time.perf_counter() - clock
    written = sum(not p.exists() or p.stat().st_mtime_ns != t for p, t in files.items())
    return {"maplets": count, "seconds": seconds, "blocks_changed": len(changed), "written": written,
            "files": len(files)}


def refine_sample(sim: Path, sample: int, nodes: int, workers: int) -> dict:
    """Refine `sample` maplets of the survey at its pixel scale; maplets per hour."""
    from pwm.footprints import places, seen_samples
    from pwm.io.downlink import read_downlink
    from pwm.io.meshio import read_mesh
    from pwm.pipeline import refine_maplets
    from pwm.raytrace import RayTracer
    from pwm.tiling import tile

    views = read_downlink(sim / "downlink").views
    start = read_mesh(sim / "downlink" / "start_model.obj")
    seen = seen_samples(RayTracer(start), views, rules=DEFAULTS.rules, min_images=DEFAULTS.min_images)
    place = places(seen, nodes=nodes, spacing_gsd=DEFAULTS.spacing_gsd)[0]
    maplets = tile(start, spacing_km=place.spacing_km, nodes=nodes, overlap=DEFAULTS.overlap, where=place.points)
    chosen = [maplets[k] for k in np.linspace(0, len(maplets) - 1, min(sample, len(maplets))).astype(int)]
    clock = time.perf_counter()
    results = refine_maplets(chosen, views, start, config=DEFAULTS, workers=workers)
    wall = time.perf_counter() - clock
    return {"maplets": len(results), "spacing_m": place.spacing_km * 1e3, "wall_s": wall,
            "images_mean": float(np.mean([len(r.images) for r in results])),
            "per_hour": 3600.0 * len(results) / wall}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--maplets", type=int, nargs="+", default=[100, 400, 1300])
    parser.add_argument("--nodes", type=int, default=DEFAULTS.nodes)
    parser.add_argument("--survey", type=Path, help="a survey simulation (with --with-start-model) to refine")
    parser.add_argument("--sample", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--blocks", type=int, nargs="*", metavar="WORKERS",
                        help="fuse in blocks (pwm.blocks) instead, on each of these process counts")
    parser.add_argument("--cells", type=int, default=BLOCKS.cells, help="lattice steps a side of a block")
    parser.add_argument("--compare", action="store_true", help="with --blocks: also fuse in one process, compare")
    parser.add_argument("--downlink", type=int, default=0, metavar="K",
                        help="with --blocks: then fuse a downlink that changes K maplets in one region")
    parser.add_argument("--no-check", dest="check", action="store_false",
                        help="with --blocks: leave out the closed-surface check (about 0.55 GiB a million faces)")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # a size in a process of its own
    parser.add_argument("--workers-one", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--compare-one", type=Path, help=argparse.SUPPRESS)  # the one-process fusion, compared
    parser.add_argument("--spacing-km", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.compare_one:
        print(json.dumps(compare_one(args.compare_one, args.spacing_km)))
        return
    if args.one:
        print(json.dumps(fuse_once(args.one, args.nodes) if args.workers_one is None else
                         fuse_blocks_once(args.one, args.nodes, args.workers_one, args.cells, args.compare,
                                          args.downlink, args.check)))
        return
    if args.blocks:
        blocks_table(args)
        return

    refined = refine_sample(args.survey, args.sample, args.nodes, args.workers) if args.survey else None
    if refined:
        print(f"refinement: {refined['maplets']} maplets of {args.nodes} nodes at {refined['spacing_m']:.2f} m, "
              f"{refined['images_mean']:.1f} images each, {refined['wall_s']:.0f} s on {args.workers} processes: "
              f"{refined['per_hour']:.0f} maplets per hour")
    print("\n| maplets | spacing m | tiling s | fusion: add s | mesh s | fusion peak GiB | lattice points "
          "| sums MiB | faces | closed (check s) | refinement h (at the rate above) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for n in args.maplets:
        r = _run_one([sys.executable, __file__, "--one", str(n), "--nodes", str(args.nodes)], n)
        if r is None:
            continue
        hours = f"{r['maplets'] / refined['per_hour']:.1f}" if refined else "-"
        print(f"| {r['maplets']} | {r['spacing_m']:.2f} | {r['tiling_s']:.0f} | {r['add_s']:.0f} | {r['mesh_s']:.0f} "
              f"| {r['peak_gib']:.2f} | {r['lattice_points']:,} | {r['grid_mib']:.0f} | {r['faces']:,} "
              f"| {CLOSED[r['closed']]} ({r['check_s']:.0f}) | {hours} |")


def _run_one(command: list[str], maplets: int) -> dict | None:
    """The last figures a size's own process printed (with "failed" and why where it then
    failed), or None after printing a row that says why it printed none."""
    out = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    printed = [line for line in out.stdout.splitlines() if line.startswith("{")]
    why = (out.stderr.strip().splitlines()[-1] if out.stderr.strip() else f"exit status {out.returncode}")
    if not printed:
        print(f"| {maplets} | failed: {why} |")
        return None
    figures = json.loads(printed[-1])
    if out.returncode:
        figures["failed"] = why
    return figures


def blocks_table(args: argparse.Namespace) -> None:
    """The table of fusion in blocks, a size and process count in a process of its own each, and
    the extrapolation of the largest size to Bennu at 5 cm (50,000 maplets of 100 x 100 nodes)."""
    print("\n| maplets | spacing m | processes | blocks | lattice points | largest block's points | sums s "
          "| mesh s | peak GiB (this, largest worker) | sums MiB | faces | closed (check s, this one's peak GiB) "
          "| to one process, vertex to vertex: RMS, max mm (its faces, peak; unpaired here, there) "
          "| downlink: maplets, s, blocks changed, files written of all |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    last = None
    for n in args.maplets:
        for workers in args.blocks:
            command = [sys.executable, __file__, "--one", str(n), "--nodes", str(args.nodes), "--workers-one",
                       str(workers), "--cells", str(args.cells), "--downlink", str(args.downlink)] + (
                           ["--compare"] if args.compare else []) + ([] if args.check else ["--no-check"])
            r = _run_one(command, n)
            if r is None:
                continue
            if "compare_dir" in r:
                kept = Path(r["compare_dir"])
                one = _run_one([sys.executable, __file__, "--compare-one", str(kept), "--spacing-km",
                                repr(r["spacing_km"])], n)
                shutil.rmtree(kept)
                if one is not None:
                    r.update(one)
            last = r
            compared = "-" if r["rms_mm"] is None else (f"{r['rms_mm']:.3f}, {r['max_mm']:.1f} "
                                                        f"({r['one_faces']:,} faces, {r['one_peak_gib']:.2f} GiB; "
                                                        f"unpaired {r['blocks_unpaired']}, {r['one_unpaired']})")
            d = r["downlink"]
            check_peak = "" if r["check_peak_gib"] is None else f", {r['check_peak_gib']:.2f}"
            downlink = "-" if d is None else (f"{d['maplets']}, {d['seconds']:.0f}, {d['blocks_changed']}, "
                                              f"{d['written']} of {d['files']}")
            print(f"| {r['maplets']} | {r['spacing_m']:.2f} | {workers} | {r['blocks']} | {r['lattice_points']:,} "
                  f"| {r['largest_block_points']:,} | {r['add_s']:.0f} | {r['mesh_s']:.0f} "
                  f"| {r['peak_gib']:.2f}, {r['worker_gib']:.2f} | {r['sums_mib']:.0f} | {r['faces']:,} "
                  f"| {CLOSED[r['closed']]} ({r['check_s']:.0f}{check_peak}) | {compared} | {downlink} |")
            if "failed" in r:
                print(f"(then failed: {r['failed']})")
    if last is not None:
        # the lattice grows with the area over the spacing squared; a block's points do not
        scale = (last["spacing_m"] / BENNU_FINE_M) ** 2
        seconds = (last["add_s"] + last["mesh_s"]) * last["workers"] * scale
        print(f"\nBennu at {BENNU_FINE_M * 100:.0f} cm from {last['maplets']} maplets at {last['spacing_m']:.2f} m: "
              f"{last['lattice_points'] * scale:,.0f} lattice points in about {last['blocks'] * scale:,.0f} blocks, "
              f"{seconds / 3600:.1f} process-hours ({seconds / 3600 / 16:.1f} h on 16 processes), "
              f"sums {last['sums_mib'] * scale / 1024:.0f} GiB on disk, a block's peak as here")


if __name__ == "__main__":
    main()
