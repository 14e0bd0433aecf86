"""hardening and accounts: case-insensitive user names, session details, reviewed version,
scene membership, audit log

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-01 17:30:00
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None


def upgrade() -> None:
    conn = op.get_bind()
    dupes = conn.execute(sa.text(
        "SELECT lower(username) FROM users GROUP BY lower(username) HAVING count(*) > 1")).all()
    if dupes:
        names = ", ".join(sorted(r[0] for r in dupes))
        raise RuntimeError(
            f"user names differing only in case exist ({names}); rename or delete all but one "
            "of each (user names become case-insensitive) and run the upgrade again")
    op.create_index('uq_users_username_lower', 'users', [sa.text('lower(username)')], unique=True)

    with op.batch_alter_table('auth_tokens', schema=None) as batch_op:
        batch_op.add_column(sa.Column('client_ip', sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column('user_agent', sa.String(length=256), nullable=True))
        batch_op.add_column(sa.Column('last_seen_at', sa.DateTime(), nullable=True))

    with op.batch_alter_table('frames', schema=None) as batch_op:
        batch_op.add_column(sa.Column('reviewed_version_id', sa.Integer(), nullable=True))
    # frames reviewed before this revision: their decision was about the then-current version
    conn.execute(sa.text("UPDATE frames SET reviewed_version_id = current_version_id "
                         "WHERE state IN ('accepted', 'rejected')"))

    op.create_table('scene_members',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('scene_id', sa.Integer(), nullable=False),
    sa.Column('user_id', sa.Integer(), nullable=False),
    sa.Column('created_at', sa.DateTime(), nullable=False),
    sa.ForeignKeyConstraint(['scene_id'], ['scenes.id'], name=op.f('fk_scene_members_scene_id_scenes'), ondelete='CASCADE'),
    sa.ForeignKeyConstraint(['user_id'], ['users.id'], name=op.f('fk_scene_members_user_id_users'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_scene_members')),
    sa.UniqueConstraint('scene_id', 'user_id', name=op.f('uq_scene_members_scene_id'))
    )
    with op.batch_alter_table('scene_members', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_scene_members_scene_id'), ['scene_id'], unique=False)
        batch_op.create_index(batch_op.f('ix_scene_members_user_id'), ['user_id'], unique=False)
    # existing deployments keep working: every existing annotator/reviewer becomes a member of
    # every existing scene (admins then narrow it down)
    conn.execute(sa.text(
        "INSERT INTO scene_members (scene_id, user_id, created_at) "
        "SELECT s.id, u.id, CURRENT_TIMESTAMP FROM scenes s CROSS JOIN users u "
        "WHERE u.role IN ('annotator', 'reviewer')"))

    op.create_table('audit_events',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('at', sa.DateTime(), nullable=False),
    sa.Column('actor_id', sa.Integer(), nullable=True),
    sa.Column('actor', sa.String(length=64), nullable=True),
    sa.Column('action', sa.String(length=32), nullable=False),
    sa.Column('scene_id', sa.Integer(), nullable=True),
    sa.Column('frame_id', sa.Integer(), nullable=True),
    sa.Column('target', sa.String(length=256), nullable=True),
    sa.Column('client_ip', sa.String(length=64), nullable=True),
    sa.Column('detail', sa.JSON(), nullable=True),
    sa.ForeignKeyConstraint(['actor_id'], ['users.id'], name=op.f('fk_audit_events_actor_id_users'), ondelete='SET NULL'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_audit_events'))
    )
    with op.batch_alter_table('audit_events', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_audit_events_action'), ['action'], unique=False)
        batch_op.create_index(batch_op.f('ix_audit_events_actor_id'), ['actor_id'], unique=False)
        batch_op.create_index(batch_op.f('ix_audit_events_at'), ['at'], unique=False)
        batch_op.create_index(batch_op.f('ix_audit_events_scene_id'), ['scene_id'], unique=False)


# SQLite rebuilds a table in batch mode: reflect it alone, not the tables its foreign keys
# name (the users table's expression index lower(username) cannot be reflected: SAWarning)
_OWN_TABLE = {'resolve_fks': False}


def downgrade() -> None:
    op.drop_table('audit_events')
    op.drop_table('scene_members')
    with op.batch_alter_table('frames', schema=None,
                              reflect_kwargs=_OWN_TABLE) as batch_op:
        batch_op.drop_column('reviewed_version_id')
    with op.batch_alter_table('auth_tokens', schema=None,
                              reflect_kwargs=_OWN_TABLE) as batch_op:
        batch_op.drop_column('last_seen_at')
        batch_op.drop_column('user_agent')
        batch_op.drop_column('client_ip')
    op.drop_index('uq_users_username_lower', table_name='users')
