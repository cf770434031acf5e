"""A version's fusion in blocks (pwm.blocks), kept from one version to the next: each block's
files (sums, closed values, mesh piece, base reach) are stored artifacts, listed by the
version's "blocks" artifact (a JSON manifest), so that the next fusion over the same base remakes
only the blocks about the maplets that changed and the others stay the same files.

The next fusion links the parent's files into a working folder (pwm.io.fusion_state.BlockFiles,
which replaces a file it writes rather than writing into it, so the stored artifact is never
touched), fuses there, and stores what it wrote; a file it left alone keeps its record. The
parent's files are carried only when they describe the same closed level over the same base
with the same layout, made by the same release of pwm in the same form (`Layout`); otherwise the fusion starts
from an empty folder. The working folders live in the store's scratch folder; one that a killed
fusion left behind is removed by the next (`working_folder`).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from service.artifacts import artifact_path, scratch_folder, store_artifact
from service.rows import ModelVersion

log = logging.getLogger(__name__)


_WORKING = "blocks-"


@dataclass(frozen=True)
class Layout:
    """What a version's blocks were made of: its base version, the closed level fused in
    blocks and its voxel (km), the blocks' size and margin (pwm.config.FusionBlocks), the
    release of pwm that fused them (a release that fuses otherwise makes every block afresh)
    and the form of their files (pwm.blocks.FILES)."""

    base_version: int
    level: int
    voxel_km: float
    cells: int
    margin: int
    code: str
    files: int


@contextmanager
def working_folder(data_dir: Path) -> Iterator[Path]:
    """A new empty folder for a fusion's blocks and the files it publishes, in the store's
    scratch folder (the store moves a file from there in atomically), removed with what it
    still holds afterwards. Take it under the publication lock (service.versions
    .publication_lock): then no other fusion is under way, and the working folders that fusions
    killed before their end left behind are removed first."""
    scratch = scratch_folder(data_dir)
    for stale in scratch.glob(f"{_WORKING}*"):
        log.warning("fusion: removing %s, left by a fusion that did not end", stale)
        shutil.rmtree(stale, ignore_errors=True)
    with tempfile.TemporaryDirectory(prefix=_WORKING, dir=scratch) as work:
        yield Path(work)


def carry_blocks(data_dir: Path, parent: ModelVersion, *, layout: Layout, into: Path) -> dict[str, dict[str, Any]]:
    """Link the parent's block files into the folder `into` where they were made with this
    layout; their records, by path relative to `into` (none carried: empty)."""
    if "blocks" not in parent.artifacts:
        return {}
    manifest = json.loads(artifact_path(data_dir, parent.artifacts["blocks"], verify=True).read_text())
    if manifest["layout"] != asdict(layout):
        return {}
    for relative, record in manifest["files"].items():
        target = (into / relative).resolve()
        if not target.is_relative_to(into.resolve()):
            raise ValueError(f"version {parent.version}'s blocks name {relative!r}, outside their folder")
        target.parent.mkdir(parents=True, exist_ok=True)
        source = artifact_path(data_dir, record)
        try:
            os.link(source, target)
        except OSError:  # a filesystem without hard links
            shutil.copyfile(source, target)
    return dict(manifest["files"])


def keep_blocks(data_dir: Path, folder: Path, carried: dict[str, dict[str, Any]], *,
                layout: Layout, manifest: Path) -> tuple[Path | None, dict[str, int]]:
    """Store the block files in `folder` (a file still the carried one keeps its record) and
    write their manifest to the file `manifest` (in the working folder), to be stored as the
    version's "blocks" artifact; the manifest (None where the folder holds no block) and how
    many files were kept as they were and written."""
    files: dict[str, dict[str, Any]] = {}
    written = 0
    for path in sorted(folder.rglob("*.npz")):
        relative = path.relative_to(folder).as_posix()
        old = carried.get(relative)
        if old is not None and os.path.samefile(path, artifact_path(data_dir, old)):
            files[relative] = old
        else:
            files[relative] = store_artifact(data_dir, path)
            written += 1
    if not files:
        return None, {"files": 0, "written": 0}
    manifest.write_text(json.dumps({"layout": asdict(layout), "files": files}, sort_keys=True))
    return manifest, {"files": len(files), "written": written}
