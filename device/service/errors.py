"""One middleware that maps every error to a JSON body: ``{"error": message, "param": name|null,
"status": code}``.

- :class:`lightprobe.core.errors.InputError` -> 400 (its ``param`` names the field at fault);
- aiohttp's HTTP exceptions (404 unknown path, 405, 413 oversized body, ...) keep their status and
  get a JSON body instead of text;
- camera errors -> 503 (the probe has no current data);
- anything else -> 500, logged with its traceback; the service keeps serving.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Awaitable, Callable
from typing import Any

from aiohttp import web

from lightprobe.core.errors import InputError

__all__ = ["ApiError", "error_middleware", "json_error"]

log = logging.getLogger(__name__)

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


class ApiError(Exception):
    """An error with an explicit HTTP status (e.g. 401 missing token, 503 no data yet)."""

    def __init__(self, status: int, message: str, *, param: str | None = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status, self.param, self.headers = status, param, headers or {}


def json_error(status: int, message: str, param: str | None = None,
               headers: dict[str, str] | None = None) -> web.Response:
    body: dict[str, Any] = {"error": message, "param": param, "status": status}
    return web.Response(status=status, text=json.dumps(body), content_type="application/json",
                        headers=headers)


@web.middleware
async def error_middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
    from lightprobe.drivers.base import CameraError

    try:
        return await handler(request)
    except ApiError as e:
        return json_error(e.status, str(e), e.param, e.headers)
    except InputError as e:
        return json_error(400, str(e), e.param)
    except web.HTTPException as e:
        if e.status < 400:  # redirects and the like pass through
            raise
        param = "body" if e.status == 413 else ("path" if e.status == 404 else None)
        headers = {k: v for k, v in e.headers.items() if k.lower() in ("allow", "www-authenticate")}
        return json_error(e.status, e.reason if e.status != 413 else str(e.text or e.reason),
                          param, headers)
    except CameraError as e:
        return json_error(503, f"camera error: {e}", "camera")
    except (ConnectionResetError, TimeoutError):
        raise
    except Exception:
        log.exception("unhandled error in %s %s", request.method, request.path)
        return json_error(500, "internal error (see the service log)")
