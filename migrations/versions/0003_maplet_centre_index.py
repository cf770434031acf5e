"""Maplets: an index on the centre latitude and longitude, for the spatial prefilter of the
catalog queries (service.queries).

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23

An index alone: SQLite creates and drops it in place, without rebuilding the maplets table that
other tables reference.
"""

from collections.abc import Sequence

from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_index(
        op.f("ix_maplets_center_lat_deg_center_lon_deg"),
        "maplets",
        ["center_lat_deg", "center_lon_deg"],
    )


def downgrade() -> None:
    op.drop_index(op.f("ix_maplets_center_lat_deg_center_lon_deg"), table_name="maplets")
