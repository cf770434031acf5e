"""Images: the detector window of the array (so that a view is made without reading its label
again), and per image geometry the cone that holds what the array can see (apex at the camera,
unit axis through the array's centre, half-angle to its farthest corner), the footprint that
coverage planning selects images by without a shape.

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-03

Nullable additions, so SQLite adds and drops them in place. Rows catalogued before stay null:
their window is read from the label when needed, and an image with no cone may see anything.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

WINDOW = ("window_first_line", "window_first_sample", "window_lines", "window_samples")
CONE = ("cone_axis_x", "cone_axis_y", "cone_axis_z", "cone_half_angle_rad")


def upgrade() -> None:
    for name in WINDOW:
        op.add_column("images", sa.Column(name, sa.Integer(), nullable=True))
    for name in CONE:
        op.add_column("image_geometry", sa.Column(name, sa.Double(), nullable=True))


def downgrade() -> None:
    for name in reversed(CONE):
        op.drop_column("image_geometry", name)
    for name in reversed(WINDOW):
        op.drop_column("images", name)
