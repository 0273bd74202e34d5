"""Shared test set-up: float64 for correctness tests and the persistent JAX cache; test
certificates for the TLS tests."""

import subprocess
from pathlib import Path

import pytest

from arcade_io import jaxsetup

jaxsetup.configure(x64=True)


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def _ca(d: Path, name: str) -> None:
    _openssl(
        "req",
        "-x509",
        "-newkey",
        "ec",
        "-pkeyopt",
        "ec_paramgen_curve:P-256",
        "-nodes",
        "-days",
        "2",
        "-subj",
        f"/CN={name}",
        "-keyout",
        f"{name}.key",
        "-out",
        f"{name}.pem",
        cwd=d,
    )


def _signed(d: Path, name: str, ca: str) -> None:
    _openssl(
        "req",
        "-newkey",
        "ec",
        "-pkeyopt",
        "ec_paramgen_curve:P-256",
        "-nodes",
        "-subj",
        f"/CN={name}",
        "-addext",
        "subjectAltName=DNS:localhost",
        "-keyout",
        f"{name}.key",
        "-out",
        f"{name}.csr",
        cwd=d,
    )
    _openssl(
        "x509",
        "-req",
        "-in",
        f"{name}.csr",
        "-CA",
        f"{ca}.pem",
        "-CAkey",
        f"{ca}.key",
        "-CAcreateserial",
        "-days",
        "2",
        "-copy_extensions",
        "copy",
        "-out",
        f"{name}.pem",
        cwd=d,
    )


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    """CA ``ca`` signs ``router`` (localhost), ``controller``, ``estimator`` and
    ``recorder``; an
    unrelated CA ``evil-ca`` signs ``intruder``."""
    d = tmp_path_factory.mktemp("certs")
    _ca(d, "ca")
    for name in ("router", "controller", "estimator", "recorder"):
        _signed(d, name, "ca")
    _ca(d, "evil-ca")
    _signed(d, "intruder", "evil-ca")
    return d
