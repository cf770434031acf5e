"""Where the service's files live in the data directory, and how the files made from them are
kept: the one artifact store of versions, revisions, exports, diffs and the console.

Stored artifacts (the files of versions and revisions) live under
`<data_dir>/artifacts/<sha256[:2]>/<sha256><suffix>`: a file's name is its checksum, so writing
it again (a retried job) is harmless and a file once published never changes. A stored file's
record, kept in the catalog, is `{"path": <relative to data_dir>, "sha256": ..., "bytes": ...}`.

Derived files (exports, the console's documents, diff maps) are made on first request and kept
under `<data_dir>/exports/`: the file `<key><suffix>` and its record `<key>.json` (the same
record), where the key is a digest of everything the file depends on, so that a request already
served needs neither the catalog's lock nor SPICE. What is kept is bounded: once the kept files
pass the configured bytes, the least recently served ones are removed (they are made again when
asked for). spiceypy's kernel pool and fast-simplification keep process-global state: making is
serialised by one lock, and only MAX_QUEUED requests of a process may wait for it or hold it;
the others are refused at once (CacheBusy), so that making files never takes all the API's
worker threads.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from pwm.io.mesh_tiles import TileIndex, read_index, read_tile
from pwm.io.meshio import read_mesh
from pwm.io.pds4 import file_sha256
from pwm.mesh import Mesh
from pwm.mesh_tiles import MeshTile, face_labels, join

ARTIFACTS_DIRNAME = "artifacts"
# The folder of derived files: named for the exports, its first tenants, which data
# directories already hold.
CACHE_DIRNAME = "exports"
# Requests of one process that may wait for the making lock or hold it; one more is refused.
MAX_QUEUED = 4
# The longest a queued request waits for the making lock (s) before it is refused.
MAKE_WAIT_S = 60.0
# What a refused request is told to wait before it asks again (s).
RETRY_AFTER_S = 5
_MAKING = threading.Lock()
_QUEUE = threading.BoundedSemaphore(MAX_QUEUED)


class ArtifactError(Exception):
    """A stored or kept file is missing, outside the data directory, or not what was stored."""


class CacheBusy(Exception):
    """Too many derived files are being made: ask again after `retry_after_s` (s)."""

    def __init__(self, retry_after_s: int = RETRY_AFTER_S) -> None:
        super().__init__(f"too many files are being made; try again in {retry_after_s} s")
        self.retry_after_s = retry_after_s


def store_artifact(data_dir: Path, path: Path) -> dict[str, Any]:
    """Move the file `path` into the data directory's content-addressed store; its record."""
    digest = file_sha256(path)
    relative = Path(ARTIFACTS_DIRNAME) / digest[:2] / f"{digest}{path.suffix}"
    target = data_dir / relative
    target.parent.mkdir(parents=True, exist_ok=True)
    size = path.stat().st_size
    if target.is_file() and target.stat().st_size == size:
        path.unlink()
    else:
        # Same filesystem (a temp file inside data_dir), so the rename is atomic.
        os.replace(path, target)
    return {"path": relative.as_posix(), "sha256": digest, "bytes": size}


def artifact_path(data_dir: Path, artifact: dict[str, Any], *, verify: bool = False) -> Path:
    """The file of an artifact record, checked to lie inside `data_dir` (and, with `verify`,
    to have its recorded checksum)."""
    root = data_dir.resolve()
    path = (root / artifact["path"]).resolve()
    if not path.is_relative_to(root):
        raise ArtifactError(f"artifact path {artifact['path']!r} leaves the data directory")
    if not path.is_file():
        raise ArtifactError(f"artifact {artifact['path']} is missing")
    if verify and file_sha256(path) != artifact["sha256"]:
        raise ArtifactError(f"artifact {artifact['path']} does not match its checksum")
    return path


def artifact_mesh(data_dir: Path, artifact: dict[str, Any]) -> Mesh:
    """The mesh of a mesh artifact record, checksum verified: a PLY or OBJ, or the index of a
    mesh stored in tiles (pwm.io.mesh_tiles; the tiles joined)."""
    if holds_tiles(artifact):
        return tiled_mesh(data_dir, artifact)[1]
    return read_mesh(artifact_path(data_dir, artifact, verify=True))


def holds_tiles(artifact: dict[str, Any]) -> bool:
    """Whether a mesh artifact record is the index of a mesh stored in tiles (a JSON file)."""
    return Path(artifact["path"]).suffix == ".json"


def tiled_mesh(data_dir: Path, artifact: dict[str, Any]) -> tuple[TileIndex, Mesh, np.ndarray]:
    """A mesh stored in tiles, checksum verified: its index, the tiles joined, and each face's
    tile (its number in the index)."""
    index = tile_index(data_dir, artifact)
    tiles = [artifact_tile(data_dir, entry.file) for entry in index.tiles]
    return index, join(tiles, vertices=index.vertices, faces=index.faces), face_labels(tiles, faces=index.faces)


def tile_index(data_dir: Path, artifact: dict[str, Any]) -> TileIndex:
    """The index of a mesh stored in tiles, checksum verified. ArtifactError where the file is
    not one."""
    path = artifact_path(data_dir, artifact, verify=True)
    try:
        return read_index(path)
    except ValueError as exc:
        raise ArtifactError(str(exc)) from None


