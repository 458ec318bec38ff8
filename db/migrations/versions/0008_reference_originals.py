"""The originals of reference images in the blob store: their keys and the image's SHA-256
(null for references added before originals were kept).

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-25
"""

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


COLUMNS = (
    ("original_key", sa.String(255)),
    ("original_sha256", sa.String(64)),
    ("depth_key", sa.String(255)),
)


def upgrade() -> None:
    # plain ALTER TABLE ADD COLUMN on both backends: no table rebuild (on SQLite a rebuild
    # drops the old table, which cascades to the references' feature arrays)
    for name, type_ in COLUMNS:
        op.add_column("reference_images", sa.Column(name, type_, nullable=True))


def downgrade() -> None:
    for name, _ in reversed(COLUMNS):
        if op.get_bind().dialect.name == "sqlite":  # SQLite >= 3.35 drops in place
            op.execute(f"ALTER TABLE reference_images DROP COLUMN {name}")
        else:
            op.drop_column("reference_images", name)
