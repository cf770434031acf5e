"""Model versions: content-addressed artifacts, numbering under concurrency, lookups, immutability."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import trimesh
from sqlalchemy.orm import Session, sessionmaker

from pwm.io.dsk import write_dsk
from pwm.io.meshio import write_obj
from pwm.mesh import Mesh
from service.artifacts import ArtifactError, artifact_path
from service.db import session_scope
from service.rows import ModelKind
from service.versions import (
    get_version,
    import_model,
    latest_version,
    mesh_statistics,
    publish_version,
    version_mesh,
)


def _sphere(radius_km: float = 0.25, subdivisions: int = 3) -> Mesh:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius_km)
    vertices = np.asarray(sphere.vertices)
    return Mesh(vertices, np.asarray(sphere.faces), albedo=0.04 + 0.01 * vertices[:, 2] / radius_km)


def test_statistics_of_a_sphere() -> None:
    stats = mesh_statistics(_sphere(0.25, subdivisions=4))
    assert stats["volume_km3"] == pytest.approx(4 / 3 * np.pi * 0.25**3, rel=5e-3)
    assert stats["area_km2"] == pytest.approx(4 * np.pi * 0.25**2, rel=5e-3)
    assert stats["mean_radius_km"] == pytest.approx(0.25, rel=1e-9)


def test_publish_and_read_back(catalog: sessionmaker[Session], tmp_path: Path) -> None:
    mesh = _sphere()
    with session_scope(catalog) as session:
        first = publish_version(session, data_dir=tmp_path, mesh=mesh, kind=ModelKind.START,
                                statistics={"note": "first"})
        second = publish_version(session, data_dir=tmp_path, mesh=mesh, kind=ModelKind.REFINED,
                                 parent=first)
    assert (first.version, second.version) == (1, 2)
    # The same content is stored once.
    assert first.artifacts == second.artifacts
    assert len(list((tmp_path / "artifacts").rglob("*.ply"))) == 1
    with catalog() as session:
        assert get_version(session, "latest").version == 2
        assert get_version(session, "1").statistics["note"] == "first"
        assert get_version(session, 2).parent.version == 1
        with pytest.raises(LookupError):
            get_version(session, "released")
        back = version_mesh(tmp_path, get_version(session, 1))
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-9)
    np.testing.assert_allclose(back.albedo, mesh.albedo, atol=1e-6)


def test_release_tag_lookup_and_immutability(catalog: sessionmaker[Session], tmp_path: Path) -> None:
    with session_scope(catalog) as session:
        version = publish_version(session, data_dir=tmp_path, mesh=_sphere(), kind=ModelKind.START)
        publish_version(session, data_dir=tmp_path, mesh=_sphere(0.3), kind=ModelKind.START)
        version.released, version.release_tag = True, "nav-1"
    with catalog() as session:
        assert get_version(session, "nav-1").version == 1
        assert latest_version(session, released_only=True).version == 1
        assert latest_version(session).version == 2
    with pytest.raises(ValueError, match="immutable"), session_scope(catalog) as session:
        get_version(session, 1).statistics = {"faces": 0}


def test_tampered_or_escaping_artifacts_are_refused(catalog: sessionmaker[Session],
                                                    tmp_path: Path) -> None:
    with session_scope(catalog) as session:
        version = publish_version(session, data_dir=tmp_path, mesh=_sphere(), kind=ModelKind.START)
    path = artifact_path(tmp_path, version.artifacts["ply"], verify=True)
    path.write_bytes(path.read_bytes()[:-8] + b"\0" * 8)
    with pytest.raises(ArtifactError, match="checksum"):
        version_mesh(tmp_path, version)
    with pytest.raises(ArtifactError, match="leaves the data directory"):
        artifact_path(tmp_path, {"path": "../../etc/passwd", "sha256": ""})


def test_import_obj_and_dsk(catalog: sessionmaker[Session], tmp_path: Path) -> None:
    mesh = _sphere()
    write_obj(tmp_path / "shape.obj", Mesh(mesh.vertices, mesh.faces))
    write_dsk(tmp_path / "shape.bds", mesh, body=2101955, frame="IAU_BENNU", comment="test")
    data = tmp_path / "data"
    with session_scope(catalog) as session:
        from_obj = import_model(session, data_dir=data, path=tmp_path / "shape.obj")
        from_dsk = import_model(session, data_dir=data, path=tmp_path / "shape.bds")
    assert from_obj.kind is ModelKind.IMPORTED
    for version in (from_obj, from_dsk):
        np.testing.assert_allclose(version_mesh(data, version).vertices, mesh.vertices, atol=1e-9)
    assert from_dsk.statistics["source"].endswith("shape.bds")


def test_concurrent_publications_get_consecutive_numbers(postgres_url: str, open_catalog_at,
                                                         tmp_path: Path) -> None:
    sessions = open_catalog_at(postgres_url)
    meshes = [_sphere(0.2 + 0.01 * k, subdivisions=2) for k in range(6)]

    def publish(mesh: Mesh) -> int:
        with session_scope(sessions) as session:
            return publish_version(session, data_dir=tmp_path, mesh=mesh,
                                   kind=ModelKind.START).version

    with ThreadPoolExecutor(3) as pool:
        numbers = sorted(pool.map(publish, meshes))
    assert numbers == list(range(1, 7))


def test_a_release_cannot_be_undone_changed_or_deleted(catalog: sessionmaker[Session],
                                                      tmp_path: Path) -> None:
    with session_scope(catalog) as session:
        version = publish_version(session, data_dir=tmp_path, mesh=_sphere(), kind=ModelKind.START)
        version.released, version.release_tag = True, "nav-1"
    for change in ({"released": False}, {"release_tag": "nav-2"}, {"release_tag": None}):
        with pytest.raises(ValueError, match="released"), session_scope(catalog) as session:
            for name, value in change.items():
                setattr(get_version(session, 1), name, value)
    with pytest.raises(ValueError, match="cannot be deleted"), session_scope(catalog) as session:
        session.delete(get_version(session, 1))
    with catalog() as session:
        assert get_version(session, "released").release_tag == "nav-1"