def artifact_tile(data_dir: Path, artifact: dict[str, Any]) -> MeshTile:
    """One tile of a mesh stored in tiles, checksum verified."""
    return read_tile(artifact_path(data_dir, artifact, verify=True))


def scratch_folder(data_dir: Path) -> Path:
    """The data directory's scratch folder, on the store's filesystem (so that `store_artifact`
    can move a file from it in atomically)."""
    directory = data_dir / ARTIFACTS_DIRNAME / "tmp"
    directory.mkdir(parents=True, exist_ok=True)
    return directory


def scratch_path(data_dir: Path, suffix: str) -> Path:
    """A new empty file in the data directory's scratch folder (`scratch_folder`)."""
    handle, name = tempfile.mkstemp(suffix=suffix, dir=scratch_folder(data_dir))
    os.close(handle)
    return Path(name)


@contextmanager
def scratch_file(data_dir: Path, suffix: str) -> Iterator[Path]:
    """A scratch file (`scratch_path`) for the block to write and move into the store; whatever
    is left of it afterwards (a write that failed, a disk that filled) is removed."""
    path = scratch_path(data_dir, suffix)
    try:
        yield path
    finally:
        path.unlink(missing_ok=True)


def digest(value: Any) -> str:
    """A hex SHA-256 of `value` as canonical JSON: a cache key of parameters."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()


def cached_artifact(data_dir: Path, key: str, *, suffix: str, make: Callable[[Path], dict[str, Any] | None],
                    cache_bytes: int | None) -> dict[str, Any]:
    """The record ({"path", "sha256", "bytes"}) of the file kept for `key` (a hex digest), made
    by `make(path)` (which writes the file `path`) the first time, or again when it went missing;
    what `make` returns, if anything, is kept in the record too (what was learnt making the file).

    Making holds the process's making lock (so `make` may use SPICE and fast-simplification);
    of requests that must make their file, MAX_QUEUED wait for it at most MAKE_WAIT_S, and the
    others are refused with CacheBusy. Once made, the least recently served files are removed
    until the kept ones total at most `cache_bytes` (the new one always stays); None (a process
    without the service's settings, such as a worker after a publication) leaves that to the
    next request that makes a file.
    """
    record = _kept(data_dir, key)
    if record is not None:
        return record
    if not _QUEUE.acquire(blocking=False):
        raise CacheBusy()
    try:
        if not _MAKING.acquire(timeout=MAKE_WAIT_S):
            raise CacheBusy()
        try:
            # made meanwhile by the request this one waited for
            record = _kept(data_dir, key)
            if record is None:
                record = _make_and_keep(data_dir, key, suffix=suffix, make=make)
                if cache_bytes is not None:
                    _evict(data_dir, cache_bytes=cache_bytes, keep=key)
        finally:
            _MAKING.release()
    finally:
        _QUEUE.release()
    return record


def _kept(data_dir: Path, key: str) -> dict[str, Any] | None:
    """The record kept for `key` if its file is there, marked as just served."""
    index = data_dir / CACHE_DIRNAME / f"{key}.json"
    try:
        record = json.loads(index.read_text())
        artifact_path(data_dir, record)
        os.utime(index)  # the eviction order: least recently served first
    except (OSError, ValueError, KeyError, TypeError, ArtifactError):
        return None  # missing, being replaced, or damaged: made again
    return record


def _make_and_keep(data_dir: Path, key: str, *, suffix: str,
                   make: Callable[[Path], dict[str, Any] | None]) -> dict[str, Any]:
    directory = data_dir / CACHE_DIRNAME
    with _workspace(data_dir) as scratch:
        path = scratch / f"made{suffix}"
        learnt = make(path) or {}
        relative = Path(CACHE_DIRNAME) / f"{key}{suffix}"
        record = {**learnt, "path": relative.as_posix(), "sha256": file_sha256(path),
                  "bytes": path.stat().st_size}
        os.replace(path, data_dir / relative)  # same filesystem: atomic
        staged = scratch / "index.json"
        staged.write_text(json.dumps(record))
        os.replace(staged, directory / f"{key}.json")  # a concurrent reader sees old or new
    return record


def _evict(data_dir: Path, *, cache_bytes: int, keep: str) -> None:
    """Remove the least recently served kept files, other than `keep`'s, until the kept files
    total at most cache_bytes. Only files inside the cache folder are removed."""
    directory = data_dir / CACHE_DIRNAME
    entries = []
    for index in directory.glob("*.json"):
        try:
            record = json.loads(index.read_text())
            entries.append((index.stat().st_mtime, index, record, int(record["bytes"])))
        except (OSError, ValueError, KeyError, TypeError):
            continue  # removed meanwhile by another process, or not a record of ours
    total = sum(size for *_, size in entries)
    for _, index, record, size in sorted(entries, key=lambda entry: entry[0]):
        if total <= cache_bytes:
            break
        if index.stem == keep:
            continue
        index.unlink(missing_ok=True)
        file = data_dir / str(record.get("path", ""))
        if file.parent.resolve() == directory.resolve():
            file.unlink(missing_ok=True)
        total -= size


@contextmanager
def _workspace(data_dir: Path) -> Iterator[Path]:
    """A scratch directory inside the cache folder (one filesystem: made files are renamed, not
    copied), removed afterwards."""
    root = data_dir / CACHE_DIRNAME / "tmp"
    root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=root) as scratch:
        yield Path(scratch)
