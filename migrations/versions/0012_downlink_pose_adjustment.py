"""Downlinks: what the adjustment of their poses did (the knowledge it took, the line of sight
before and after, the pose model's unknowns), or why none ran.

Revision ID: 0012
Revises: 0011
Create Date: 2026-12-03

A nullable addition, so SQLite adds and drops it in place.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0012"
down_revision: str | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("downlinks", sa.Column("pose_adjustment", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("downlinks", "pose_adjustment")
