"""Jobs: which worker runs the attempt, its heartbeat, and when the job was last handed to the
broker (with why that failed).

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-02

The database is the truth about what must run next (service.jobs): an attempt whose heartbeat
stopped is lost and taken over after a short grace, and a job whose message never reached the
broker, or was lost with it, is handed over again by the reconciler. Nullable additions, so
SQLite adds and drops them in place.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

COLUMNS = (
    ("worker", sa.String(255)),
    ("heartbeat_at", sa.DateTime(timezone=True)),
    ("enqueued_at", sa.DateTime(timezone=True)),
    ("enqueue_error", sa.Text()),
)


def upgrade() -> None:
    for name, type_ in COLUMNS:
        op.add_column("jobs", sa.Column(name, type_, nullable=True))


def downgrade() -> None:
    for name, _ in reversed(COLUMNS):
        op.drop_column("jobs", name)
