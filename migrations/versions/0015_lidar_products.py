"""Laser altimetry: lidar products (one row per LIDVID, their shots in the artifact store) and
their tracks (span, cone and box of their spots, strip correction and sigma, residuals).

Revision ID: 0015
Revises: 0014
Create Date: 2026-12-06

Two new tables; nothing else changes, so downgrading drops them.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0015"
down_revision: str | None = "0014"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

UTC_TIME = sa.DateTime(timezone=True)


def _doubles(*names: str, nullable: bool) -> list[sa.Column]:
    return [sa.Column(name, sa.Double(), nullable=nullable) for name in names]


def upgrade() -> None:
    op.create_table(
        "lidar_products",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("lidvid", sa.String(length=255), nullable=False),
        sa.Column("lid", sa.String(length=255), nullable=False),
        sa.Column("vid", sa.String(length=32), nullable=False),
        sa.Column("label_path", sa.Text(), nullable=False),
        sa.Column("data_path", sa.Text(), nullable=False),
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("downlink_id", sa.Integer(), nullable=True),
        sa.Column("status", sa.Enum("accepted", "rejected", name="lidar_status", native_enum=False,
                                    create_constraint=True, length=16), nullable=False),
        sa.Column("rejection_code", sa.String(length=32), nullable=True),
        sa.Column("rejection_reason", sa.Text(), nullable=True),
        sa.Column("layout", sa.String(length=16), nullable=True),
        sa.Column("instrument", sa.String(length=64), nullable=True),
        sa.Column("target", sa.String(length=64), nullable=True),
        sa.Column("body_frame", sa.String(length=64), nullable=True),
        *_doubles("start_et", "stop_et", nullable=True),
        sa.Column("start_utc", UTC_TIME, nullable=True),
        sa.Column("stop_utc", UTC_TIME, nullable=True),
        sa.Column("shots", sa.BigInteger(), nullable=False),
        sa.Column("valid_shots", sa.BigInteger(), nullable=False),
        sa.Column("invalid_shots", sa.JSON(), nullable=False),
        sa.Column("shots_artifact", sa.JSON(), nullable=True),
        sa.Column("ingested_at", UTC_TIME, nullable=False),
        sa.CheckConstraint("valid_shots >= 0 AND valid_shots <= shots", name=op.f("ck_lidar_products_shot_counts")),
        sa.ForeignKeyConstraint(["downlink_id"], ["downlinks.id"], name=op.f("fk_lidar_products_downlink_id"),
                                ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_lidar_products")),
        sa.UniqueConstraint("lidvid", name=op.f("uq_lidar_products_lidvid")),
    )
    op.create_index(op.f("ix_lidar_products_downlink_id"), "lidar_products", ["downlink_id"])
    op.create_index(op.f("ix_lidar_products_status"), "lidar_products", ["status"])
    op.create_index(op.f("ix_lidar_products_start_utc"), "lidar_products", ["start_utc"])
    op.create_table(
        "lidar_tracks",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("product_id", sa.Integer(), nullable=False),
        sa.Column("track", sa.Integer(), nullable=False),
        *_doubles("start_et", "stop_et", nullable=False),
        sa.Column("shots", sa.Integer(), nullable=False),
        *_doubles("cone_axis_x", "cone_axis_y", "cone_axis_z", "cone_half_angle_rad", "axis_lat_deg",
                  "axis_lon_deg", "min_x_km", "min_y_km", "min_z_km", "max_x_km", "max_y_km", "max_z_km",
                  nullable=False),
        *_doubles("rotation_x_rad", "rotation_y_rad", "rotation_z_rad", "translation_x_km", "translation_y_km",
                  "translation_z_km", "about_x_km", "about_y_km", "about_z_km", nullable=True),
        sa.Column("correction_sigma", sa.JSON(), nullable=True),
        sa.Column("adjusted_at", UTC_TIME, nullable=True),
        *_doubles("residual_mean_km", "residual_rms_km", "residual_p95_km", nullable=True),
        sa.Column("residual_version", sa.Integer(), nullable=True),
        sa.CheckConstraint("cone_half_angle_rad >= 0", name=op.f("ck_lidar_tracks_cone_half_angle_nonnegative")),
        sa.ForeignKeyConstraint(["product_id"], ["lidar_products.id"], name=op.f("fk_lidar_tracks_product_id"),
                                ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_lidar_tracks")),
        sa.UniqueConstraint("product_id", "track", name=op.f("uq_lidar_tracks_product_id_track")),
    )
    op.create_index(op.f("ix_lidar_tracks_axis_lat_deg_axis_lon_deg"), "lidar_tracks",
                    ["axis_lat_deg", "axis_lon_deg"])


def downgrade() -> None:
    op.drop_table("lidar_tracks")
    op.drop_table("lidar_products")
