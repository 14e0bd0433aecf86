"""viewer sockets counted in the database; comments by author (issue 36)

Revision ID: 0013
Revises: 0012
Create Date: 2026-12-12 10:00:00

``viewer_sockets``: one row per open ``/viewer/`` socket, with the API process holding it and
a lease that process renews (app/shared_limits.py): the per-user socket cap counts the
sockets of every API process (before: each process counted its own, N replicas allowed N x
the cap), and a killed process's rows stop counting when their lease runs out. The comments'
author gets an index: the per-user comment quota counts a user's comments of the last hour.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0013'
down_revision = '0012'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'viewer_sockets',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('username', sa.String(length=64), nullable=False),
        sa.Column('process', sa.String(length=64), nullable=False),
        sa.Column('opened_at', sa.DateTime(), nullable=False),
        sa.Column('expires_at', sa.DateTime(), nullable=False),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_viewer_sockets')),
    )
    op.create_index(op.f('ix_viewer_sockets_username'), 'viewer_sockets', ['username'],
                    unique=False)
    op.create_index(op.f('ix_viewer_sockets_process'), 'viewer_sockets', ['process'],
                    unique=False)
    op.create_index(op.f('ix_viewer_sockets_expires_at'), 'viewer_sockets', ['expires_at'],
                    unique=False)
    op.create_index(op.f('ix_review_comments_author_id'), 'review_comments', ['author_id'],
                    unique=False)


def downgrade() -> None:
    op.drop_index(op.f('ix_review_comments_author_id'), table_name='review_comments')
    op.drop_index(op.f('ix_viewer_sockets_expires_at'), table_name='viewer_sockets')
    op.drop_index(op.f('ix_viewer_sockets_process'), table_name='viewer_sockets')
    op.drop_index(op.f('ix_viewer_sockets_username'), table_name='viewer_sockets')
    op.drop_table('viewer_sockets')
