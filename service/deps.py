"""FastAPI dependencies: settings, the job service and the calling user, as ``Annotated`` types."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from lidar_outliers.jobs.settings import Settings
from lidar_outliers.jobs.store import User
from service.jobs import JobService

_bearer = HTTPBearer(auto_error=False, description="An API key from `lidar-outliers users add`.")


# async: FastAPI runs a plain ``def`` dependency in the thread pool, a hop these do not need
async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_service(request: Request) -> JobService:
    return request.app.state.service


SettingsDep = Annotated[Settings, Depends(get_settings)]
ServiceDep = Annotated[JobService, Depends(get_service)]


def current_user(
    request: Request,
    service: ServiceDep,
    _credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> User:
    return service.authenticate(request.headers.get("authorization"))


UserDep = Annotated[User, Depends(current_user)]
#: The key as documented in the OpenAPI schema, for routes that check it themselves.
BearerDep = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
