"""Read and write meshes: Wavefront OBJ and binary PLY (with per-vertex albedo), in km.

PLY carries the albedo as a named vertex property (`albedo`, float, after x y z), and the 1-sigma
height as `height_sigma` (float, km, NaN where nothing says; pwm.uncertainty), which OBJ does
not carry. OBJ has no albedo field: it goes as a grey vertex colour stretched over the mesh's albedo range
(ALBEDO_COLOUR_FLOOR at the darkest, 1 at the brightest) so that viewers show the body's
pattern instead of a near-black body (albedos are a few per cent), and a comment header
(`# albedo_colour_scale lo hi floor`) gives the range to read the albedo back. Both headers
carry free comments (frame, units, version).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pwm.mesh import Mesh

# The first bytes of a DSK file: a DAS file's ID word, its file type DSK.
DSK_ID_WORD = b"DAS/DSK"
# OBJ vertex colour of the darkest albedo: dark enough to show the pattern, light enough to see.
ALBEDO_COLOUR_FLOOR = 0.25
# First bytes of the files pwm exports that hold no mesh, and what they are.
_NOT_MESHES = ((b"LASF", "a LAS point cloud (points only)"),
               (b"II*\0", "a TIFF raster (a site's terrain)"), (b"MM\0*", "a TIFF raster (a site's terrain)"),
               (b"Object = IsisCube", "an ISIS cube (a site's terrain)"),
               (b"PK\x03\x04", "a zip archive (a site product)"))
_ALBEDO_SCALE = re.compile(r"#\s*albedo_colour_scale\s+(\S+)\s+(\S+)\s+(\S+)")


def read_obj(path: str | Path) -> Mesh:
    """Read a triangle OBJ (v and f records; polygons are fanned). An albedo is read from
    'v x y z a' or 'v x y z r g b' records (first colour channel), mapped back through the
    `albedo_colour_scale` comment when the file has one (write_obj)."""
    verts: list[list[float]] = []
    faces: list[list[int]] = []
    albedo: list[float] = []
    scale: tuple[float, float, float] | None = None
    with open(path, encoding="ascii", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split()
            if not parts:
                continue
            if parts[0].startswith("#"):
                if match := _ALBEDO_SCALE.match(line):
                    lo, hi, floor = (float(v) for v in match.groups())
                    if not (np.isfinite([lo, hi, floor]).all() and hi >= lo and 0 <= floor < 1):
                        raise ValueError(f"{path}:{lineno}: bad albedo_colour_scale {line.strip()!r}")
                    scale = (lo, hi, floor)
            elif parts[0] == "v":
                vals = [float(x) for x in parts[1:]]
                if len(vals) < 3:
                    raise ValueError(f"{path}:{lineno}: vertex needs 3 coordinates")
                verts.append(vals[:3])
                if len(vals) >= 4:
                    albedo.append(vals[3])
            elif parts[0] == "f":
                idx = [int(p.split("/")[0]) for p in parts[1:]]
                idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                for k in range(1, len(idx) - 1):
                    faces.append([idx[0], idx[k], idx[k + 1]])
    if not verts or not faces:
        raise ValueError(f"{path}: no vertices or faces")
    a = np.array(albedo) if len(albedo) == len(verts) else None
    if a is not None and scale is not None:
        lo, hi, floor = scale
        a = lo + (a - floor) / (1.0 - floor) * (hi - lo)
    return Mesh(np.array(verts), np.array(faces), a)


def write_obj(path: str | Path, mesh: Mesh, *, comments: Sequence[str] = ()) -> None:
    """Write OBJ, km, with `comments` (one line each) in its header; the albedo, if any, goes as
    a grey vertex colour stretched over its range (the module's docstring says how)."""
    header = ["pwm mesh, body-fixed frame, km", *_comment_lines(comments)]
    with open(path, "w", encoding="ascii") as fh:
        fh.writelines(f"# {line}\n" for line in header)
        if mesh.albedo is not None:
            lo, hi = float(mesh.albedo.min()), float(mesh.albedo.max())
            if not np.isfinite([lo, hi]).all():
                raise ValueError("the albedo has values that are not finite")
            floor = ALBEDO_COLOUR_FLOOR
            fh.write(f"# albedo_colour_scale {lo!r} {hi!r} {floor!r} (lo hi floor; grey vertex "
                     f"colour = floor + (1 - floor) (albedo - lo) / (hi - lo))\n")
            grey = (floor + (1.0 - floor) * (mesh.albedo - lo) / (hi - lo) if hi > lo
                    else np.full(len(mesh.albedo), floor))
            data = np.column_stack([mesh.vertices, grey, grey, grey])
            np.savetxt(fh, data, fmt="v %.9f %.9f %.9f %.7f %.7f %.7f")
        else:
            np.savetxt(fh, mesh.vertices, fmt="v %.9f %.9f %.9f")
        np.savetxt(fh, mesh.faces + 1, fmt="f %d %d %d")


def _comment_lines(comments: Sequence[str]) -> list[str]:
    lines = [str(c) for c in comments]
    if any("\n" in line or "\r" in line or not line.isascii() for line in lines):
        raise ValueError("header comments must be single ASCII lines")
    return lines


def write_ply(path: str | Path, mesh: Mesh, *, comments: Sequence[str] = ()) -> None:
    """Write binary little-endian PLY: float64 x y z (km), float32 albedo and height_sigma (km)
    if present, and `comments` (one line each) in its header."""
    n, m = len(mesh.vertices), len(mesh.faces)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    extra = [(name, values) for name, values in (("albedo", mesh.albedo), ("height_sigma", mesh.sigma))
             if values is not None]
    fields += [(name, "<f4") for name, _ in extra]
    vert = np.empty(n, dtype=fields)
    vert["x"], vert["y"], vert["z"] = mesh.vertices.T
    for name, values in extra:
        vert[name] = values
    face = np.empty(m, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"] = 3
    face["i"] = mesh.faces
    header = ["ply", "format binary_little_endian 1.0", "comment pwm mesh, body-fixed frame, km",
              *(f"comment {line}" for line in _comment_lines(comments)), f"element vertex {n}",
              "property double x", "property double y", "property double z"]
    header += [f"property float {name}" for name, _ in extra]
    header += [f"element face {m}", "property list uchar int vertex_indices", "end_header"]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        vert.tofile(fh)
        face.tofile(fh)


_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4",
              "float": "f4", "double": "f8", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2",
              "int32": "i4", "uint32": "u4", "float32": "f4", "float64": "f8"}


def read_ply(path: str | Path) -> Mesh:
    """Read a binary little-endian triangle PLY as written by `write_ply` (albedo optional)."""
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file")
        elements: list[tuple[str, int, list[tuple[str, str]]]] = []
        fmt = ""
        while True:
            line = fh.readline()
            if not line:
                raise ValueError(f"{path}: header not terminated")
            parts = line.decode("ascii").split()
            if not parts:
                continue
            if parts[0] == "format":
                fmt = parts[1]
            elif parts[0] == "element":
                elements.append((parts[1], int(parts[2]), []))
            elif parts[0] == "property":
                elements[-1][2].append((parts[-1], " ".join(parts[1:-1])))
            elif parts[0] == "end_header":
                break
        if fmt != "binary_little_endian":
            raise ValueError(f"{path}: only binary_little_endian PLY is supported, got {fmt!r}")
        verts = albedo = sigma = faces = None
        for name, count, props in elements:
            if name == "vertex":
                dt = np.dtype([(p, "<" + _PLY_TYPES[t]) for p, t in props])
                data = np.frombuffer(fh.read(dt.itemsize * count), dtype=dt, count=count)
                verts = np.column_stack([data["x"], data["y"], data["z"]]).astype(np.float64)
                if "albedo" in (data.dtype.names or ()):
                    albedo = data["albedo"].astype(np.float64)
                if "height_sigma" in (data.dtype.names or ()):
                    sigma = data["height_sigma"].astype(np.float64)
            elif name == "face":
                (pname, ptype), = props
                _, ctype, itype = ptype.split()
                dt = np.dtype([("n", "<" + _PLY_TYPES[ctype]), ("i", "<" + _PLY_TYPES[itype], (3,))])
                data = np.frombuffer(fh.read(dt.itemsize * count), dtype=dt, count=count)
                if np.any(data["n"] != 3):
                    raise ValueError(f"{path}: only triangle faces are supported")
                faces = data["i"].astype(np.int64)
            else:
                raise ValueError(f"{path}: unsupported element {name!r}")
    if verts is None or faces is None:
        raise ValueError(f"{path}: missing vertex or face element")
    return Mesh(verts, faces, albedo, sigma)


def read_shape_model(path: str | Path) -> Mesh:
    """A shape model in any format pwm exports (service.exports), told by its content whatever
    the file is called: a SPICE DSK type 2 (a DAS file, `DAS/DSK` first), binary PLY (`ply`),
    Gaskell's ICQ (q alone on the first line), else OBJ. Raises ValueError for a file that is
    none of them, or a damaged one, and says why for the exports that hold no mesh (a LAS
    point cloud, a site's terrain)."""
    with open(path, "rb") as fh:
        first = fh.readline(64).strip()
    for signature, what in _NOT_MESHES:
        if first.startswith(signature):
            raise ValueError(f"{path} is {what}, not a shape model: it has no faces. Give a mesh: "
                             f"OBJ, PLY, SPICE DSK or ICQ")
    if first.startswith(DSK_ID_WORD):
        return _read_dsk(path)
    if first == b"ply":
        return read_ply(path)
    if first.isdigit():
        from pwm.io.icq import icq_to_mesh, read_icq

        return icq_to_mesh(read_icq(path))
    return read_obj(path)


def _read_dsk(path: str | Path) -> Mesh:
    from spiceypy.utils.exceptions import SpiceyError

    from pwm.io.dsk import read_dsk

    try:
        return read_dsk(path)
    except SpiceyError as exc:  # a truncated or damaged file: SPICE says why in its short message
        raise ValueError(f"{path}: not a readable DSK file: {exc.short} {exc.long}".rstrip()) from None


def read_mesh(path: str | Path) -> Mesh:
    """Read a mesh by file extension (.obj or .ply)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".obj":
        return read_obj(path)
    if suffix == ".ply":
        return read_ply(path)
    raise ValueError(f"{path}: unsupported mesh format {suffix!r} (use .obj or .ply)")
