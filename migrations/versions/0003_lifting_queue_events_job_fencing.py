"""lifting queue, lifting status, events; job owner + heartbeat (attempt fencing)

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-01 17:00:00
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'lift_queue',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('scene_id', sa.Integer(), nullable=False),
        sa.Column('frame_id', sa.Integer(), nullable=False),
        sa.Column('frame_index', sa.Integer(), nullable=False),
        sa.Column('version_id', sa.Integer(), nullable=True),
        sa.Column('status', sa.String(length=16), nullable=False),
        sa.Column('created_at', sa.DateTime(), nullable=False),
        sa.Column('applied_at', sa.DateTime(), nullable=True),
        sa.Column('applied_seq', sa.Integer(), nullable=True),
        sa.Column('error', sa.String(length=512), nullable=True),
        sa.ForeignKeyConstraint(['frame_id'], ['frames.id'],
                                name=op.f('fk_lift_queue_frame_id_frames'), ondelete='CASCADE'),
        sa.ForeignKeyConstraint(['scene_id'], ['scenes.id'],
                                name=op.f('fk_lift_queue_scene_id_scenes'), ondelete='CASCADE'),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_lift_queue')),
    )
    with op.batch_alter_table('lift_queue', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_lift_queue_scene_id'), ['scene_id'], unique=False)
        batch_op.create_index('ix_lift_queue_status_id', ['status', 'id'], unique=False)

    op.create_table(
        'lift_status',
        sa.Column('scene_id', sa.Integer(), nullable=False),
        sa.Column('fill_state', sa.String(length=16), nullable=False),
        sa.Column('fills', sa.Integer(), nullable=False),
        sa.Column('labels_stamp', sa.String(length=64), nullable=True),
        sa.Column('last_error', sa.String(length=512), nullable=True),
        sa.Column('updated_at', sa.DateTime(), nullable=False),
        sa.ForeignKeyConstraint(['scene_id'], ['scenes.id'],
                                name=op.f('fk_lift_status_scene_id_scenes'), ondelete='CASCADE'),
        sa.PrimaryKeyConstraint('scene_id', name=op.f('pk_lift_status')),
    )

    op.create_table(
        'events',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('kind', sa.String(length=32), nullable=False),
        sa.Column('scene_id', sa.Integer(), nullable=True),
        sa.Column('payload', sa.JSON(), nullable=False),
        sa.Column('created_at', sa.DateTime(), nullable=False),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_events')),
    )
    with op.batch_alter_table('events', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_events_created_at'), ['created_at'], unique=False)

    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('owner', sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column('heartbeat_at', sa.DateTime(), nullable=True))


# SQLite rebuilds a table in batch mode: reflect it alone, not the tables its foreign keys
# name (the users table's expression index lower(username) cannot be reflected: SAWarning)
_OWN_TABLE = {'resolve_fks': False}


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None,
                              reflect_kwargs=_OWN_TABLE) as batch_op:
        batch_op.drop_column('heartbeat_at')
        batch_op.drop_column('owner')
    with op.batch_alter_table('events', schema=None,
                              reflect_kwargs=_OWN_TABLE) as batch_op:
        batch_op.drop_index(batch_op.f('ix_events_created_at'))
    op.drop_table('events')
    op.drop_table('lift_status')
    with op.batch_alter_table('lift_queue', schema=None,
                              reflect_kwargs=_OWN_TABLE) as batch_op:
        batch_op.drop_index('ix_lift_queue_status_id')
        batch_op.drop_index(batch_op.f('ix_lift_queue_scene_id'))
    op.drop_table('lift_queue')
