"""Maps, reference images and their feature arrays.

Revision ID: 0001
Revises:
Create Date: 2026-11-21
"""

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "maps",
        sa.Column("id", sa.String(36), nullable=False),
        sa.Column("name", sa.String(255), nullable=False),
        sa.Column("description", sa.Text(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_maps"),
        sa.UniqueConstraint("name", name="uq_maps_name"),
    )
    op.create_table(
        "reference_images",
        sa.Column("id", sa.String(36), nullable=False),
        sa.Column("map_id", sa.String(36), nullable=False),
        sa.Column("name", sa.String(255), nullable=False),
        sa.Column("camera_model", sa.String(32), nullable=False),
        sa.Column("width", sa.Integer(), nullable=False),
        sa.Column("height", sa.Integer(), nullable=False),
        sa.Column("camera_params", sa.JSON(), nullable=False),
        sa.Column("qw", sa.Float(), nullable=False),
        sa.Column("qx", sa.Float(), nullable=False),
        sa.Column("qy", sa.Float(), nullable=False),
        sa.Column("qz", sa.Float(), nullable=False),
        sa.Column("tx", sa.Float(), nullable=False),
        sa.Column("ty", sa.Float(), nullable=False),
        sa.Column("tz", sa.Float(), nullable=False),
        sa.Column("num_keypoints", sa.Integer(), nullable=False),
        sa.Column("has_depth", sa.Boolean(), nullable=False),
        sa.Column("feature_model", sa.String(128), nullable=False),
        sa.Column("descriptor_model", sa.String(128), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["map_id"], ["maps.id"], name="fk_reference_images_map_id_maps", ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name="pk_reference_images"),
        sa.UniqueConstraint("map_id", "name", name="uq_reference_images_map_id_name"),
    )
    op.create_index("ix_reference_images_map_id", "reference_images", ["map_id"])
    op.create_table(
        "feature_arrays",
        sa.Column("image_id", sa.String(36), nullable=False),
        sa.Column("kind", sa.String(32), nullable=False),
        sa.Column("dtype", sa.String(16), nullable=False),
        sa.Column("shape", sa.JSON(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(
            ["image_id"],
            ["reference_images.id"],
            name="fk_feature_arrays_image_id_reference_images",
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("image_id", "kind", name="pk_feature_arrays"),
    )


def downgrade() -> None:
    op.drop_table("feature_arrays")
    op.drop_index("ix_reference_images_map_id", table_name="reference_images")
    op.drop_table("reference_images")
    op.drop_table("maps")
