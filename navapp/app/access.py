"""Who may use a viewer: the access tokens of ``navapp serve`` and the role each gives. No viser here.

Beyond this machine (``--host`` not a loopback address) a viewer needs a token, as Jupyter
does: a random one is made at start (or given with ``--token`` / ``$NAVAPP_TOKEN``), printed
in the viewer's URL, and asked for by the 3D viewer's page and websocket (``front``) and by
the 2D view's server (``view2d.http``). A second token opens an *observer* link: it shows
everything live and changes nothing. On a loopback address nothing is asked unless a token
is given. Tokens are compared in constant time.
"""

from __future__ import annotations

import hmac
import ipaddress
import os
import re
import secrets
import ssl
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from ..errors import InputError

TOKEN_ENV = "NAVAPP_TOKEN"
USER_TOKEN = re.compile(r"[A-Za-z0-9._~-]{8,256}")  # a link's query carries it unchanged
TOKEN_BYTES = 32  # secrets.token_urlsafe: 43 characters, 256 bits
REFUSED = b"403 Forbidden: this viewer asks for the token of its link (printed where navapp serve was started)."
OBSERVING = "Observer link: this view shows everything live and changes nothing. The change was refused."


class Role(Enum):
    EDITOR = "editor"  # may change the shared data
    OBSERVER = "observer"  # watches only


def is_loopback(host: str) -> bool:
    """Whether listening on ``host`` reaches this machine only. A name other than
    ``localhost`` counts as reaching beyond it (it may resolve anywhere), as do the
    wildcard addresses ("", 0.0.0.0, ::)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class Access:
    """The tokens a viewer asks for; ``None`` tokens: nothing asked, every tab an editor."""

    editor: str | None = None
    observer: str | None = None

    @property
    def required(self) -> bool:
        return self.editor is not None

    def role_for(self, token: str | None) -> Role | None:
        """The role ``token`` gives, or None when it gives none (compared in constant time;
        both tokens are always compared so the time does not tell which one was near)."""
        if not self.required:
            return Role.EDITOR
        given = (token or "").encode()
        editor = hmac.compare_digest(given, (self.editor or "").encode())
        observer = self.observer is not None and hmac.compare_digest(given, self.observer.encode())
        if editor and token:
            return Role.EDITOR
        if observer and token:
            return Role.OBSERVER
        return None

    def token_for(self, role: Role) -> str | None:
        return self.editor if role is Role.EDITOR else self.observer


OPEN = Access()  # nothing asked: a loopback viewer without --token


def decide(host: str, token: str | None = None, env: Mapping[str, str] | None = None) -> Access:
    """The access of a viewer listening on ``host``: ``token`` (``--token``), else
    ``$NAVAPP_TOKEN``, else a random token when ``host`` reaches beyond this machine; with
    a token, a random observer token beside it. On a loopback address without a token:
    nothing asked (as before tokens)."""
    token = token or (os.environ if env is None else env).get(TOKEN_ENV) or None
    if token is None and is_loopback(host):
        return Access()
    if token is not None and not USER_TOKEN.fullmatch(token):
        raise InputError("--token (or $NAVAPP_TOKEN) wants at least 8 characters, each a letter, a digit or one "
                         "of - _ . ~ (it travels in a link as it is)")
    return Access(token or secrets.token_urlsafe(TOKEN_BYTES), secrets.token_urlsafe(TOKEN_BYTES))


def tls_context(certfile: Path | None, keyfile: Path | None) -> ssl.SSLContext | None:
    """The servers' TLS context from a certificate and its key (PEM), or None without them."""
    if certfile is None and keyfile is None:
        return None
    if certfile is None:
        raise InputError("--keyfile needs --certfile (the certificate it belongs to)")
    for path in (certfile, keyfile):
        if path is not None and not Path(path).is_file():
            raise InputError("no such file", path)
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    try:
        ctx.load_cert_chain(certfile, keyfile)
    except ssl.SSLError as exc:
        raise InputError(f"not a PEM certificate with its private key ({exc.reason or exc})",
                         certfile if keyfile is None else f"{certfile} / {keyfile}") from None
    return ctx
