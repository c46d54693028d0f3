"""The test suite's own pytest hooks, registered through tests/conftest.py (which imports them):

- measured figures: ``report_figures(title, text)`` records numbers the README quotes; they ride on the test
  reports (so xdist brings them from its workers) and print at the end of every run;
- grouping for ``pytest -n 2`` (``--dist loadgroup``): a test runs with the rest of its module, and the
  tests that read the accuracy runs share ``ACCURACY_GROUP``.
"""
from __future__ import annotations

import pytest

_FIGURES: list[tuple[str, str]] = []   # reported in this process, not yet attached to a test report
_PRINTED: list[tuple[str, str]] = []   # collected from the reports (under xdist: from every worker)


def report_figures(title: str, text: str) -> None:
    """Measured figures that the README quotes: printed at the end of every pytest run (no ``-s``
    needed), so each README number named after a test is reproduced by running that test."""
    _FIGURES.append((title, text))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """The figures a test (or its fixtures) reported ride on its report, which xdist sends from the
    worker to the main process; a new list, because the phases' reports share the item's."""
    outcome = yield
    report = outcome.get_result()
    if _FIGURES:
        report.user_properties = list(report.user_properties) + [("figures", figure) for figure in _FIGURES]
        _FIGURES.clear()


def pytest_runtest_logreport(report) -> None:
    for key, value in report.user_properties:
        if key == "figures" and tuple(value) not in _PRINTED:   # a module fixture made on both workers: once
            _PRINTED.append(tuple(value))


# The suite runs on both cores (``pytest -n 2``; pyproject.toml adds ``--dist loadgroup``): xdist hands out a
# group's tests to one worker together. Every test is grouped with its module, so the module's expensive
# fixtures (a hard scene's run, the drift room's walks, a demo recording, a saved map) are made once and not
# on both workers; the tests that read the accuracy runs (tools/accuracy.py's 13 dynslam runs, a session
# fixture) share the group ACCURACY_GROUP, so those runs happen once. Measured on the fast tier (2026-11-28,
# 1,147 tests, this 2-core machine): 164-170 s with fast tests spread one by one, 134-141 s grouped (the
# tests' own time 297-310 -> 235-250 s: fixtures no longer made twice).
ACCURACY_GROUP = "accuracy_runs"


@pytest.hookimpl(tryfirst=True)    # before xdist reads the groups
def pytest_collection_modifyitems(config, items) -> None:
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(item.module.__name__))


def pytest_terminal_summary(terminalreporter) -> None:
    if not _PRINTED:
        return
    terminalreporter.section("measured figures (quoted in the README)")
    for title, text in _PRINTED:
        terminalreporter.write_line(f"{title}:")
        for line in text.splitlines():
            terminalreporter.write_line(f"    {line}")
