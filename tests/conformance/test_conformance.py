"""Every registered plugin (built-in or third-party, by entry point) passes the shipped conformance checks.

One test per (plugin, check), from ``rollingstar.estimators.conformance.plugin_checks``; the checks
themselves are tested in ``test_checks.py``.
"""
from __future__ import annotations

import pytest

from rollingstar.estimators.conformance import plugin_checks
from rollingstar.pipelines.registry import plugins_by_role

PLUGINS = [(role, cls) for role, classes in plugins_by_role().items() for cls in classes]
CHECKS = [check for _, cls in PLUGINS for check in plugin_checks(cls)]


@pytest.mark.parametrize("check", CHECKS, ids=str)
def test_plugin_conforms(check):
    check()


@pytest.mark.parametrize("role, cls", PLUGINS, ids=[f"{role}-{cls.name or cls.__name__}" for role, cls in PLUGINS])
def test_registry_groups_plugins_by_their_role(role, cls):
    assert cls.role == role
