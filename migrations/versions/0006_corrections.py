"""label corrections: the override layer's edits, proposed mask changes, notifications

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-03 07:30:00

Issue 25: ``correction_edits`` (one row per 3D relabel; the point ids live in the scene
workspace), ``mask_proposals`` (a reviewer's proposed change of a frame's mask) and
``notifications`` (per user: a frame rejected, commented on, a proposal).
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None


def _fk(table: str, col: str, ref: str, ondelete: str) -> sa.ForeignKeyConstraint:
    return sa.ForeignKeyConstraint([col], [f'{ref}.id'], name=op.f(f'fk_{table}_{col}_{ref}'),
                                   ondelete=ondelete)


def upgrade() -> None:
    op.create_table(
        'correction_edits',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('scene_id', sa.Integer(), nullable=False),
        sa.Column('author_id', sa.Integer(), nullable=True),
        sa.Column('created_at', sa.DateTime(), nullable=False),
        sa.Column('to_class', sa.Integer(), nullable=False),
        sa.Column('comment', sa.Text(), nullable=True),
        sa.Column('n_points', sa.Integer(), nullable=False),
        sa.Column('from_hist', sa.JSON(), nullable=False),
        sa.Column('frame_id', sa.Integer(), nullable=True),
        sa.Column('state', sa.String(length=16), nullable=False),
        sa.Column('redoable', sa.Boolean(), nullable=False),
        sa.Column('undone_by_id', sa.Integer(), nullable=True),
        sa.Column('undone_at', sa.DateTime(), nullable=True),
        sa.Column('reverted_by_id', sa.Integer(), nullable=True),
        sa.Column('reverted_at', sa.DateTime(), nullable=True),
        _fk('correction_edits', 'scene_id', 'scenes', 'CASCADE'),
        _fk('correction_edits', 'author_id', 'users', 'SET NULL'),
        _fk('correction_edits', 'frame_id', 'frames', 'SET NULL'),
        _fk('correction_edits', 'undone_by_id', 'users', 'SET NULL'),
        _fk('correction_edits', 'reverted_by_id', 'users', 'SET NULL'),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_correction_edits')),
    )
    with op.batch_alter_table('correction_edits', schema=None) as b:
        b.create_index(b.f('ix_correction_edits_scene_id'), ['scene_id'], unique=False)
        b.create_index(b.f('ix_correction_edits_author_id'), ['author_id'], unique=False)
        b.create_index(b.f('ix_correction_edits_state'), ['state'], unique=False)

    op.create_table(
        'mask_proposals',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('frame_id', sa.Integer(), nullable=False),
        sa.Column('edit_id', sa.Integer(), nullable=True),
        sa.Column('author_id', sa.Integer(), nullable=True),
        sa.Column('created_at', sa.DateTime(), nullable=False),
        sa.Column('sha256', sa.String(length=64), nullable=False),
        sa.Column('change_sha256', sa.String(length=64), nullable=False),
        sa.Column('changed_px', sa.Integer(), nullable=False),
        sa.Column('status', sa.String(length=16), nullable=False),
        sa.Column('reply', sa.Text(), nullable=True),
        sa.Column('decided_by_id', sa.Integer(), nullable=True),
        sa.Column('decided_at', sa.DateTime(), nullable=True),
        sa.Column('taken_version_id', sa.Integer(), nullable=True),
        _fk('mask_proposals', 'frame_id', 'frames', 'CASCADE'),
        _fk('mask_proposals', 'edit_id', 'correction_edits', 'SET NULL'),
        _fk('mask_proposals', 'author_id', 'users', 'SET NULL'),
        _fk('mask_proposals', 'decided_by_id', 'users', 'SET NULL'),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_mask_proposals')),
    )
    with op.batch_alter_table('mask_proposals', schema=None) as b:
        b.create_index(b.f('ix_mask_proposals_frame_id'), ['frame_id'], unique=False)

    op.create_table(
        'notifications',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('user_id', sa.Integer(), nullable=False),
        sa.Column('kind', sa.String(length=32), nullable=False),
        sa.Column('scene_id', sa.Integer(), nullable=True),
        sa.Column('frame_id', sa.Integer(), nullable=True),
        sa.Column('item_id', sa.Integer(), nullable=True),
        sa.Column('text', sa.Text(), nullable=False),
        sa.Column('created_at', sa.DateTime(), nullable=False),
        sa.Column('read_at', sa.DateTime(), nullable=True),
        _fk('notifications', 'user_id', 'users', 'CASCADE'),
        _fk('notifications', 'scene_id', 'scenes', 'CASCADE'),
        _fk('notifications', 'frame_id', 'frames', 'CASCADE'),
        _fk('notifications', 'item_id', 'review_items', 'CASCADE'),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_notifications')),
    )
    with op.batch_alter_table('notifications', schema=None) as b:
        b.create_index(b.f('ix_notifications_user_id'), ['user_id'], unique=False)


def downgrade() -> None:
    with op.batch_alter_table('notifications', schema=None) as b:
        b.drop_index(b.f('ix_notifications_user_id'))
    op.drop_table('notifications')
    with op.batch_alter_table('mask_proposals', schema=None) as b:
        b.drop_index(b.f('ix_mask_proposals_frame_id'))
    op.drop_table('mask_proposals')
    with op.batch_alter_table('correction_edits', schema=None) as b:
        b.drop_index(b.f('ix_correction_edits_state'))
        b.drop_index(b.f('ix_correction_edits_author_id'))
        b.drop_index(b.f('ix_correction_edits_scene_id'))
    op.drop_table('correction_edits')
