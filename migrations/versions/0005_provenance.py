"""mask provenance: version states, source, decisions, the frame's voting version; job
request idempotency keys

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-03 07:30:00

``mask_versions.kind`` becomes the version's state (draft, submitted, accepted, rejected,
conflict, imported; docs/provenance.md). Existing rows: the version a frame's last review
decided on (``frames.reviewed_version_id`` of an accepted / rejected frame) takes that state.
``frames.voting_version_id``: the newest submitted / accepted / imported version of each
frame, unless a rejected version is newer. Frames whose current version is not their voting
version (a draft, a rejected version) get a lifting queue entry for their voting version (or
for the removal of their votes), so the lifting worker drops the draft votes it counted
before this revision.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None


def upgrade() -> None:
    # SQLite rebuilds the table: reflect it alone, not the tables its foreign keys name (the
    # users table's expression index lower(username) cannot be reflected: SAWarning)
    with op.batch_alter_table('mask_versions', schema=None,
                              reflect_kwargs={'resolve_fks': False}) as batch_op:
        batch_op.add_column(sa.Column('source', sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column('decided_by_id', sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column('decided_at', sa.DateTime(), nullable=True))
        batch_op.create_foreign_key(batch_op.f('fk_mask_versions_decided_by_id_users'),
                                    'users', ['decided_by_id'], ['id'], ondelete='SET NULL')
    with op.batch_alter_table('frames', schema=None) as batch_op:
        batch_op.add_column(sa.Column('voting_version_id', sa.Integer(), nullable=True))
    op.create_table(
        'job_request_keys',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('user_id', sa.Integer(), nullable=False),
        sa.Column('key', sa.String(length=128), nullable=False),
        sa.Column('request_hash', sa.String(length=64), nullable=False),
        sa.Column('job_id', sa.Integer(), nullable=False),
        sa.Column('created_at', sa.DateTime(), nullable=False),
        sa.ForeignKeyConstraint(['job_id'], ['jobs.id'],
                                name=op.f('fk_job_request_keys_job_id_jobs'), ondelete='CASCADE'),
        sa.ForeignKeyConstraint(['user_id'], ['users.id'],
                                name=op.f('fk_job_request_keys_user_id_users'), ondelete='CASCADE'),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_job_request_keys')),
        sa.UniqueConstraint('user_id', 'key', name=op.f('uq_job_request_keys_user_id')),
    )
    _migrate_rows()


def _migrate_rows() -> None:
    conn = op.get_bind()
    mv = sa.table('mask_versions', sa.column('id', sa.Integer), sa.column('frame_id', sa.Integer),
                  sa.column('kind', sa.String), sa.column('decided_by_id', sa.Integer),
                  sa.column('decided_at', sa.DateTime))
    fr = sa.table('frames', sa.column('id', sa.Integer), sa.column('scene_id', sa.Integer),
                  sa.column('index', sa.Integer), sa.column('state', sa.String),
                  sa.column('current_version_id', sa.Integer),
                  sa.column('reviewed_version_id', sa.Integer),
                  sa.column('reviewed_by_id', sa.Integer), sa.column('reviewed_at', sa.DateTime),
                  sa.column('voting_version_id', sa.Integer))
    lq = sa.table('lift_queue', sa.column('scene_id', sa.Integer), sa.column('frame_id', sa.Integer),
                  sa.column('frame_index', sa.Integer), sa.column('version_id', sa.Integer),
                  sa.column('status', sa.String), sa.column('created_at', sa.DateTime))
    decided = conn.execute(sa.select(fr.c.reviewed_version_id, fr.c.state, fr.c.reviewed_by_id,
                                     fr.c.reviewed_at)
                           .where(fr.c.state.in_(('accepted', 'rejected')),
                                  fr.c.reviewed_version_id.is_not(None))).all()
    for vid, state, by, at in decided:
        conn.execute(sa.update(mv).where(mv.c.id == vid, mv.c.kind.in_(('submitted', 'draft')))
                     .values(kind=state, decided_by_id=by, decided_at=at))
    rows = conn.execute(sa.select(mv.c.id, mv.c.frame_id, mv.c.kind).order_by(mv.c.id)).all()
    voting: dict[int, int | None] = {}
    for vid, fid, kind in rows:  # id order: the newest decides
        if kind in ('submitted', 'accepted', 'imported'):
            voting[fid] = vid
        elif kind == 'rejected':
            voting[fid] = None
    frames = conn.execute(sa.select(fr.c.id, fr.c.scene_id, fr.c.index,
                                    fr.c.current_version_id)
                          .where(fr.c.current_version_id.is_not(None))).all()
    from datetime import UTC, datetime

    now = datetime.now(UTC).replace(tzinfo=None)
    for fid, sid, index, current in frames:
        vote = voting.get(fid)
        if vote is not None:
            conn.execute(sa.update(fr).where(fr.c.id == fid).values(voting_version_id=vote))
        if vote != current:  # the worker may count this frame's draft / rejected version
            conn.execute(sa.insert(lq).values(scene_id=sid, frame_id=fid, frame_index=index,
                                              version_id=vote, status='pending', created_at=now))


def downgrade() -> None:
    conn = op.get_bind()
    mv = sa.table('mask_versions', sa.column('kind', sa.String))
    conn.execute(sa.update(mv).where(mv.c.kind.in_(('accepted', 'rejected', 'imported')))
                 .values(kind='submitted'))
    op.drop_table('job_request_keys')
    with op.batch_alter_table('frames', schema=None,
                              reflect_kwargs={'resolve_fks': False}) as batch_op:
        batch_op.drop_column('voting_version_id')
    # SQLite rebuilds the table: reflect it alone, not the tables its foreign keys name (the
    # users table's expression index lower(username) cannot be reflected: SAWarning)
    with op.batch_alter_table('mask_versions', schema=None,
                              reflect_kwargs={'resolve_fks': False}) as batch_op:
        batch_op.drop_constraint(batch_op.f('fk_mask_versions_decided_by_id_users'),
                                 type_='foreignkey')
        batch_op.drop_column('decided_at')
        batch_op.drop_column('decided_by_id')
        batch_op.drop_column('source')
