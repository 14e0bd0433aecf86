"""lifting scale-out (issue 29): lift_queue.applied_by (the worker that applied an entry;
applied_seq becomes a per-scene sequence)

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-03 13:20:00
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0008'
down_revision = '0007'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('lift_queue', schema=None) as batch_op:
        batch_op.add_column(sa.Column('applied_by', sa.String(length=64), nullable=True))


def downgrade() -> None:
    # SQLite rebuilds the table: reflect it alone (see 0004)
    with op.batch_alter_table('lift_queue', schema=None,
                              reflect_kwargs={'resolve_fks': False}) as batch_op:
        batch_op.drop_column('applied_by')
