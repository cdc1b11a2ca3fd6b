"""Estimation plugins, one sub-package per role, each with a small base class.

Roles: ``centroider``, ``identifier``, ``filter`` (star motion), ``correction`` (rolling shutter),
``attitude`` (solvers and smoothers), ``rate`` (angular-rate estimators).
Every plugin passes its role's conformance checks (:mod:`rollingstar.estimators.conformance`, which
third-party plugins run in their own tests).
"""
