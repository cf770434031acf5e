"""A version kind `lidar`: the model made from the lidar alone; lidar tracks' crossovers
(issue 46).

Revision ID: 0016
Revises: 0015
Create Date: 2026-12-06

model_versions.kind is a VARCHAR checked by the constraint ck_model_versions_model_kind; the
constraint is replaced by one that also admits 'lidar'. PostgreSQL alters it in place; SQLite
rebuilds the table (batch mode), which service.db.migration_transaction runs with foreign keys
off so that the lineage rows referencing model_versions stay as they are. Downgrading refuses
while a version of kind lidar exists rather than lose it.

lidar_tracks gains two nullable columns: crossovers (count) and crossover_rms_km.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0016"
down_revision: str | None = "0015"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

KINDS = ("start", "photogrammetric", "refined", "imported")


def _kind(*kinds: str) -> sa.Enum:
    return sa.Enum(*kinds, name="model_kind", native_enum=False, create_constraint=True, length=16)


def _replace_kind_check(old: tuple[str, ...], new: tuple[str, ...]) -> None:
    with op.batch_alter_table("model_versions") as batch_op:
        batch_op.alter_column("kind", existing_type=_kind(*old), type_=_kind(*new),
                              existing_nullable=False)


def upgrade() -> None:
    _replace_kind_check(KINDS, (*KINDS, "lidar"))
    with op.batch_alter_table("lidar_tracks") as batch_op:
        batch_op.add_column(sa.Column("crossovers", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("crossover_rms_km", sa.Double(), nullable=True))


def downgrade() -> None:
    lidar = op.get_bind().execute(
        sa.text("SELECT count(*) FROM model_versions WHERE kind = 'lidar'")).scalar_one()
    if lidar:
        raise RuntimeError(f"{lidar} model versions are of kind lidar; the downgrade would "
                           "leave them unreadable: delete them first")
    with op.batch_alter_table("lidar_tracks") as batch_op:
        batch_op.drop_column("crossover_rms_km")
        batch_op.drop_column("crossovers")
    _replace_kind_check((*KINDS, "lidar"), KINDS)
