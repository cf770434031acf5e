"""Images: the prior and posterior 1-sigma figures of the latest bundle adjustment of each pose
(lateral and along-boresight position, pointing, line of sight), beside its correction.

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-03

A nullable addition, so SQLite adds and drops it in place.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("images", sa.Column("pose_sigma", sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column("images", "pose_sigma")
