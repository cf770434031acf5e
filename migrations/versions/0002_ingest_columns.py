"""Ingest: rejection codes of images and the boresight intercept range of their geometry.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22

Both columns are nullable additions, so SQLite adds and drops them in place (ALTER TABLE, SQLite
3.35+) without rebuilding the tables that other tables reference.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("images", sa.Column("rejection_code", sa.String(length=32), nullable=True))
    op.add_column(
        "image_geometry", sa.Column("intercept_range_km", sa.Double(), nullable=True)
    )


def downgrade() -> None:
    op.drop_column("image_geometry", "intercept_range_km")
    op.drop_column("images", "rejection_code")
