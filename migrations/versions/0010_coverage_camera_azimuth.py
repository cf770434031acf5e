"""Coverage: the camera's azimuth at the maplet (degrees from local north, east positive), the
last of the geometry the five-view selection needs, so that a new downlink's images are weighed
into a maplet with the stored rows of the images already catalogued, without tracing those again.

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-03

A nullable addition, so SQLite adds and drops it in place. Rows weighed before stay null: the next
update that weighs their maplet traces their image again and fills it in.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("coverage", sa.Column("camera_azimuth_deg", sa.Double(), nullable=True))


def downgrade() -> None:
    op.drop_column("coverage", "camera_azimuth_deg")
