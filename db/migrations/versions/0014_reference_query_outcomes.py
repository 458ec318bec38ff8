"""References count the queries that resembled them most: those localized and those that
failed (where a map is weak).

Revision ID: 0014
Revises: 0013
Create Date: 2026-11-28
"""

import sqlalchemy as sa
from alembic import op

revision = "0014"
down_revision = "0013"
branch_labels = None
depends_on = None

COLUMNS = ("queries_localized", "queries_failed")


def upgrade() -> None:
    # plain ALTER TABLE ADD COLUMN on both backends (no table rebuild: see 0009)
    for name in COLUMNS:
        op.add_column(
            "reference_images",
            sa.Column(name, sa.BigInteger(), nullable=False, server_default="0"),
        )


def downgrade() -> None:
    sqlite = op.get_bind().dialect.name == "sqlite"
    for name in reversed(COLUMNS):
        if sqlite:
            op.execute(f"ALTER TABLE reference_images DROP COLUMN {name}")
        else:
            op.drop_column("reference_images", name)
