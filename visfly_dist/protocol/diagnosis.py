"""Why a Zenoh client could not join: unreachable router, TLS failure or refused credentials.

Zenoh reports every failed open the same way (``Unable to connect to any of [...]``), so after a
failure we probe the endpoints ourselves, in order of the layers:

1. TCP: nothing accepts a connection at any endpoint -> :class:`RouterUnreachableError`.
2. TLS (``tls/`` endpoints): a handshake with the config's own CA and client certificate; a plain
   ``tcp/`` endpoint that answers a TLS handshake is a TLS listener -> :class:`TlsHandshakeError`.
3. Otherwise the router was reached and closed the session during Zenoh's own handshake, which is
   what a usrpwd refusal looks like -> :class:`AuthenticationError`.

Access-control denials never reach the client at open (the session opens; denied messages are
dropped), so they are diagnosed later, by the aggregator (:class:`AccessDeniedError`).
"""

from __future__ import annotations

import json
import re
import socket
import ssl

from visfly_dist.errors import (
    AuthenticationError,
    RouterUnreachableError,
    SessionConnectError,
    TlsHandshakeError,
)

PROBE_TIMEOUT_S = 2.0
_ENDPOINT = re.compile(r"^(?P<proto>[a-z\-]+)/(?:\[(?P<v6>[0-9A-Fa-f:.]+)\]|(?P<host>[A-Za-z0-9_.\-]+)):(?P<port>\d{1,5})")


def _split(endpoint: str) -> tuple[str, str, int] | None:
    m = _ENDPOINT.match(endpoint)
    if m is None:
        return None
    return m["proto"], m["v6"] or m["host"], int(m["port"])


def _tcp_reachable(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S):
            return True
    except OSError:
        return False


def _setting(zcfg, key: str):
    return json.loads(zcfg.get_json(key))


def _tls_problem(host: str, port: int, zcfg) -> str | None:
    """What goes wrong in a TLS handshake with ``host:port`` under this config (None: nothing)."""
    ca = _setting(zcfg, "transport/link/tls/root_ca_certificate")
    if ca is None:
        return ("the config gives no transport/link/tls/root_ca_certificate, so the router's certificate "
                "cannot be verified; add the CA that signed it (ca.pem from deploy/gen-certs.sh)")
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.load_verify_locations(ca)
    ctx.check_hostname = _setting(zcfg, "transport/link/tls/verify_name_on_connect") is not False
    cert = _setting(zcfg, "transport/link/tls/connect_certificate")
    key = _setting(zcfg, "transport/link/tls/connect_private_key")
    if _setting(zcfg, "transport/link/tls/enable_mtls") and cert and key:
        ctx.load_cert_chain(cert, key)
    try:
        with socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S) as raw:
            with ctx.wrap_socket(raw, server_hostname=host) as tls:
                tls.settimeout(0.5)
                try:  # TLS 1.3: a refused client certificate arrives as an alert after the handshake
                    tls.recv(1)
                except (socket.timeout, TimeoutError):
                    pass
    except ssl.SSLCertVerificationError as exc:
        return f"the router's certificate failed verification against {ca!r}: {exc.verify_message}"
    except ssl.SSLError as exc:
        reason = exc.reason or str(exc)
        if "CERTIFICATE_REQUIRED" in str(reason).upper():
            return ("the router requires a client certificate (mutual TLS): set enable_mtls, connect_certificate "
                    "and connect_private_key under transport/link/tls")
        return f"TLS handshake failed: {reason}"
    except OSError:
        return None
    return None


def _speaks_tls(host: str, port: int) -> bool:
    """Whether the listener at ``host:port`` completes a TLS handshake (certificate not checked)."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    try:
        with socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S) as raw:
            raw.settimeout(1.0)
            with ctx.wrap_socket(raw, server_hostname=host):
                return True
    except (OSError, ssl.SSLError):
        return False


def diagnose_open_failure(where: str, endpoints: tuple[str, ...], zcfg, exc: Exception) -> SessionConnectError:
    """The typed error for a failed ``zenoh.open`` of a session that connects to ``endpoints``.

    Args:
        where: the start of the message (which session, endpoints, config file).
        endpoints: the connect endpoints.
        zcfg: the ``zenoh.Config`` that failed (its TLS and usrpwd settings guide the probes).
        exc: Zenoh's exception, quoted at the end of the message.
    """
    tail = f" (zenoh: {str(exc).split(' at /')[0].strip()})"  # drop the Rust source location
    parsed = {ep: _split(ep) for ep in endpoints}
    probed = {ep: p for ep, p in parsed.items() if p is not None and p[0] in ("tcp", "tls")}
    if not probed:
        return SessionConnectError(f"{where}: {exc}", endpoints)
    reachable = {ep: p for ep, p in probed.items() if _tcp_reachable(p[1], p[2])}
    if not reachable:
        return RouterUnreachableError(
            f"{where}: nothing accepts connections at {sorted(probed)}; is the router running "
            "(`visfly-dist router`), and are the host and port right and reachable from here?" + tail, endpoints)
    for ep, (proto, host, port) in reachable.items():
        if proto == "tls":
            problem = _tls_problem(host, port, zcfg)
            if problem:
                return TlsHandshakeError(f"{where}: TLS to {ep}: {problem}" + tail, endpoints)
        elif _speaks_tls(host, port):
            return TlsHandshakeError(
                f"{where}: {ep} is a TLS listener; connect with tls/{ep.split('/', 1)[1]} and a config that "
                "gives transport/link/tls/root_ca_certificate" + tail, endpoints)
    user = _setting(zcfg, "transport/auth/usrpwd/user")
    if user:
        why = (f"the router refused user {user!r}: wrong password, or the user is not in the router's "
               "dictionary_file")
    else:
        why = ("the router refused the session during Zenoh's handshake; it most likely requires a user and "
               "password: give transport/auth/usrpwd/user and password in the --zenoh-config file")
    return AuthenticationError(f"{where}: {why}" + tail, endpoints)
