"""Kernels: how a rejected one was refused (its code), retirement by an operator, and every
downlink that delivered each.

Revision ID: 0013
Revises: 0012
Create Date: 2026-12-04

The kernel columns are nullable additions, so SQLite adds and drops them in place without
rebuilding the kernels table, which kernel_coverage references.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0013"
down_revision: str | None = "0012"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

UTC_TIME = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.add_column("kernels", sa.Column("rejection_code", sa.String(length=32), nullable=True))
    op.add_column("kernels", sa.Column("retired_at", UTC_TIME, nullable=True))
    op.add_column("kernels", sa.Column("retirement_reason", sa.Text(), nullable=True))
    op.create_table(
        "kernel_deliveries",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("kernel_id", sa.Integer(), nullable=False),
        sa.Column("downlink_id", sa.Integer(), nullable=False),
        sa.Column("path", sa.Text(), nullable=False),
        sa.ForeignKeyConstraint(["kernel_id"], ["kernels.id"], ondelete="CASCADE",
                                name=op.f("fk_kernel_deliveries_kernel_id")),
        sa.ForeignKeyConstraint(["downlink_id"], ["downlinks.id"], ondelete="CASCADE",
                                name=op.f("fk_kernel_deliveries_downlink_id")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_kernel_deliveries")),
        sa.UniqueConstraint("kernel_id", "downlink_id",
                            name=op.f("uq_kernel_deliveries_kernel_id_downlink_id")),
    )
    op.create_index(op.f("ix_kernel_deliveries_downlink_id"), "kernel_deliveries",
                    ["downlink_id"])
    # The kernels catalogued so far were delivered by the downlink that first brought them.
    op.execute("INSERT INTO kernel_deliveries (kernel_id, downlink_id, path) "
               "SELECT id, downlink_id, path FROM kernels WHERE downlink_id IS NOT NULL")


def downgrade() -> None:
    op.drop_index(op.f("ix_kernel_deliveries_downlink_id"), table_name="kernel_deliveries")
    op.drop_table("kernel_deliveries")
    for column in ("retirement_reason", "retired_at", "rejection_code"):
        op.drop_column("kernels", column)
