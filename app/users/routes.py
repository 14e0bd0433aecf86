from __future__ import annotations

from fastapi import APIRouter, Request, Response

from app.deps import SESSION_COOKIE, AdminUser, CtxDep, CurrentUser, SessionDep, token_from
from app.users import service
from app.users.schemas import LoginIn, LoginOut, UserCreate, UserListItem, UserOut

router = APIRouter(prefix="/api", tags=["users"])


@router.post("/auth/login", response_model=LoginOut,
             responses={401: {"description": "wrong credentials"}, 429: {"description": "throttled"}})
def login(body: LoginIn, request: Request, response: Response, session: SessionDep, ctx: CtxDep):
    ip = request.client.host if request.client else "unknown"
    user, token = service.login(session=session, settings=ctx.settings, username=body.username,
                                password=body.password, client_ip=ip)
    response.set_cookie(SESSION_COOKIE, token, httponly=True, samesite="lax",
                        secure=not ctx.settings.is_dev and request.url.scheme == "https",
                        max_age=ctx.settings.session_seconds, path="/")
    return LoginOut(user=UserOut.model_validate(user), token=token)


@router.post("/auth/logout", status_code=204, response_class=Response)
def logout(request: Request, session: SessionDep, ctx: CtxDep, _user: CurrentUser) -> Response:
    token = token_from(request)
    if token:
        service.logout(session=session, settings=ctx.settings, token=token)
    response = Response(status_code=204)
    response.delete_cookie(SESSION_COOKIE, path="/")
    return response


@router.get("/auth/me", response_model=UserOut)
def me(user: CurrentUser):
    return user


@router.get("/users", response_model=list[UserListItem])
def list_users(session: SessionDep, _admin: AdminUser):
    return service.list_users(session=session)


@router.post("/users", response_model=UserListItem, status_code=201)
def create_user(body: UserCreate, session: SessionDep, _admin: AdminUser):
    return service.create_user(session=session, username=body.username, password=body.password,
                               role=body.role)
