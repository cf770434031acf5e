"""A changed refinement configuration re-refines only when the operator asks: a catalog refined
under one configuration plans nothing under another, and `pwm downlinks` counts its maplets;
asked (refine_on_config_change, `pwm refine-catalog --because-config-changed`), they are refined;
a maplet whose images changed is due under the new configuration either way; a revision made
before digests were recorded is due once."""

from __future__ import annotations

import dataclasses

from sqlalchemy import select, update

from pwm.config import RefinementConfig
from pwm.photoclinometry import Solver
from service.cli import app
from service.conductor import ingest_and_plan
from service.db import session_scope
from service.downlinks import other_configurations
from service.refinement import stale_maplets
from service.rows import Coverage, Image, Maplet, MapletRevision
from service.run import run_directory
from service.settings import get_settings

# One maplet on the site's centre, one pass; its digest is the defaults', which `pwm` uses.
NEW = RefinementConfig(nodes=40, tile_radius_km=0.0003, passes=1)
OLD = dataclasses.replace(NEW, solver=Solver(cost_tolerance=0.05))


def _correct_pose_of_an_input(catalog, maplet_id: int, correction: float | None) -> None:
    """Set (or, None, clear) the pose correction of the first image the maplet weighs in."""
    with session_scope(catalog) as session:
        image = session.scalars(select(Image).join(Coverage).where(
            Coverage.maplet_id == maplet_id, Coverage.weight > 0).order_by(Image.id)).first()
        image.pose_dx_km = correction


def test_a_changed_configuration_re_refines_only_when_asked(tiny_sim, pwm, tmp_path, open_catalog_at,
                                                            monkeypatch):
    data = tmp_path / "data"  # the `pwm` fixture's catalog
    data.mkdir()
    catalog = open_catalog_at(f"sqlite:///{data / 'catalog.sqlite'}")
    run = run_directory(catalog, tiny_sim / "downlink", data_dir=data, config=OLD)
    [work] = run.plan.work
    assert run.versions == [2] and OLD.digest() != NEW.digest()
    with catalog() as session:
        [revision] = session.scalars(select(MapletRevision))
        assert revision.config_digest == OLD.digest()
        assert stale_maplets(session, config=OLD) == []
        # (a) another configuration plans nothing, whatever its passes
        assert stale_maplets(session, config=NEW) == []
        assert stale_maplets(session, config=dataclasses.replace(NEW, passes=2)) == []
        assert [w.pass_number for w in stale_maplets(session, config=dataclasses.replace(OLD, passes=2))] == [2]
        # (b) unless asked: then each is due, at pass 1 of its input under the new configuration
        [due] = stale_maplets(session, config=NEW, refine_on_config_change=True)
        assert other_configurations(session, NEW) == {work.maplet_id: OLD.digest()}
    assert (due.maplet_id, due.pass_number) == (work.maplet_id, 1) and due.input_hash != work.input_hash
    # the conductor's plan, as the drivers make it with PWM_REFINE_ON_CONFIG_CHANGE unset and set
    assert ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=data, config=NEW).work == []
    assert ingest_and_plan(catalog, tiny_sim / "downlink", data_dir=data, config=NEW,
                           refine_on_config_change=True).work == [due]

    note = (f"1 maplet's current revision was made with another configuration (digest {OLD.digest()[:12]}..., "
            f"current {NEW.digest()[:12]}...); `pwm refine-catalog --because-config-changed` refines it")
    listed = pwm.invoke(app, ["downlinks"])
    assert listed.exit_code == 0, listed.output
    assert note in listed.output
    told = pwm.invoke(app, ["refine-catalog"])  # without the flag: says what it would do
    assert told.exit_code == 0, told.output
    assert note in told.output

    # (c) an image changed: due under the new configuration, unasked
    _correct_pose_of_an_input(catalog, work.maplet_id, 1e-4)
    with catalog() as session:
        [moved] = stale_maplets(session, config=NEW)
    assert (moved.maplet_id, moved.pass_number) == (work.maplet_id, 1)
    assert moved.input_hash not in (work.input_hash, due.input_hash)
    _correct_pose_of_an_input(catalog, work.maplet_id, None)

    # a revision made before digests were recorded: due once the configuration changed, not counted
    with session_scope(catalog) as session:
        session.execute(update(MapletRevision).values(config_digest=None))
    with catalog() as session:
        assert stale_maplets(session, config=NEW) == [due] and stale_maplets(session, config=OLD) == []
        assert other_configurations(session, NEW) == {}
    with session_scope(catalog) as session:
        session.execute(update(MapletRevision).values(config_digest=OLD.digest()))

    monkeypatch.setenv("PWM_REFINE_PASSES", "1")  # not in the digest
    get_settings.cache_clear()
    refined = pwm.invoke(app, ["refine-catalog", "--because-config-changed"])
    assert refined.exit_code == 0, refined.output
    assert f"1 maplet refinements under configuration {NEW.digest()[:12]}...; published version 3" in refined.output
    with catalog() as session:
        current = session.scalars(select(MapletRevision).join(
            Maplet, Maplet.current_revision_id == MapletRevision.id)).one()
        assert (current.input_hash, current.config_digest) == (due.input_hash, NEW.digest())
        assert stale_maplets(session, config=NEW) == [] and other_configurations(session, NEW) == {}
    listed = pwm.invoke(app, ["downlinks"])
    assert listed.exit_code == 0 and "another configuration" not in listed.output
