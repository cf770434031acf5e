"""A later downlink made from a simulated one: detector windows of its exposures, issued as new
products (LIDs of their own) beside the source's kernels, as a revisit of part of the site with
narrow subframes would deliver them.

The window is at the same place in every product's array, so with the site-centred plans of
pwm.simulate (every image aimed at the site centre, north up) it looks at about the same part of
the site in each.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from pwm.io.pds4 import file_sha256, read_image_product, write_image_product

MANIFEST_NAME = "manifest.json"


def window_downlink(source: Path, out: Path, *, size_px: int, first_px: tuple[int, int],
                    count: int, tag: str) -> list[Path]:
    """Write OUT as a downlink of `count` products, each the window of size_px x size_px
    starting at first_px (line, sample; zero-based, within the source product's array) of one
    source image, taken in turn; with the source's kernels and a manifest.json written last.
    Product k's LID and file name end in _{tag}{k:03d}. Returns the labels written."""
    labels = sorted((source / "images").glob("*.xml"))
    if not labels:
        raise FileNotFoundError(f"{source / 'images'} holds no PDS4 labels")
    line, sample = first_px
    (out / "images").mkdir(parents=True)
    shutil.copytree(source / "kernels", out / "kernels")
    written = []
    for k in range(count):
        source_label = labels[k % len(labels)]
        product = read_image_product(source_label)
        window = product.data[line:line + size_px, sample:sample + size_px]
        if window.shape != (size_px, size_px):
            raise ValueError(f"the window {size_px} px at {first_px} leaves the "
                             f"{product.data.shape} array")
        if product.fits_header is None:
            raise ValueError(f"{source_label.name} has no FITS header to take BSCALE from")
        scale = product.fits_header["BSCALE"]
        mission, host, instrument, target = (product.mission, product.host_name, product.instrument_name,
                                             product.target_name)
        if mission is None or host is None or instrument is None or target is None:
            raise ValueError(f"{source_label.name} does not name its mission, host, instrument and target")
        name = f"{source_label.stem}_{tag}{k:03d}"
        label, _ = write_image_product(
            directory=out / "images", basename=name,
            dn=np.round(np.nan_to_num(window) / scale).astype(np.int16), scaling_factor=scale,
            value_offset=0.0, lid=f"{product.lid}_{tag}{k:03d}", start_utc=product.start_utc,
            stop_utc=product.stop_utc, mission=mission, host_name=host, instrument_name=instrument,
            target_name=target, title=name, exposure_s=product.exposure_s,
            subframe=(product.first_line + line, product.first_sample + sample))
        written.append(label)
    files = sorted(p for p in out.rglob("*") if p.is_file())
    (out / MANIFEST_NAME).write_text(json.dumps({"source": str(source), "files": [
        {"path": p.relative_to(out).as_posix(), "bytes": p.stat().st_size,
         "sha256": file_sha256(p)} for p in files]}, indent=1))
    return written
