"""FastAPI dependencies as ``Annotated`` aliases: one place checks auth, roles and existence.

``SessionDep`` a database session; ``CurrentUser`` any logged-in user; ``ReviewerUser`` and
``AdminUser`` role-checked users; ``SceneDep`` / ``FrameDep`` load the path's scene/frame (404)
for a logged-in user.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Path, Request
from sqlalchemy.orm import Session

from app.context import AppContext
from app.errors import Forbidden, NotAuthenticated, NotFound
from app.scenes.models import Frame, Scene
from app.users.models import User

SESSION_COOKIE = "occufly_session"


def get_ctx(request: Request) -> AppContext:
    return request.app.state.ctx


def get_session(request: Request) -> Iterator[Session]:
    with request.app.state.ctx.sessions() as session:
        yield session


CtxDep = Annotated[AppContext, Depends(get_ctx)]
SessionDep = Annotated[Session, Depends(get_session)]


def token_from(conn) -> str | None:  # noqa: ANN001 - Request or WebSocket
    auth = conn.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip() or None
    return conn.cookies.get(SESSION_COOKIE) or None


def get_current_user(request: Request, session: SessionDep) -> User:
    from app.users import service

    token = token_from(request)
    if not token:
        raise NotAuthenticated("not logged in: send the session cookie or a Bearer token")
    user = service.user_for_token(session=session, settings=request.app.state.ctx.settings,
                                  token=token)
    if user is None:
        raise NotAuthenticated("session expired or invalid: log in again")
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
              _user: CurrentUser) -> Scene:
    scene = session.get(Scene, sid)
    if scene is None:
        raise NotFound(f"scene {sid} does not exist")
    return scene


def get_frame(fid: Annotated[int, Path(ge=1, le=2**31 - 1)], session: SessionDep,
              _user: CurrentUser) -> Frame:
    frame = session.get(Frame, fid)
    if frame is None:
        raise NotFound(f"frame {fid} does not exist")
    return frame


SceneDep = Annotated[Scene, Depends(get_scene)]
FrameDep = Annotated[Frame, Depends(get_frame)]
