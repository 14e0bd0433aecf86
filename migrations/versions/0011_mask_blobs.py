"""mask blobs (issue 36): one row per blob of the content store, claimed with its references

Revision ID: 0011
Revises: 0010
Create Date: 2026-12-10 10:00:00

``mask_blobs``: the sha256 of every stored mask PNG. A save upserts the row in the transaction
that adds its version (prefill, proposal), and a scene deletion removes a blob only after
locking its row and finding no reference (app/blobs.py) -- before, a deletion could remove
a blob another scene's concurrent save had just found present. Filled here from every digest
the versions, prefills and proposals reference. The digest columns of versions and prefills
get an index: the reference check looks them up by digest.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0011'
down_revision = '0010'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'mask_blobs',
        sa.Column('sha256', sa.String(length=64), nullable=False),
        sa.Column('touched_at', sa.DateTime(), nullable=False),
        sa.PrimaryKeyConstraint('sha256', name=op.f('pk_mask_blobs')),
    )
    op.execute(
        "INSERT INTO mask_blobs (sha256, touched_at) SELECT sha256, CURRENT_TIMESTAMP FROM ("
        "SELECT sha256 FROM mask_versions UNION SELECT sha256 FROM prefills "
        "UNION SELECT sha256 FROM mask_proposals UNION SELECT change_sha256 FROM mask_proposals"
        ") AS used")
    # plain CREATE INDEX on both databases (no SQLite table rebuild)
    op.create_index(op.f('ix_mask_versions_sha256'), 'mask_versions', ['sha256'], unique=False)
    op.create_index(op.f('ix_prefills_sha256'), 'prefills', ['sha256'], unique=False)


def downgrade() -> None:
    op.drop_index(op.f('ix_prefills_sha256'), table_name='prefills')
    op.drop_index(op.f('ix_mask_versions_sha256'), table_name='mask_versions')
    op.drop_table('mask_blobs')
