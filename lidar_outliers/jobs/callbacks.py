"""Subscriber callbacks of OGC API - Processes: a job's ``successUri``, ``failedUri`` and
``inProgressUri`` receive its documents by POST.

The worker calls them (it is where a job starts, succeeds and fails; the API would have to poll
for that). A target must not reach the service's own network: every address its host name
resolves to has to be public (not private, loopback, link-local, multicast, reserved or
unspecified) unless the host is listed in ``CALLBACK_ALLOW``. The check is made when the job is
submitted and again at each call, and the call connects to the very address that was checked,
so a name that resolves to a public address first and to an internal one later (DNS rebinding)
reaches nothing inside.

Delivery is retried with exponential backoff, a bounded number of times; a callback that cannot
be delivered is logged and never changes the job.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import time
from collections.abc import Callable, Iterable
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import httpx

from lidar_outliers.errors import LidarOutliersError

log = logging.getLogger(__name__)

SUCCESS, FAILED, IN_PROGRESS = "successUri", "failedUri", "inProgressUri"
SUBSCRIBER_KEYS = (SUCCESS, FAILED, IN_PROGRESS)
#: Deliveries tried per callback, the first retry's delay (doubled each time, at most
#: MAX_DELAY) and each request's timeout: a dead target holds a worker for at most
#: 3 x 5 s + 1 s + 2 s = 18 s.
ATTEMPTS = 3
FIRST_DELAY = 1.0
MAX_DELAY = 8.0
TIMEOUT = 5.0
MAX_URI_LENGTH = 2048

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address


class CallbackRefused(LidarOutliersError):
    """A callback target the guard does not let the service call."""


class CallbackFailed(LidarOutliersError):
    """A callback target that answered with an error status."""


def is_public(address: IPAddress) -> bool:
    """Whether an address is on the public internet (an IPv4-mapped IPv6 address is judged by
    its IPv4 address)."""
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return address.is_global and not address.is_multicast


def _host_and_port(url: str) -> tuple[str, int]:
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https"):
        raise CallbackRefused(f"{url!r}: only http and https callbacks are called")
    if not parts.hostname:
        raise CallbackRefused(f"{url!r}: no host")
    if parts.username or parts.password:
        raise CallbackRefused(f"{url!r}: no credentials in callback URIs")
    try:
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError:
        raise CallbackRefused(f"{url!r}: invalid port") from None
    return parts.hostname.lower().rstrip("."), port


def resolve(host: str, port: int) -> list[IPAddress]:
    """Every address the host name resolves to (an address literal: itself)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise CallbackRefused(f"host {host!r} does not resolve: {exc}") from None
    # drop an IPv6 zone ("fe80::1%eth0"): the address alone decides
    return list(dict.fromkeys(ipaddress.ip_address(str(info[4][0]).split("%")[0])
                              for info in infos))


def check_target(url: str, allow: Iterable[str]) -> list[IPAddress]:
    """The addresses a callback to ``url`` may connect to: empty for a host listed in ``allow``
    (it is called by name), else all of its addresses, each checked to be public.

    Raises CallbackRefused naming the first address that is not."""
    if len(url) > MAX_URI_LENGTH:
        raise CallbackRefused(f"callback URI longer than {MAX_URI_LENGTH} characters")
    host, port = _host_and_port(url)
    if host in {h.lower().rstrip(".") for h in allow}:
        return []
    addresses = resolve(host, port)
    for address in addresses:
        if not is_public(address):
            raise CallbackRefused(
                f"{url!r}: host {host} resolves to {address}, which is not a public address "
                "(list the host in CALLBACK_ALLOW to allow it)")
    return addresses


def parse_subscriber(value: Any, allow: Iterable[str]) -> dict[str, str]:
    """The subscriber object of an execute request, checked: only the standard's three keys,
    each an http(s) URI the guard lets through. Raises CallbackRefused naming the key."""
    if not isinstance(value, dict):
        raise CallbackRefused("subscriber: must be an object with successUri, failedUri "
                              "and/or inProgressUri")
    unknown = sorted(set(value) - set(SUBSCRIBER_KEYS))
    if unknown:
        raise CallbackRefused(f"subscriber.{unknown[0]}: unknown; use "
                              f"{', '.join(SUBSCRIBER_KEYS)}")
    checked: dict[str, str] = {}
    for key, uri in value.items():
        if not isinstance(uri, str):
            raise CallbackRefused(f"subscriber.{key}: must be a URI string")
        try:
            check_target(uri, allow)
        except CallbackRefused as exc:
            raise CallbackRefused(f"subscriber.{key}: {exc}") from None
        checked[key] = uri
    return checked


def _post_once(url: str, document: dict[str, Any], allow: Iterable[str],
               timeout: float) -> None:
    addresses = check_target(url, allow)
    parts = urlsplit(url)
    headers = {"Content-Type": "application/json", "User-Agent": "lidar-outliers callback"}
    extensions: dict[str, Any] = {}
    target = url
    if addresses:  # connect to the checked address; the name goes in Host and TLS SNI
        address = addresses[0]
        literal = f"[{address}]" if address.version == 6 else str(address)
        netloc = literal if parts.port is None else f"{literal}:{parts.port}"
        target = urlunsplit((parts.scheme, netloc, parts.path or "/", parts.query, ""))
        headers["Host"] = parts.netloc.rsplit("@", 1)[-1]
        if parts.scheme == "https":
            extensions["sni_hostname"] = parts.hostname
    with httpx.Client(timeout=timeout, follow_redirects=False) as client:
        answer = client.post(target, json=document, headers=headers, extensions=extensions)
    if not 200 <= answer.status_code < 300:
        raise CallbackFailed(f"{url} answered {answer.status_code}")


def deliver(url: str, document: dict[str, Any], allow: Iterable[str], *,
            attempts: int = ATTEMPTS, first_delay: float = FIRST_DELAY,
            timeout: float = TIMEOUT,
            sleep: Callable[[float], None] = time.sleep) -> bool:
    """POST ``document`` as JSON to ``url``; retry failed deliveries after 1, 2, 4 ... s (at
    most MAX_DELAY) up to ``attempts`` in all. A refused target is not retried. Returns whether
    the target accepted it (any 2xx)."""
    allow = list(allow)
    for attempt in range(attempts):
        try:
            _post_once(url, document, allow, timeout)
            return True
        except CallbackRefused as exc:
            log.warning("callback not sent: %s", exc)
            return False
        except (httpx.HTTPError, CallbackFailed) as exc:
            log.warning("callback to %s failed (attempt %d of %d): %s", url, attempt + 1,
                        attempts, exc)
        if attempt + 1 < attempts:
            sleep(min(first_delay * 2**attempt, MAX_DELAY))
    return False
