"""FastAPI dependencies as ``Annotated`` aliases: one place checks auth, roles and existence.

``SessionDep`` a database session; ``CurrentUser`` any logged-in user; ``ReviewerUser`` and
``AdminUser`` role-checked users; ``SceneDep`` / ``FrameDep`` load the path's scene/frame (404)
for a logged-in user who may see that scene (admins: every scene; annotators and reviewers:
the scenes they are members of, else 403). ``ClientIp`` the caller's address (X-Forwarded-For
only from configured proxies).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Path, Request
from sqlalchemy.orm import Session

from app.context import AppContext
from app.errors import Forbidden, NotAuthenticated, NotFound
from app.scenes.membership import check_member, is_member  # noqa: F401 - re-exported for routes
from app.scenes.models import Frame, Scene
from app.security import SESSION_COOKIE, client_ip, token_from  # noqa: F401 - re-exported
from app.users import service
from app.users.models import User


def get_ctx(request: Request) -> AppContext:
    return request.app.state.ctx


def get_session(request: Request) -> Iterator[Session]:
    with request.app.state.ctx.sessions() as session:
        yield session


CtxDep = Annotated[AppContext, Depends(get_ctx)]
SessionDep = Annotated[Session, Depends(get_session)]


def client_ip_of(conn: Request) -> str:
    peer = conn.client.host if conn.client else None
    return client_ip(peer, conn.headers.get("x-forwarded-for"),
                     conn.app.state.ctx.settings.trusted_proxies)


ClientIp = Annotated[str, Depends(client_ip_of)]


def get_current_user(request: Request, session: SessionDep) -> User:
    token = token_from(request)
    if not token:
        raise NotAuthenticated("not logged in: send the session cookie or a Bearer token")
    row = service.session_for_token(session=session, settings=request.app.state.ctx.settings,
                                    token=token)
    user = session.get(User, row.user_id) if row is not None else None
    if user is None or not user.active:
        raise NotAuthenticated("session expired or invalid: log in again")
    request.state.auth_session_id = row.id
    return user


CurrentUser = Annotated[User, Depends(get_current_user)]


def require_roles(*roles: str):
    def check(user: CurrentUser) -> User:
        if user.role not in roles:
            raise Forbidden(f"this action needs role {' or '.join(roles)}; you are {user.role}")
        return user

    return check


AnnotatorUser = Annotated[User, Depends(require_roles("annotator", "admin"))]
ReviewerUser = Annotated[User, Depends(require_roles("reviewer", "admin"))]
AdminUser = Annotated[User, Depends(require_roles("admin"))]


def get_scene(sid: Annotated[int, Path(ge=1, le=2**31 - 1)], session: SessionDep,
              user: CurrentUser) -> Scene:
    scene = session.get(Scene, sid)
    if scene is None:
        raise NotFound(f"scene {sid} does not exist")
    check_member(session, user, scene.id)
    return scene


def get_frame(fid: Annotated[int, Path(ge=1, le=2**31 - 1)], session: SessionDep,
              user: CurrentUser) -> Frame:
    frame = session.get(Frame, fid)
    if frame is None:
        raise NotFound(f"frame {fid} does not exist")
    check_member(session, user, frame.scene_id)
    return frame


SceneDep = Annotated[Scene, Depends(get_scene)]
FrameDep = Annotated[Frame, Depends(get_frame)]
