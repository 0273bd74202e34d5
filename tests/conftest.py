"""Shared test set-up: float64 for correctness tests and the persistent JAX cache; each
test's kind from its folder; test certificates for the TLS tests.

A test's kind is the folder it sits in, and its marker (``-m unit``, ``-m integration``):

- ``unit/``: one function, class or service handler in process (seconds);
- ``property/``: properties over many generated inputs (Hypothesis, fuzzing, soaks);
- ``integration/``: real processes or a Zenoh session on loopback (the stack, a service,
  the router, the PX4 bridge and simulated PX4);
- ``workflow/``: offline workflows end to end (the cartpole evaluation, the discrepancy
  workflow, the quadrotor data, training and closed-loop pipeline).

Modules shared by every folder (``loopback``) sit beside this file, which pytest puts on
``sys.path``.
"""

import subprocess
from pathlib import Path

import pytest

from arcade_io import jaxsetup

jaxsetup.configure(x64=True)

TESTS = Path(__file__).resolve().parent
KINDS = ("unit", "property", "integration", "workflow")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items) -> None:
    """Mark every test with its folder's kind (before ``-m`` selects on the markers)."""
    for item in items:
        folder = Path(item.path).resolve().relative_to(TESTS).parts[0]
        if folder not in KINDS:
            raise pytest.UsageError(f"{item.nodeid}: a test belongs in one of tests/{KINDS}")
        item.add_marker(folder)


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
