"""Shared test set-up: float64 for correctness tests and the persistent JAX cache; each
test's kind from its folder; test certificates for the TLS tests.

A test's kind is the folder it sits in, and its marker (``-m unit``, ``-m integration``):

- ``unit/``: one function, class or service handler in process (seconds);
- ``property/``: properties over many generated inputs (Hypothesis, fuzzing, soaks);
- ``integration/``: real processes or a Zenoh session on loopback (the stack, a service,
  the router, the PX4 bridge and simulated PX4);
- ``workflow/``: offline workflows end to end (the cartpole evaluation, the discrepancy
  workflow, the quadrotor data, training and closed-loop pipeline).

Tests that fly on the wall clock and assert on its timing are also marked ``realtime``:
``make test`` runs them alone, after the others, so that what they measure is not the load
of other tests; they belong in ``integration/`` (that run collects only that folder).

Modules shared by every folder (``loopback``) sit beside this file, which pytest puts on
``sys.path``. Expensive fixtures that tests only read are built once per session here.

Scheduling over ``pytest-xdist`` workers (``-n 2 --dist loadfile``): the tests of one file
run on one worker (their module fixtures are built once), except the files in
:data:`BY_CASE`, whose cases are independent and spread over the workers; the slower kinds
are queued first (integration, workflow, property, unit), so that the many short tests fill
in at the end and the workers finish together.
"""

import subprocess
from pathlib import Path

import pytest

from arcade_io import jaxsetup

jaxsetup.configure(x64=True)

TESTS = Path(__file__).resolve().parent
KINDS = ("unit", "property", "integration", "workflow")
#: The order in which the kinds are queued for the workers: the slowest first.
QUEUED = ("integration", "workflow", "property", "unit")


#: Files whose parametrized cases (each a case of a module-scoped fixture) are independent:
#: each case is a unit of work of its own (the others' units are whole files), except the
#: cases named here, whose flight the file's other tests reuse (``_case`` is cached in the
#: worker that runs them): they stay with those tests.
BY_CASE = {"workflow/test_discrepancy_quadrotor.py": ("rotor_drag",)}


def _kind(item: pytest.Item) -> str:
    return Path(item.path).resolve().relative_to(TESTS).parts[0]


def _unit(nodeid: str) -> str:
    """The unit of work a test belongs to: its file, or its file and case (:data:`BY_CASE`)."""
    path, _, name = nodeid.partition("::")
    shared = BY_CASE.get(path.removeprefix("tests/"))
    if shared is not None and name.endswith("]"):
        case = name.rsplit("[", 1)[1].rstrip("]")
        if case not in shared:
            return f"{path}[{case}]"
    return path


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items) -> None:
    """Mark every test with its folder's kind (before ``-m`` selects on the markers)."""
    for item in items:
        kind = _kind(item)
        if kind not in KINDS:
            raise pytest.UsageError(f"{item.nodeid}: a test belongs in one of tests/{KINDS}")
        item.add_marker(kind)
        # make test runs tests/integration alone, one test at a time: a realtime test
        # elsewhere would be measured under the load of the parallel run.
        if kind != "integration" and item.get_closest_marker("realtime") is not None:
            raise pytest.UsageError(f"{item.nodeid}: a realtime test belongs in tests/integration")


class _Queue:
    @pytest.hookimpl(trylast=True)
    def pytest_collection_modifyitems(self, items) -> None:
        """Queue the slower kinds first, after pytest ordered the tests by their fixtures
        (a stable sort: the order within a kind is kept)."""
        items.sort(key=lambda item: QUEUED.index(_kind(item)))


def pytest_configure(config) -> None:
    config.pluginmanager.register(_Queue(), "arcade-test-queue")


def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile``: units of work by :func:`_unit`, handed out in the collection's
    order (the slower kinds first)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class Units(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _unit(nodeid)

    config.option.loadscopereorder = False
    return Units(config, log)


@pytest.fixture(scope="session")
def estimator_factory():
    """:func:`loopback.lockstep_estimator`, its filter step compiled once for the session."""
    from loopback import lockstep_estimator

    est, _ = lockstep_estimator()
    est.warmup()
    return lockstep_estimator


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


@pytest.fixture(scope="session")
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
