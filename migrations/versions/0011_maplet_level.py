"""Maplets: the level of the node spacing (pwm.tiling.level_of: level k holds the spacings
within a factor sqrt(2) of 2^k m), by which queries filter the maplets of a site nested in a
survey from the survey's.

Revision ID: 0011
Revises: 0010
Create Date: 2026-12-03

Added NOT NULL with a server default so that SQLite adds it in place (no table copy, which would
cascade to coverage and revisions), then set from each row's gsd_m.
"""

import math
from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0011"
down_revision: str | None = "0010"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("maplets", sa.Column("level", sa.Integer(), nullable=False, server_default="0"))
    maplets = sa.table("maplets", sa.column("id", sa.Integer()), sa.column("gsd_m", sa.Double()),
                       sa.column("level", sa.Integer()))
    connection = op.get_bind()
    levels = [{"key": row.id, "value": round(math.log2(row.gsd_m))}
              for row in connection.execute(sa.select(maplets.c.id, maplets.c.gsd_m))]
    if levels:
        connection.execute(maplets.update().where(maplets.c.id == sa.bindparam("key"))
                           .values(level=sa.bindparam("value")), levels)


def downgrade() -> None:
    op.drop_column("maplets", "level")
