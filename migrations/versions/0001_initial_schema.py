"""Initial catalog schema.

Revision ID: 0001
Revises:
Create Date: 2026-11-22

Written out in full (not generated at run time); `tests/service` checks that it matches
service.rows on SQLite and PostgreSQL.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

UTC_TIME = sa.DateTime(timezone=True)


def _enum(name: str, *values: str) -> sa.Enum:
    """VARCHAR(16) with a CHECK constraint, as service.rows declares its enumerations."""
    return sa.Enum(*values, name=name, native_enum=False, create_constraint=True, length=16)


def upgrade() -> None:
    op.create_table(
        "downlinks",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=255), nullable=False),
        sa.Column("path", sa.Text(), nullable=False),
        sa.Column("received_at", UTC_TIME, nullable=False),
        sa.Column(
            "status",
            _enum("downlink_status", "received", "ingesting", "ingested", "failed"),
            nullable=False,
        ),
        sa.Column("manifest_sha256", sa.String(length=64), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_downlinks")),
        sa.UniqueConstraint("name", name=op.f("uq_downlinks_name")),
    )
    op.create_table(
        "instruments",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("naif_id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=64), nullable=False),
        sa.Column("spacecraft_id", sa.Integer(), nullable=False),
        sa.Column("frame_name", sa.String(length=64), nullable=False),
        sa.Column("width_px", sa.Integer(), nullable=False),
        sa.Column("height_px", sa.Integer(), nullable=False),
        sa.Column("fx_px", sa.Double(), nullable=False),
        sa.Column("fy_px", sa.Double(), nullable=False),
        sa.Column("cx_px", sa.Double(), nullable=False),
        sa.Column("cy_px", sa.Double(), nullable=False),
        sa.Column("focal_length_source", sa.String(length=64), nullable=False),
        sa.Column("units_note", sa.Text(), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_instruments")),
        sa.UniqueConstraint("naif_id", name=op.f("uq_instruments_naif_id")),
    )
    op.create_table(
        "kernels",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("path", sa.Text(), nullable=False),
        sa.Column(
            "kind",
            _enum("kernel_kind", "lsk", "pck", "fk", "ik", "sclk", "spk", "ck", "mk", "dsk"),
            nullable=False,
        ),
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("status", _enum("kernel_status", "accepted", "rejected"), nullable=False),
        sa.Column("rejection_reason", sa.Text(), nullable=True),
        sa.Column("downlink_id", sa.Integer(), nullable=True),
        sa.ForeignKeyConstraint(
            ["downlink_id"],
            ["downlinks.id"],
            name=op.f("fk_kernels_downlink_id"),
            ondelete="SET NULL",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_kernels")),
        sa.UniqueConstraint("sha256", name=op.f("uq_kernels_sha256")),
    )
    op.create_index(op.f("ix_kernels_downlink_id"), "kernels", ["downlink_id"])
    op.create_table(
        "kernel_coverage",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("kernel_id", sa.Integer(), nullable=False),
        sa.Column("naif_id", sa.Integer(), nullable=False),
        sa.Column("start_et", sa.Double(), nullable=False),
        sa.Column("stop_et", sa.Double(), nullable=False),
        sa.Column("start_utc", UTC_TIME, nullable=False),
        sa.Column("stop_utc", UTC_TIME, nullable=False),
        sa.CheckConstraint("stop_et >= start_et", name=op.f("ck_kernel_coverage_window_order")),
        sa.ForeignKeyConstraint(
            ["kernel_id"],
            ["kernels.id"],
            name=op.f("fk_kernel_coverage_kernel_id"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_kernel_coverage")),
    )
    op.create_index(op.f("ix_kernel_coverage_kernel_id"), "kernel_coverage", ["kernel_id"])
    op.create_index(op.f("ix_kernel_coverage_naif_id"), "kernel_coverage", ["naif_id"])
    op.create_table(
        "images",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("lidvid", sa.String(length=255), nullable=False),
        sa.Column("lid", sa.String(length=255), nullable=False),
        sa.Column("vid", sa.String(length=32), nullable=False),
        sa.Column("label_path", sa.Text(), nullable=False),
        sa.Column("data_path", sa.Text(), nullable=False),
        sa.Column("md5", sa.String(length=32), nullable=True),
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("instrument_id", sa.Integer(), nullable=True),
        sa.Column("target", sa.String(length=64), nullable=True),
        sa.Column("start_utc", UTC_TIME, nullable=True),
        sa.Column("stop_utc", UTC_TIME, nullable=True),
        sa.Column("start_et", sa.Double(), nullable=True),
        sa.Column("stop_et", sa.Double(), nullable=True),
        sa.Column(
            "status", _enum("image_status", "accepted", "rejected", "conflict"), nullable=False
        ),
        sa.Column("rejection_reason", sa.Text(), nullable=True),
        sa.Column(
            "geometry_status",
            _enum("geometry_status", "pending", "computed", "unavailable"),
            nullable=False,
        ),
        sa.Column("geometry_unavailable_reason", sa.Text(), nullable=True),
        sa.Column("downlink_id", sa.Integer(), nullable=True),
        sa.Column("pose_dx_km", sa.Double(), nullable=True),
        sa.Column("pose_dy_km", sa.Double(), nullable=True),
        sa.Column("pose_dz_km", sa.Double(), nullable=True),
        sa.Column("pose_rx_rad", sa.Double(), nullable=True),
        sa.Column("pose_ry_rad", sa.Double(), nullable=True),
        sa.Column("pose_rz_rad", sa.Double(), nullable=True),
        sa.Column("pose_corrected_at", UTC_TIME, nullable=True),
        sa.ForeignKeyConstraint(
            ["downlink_id"],
            ["downlinks.id"],
            name=op.f("fk_images_downlink_id"),
            ondelete="SET NULL",
        ),
        sa.ForeignKeyConstraint(
            ["instrument_id"], ["instruments.id"], name=op.f("fk_images_instrument_id")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_images")),
        sa.UniqueConstraint("lidvid", name=op.f("uq_images_lidvid")),
    )
    op.create_index(op.f("ix_images_downlink_id"), "images", ["downlink_id"])
    op.create_index(op.f("ix_images_instrument_id"), "images", ["instrument_id"])
    op.create_index(op.f("ix_images_lid"), "images", ["lid"])
    op.create_index(op.f("ix_images_start_utc"), "images", ["start_utc"])
    op.create_index(op.f("ix_images_status"), "images", ["status"])
    op.create_table(
        "image_geometry",
        sa.Column("image_id", sa.Integer(), nullable=False),
        sa.Column("camera_x_km", sa.Double(), nullable=False),
        sa.Column("camera_y_km", sa.Double(), nullable=False),
        sa.Column("camera_z_km", sa.Double(), nullable=False),
        sa.Column("camera_rotation", sa.JSON(), nullable=False),
        sa.Column("sun_x", sa.Double(), nullable=False),
        sa.Column("sun_y", sa.Double(), nullable=False),
        sa.Column("sun_z", sa.Double(), nullable=False),
        sa.Column("range_km", sa.Double(), nullable=False),
        sa.Column("pixel_scale_m", sa.Double(), nullable=True),
        sa.Column("phase_deg", sa.Double(), nullable=True),
        sa.Column("incidence_deg", sa.Double(), nullable=True),
        sa.Column("emission_deg", sa.Double(), nullable=True),
        sa.Column("intercept_lat_deg", sa.Double(), nullable=True),
        sa.Column("intercept_lon_deg", sa.Double(), nullable=True),
        sa.Column("footprint", sa.JSON(), nullable=True),
        sa.Column("body_frame", sa.String(length=64), nullable=False),
        sa.Column("abcorr", sa.String(length=16), nullable=False),
        sa.Column("computed_at", UTC_TIME, nullable=False),
        sa.ForeignKeyConstraint(
            ["image_id"], ["images.id"], name=op.f("fk_image_geometry_image_id"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("image_id", name=op.f("pk_image_geometry")),
    )
    op.create_table(
        "maplets",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=64), nullable=False),
        sa.Column("center_lat_deg", sa.Double(), nullable=False),
        sa.Column("center_lon_deg", sa.Double(), nullable=False),
        sa.Column("origin_x_km", sa.Double(), nullable=False),
        sa.Column("origin_y_km", sa.Double(), nullable=False),
        sa.Column("origin_z_km", sa.Double(), nullable=False),
        sa.Column("rotation", sa.JSON(), nullable=False),
        sa.Column("size_km", sa.Double(), nullable=False),
        sa.Column("gsd_m", sa.Double(), nullable=False),
        sa.Column("nodes_per_side", sa.Integer(), nullable=False),
        sa.Column("region_weight", sa.Double(), nullable=False),
        sa.Column("current_revision_id", sa.Integer(), nullable=True),
        sa.CheckConstraint("region_weight > 0", name=op.f("ck_maplets_region_weight_positive")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_maplets")),
        sa.UniqueConstraint("name", name=op.f("uq_maplets_name")),
    )
    op.create_table(
        "maplet_revisions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("maplet_id", sa.Integer(), nullable=False),
        sa.Column("revision", sa.Integer(), nullable=False),
        sa.Column("input_hash", sa.String(length=64), nullable=False),
        sa.Column("mode", sa.String(length=32), nullable=False),
        sa.Column("created_at", UTC_TIME, nullable=False),
        sa.Column("statistics", sa.JSON(), nullable=False),
        sa.Column("artifact_path", sa.Text(), nullable=False),
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.ForeignKeyConstraint(
            ["maplet_id"],
            ["maplets.id"],
            name=op.f("fk_maplet_revisions_maplet_id"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_maplet_revisions")),
        sa.UniqueConstraint(
            "maplet_id", "input_hash", name=op.f("uq_maplet_revisions_maplet_id_input_hash")
        ),
        sa.UniqueConstraint(
            "maplet_id", "revision", name=op.f("uq_maplet_revisions_maplet_id_revision")
        ),
    )
    # maplets and maplet_revisions reference each other: the maplet"s current revision comes
    # last (batch mode, so SQLite, which cannot ALTER constraints, rebuilds the still empty table).
    with op.batch_alter_table("maplets") as batch_op:
        batch_op.create_foreign_key(
            op.f("fk_maplets_current_revision_id"),
            "maplet_revisions",
            ["current_revision_id"],
            ["id"],
            ondelete="SET NULL",
        )
    op.create_table(
        "coverage",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("image_id", sa.Integer(), nullable=False),
        sa.Column("maplet_id", sa.Integer(), nullable=False),
        sa.Column("visible_fraction", sa.Double(), nullable=False),
        sa.Column("shadowed_fraction", sa.Double(), nullable=False),
        sa.Column("incidence_deg", sa.Double(), nullable=False),
        sa.Column("emission_deg", sa.Double(), nullable=False),
        sa.Column("phase_deg", sa.Double(), nullable=False),
        sa.Column("sun_azimuth_deg", sa.Double(), nullable=False),
        sa.Column("resolution_m_per_px", sa.Double(), nullable=False),
        sa.Column("weight", sa.Double(), nullable=False),
        sa.Column(
            "role", _enum("coverage_role", "nadir", "east", "west", "north", "south"), nullable=True
        ),
        sa.CheckConstraint(
            "shadowed_fraction BETWEEN 0 AND 1", name=op.f("ck_coverage_shadowed_fraction_range")
        ),
        sa.CheckConstraint(
            "visible_fraction BETWEEN 0 AND 1", name=op.f("ck_coverage_visible_fraction_range")
        ),
        sa.CheckConstraint("weight >= 0", name=op.f("ck_coverage_weight_nonnegative")),
        sa.ForeignKeyConstraint(
            ["image_id"], ["images.id"], name=op.f("fk_coverage_image_id"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["maplet_id"], ["maplets.id"], name=op.f("fk_coverage_maplet_id"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_coverage")),
        sa.UniqueConstraint("image_id", "maplet_id", name=op.f("uq_coverage_image_id_maplet_id")),
    )
    op.create_index(op.f("ix_coverage_maplet_id"), "coverage", ["maplet_id"])
    op.create_table(
        "model_versions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column(
            "kind",
            _enum("model_kind", "start", "photogrammetric", "refined", "imported"),
            nullable=False,
        ),
        sa.Column("parent_id", sa.Integer(), nullable=True),
        sa.Column("created_at", UTC_TIME, nullable=False),
        sa.Column("statistics", sa.JSON(), nullable=False),
        sa.Column("artifacts", sa.JSON(), nullable=False),
        sa.Column("released", sa.Boolean(), nullable=False),
        sa.Column("release_tag", sa.String(length=64), nullable=True),
        sa.ForeignKeyConstraint(
            ["parent_id"],
            ["model_versions.id"],
            name=op.f("fk_model_versions_parent_id"),
            ondelete="RESTRICT",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_model_versions")),
        sa.UniqueConstraint("release_tag", name=op.f("uq_model_versions_release_tag")),
        sa.UniqueConstraint("version", name=op.f("uq_model_versions_version")),
    )
    op.create_index(op.f("ix_model_versions_parent_id"), "model_versions", ["parent_id"])
    op.create_table(
        "model_version_maplet_revisions",
        sa.Column("model_version_id", sa.Integer(), nullable=False),
        sa.Column("maplet_revision_id", sa.Integer(), nullable=False),
        sa.ForeignKeyConstraint(
            ["maplet_revision_id"],
            ["maplet_revisions.id"],
            name=op.f("fk_model_version_maplet_revisions_maplet_revision_id"),
            ondelete="RESTRICT",
        ),
        sa.ForeignKeyConstraint(
            ["model_version_id"],
            ["model_versions.id"],
            name=op.f("fk_model_version_maplet_revisions_model_version_id"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint(
            "model_version_id", "maplet_revision_id", name=op.f("pk_model_version_maplet_revisions")
        ),
    )
    op.create_table(
        "model_version_downlinks",
        sa.Column("model_version_id", sa.Integer(), nullable=False),
        sa.Column("downlink_id", sa.Integer(), nullable=False),
        sa.ForeignKeyConstraint(
            ["downlink_id"],
            ["downlinks.id"],
            name=op.f("fk_model_version_downlinks_downlink_id"),
            ondelete="RESTRICT",
        ),
        sa.ForeignKeyConstraint(
            ["model_version_id"],
            ["model_versions.id"],
            name=op.f("fk_model_version_downlinks_model_version_id"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint(
            "model_version_id", "downlink_id", name=op.f("pk_model_version_downlinks")
        ),
    )
    op.create_table(
        "jobs",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("kind", _enum("job_kind", "ingest", "refine", "fuse"), nullable=False),
        sa.Column("key", sa.String(length=255), nullable=False),
        sa.Column(
            "status", _enum("job_status", "queued", "running", "done", "failed"), nullable=False
        ),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("progress", sa.Double(), nullable=False),
        sa.Column("message", sa.Text(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("created_at", UTC_TIME, nullable=False),
        sa.Column("started_at", UTC_TIME, nullable=True),
        sa.Column("finished_at", UTC_TIME, nullable=True),
        sa.Column("downlink_id", sa.Integer(), nullable=True),
        sa.Column("maplet_id", sa.Integer(), nullable=True),
        sa.CheckConstraint("attempts >= 0", name=op.f("ck_jobs_attempts_nonnegative")),
        sa.CheckConstraint("progress BETWEEN 0 AND 1", name=op.f("ck_jobs_progress_range")),
        sa.ForeignKeyConstraint(
            ["downlink_id"], ["downlinks.id"], name=op.f("fk_jobs_downlink_id"), ondelete="SET NULL"
        ),
        sa.ForeignKeyConstraint(
            ["maplet_id"], ["maplets.id"], name=op.f("fk_jobs_maplet_id"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_jobs")),
        sa.UniqueConstraint("key", name=op.f("uq_jobs_key")),
    )
    op.create_index(op.f("ix_jobs_downlink_id"), "jobs", ["downlink_id"])
    op.create_index(op.f("ix_jobs_maplet_id"), "jobs", ["maplet_id"])
    op.create_index(op.f("ix_jobs_status"), "jobs", ["status"])


def downgrade() -> None:
    with op.batch_alter_table("maplets") as batch_op:
        batch_op.drop_constraint(op.f("fk_maplets_current_revision_id"), type_="foreignkey")
    op.drop_table("jobs")
    op.drop_table("model_version_downlinks")
    op.drop_table("model_version_maplet_revisions")
    op.drop_table("model_versions")
    op.drop_table("coverage")
    op.drop_table("maplet_revisions")
    op.drop_table("maplets")
    op.drop_table("image_geometry")
    op.drop_table("images")
    op.drop_table("kernel_coverage")
    op.drop_table("kernels")
    op.drop_table("instruments")
    op.drop_table("downlinks")
