"""Release tags: a version marked released is what `released` names; its tag is set once and
a release is never undone or changed."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.models import ModelVersion
from service.versions import get_version


class ReleaseConflict(Exception):
    """The version is released under another tag already, or the tag names another version."""


def release_version(session: Session, ref: str | int, *, tag: str) -> ModelVersion:
    """Mark the version `ref` released as `tag`, in the caller's transaction. Releasing it again
    with the same tag changes nothing. Raises LookupError (no such version) or ReleaseConflict."""
    number = get_version(session, ref).version
    # Locked, so that of two concurrent releases of one version the second sees the first.
    version = session.scalars(select(ModelVersion).filter_by(version=number).with_for_update()
                              .execution_options(populate_existing=True)).one()
    if version.released or version.release_tag is not None:
        if version.release_tag == tag:
            return version
        raise ReleaseConflict(f"version {number} is released as {version.release_tag!r}; a "
                              "release cannot be changed")
    holder = session.scalar(select(ModelVersion.version).filter_by(release_tag=tag))
    if holder is not None:
        raise ReleaseConflict(f"tag {tag!r} names version {holder} already")
    version.released, version.release_tag = True, tag
    try:
        with session.begin_nested():
            session.flush()
    except IntegrityError as exc:  # a concurrent release took the tag
        raise ReleaseConflict(f"tag {tag!r} was taken meanwhile") from exc
    return version
