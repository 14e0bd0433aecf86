"""suspect marks (issue 23): reviewers' done / dismissed verdicts on a scene's suspects

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-04 14:30:00

``suspect_marks``: one row per (scene, suspect key) -- the key is the region's smallest point
id, stable across re-rankings -- with the status (done / dismissed), who set it and when.
Before, the marks lived in each reviewer's browser (localStorage); the reviewer page moves
those into this table the first time it loads a scene's suspects.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0010'
down_revision = '0009'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'suspect_marks',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('scene_id', sa.Integer(), nullable=False),
        sa.Column('key', sa.String(length=32), nullable=False),
        sa.Column('status', sa.String(length=16), nullable=False),
        sa.Column('author_id', sa.Integer(), nullable=True),
        sa.Column('updated_at', sa.DateTime(), nullable=False),
        sa.ForeignKeyConstraint(['scene_id'], ['scenes.id'],
                                name=op.f('fk_suspect_marks_scene_id_scenes'), ondelete='CASCADE'),
        sa.ForeignKeyConstraint(['author_id'], ['users.id'],
                                name=op.f('fk_suspect_marks_author_id_users'), ondelete='SET NULL'),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_suspect_marks')),
        sa.UniqueConstraint('scene_id', 'key', name='uq_suspect_marks_scene_id_key'),
    )
    with op.batch_alter_table('suspect_marks', schema=None) as b:
        b.create_index(b.f('ix_suspect_marks_scene_id'), ['scene_id'], unique=False)


def downgrade() -> None:
    with op.batch_alter_table('suspect_marks', schema=None) as b:
        b.drop_index(b.f('ix_suspect_marks_scene_id'))
    op.drop_table('suspect_marks')
