"""Downlinks: what became of the model when one arrived at a catalog without any (made from its
images by photogrammetry, or why not yet).

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-03

A nullable addition, so SQLite adds and drops it in place.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("downlinks", sa.Column("model_note", sa.Text(), nullable=True))


def downgrade() -> None:
    op.drop_column("downlinks", "model_note")
