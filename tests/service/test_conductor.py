"""The conductor's order (service.conductor) on one downlink through the in-process runner: the
images are weighed once, after their poses are final, however many passes follow."""

from __future__ import annotations

import shutil

from sqlalchemy import select

import service.conductor
from pwm.config import RefinementConfig
from service.rows import Image
from service.run import run_directory

# a few maplets about the site's centre, two passes each (the settling passes: tests/service/test_settling.py)
CONFIG = RefinementConfig(nodes=40, tile_radius_km=0.0008, max_passes=2)


def test_a_downlink_is_weighed_once_for_all_its_passes(tiny_sim, sqlite_url, open_catalog_at, tmp_path,
                                                      monkeypatch):
    catalog = open_catalog_at(sqlite_url)
    weighed: list[set[int]] = []
    update_coverage = service.conductor.update_coverage

    def counted(session, shape, **kwargs):
        weighed.append(set(kwargs["image_ids"]))
        return update_coverage(session, shape, **kwargs)

    monkeypatch.setattr(service.conductor, "update_coverage", counted)
    run = run_directory(catalog, shutil.copytree(tiny_sim / "downlink", tmp_path / "first"),
                        data_dir=tmp_path / "data", config=CONFIG)
    assert CONFIG.passes == 2 and len(run.versions) == 2 and run.plan.coverage is not None
    with catalog() as session:
        images = set(session.scalars(select(Image.id)))
    # no feedback on tiny (its kernels state no pose knowledge): nothing weighed after the ingest
    assert weighed == [images] and run.plan.coverage.maplets_added > 0
