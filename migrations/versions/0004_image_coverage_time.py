"""Images: when their coverage rows were computed.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-24

An ingest weighs only the images not weighed yet (service.ingest), so a repeated ingest leaves
the coverage rows, and with them the maplets' refinement inputs, as they are. A nullable
addition, so SQLite adds and drops it in place without rebuilding the images table.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("images", sa.Column("coverage_computed_at", sa.DateTime(timezone=True),
                                      nullable=True))


def downgrade() -> None:
    op.drop_column("images", "coverage_computed_at")
