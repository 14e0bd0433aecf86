"""annotation effort: the prefills handed out, and per submitted version the prefill it
started from, its painted pixels and the pixels changed versus that prefill; the frames'
hand-out rank

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-01 20:10:00
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'prefills',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('frame_id', sa.Integer(), nullable=False),
        sa.Column('user_id', sa.Integer(), nullable=True),
        sa.Column('created_at', sa.DateTime(), nullable=False),
        sa.Column('sha256', sa.String(length=64), nullable=False),
        sa.Column('width', sa.Integer(), nullable=False),
        sa.Column('height', sa.Integer(), nullable=False),
        sa.Column('labelled_px', sa.Integer(), nullable=False),
        sa.Column('masks', sa.Integer(), nullable=True),
        sa.ForeignKeyConstraint(['frame_id'], ['frames.id'],
                                name=op.f('fk_prefills_frame_id_frames'), ondelete='CASCADE'),
        sa.ForeignKeyConstraint(['user_id'], ['users.id'],
                                name=op.f('fk_prefills_user_id_users'), ondelete='SET NULL'),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_prefills')),
    )
    with op.batch_alter_table('prefills', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_prefills_frame_id'), ['frame_id'], unique=False)

    # SQLite rebuilds the table: reflect it alone, not the tables its foreign keys name (the
    # users table's expression index lower(username) cannot be reflected: SAWarning)
    with op.batch_alter_table('mask_versions', schema=None,
                              reflect_kwargs={'resolve_fks': False}) as batch_op:
        batch_op.add_column(sa.Column('prefill_id', sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column('painted_px', sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column('changed_px', sa.Integer(), nullable=True))
        batch_op.create_foreign_key(batch_op.f('fk_mask_versions_prefill_id_prefills'),
                                    'prefills', ['prefill_id'], ['id'], ondelete='SET NULL')

    with op.batch_alter_table('frames', schema=None) as batch_op:
        batch_op.add_column(sa.Column('handout_rank', sa.Integer(), nullable=True))


# SQLite rebuilds a table in batch mode: reflect it alone, not the tables its foreign keys
# name (the users table's expression index lower(username) cannot be reflected: SAWarning)
_OWN_TABLE = {'resolve_fks': False}


def downgrade() -> None:
    with op.batch_alter_table('frames', schema=None,
                              reflect_kwargs=_OWN_TABLE) as batch_op:
        batch_op.drop_column('handout_rank')
    # SQLite rebuilds the table: reflect it alone, not the tables its foreign keys name (the
    # users table's expression index lower(username) cannot be reflected: SAWarning)
    with op.batch_alter_table('mask_versions', schema=None,
                              reflect_kwargs={'resolve_fks': False}) as batch_op:
        batch_op.drop_constraint(batch_op.f('fk_mask_versions_prefill_id_prefills'),
                                 type_='foreignkey')
        batch_op.drop_column('changed_px')
        batch_op.drop_column('painted_px')
        batch_op.drop_column('prefill_id')
    with op.batch_alter_table('prefills', schema=None,
                              reflect_kwargs=_OWN_TABLE) as batch_op:
        batch_op.drop_index(batch_op.f('ix_prefills_frame_id'))
    op.drop_table('prefills')
