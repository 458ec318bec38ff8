"""Maps on the globe: a map's geo-registration and the references' GPS positions.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-24
"""

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None

GPS_COLUMNS = ("gps_latitude", "gps_longitude", "gps_height", "gps_accuracy_m")


def upgrade() -> None:
    with op.batch_alter_table("maps") as batch:
        batch.add_column(sa.Column("geo_registration", sa.JSON(), nullable=True))
    with op.batch_alter_table("reference_images") as batch:
        for name in GPS_COLUMNS:
            batch.add_column(sa.Column(name, sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("reference_images") as batch:
        for name in reversed(GPS_COLUMNS):
            batch.drop_column(name)
    with op.batch_alter_table("maps") as batch:
        batch.drop_column("geo_registration")
