"""The settling passes through the catalog (service.refinement.stale_maplets, the pass rule of
pwm.config.RefinementConfig.another_pass): after the passes every maplet gets, a maplet is
refined again, against the version that fused its last pass, while that pass still changed its
solution by more than RefinementConfig.settled_spacings, and no more than max_passes times."""

from __future__ import annotations

import shutil
from collections import defaultdict

from sqlalchemy import select

from pwm.config import RefinementConfig
from service.rows import MapletRevision
from service.run import run_directory

# a few maplets about the tiny site's centre; their second passes change them by 0.2-0.8 node
# spacings, so that some settle at 0.5 and some do not
CONFIG = RefinementConfig(nodes=40, tile_radius_km=0.0008, passes=2, max_passes=3, settled_spacings=0.5)


def test_a_maplet_is_refined_again_while_its_last_pass_changed_it(tiny_sim, catalog, tmp_path):
    # on SQLite and PostgreSQL: the rule reads each revision's change out of its JSON statistics
    run = run_directory(catalog, shutil.copytree(tiny_sim / "downlink", tmp_path / "first"),
                        data_dir=tmp_path / "data", config=CONFIG)
    with catalog() as session:
        revisions = session.scalars(select(MapletRevision).order_by(MapletRevision.id)).all()
        by_pass: dict[int, dict[int, dict]] = defaultdict(dict)
        for revision in revisions:
            by_pass[revision.statistics["pass"]][revision.maplet_id] = revision.statistics
    maplets = set(by_pass[1])
    assert set(by_pass[2]) == maplets and set(by_pass) == {1, 2, 3}
    # a first pass has nothing to be compared with; each later one is compared with the one before
    assert all(s["changed_spacings"] is None for s in by_pass[1].values())
    assert all(s["changed_spacings"] >= 0 for p in (2, 3) for s in by_pass[p].values())
    unsettled = {m for m, s in by_pass[2].items() if s["changed_spacings"] > CONFIG.settled_spacings}
    assert set(by_pass[3]) == unsettled and 0 < len(unsettled) < len(maplets)
    # the third pass against the version that fused the second; none after it, however far it moved
    assert run.versions == [2, 3, 4]
    assert {s["model_version"] for s in by_pass[3].values()} == {3}
