"""Zenoh session configurations of the bus: the embedded peers on loopback (with or without
a password), a router, clients of a router, the files in ``deploy/zenoh/``, and Zenoh's
errors on one line. :mod:`services.bus` re-exports all of it (see its docstring for the
default set-up)."""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import zenoh

__all__ = [
    "DEFAULT_HUB",
    "LOOPBACK_ANY",
    "client_config",
    "config_path",
    "load_config",
    "peer_config",
    "peer_tree",
    "read_config",
    "router_config",
    "zenoh_reason",
]

#: Well-known loopback endpoint of the default peer mesh.
DEFAULT_HUB = "tcp/127.0.0.1:7450"
#: An ephemeral loopback endpoint (the OS picks the port).
LOOPBACK_ANY = "tcp/127.0.0.1:0"
#: Connection retry of peers: fast on loopback, capped at 1 s.
_RETRY = {"period_init_ms": 50, "period_max_ms": 1000, "period_increase_factor": 2}


def _config(tree: Mapping[str, Any]) -> zenoh.Config:
    return zenoh.Config.from_json5(json.dumps(tree))


def peer_config(hub: str | None = DEFAULT_HUB, **options: Any) -> zenoh.Config:
    """Peer mode without multicast scouting (the embedded default, see module docstring);
    ``options`` are those of :func:`peer_tree`."""
    return _config(peer_tree(hub, **options))


def peer_tree(
    hub: str | None = DEFAULT_HUB,
    *,
    listen: Sequence[str] = (LOOPBACK_ANY,),
    connect: Sequence[str] = (),
    gossip: bool = True,
    credentials: tuple[str, str, str | Path] | None = None,
) -> dict[str, Any]:
    """The configuration of :func:`peer_config` as a JSON-able tree (to write a file).

    Args:
        hub: endpoint every peer tries to listen on and connects to; ``None`` for none.
        listen: further listen endpoints (an ephemeral loopback port by default, which
            gossip advertises so that peers link directly).
        connect: further endpoints to connect to (retried until they answer).
        gossip: learn other peers' endpoints from the peers already connected.
        credentials: ``(user, password, dictionary file)``: every link, either way,
            authenticates with this user and password (the file lists ``user:password``).
    """
    hub_eps = [hub] if hub else []
    tree: dict[str, Any] = {
        "mode": "peer",
        # The hub port is taken by whichever peer came first: not an error.
        "listen": {"endpoints": hub_eps + list(listen), "exit_on_failure": False},
        "connect": {
            "endpoints": hub_eps + list(connect),
            "exit_on_failure": False,
            "retry": _RETRY,
        },
        # No multicast, hence nothing to wait for at open.
        "scouting": {
            "delay": 0,
            "multicast": {"enabled": False},
            "gossip": {"enabled": gossip},
        },
    }
    if credentials is not None:
        user, password, users = credentials
        usrpwd = {"user": user, "password": password, "dictionary_file": str(users)}
        tree["transport"] = {"auth": {"usrpwd": usrpwd}}
        # Of two peers that learn of each other, only one connects: with eclipse-zenoh 1.10
        # and usrpwd, two peers connecting to each other at once sometimes ended with no
        # link between them at all (zenoh issue 2577), e.g. a restarted controller that
        # never heard the estimator.
        tree["scouting"]["gossip"]["autoconnect_strategy"] = {
            "peer": {"to_router": "always", "to_peer": "greater-zid"}
        }
    return tree


def router_config(
    listen: Sequence[str] = ("tcp/0.0.0.0:7447",), *, connect: Sequence[str] = ()
) -> zenoh.Config:
    """A router (a Python session in ``mode: "router"``) listening on ``listen``.

    For access control, TLS or user/password, start from the files in ``deploy/zenoh/``
    (:func:`load_config`).
    """
    return _config(
        {
            "mode": "router",
            "listen": {"endpoints": list(listen)},
            "connect": {"endpoints": list(connect)},
            "scouting": {"multicast": {"enabled": False}},
        }
    )


def client_config(
    connect: Sequence[str],
    *,
    user: str | None = None,
    password: str | None = None,
    root_ca: str | Path | None = None,
    cert: str | Path | None = None,
    key: str | Path | None = None,
) -> zenoh.Config:
    """Client of a router at ``connect`` (opening fails if none answers).

    ``user``/``password`` authenticate (the router's ACL subjects name users); ``root_ca``
    verifies a ``tls/`` router; ``cert``/``key`` add a client certificate for mTLS.
    """
    tree: dict[str, Any] = {
        "mode": "client",
        "connect": {"endpoints": list(connect)},
        "scouting": {"multicast": {"enabled": False}},
    }
    transport: dict[str, Any] = {}
    if user is not None or password is not None:
        transport["auth"] = {"usrpwd": {"user": user, "password": password}}
    files = (
        ("root_ca_certificate", root_ca),
        ("connect_certificate", cert),
        ("connect_private_key", key),
    )
    tls: dict[str, Any] = {k: str(v) for k, v in files if v is not None}
    if cert is not None or key is not None:
        tls["enable_mtls"] = True
    if tls:
        transport["link"] = {"tls": tls}
    if transport:
        tree["transport"] = transport
    return _config(tree)


def config_path(name: str = "peer-loopback.json5") -> Path:
    """Path of a configuration shipped in ``deploy/zenoh/``."""
    path = Path(str(resources.files("deploy") / "zenoh" / name))
    if not path.is_file():
        raise FileNotFoundError(path)
    return path


def load_config(path: str | Path, overrides: Mapping[str, Any] | None = None) -> zenoh.Config:
    """Load a JSON5 configuration and apply ``overrides`` (``{"listen/endpoints": [...]}``)."""
    config = zenoh.Config.from_file(str(path))
    for key, value in (overrides or {}).items():
        config.insert_json5(key, json.dumps(value))
    return config


#: The source location Zenoh appends to its error messages.
_ZENOH_WHERE = re.compile(r"\s+at \S+\.rs:\d+\.?\s*$")


def zenoh_reason(err: BaseException) -> str:
    """A Zenoh error on one line, without the library's source location."""
    text = _ZENOH_WHERE.sub("", str(err)).strip()
    if "\n" in text:  # a JSON5 syntax error: " --> line:col", the source, "= expected ..."
        where = re.search(r"-->\s*(\d+:\d+)", text)
        last = text.splitlines()[-1].strip().lstrip("= ")
        text = f"line:column {where.group(1)}: {last}" if where else " ".join(text.split())
    return text


def read_config(path: str | Path) -> zenoh.Config:
    """The session configuration in the file ``path`` (JSON5, JSON or YAML).

    Raises ``ValueError`` with one line naming the file when it is missing, unreadable or
    not a valid Zenoh configuration.
    """
    try:
        return load_config(path)
    except zenoh.ZError as err:
        raise ValueError(f"bus config {path}: {zenoh_reason(err)}") from None
