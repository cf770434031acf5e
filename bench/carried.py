"""What a version kept of an earlier one: its faces found, exactly, in the earlier version's mesh
(faces compared by their corners' coordinates), and where the others lie. Prints a table.

    PWM_DATA_DIR=DIR .venv/bin/python bench/carried.py NEW OLD [OLD ...]

The catalog and data directory are the service's settings (PWM_DATA_DIR, PWM_DATABASE_URL), as
for `pwm run`. Issue 16.3: after a site downlink, the faces outside that site should be the
earlier version's.
"""

from __future__ import annotations

import argparse

import numpy as np

from pwm.frames import unit_to_latlon
from pwm.mesh import face_keys
from service.catalog import open_catalog
from service.settings import get_settings
from service.versions import get_version, version_mesh


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("new", help="version number or tag")
    parser.add_argument("old", nargs="+", help="earlier versions")
    args = parser.parse_args()
    settings = get_settings()
    with open_catalog(settings)() as session:
        meshes = {ref: version_mesh(settings.data_dir, get_version(session, ref)) for ref in [args.new, *args.old]}
    new = meshes[args.new]
    keys = face_keys(new)
    print("| new | old | new faces | old faces | old faces kept | new faces not in old: lat (deg) | lon (deg) |")
    print("|---|---|---|---|---|---|---|")
    for ref in args.old:
        old_keys = face_keys(meshes[ref])
        changed = ~np.isin(keys, old_keys)
        centres = new.vertices[new.faces[changed]].mean(axis=1)
        lat, lon = unit_to_latlon(centres / np.linalg.norm(centres, axis=1, keepdims=True))
        where = (f"{lat.min():.1f} to {lat.max():.1f} | {lon.min():.1f} to {lon.max():.1f}" if changed.any()
                 else "- | -")
        kept = np.isin(old_keys, keys).sum()
        print(f"| {args.new} | {ref} | {len(keys):,} | {len(old_keys):,} | {kept:,} | {where} |")


if __name__ == "__main__":
    main()
