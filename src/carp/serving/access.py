"""Who may reach the server and what its access log says: the token's schemes, loopback addresses, TLS.

A token travels in the ``Authorization`` header as ``Bearer <token>``, or as ``Api-Key <token>`` (the scheme openpi's
websocket client sends); schemes compare case-insensitively, as HTTP has it (RFC 9110, section 11.1). The server
binds loopback unless told otherwise; another address needs a token or an explicit choice to serve without one
(`ServerSettings.allow_no_token`). TLS uses Python's `ssl` with a PEM certificate chain and key.
"""

import hmac
import ipaddress
import logging
import os
import ssl
from typing import Any

from websockets.datastructures import Headers

AUTHORIZATION_SCHEMES = ("bearer", "api-key")
"""Accepted ``Authorization`` schemes, compared in lower case: the usual bearer token, and openpi's client's."""


def authorized_request(headers: Headers, token: str | None) -> bool:
    """Whether `headers` carry `token` in one ``Authorization`` header of an accepted scheme (always, without a token).

    Raises:
        MultipleValuesError: the request has several ``Authorization`` headers.
    """
    if token is None:
        return True
    scheme, _, credential = headers.get("Authorization", "").strip().partition(" ")
    # The comparison runs whatever the scheme, so that its time does not tell a wrong scheme from a wrong token.
    matches = hmac.compare_digest(credential.strip().encode(), token.encode())
    return matches and scheme.lower() in AUTHORIZATION_SCHEMES


def is_loopback(host: str) -> bool:
    """Whether binding `host` accepts connections from the same host only (``localhost`` or a loopback address)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name other than localhost may resolve to any interface


def tls_context(certificate: str, key: str | None = None) -> ssl.SSLContext:
    """A server TLS context (TLS 1.2 or later) for the PEM `certificate` chain and its `key`.

    Raises:
        ValueError: a file is missing, or the two are not a certificate and its key; the message names them.
    """
    for path in (certificate, key):
        if path is not None and not os.path.isfile(path):
            raise ValueError(f"tls: {path}: no such file")
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        context.load_cert_chain(certificate, key)
    except ssl.SSLError as error:
        raise ValueError(f"tls: {certificate}: not a PEM certificate and key that match ({error.reason})") from None
    return context


class ProbeQuietLogger(logging.LoggerAdapter):
    """websockets' server logger with its per-connection lines for answered plain routes and connections demoted.

    A load balancer's health probe every few seconds would otherwise write two lines each time ("connection rejected
    (200 OK)", "connection closed"); refusals (401, 400, 503) stay at info level.
    """

    QUIET = ("connection open", "connection closed")

    def log(self, level: int, msg: Any, *args: Any, **kwargs: Any) -> None:
        """Log as the wrapped logger would, at debug level for the lines of answered routes and connections."""
        if level == logging.INFO and (
            msg in self.QUIET or (str(msg).endswith("(%d %s)") and args and 200 <= int(args[0]) < 300)
        ):
            level = logging.DEBUG
        super().log(level, msg, *args, **kwargs)
