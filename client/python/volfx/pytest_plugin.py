"""pytest fixtures for testing against volfxd; load with ``pytest_plugins = ["volfx.pytest_plugin"]``
in a conftest.py (or ``-p volfx.pytest_plugin``).

- ``volfx_server``: one private volfxd for the session (``volfx.testing.Server``); options from
  ``--volfxd PATH`` (else ``$VOLFX_VOLFXD`` or ``volfxd`` on PATH).
- ``volfx_client``: a new authenticated connection per test.
- ``volfx_scene``: a fresh scene per test (``volfx.testing.Scene``), the default scene unless
  the test is marked ``@pytest.mark.volfx_scene(preset="demo")`` or
  ``@pytest.mark.volfx_scene(document={...})``.

A failed test's report gets a "volfxd log" section with what the server logged during it.
Nothing here imports pytest at module level beyond what pytest itself loads.
"""

import pytest

from volfx import testing


def pytest_addoption(parser):
    parser.addoption("--volfxd", default=None, help="the volfxd executable for volfx fixtures")


def pytest_configure(config):
    config.addinivalue_line("markers", "volfx_scene(preset=None, document=None): the scene "
                            "the volfx_scene fixture makes")


@pytest.fixture(scope="session")
def volfx_server(request):
    with testing.Server(request.config.getoption("--volfxd")) as srv:
        yield srv


@pytest.fixture
def volfx_client(volfx_server, request):
    request.node._volfx_log = (volfx_server, volfx_server.log_offset())
    with volfx_server.client() as c:
        yield c


@pytest.fixture
def volfx_scene(volfx_client, request):
    mark = request.node.get_closest_marker("volfx_scene")
    kw = dict(mark.kwargs) if mark else {}
    with testing.Scene(volfx_client, preset=kw.get("preset"), document=kw.get("document")) as s:
        yield s


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    held = getattr(item, "_volfx_log", None)
    if held and report.failed:
        server, since = held
        report.sections.append(("volfxd log (%s)" % report.when,
                                server.log_text(since) or "(nothing)"))
