"""Limits on what a request may carry, checked before any route parses it.

JSON bodies are bounded in size and nesting depth and must parse (a 5000-digit
number or 100 000 nested brackets would otherwise escape as a 500 from the
parser); URLs, query strings and JSON strings may not hold NUL or other
control characters (a path with a NUL cannot be opened, a name with one
cannot be stored). Each refusal is a 4xx problem response.

Every response carries ``Server-Timing: app;dur=<ms>``, the time from the
request reaching the app to its response starting: a client that sees more
than that waited for the network, the event loop or a CPU.
"""

from __future__ import annotations

import json
import re
import time
from typing import Any
from urllib.parse import unquote

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from terrasift.service.problems import PROBLEM_TYPES, problem_response

MAX_JSON_BYTES = 1024 * 1024
MAX_JSON_DEPTH = 32
# C0 controls and DEL, except tab, newline and carriage return (filter texts hold lines)
CONTROL_CHARS = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]")


class RequestRefused(ValueError):
    """What is wrong with a request, and the problem slug to answer with."""

    def __init__(self, slug: str, detail: str):
        super().__init__(detail)
        self.slug = slug


def json_depth(text: str | bytes) -> int:
    """Deepest bracket nesting of a JSON text, brackets inside strings ignored (no parsing)."""
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def check_strings(value: Any, where: str = "body") -> None:
    """Refuse control characters in any string (keys included) of a decoded JSON value."""
    stack = [(value, where)]
    while stack:
        item, at = stack.pop()
        if isinstance(item, str):
            if CONTROL_CHARS.search(item):
                raise RequestRefused("invalid-request", f"{at} holds a control character")
        elif isinstance(item, dict):
            for k, v in item.items():
                if CONTROL_CHARS.search(str(k)):
                    raise RequestRefused(
                        "invalid-request", f"a key in {at} holds a control character"
                    )
                stack.append((v, f"{at}.{k}"))
        elif isinstance(item, list):
            stack.extend((v, f"{at}[{i}]") for i, v in enumerate(item))


def load_json(text: str | bytes, what: str = "the JSON body") -> Any:
    """Decode bounded JSON: size, depth, numbers Python can hold, no control characters."""
    if len(text) > MAX_JSON_BYTES:
        raise RequestRefused(
            "payload-too-large", f"{what} has {len(text)} bytes; at most {MAX_JSON_BYTES}"
        )
    if json_depth(text) > MAX_JSON_DEPTH:
        raise RequestRefused("invalid-request", f"{what} nests deeper than {MAX_JSON_DEPTH} levels")
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RequestRefused(
            "invalid-request",
            f"{what} is not JSON: {exc.msg} at line {exc.lineno} column {exc.colno}",
        ) from None
    except (ValueError, RecursionError) as exc:  # e.g. an integer of more than 4300 digits
        raise RequestRefused("invalid-request", f"{what} cannot be read: {exc}") from None
    check_strings(value, what)
    return value


class RequestGuard:
    """ASGI middleware: refuse oversized, too deep or unparsable JSON bodies and control
    characters in the URL before the app sees the request."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        send = _timed(send, time.perf_counter())
        try:
            self._check_url(scope)
            ctype = _header(scope, b"content-type").split(";")[0].strip().lower()
            if ctype.endswith("json") and scope["method"] in ("POST", "PUT", "PATCH"):
                body = await _read_body(receive, MAX_JSON_BYTES)
                if body.strip():
                    load_json(body)
                receive = _replay(body, receive)
        except RequestRefused as exc:
            response = problem_response(None, PROBLEM_TYPES[exc.slug], str(exc))
            await response(scope, receive, send)
            return
        await self.app(scope, receive, send)

    @staticmethod
    def _check_url(scope: Scope) -> None:
        path = scope.get("path", "")
        query = unquote(scope.get("query_string", b"").decode("latin-1"))
        if CONTROL_CHARS.search(path) or CONTROL_CHARS.search(query):
            raise RequestRefused("invalid-request", "the URL holds a control character")


def _timed(send: Send, start: float) -> Send:
    """``send`` that adds the app's time so far to the response headers."""

    async def timed(message: Message) -> None:
        if message["type"] == "http.response.start":
            ms = 1000 * (time.perf_counter() - start)
            headers = [*message.get("headers", []), (b"server-timing", b"app;dur=%.2f" % ms)]
            message = {**message, "headers": headers}
        await send(message)

    return timed


def _header(scope: Scope, name: bytes) -> str:
    for key, value in scope.get("headers", []):
        if key.lower() == name:
            return value.decode("latin-1")
    return ""


async def _read_body(receive: Receive, limit: int) -> bytes:
    chunks, size = [], 0
    while True:
        message = await receive()
        if message["type"] == "http.disconnect":
            break
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > limit:
            raise RequestRefused("payload-too-large", f"the JSON body exceeds {limit} bytes")
        chunks.append(chunk)
        if not message.get("more_body", False):
            break
    return b"".join(chunks)


def _replay(body: bytes, then: Receive) -> Receive:
    """The body already read, then the client's own messages (a disconnect)."""
    sent = False

    async def receive() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await then()

    return receive
