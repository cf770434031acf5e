"""Release tags: a version marked released is what `released` names; its tag is set once and
a release is never undone or changed."""

from __future__ import annotations

from typing import Any, cast

from sqlalchemy import CursorResult, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.rows import ModelVersion
from service.versions import get_version


class ReleaseConflict(Exception):
    """The version is released under another tag already, or the tag names another version."""


def release_version(session: Session, ref: str | int, *, tag: str) -> ModelVersion:
    """Mark the version `ref` released as `tag`, in the caller's transaction. Releasing it again
    with the same tag changes nothing. Raises LookupError (no such version) or ReleaseConflict.

    One conditional UPDATE decides, so that of concurrent releases exactly one sets the tag on
    both databases: PostgreSQL makes a second writer of the row wait for the first and re-check
    the condition, SQLite runs writes one at a time (a read first and a write later would not
    do: SQLite takes no lock for the read, and with_for_update is a no-op there).
    """
    number = get_version(session, ref).version
    try:
        with session.begin_nested():
            result = cast(CursorResult[Any], session.execute(
                update(ModelVersion).where(ModelVersion.version == number,
                                           ModelVersion.released.is_(False),
                                           ModelVersion.release_tag.is_(None))
                .values(released=True, release_tag=tag)
                .execution_options(synchronize_session=False)))
            released = result.rowcount == 1
    except IntegrityError as exc:  # the unique tag: another version holds it
        holder = session.scalar(select(ModelVersion.version).filter_by(release_tag=tag))
        raise ReleaseConflict(f"tag {tag!r} names version {holder} already") from exc
    version = session.scalars(select(ModelVersion).filter_by(version=number)
                              .execution_options(populate_existing=True)).one()
    if not released and version.release_tag != tag:
        raise ReleaseConflict(f"version {number} is released as {version.release_tag!r}; a "
                              "release cannot be changed")
    return version
