"""Callback URLs: what a job may name (checked at submission) and where a delivery may go (checked again at
delivery, after DNS resolution).

Deliveries go only to public addresses: not private, loopback, link-local (cloud metadata), shared, reserved or
multicast ones, in any spelling (``2130706433``, ``0x7f.0.0.1``, ``127.1``, ``[::1]``, ``::ffff:10.0.0.1``). A
host named in the setting ``callback_allowed_hosts`` may resolve to any address (on-premises receivers). URLs
with credentials (``user:pass@``) are refused. The worker connects to the address it checked (no second DNS
lookup a rebinding name could change) and never follows redirects.
"""

from __future__ import annotations

import ipaddress
import socket
from dataclasses import dataclass
from urllib.parse import urlsplit

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
INTERNAL_SUFFIXES = (".localhost", ".local", ".internal", ".lan", ".home.arpa", ".intranet", ".corp")


class CallbackRefused(ValueError):
    """A callback URL or address that may not be used; the message says why (and names no remote answer)."""


@dataclass(frozen=True)
class Target:
    """Where one delivery connects: the checked address, and the name to send as Host and TLS server name."""

    url: str  # the URL with the host replaced by the checked address
    host: str
    address: str


def literal_address(host: str) -> IPAddress | None:
    """``host`` as an IP address when it is one in any spelling the resolver accepts (``127.1``, ``0x7f.1``,
    ``2130706433``, ``[::1]``), else None."""
    bare = host.strip("[]")
    try:
        return ipaddress.ip_address(bare)
    except ValueError:
        pass
    try:
        return ipaddress.IPv4Address(socket.inet_aton(bare))
    except (OSError, ValueError):
        return None


def is_public(ip: IPAddress) -> bool:
    """True for a globally routable unicast address (an IPv4-mapped IPv6 address is judged as its IPv4)."""
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return bool(ip.is_global) and not ip.is_multicast and not ip.is_unspecified


def _allowed(host: str, allowed_hosts: list[str]) -> bool:
    return host.lower().rstrip(".") in {h.lower().rstrip(".") for h in allowed_hosts}


def check_url(url: str, allowed_hosts: list[str], max_length: int) -> str:
    """The URL when a job may name it; raises CallbackRefused with the reason otherwise (no DNS lookup here)."""
    if len(url) > max_length:
        raise CallbackRefused(f"callback_url is longer than {max_length} characters")
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https"):
        raise CallbackRefused("callback_url must be an http:// or https:// URL")
    if "@" in parts.netloc or parts.username or parts.password:
        raise CallbackRefused("callback_url must not contain credentials (user:password@); authenticate the "
                              "deliveries with their signature header instead")
    host = (parts.hostname or "").rstrip(".")
    if not host:
        raise CallbackRefused("callback_url has no host")
    try:
        parts.port  # noqa: B018 (validates the port)
    except ValueError as exc:
        raise CallbackRefused("callback_url has an invalid port") from exc
    if _allowed(host, allowed_hosts):
        return url
    ip = literal_address(host)
    if ip is not None:
        if not is_public(ip):
            raise CallbackRefused(f"callback_url points at {host}, which is not a public address (private, "
                                  "loopback, link-local or reserved)")
        return url
    if host == "localhost" or host.endswith(INTERNAL_SUFFIXES) or "." not in host:
        raise CallbackRefused(f"callback_url names {host!r}, an internal host name; callbacks go to public hosts "
                              "(an operator can allow named hosts with RETARGET_API_CALLBACK_ALLOWED_HOSTS)")
    return url


def resolve(url: str, allowed_hosts: list[str]) -> Target:
    """Check ``url`` again and resolve its host; every address it resolves to must be public unless the host is
    allowed. Raises CallbackRefused."""
    parts = urlsplit(url)
    check_url(url, allowed_hosts, max_length=1 << 16)
    host = (parts.hostname or "").rstrip(".")
    port = parts.port or (443 if parts.scheme == "https" else 80)
    try:
        infos = socket.getaddrinfo(host.strip("[]"), port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as exc:
        raise CallbackRefused("the callback host does not resolve") from exc
    addresses = [ipaddress.ip_address(str(info[4][0]).split("%", 1)[0]) for info in infos]
    if not addresses:
        raise CallbackRefused("the callback host does not resolve")
    if not _allowed(host, allowed_hosts) and not all(is_public(a) for a in addresses):
        raise CallbackRefused("the callback host resolves to an address that is not public; deliveries go only "
                              "to public addresses")
    chosen = addresses[0]
    shown = f"[{chosen}]" if chosen.version == 6 else str(chosen)
    netloc = f"{shown}:{port}"
    rest = url.split(parts.netloc, 1)[1] if parts.netloc else ""
    return Target(url=f"{parts.scheme}://{netloc}{rest}", host=host, address=str(chosen))
