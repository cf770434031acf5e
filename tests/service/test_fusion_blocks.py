"""A version fused in blocks keeps its blocks' files (service.fusion_blocks): the next fusion,
after a downlink that changed maplets at one end of the body, writes only the blocks about
them; every other block of the new version is the parent's file, byte for byte, and the model
is the one a fusion from the start makes."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from sqlalchemy import select

import pwm
from pwm.blocks import _UPPER, FILES, around
from pwm.config import FusionBlocks
from pwm.evaluate.closure import closure
from pwm.io.fusion_state import write_maplet
from pwm.io.meshio import write_ply
from pwm.maplets import MapletGrid
from pwm.voxels import pack
from service import publish
from service.artifacts import artifact_path, scratch_path, store_artifact
from service.db import session_scope
from service.fusion_blocks import Layout, carry_blocks, keep_blocks
from service.publish import fuse_and_publish
from service.rows import Maplet, MapletRevision
from service.versions import get_version, import_model, version_mesh
from tests.conftest import LONG_BLOCK

BLOCKS = FusionBlocks(cells=LONG_BLOCK, margin=4)


def _revise(sessions, data_dir, maplet: MapletGrid) -> None:
    """A new current revision of the maplet (its row made on first sight)."""
    path = scratch_path(data_dir, ".npz")
    write_maplet(path, maplet)
    record = store_artifact(data_dir, path)
    with session_scope(sessions) as session:
        row = session.scalars(select(Maplet).where(Maplet.name == maplet.name)).one_or_none()
        if row is None:
            row = Maplet.of(maplet)
            session.add(row)
        revision = MapletRevision(maplet=row, revision=len(row.revisions) + 1, input_hash=record["sha256"],
                                  mode="pwm", artifact_path=record["path"], sha256=record["sha256"])
        session.add(revision)
        session.flush()
        row.current_revision = revision


def _files(sessions, data_dir, version: int) -> dict[str, dict]:
    with sessions() as session:
        record = get_version(session, version).artifacts["blocks"]
    return json.loads(artifact_path(data_dir, record, verify=True).read_text())["files"]


def _block(relative: str) -> tuple[str, int]:
    kind, name = relative.split("/")
    return kind, int(pack(np.array([[int(v) for v in name.removesuffix(".npz").split("_")]]))[0])


def test_a_downlink_at_one_end_refuses_only_the_blocks_it_touches(long_body, sqlite_url, open_catalog_at,
                                                                    tmp_path, monkeypatch):
    base, maplets = long_body
    sessions, data = open_catalog_at(sqlite_url), tmp_path / "data"
    write_ply(tmp_path / "base.ply", base)
    with session_scope(sessions) as session:
        import_model(session, data_dir=data, path=tmp_path / "base.ply")
    for maplet in maplets:
        _revise(sessions, data, maplet)
    assert fuse_and_publish(sessions, data_dir=data, blocks=BLOCKS) == 2
    before = _files(sessions, data, 2)
    content = {relative: artifact_path(data, record).read_bytes() for relative, record in before.items()}
    assert {_block(r)[0] for r in before} == {"sums", "closed", "pieces", "seams", "body", "reach"}
    with sessions() as session:
        parent = get_version(session, 2)
        layout = Layout(**json.loads(artifact_path(data, parent.artifacts["blocks"]).read_text())["layout"])
        assert layout.files == FILES
        assert len(carry_blocks(data, parent, layout=layout, into=tmp_path / "carried")) == len(before)
        # blocks kept in another form are not carried
        assert carry_blocks(data, parent, layout=dataclasses.replace(layout, files=FILES - 1),
                            into=tmp_path / "other") == {}

    # the next downlink moves the maplets at the body's +x end up by 2 m
    end = [m for m in maplets if m.frame.origin[0] > 0.13]
    for old in end:
        _revise(sessions, data, MapletGrid(name=old.name, frame=old.frame, spacing_km=old.spacing_km,
                                           heights=old.heights + 0.002, albedo=old.albedo))
    assert fuse_and_publish(sessions, data_dir=data, blocks=BLOCKS) == 3
    after = _files(sessions, data, 3)
    with sessions() as session:
        statistics = get_version(session, 3).statistics["blocks"]
        incremental = version_mesh(data, get_version(session, 3))
    changed = {_block(r)[1] for r, record in after.items() if _block(r)[0] == "sums" and before.get(r) != record}
    closed = around(changed)
    meshed = around(closed, steps=-_UPPER)
    remade = {"sums": changed, "closed": closed, "reach": closed, "pieces": meshed, "seams": meshed, "body": meshed}
    untouched = [r for r in before if _block(r)[1] not in remade[_block(r)[0]]]
    # of each kind, some blocks' files are carried as they were
    assert changed and {_block(r)[0] for r in untouched} == set(remade)
    for relative in untouched:
        # the same stored file, which nothing wrote into
        assert after[relative] == before[relative]
        assert artifact_path(data, after[relative], verify=True).read_bytes() == content[relative]
    assert statistics["written"] <= len(after) - len(untouched)

    # the model is the one that fusing every current revision from the start makes
    with session_scope(sessions) as session:
        import_model(session, data_dir=data, path=tmp_path / "base.ply")
    assert fuse_and_publish(sessions, data_dir=data, blocks=BLOCKS) == 5
    with sessions() as session:
        fresh = version_mesh(data, get_version(session, 5))
        assert not get_version(session, 5).statistics["incremental"]
    assert closure(incremental).closed
    assert incremental.faces.shape == fresh.faces.shape
    # the sums of the incremental version took the old revisions out again: equal to 1e-12
    assert np.abs(incremental.vertices - fresh.vertices).max() < 1e-9

    # a fusion killed before its end left its working folder, with the files it was about to
    # publish; a new release of pwm fuses the next version, and fails as it publishes: the
    # folder left is removed, nothing of the parent's blocks was carried, and the failed fusion
    # leaves none of its files behind either (nor does one that ends)
    assert not list((data / "artifacts" / "tmp").iterdir())
    stale = data / "artifacts" / "tmp" / "blocks-killed"
    (stale / "L0").mkdir(parents=True)
    (stale / "grid.npz").write_bytes(b"half written")
    monkeypatch.setattr(pwm, "__version__", "0-another-release")
    old = end[0]
    _revise(sessions, data, MapletGrid(name=old.name, frame=old.frame, spacing_km=old.spacing_km,
                                       heights=old.heights + 0.003, albedo=old.albedo))
    kept = []

    def keeping(*args, **kwargs):
        manifest, counts = keep_blocks(*args, **kwargs)
        kept.append(counts)
        return manifest, counts

    def failing(*args, **kwargs):
        assert not stale.exists()
        raise RuntimeError("the disk filled")

    monkeypatch.setattr(publish, "keep_blocks", keeping)
    monkeypatch.setattr(publish, "publish_version", failing)
    with pytest.raises(RuntimeError, match="disk filled"):
        fuse_and_publish(sessions, data_dir=data, blocks=BLOCKS)
    assert kept and kept[0]["written"] == kept[0]["files"] > 0
    assert not list((data / "artifacts" / "tmp").iterdir())
