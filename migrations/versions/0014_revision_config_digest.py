"""Maplet revisions: the digest of the refinement configuration each was made with.

Revision ID: 0014
Revises: 0013
Create Date: 2026-12-06

Null for the revisions made before it was recorded: the planner treats those as it did before
(service.refinement.stale_maplets). A nullable addition, so SQLite adds and drops it in place.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0014"
down_revision: str | None = "0013"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("maplet_revisions", sa.Column("config_digest", sa.String(length=64), nullable=True))


def downgrade() -> None:
    op.drop_column("maplet_revisions", "config_digest")
