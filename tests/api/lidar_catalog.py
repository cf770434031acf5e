"""A small catalog with lidar for the API, CLI and console tests: a downlink with one accepted
lidar product of two tracks (one strip-adjusted), a version of kind lidar whose lidar statistics
come from pwm.lidar.model.residual_summary itself (200 spots 2 m outside a 250 m sphere), and an
imported version that was not checked against the lidar."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import trimesh
from sqlalchemy.orm import Session, sessionmaker

from pwm.lidar.model import residual_summary
from pwm.lidar.shots import Shots
from pwm.mesh import Mesh
from service.db import session_scope
from service.rows import Acceptance, Downlink, LidarProduct, LidarTrack, ModelKind
from service.versions import publish_version

RADIUS_KM = 0.25
OFFSET_KM = 0.002  # every spot 2 m outside the sphere


def _shots(n: int) -> Shots:
    """n shots straight down from 1 km above a 250 m sphere, ranging OFFSET_KM short."""
    rng = np.random.default_rng(3)
    down = rng.normal(size=(n, 3))
    down /= np.linalg.norm(down, axis=1, keepdims=True)
    return Shots(frame="IAU_BENNU", et=np.arange(n, dtype=float), origin_km=down * (RADIUS_KM + 1.0),
                 direction=-down, range_km=np.full(n, 1.0 - OFFSET_KM), sigma_km=np.full(n, 1e-4),
                 invalid=np.zeros(n, dtype=np.int8))


def add_lidar_catalog(sessions: sessionmaker[Session], data_dir: Path) -> None:
    """The rows above, in the catalog of `sessions` (versions 1, lidar, and 2, imported)."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS_KM)
    mesh = Mesh(sphere.vertices, sphere.faces)
    with session_scope(sessions) as session:
        downlink = Downlink(name="dl1", path="/downlinks/dl1")
        session.add(downlink)
        session.flush()
        product = LidarProduct(lidvid="urn:lidar:a::1.0", lid="urn:lidar:a", vid="1.0", label_path="a.xml",
                               data_path="a.dat", sha256="0" * 64, size_bytes=10, downlink_id=downlink.id,
                               status=Acceptance.ACCEPTED, shots=300, valid_shots=200, invalid_shots={})
        box = dict(min_x_km=-1.0, min_y_km=-1.0, min_z_km=-1.0, max_x_km=1.0, max_y_km=1.0, max_z_km=1.0)
        adjusted = LidarTrack(product=product, track=0, start_et=0.0, stop_et=99.0, shots=100, cone_axis_x=1.0,
                              cone_axis_y=0.0, cone_axis_z=0.0, cone_half_angle_rad=0.5, axis_lat_deg=0.0,
                              axis_lon_deg=0.0, rotation_x_rad=1e-4, rotation_y_rad=0.0, rotation_z_rad=0.0,
                              translation_x_km=0.003, translation_y_km=-0.001, translation_z_km=0.0,
                              about_x_km=0.25, about_y_km=0.0, about_z_km=0.0,
                              correction_sigma=[1e-5, 1e-5, None, 1e-4, 1e-4, 1e-4], crossovers=3,
                              crossover_rms_km=2e-4,
                              adjusted_at=datetime(2026, 12, 6, tzinfo=UTC), **box)
        plain = LidarTrack(product=product, track=1, start_et=100.0, stop_et=199.0, shots=100, cone_axis_x=0.0,
                           cone_axis_y=1.0, cone_axis_z=0.0, cone_half_angle_rad=0.5, axis_lat_deg=0.0,
                           axis_lon_deg=90.0, **box)
        session.add(product)
        session.flush()
        track = np.repeat([adjusted.id, plain.id], 100)
        figures = residual_summary(_shots(200), mesh, track)
        adjusted.residual_version, adjusted.residual_rms_km = 1, figures["tracks"][str(adjusted.id)]["rms_km"]
        publish_version(session, data_dir=data_dir, mesh=mesh,
                        kind=ModelKind.LIDAR, statistics={"lidar": figures | {"products": 1, "usable_shots": 200}},
                        downlinks=[downlink])
        publish_version(session, data_dir=data_dir, mesh=mesh,
                        kind=ModelKind.IMPORTED)
