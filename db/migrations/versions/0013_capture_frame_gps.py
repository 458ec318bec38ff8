"""Capture frames keep the device's GPS fix (or their EXIF's), which the references they
become carry.

Revision ID: 0013
Revises: 0012
Create Date: 2026-11-27
"""

import sqlalchemy as sa
from alembic import op

revision = "0013"
down_revision = "0012"
branch_labels = None
depends_on = None

GPS_COLUMNS = ("gps_latitude", "gps_longitude", "gps_height", "gps_accuracy_m")


def upgrade() -> None:
    # plain ALTER TABLE ADD COLUMN on both backends (no table rebuild: see 0009)
    for name in GPS_COLUMNS:
        op.add_column("capture_frames", sa.Column(name, sa.Float(), nullable=True))


def downgrade() -> None:
    sqlite = op.get_bind().dialect.name == "sqlite"
    for name in reversed(GPS_COLUMNS):
        if sqlite:
            op.execute(f"ALTER TABLE capture_frames DROP COLUMN {name}")
        else:
            op.drop_column("capture_frames", name)
