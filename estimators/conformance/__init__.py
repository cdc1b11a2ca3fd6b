"""The conformance suite every plugin passes, shipped so that a plugin's own tests can run it.

Like scikit-learn's ``check_estimator``: :func:`check_plugin` runs every check that applies to a
plugin class and raises AssertionError naming the first check that failed and what failed::

    from rollingstar.estimators.conformance import check_plugin

    def test_my_filter_conforms():
        check_plugin(MyFilter)

and :func:`plugin_checks` yields the checks one by one (each a callable :class:`Check` whose
``str`` is a test id), for one test per check::

    import pytest
    from rollingstar.estimators.conformance import plugin_checks

    @pytest.mark.parametrize("check", list(plugin_checks(MyFilter)), ids=str)
    def test_my_filter(check):
        check()

The checks run the plugin on two small simulated scenes (:mod:`.scenes`, built once per process):
a static one (every role's standard input, with and without stars) and a moving one (the camera
turning at ~2 deg/s, with gyro samples). Every plugin: the constructor only stores validated
parameters, unknown parameters are rejected, parameters round-trip, the hooks of
:class:`~rollingstar.estimators.plugin.Plugin` keep their defaults, output frames are well formed,
the input frames are never mutated, runs are deterministic and restartable. Each role's contract
on the moving scene: centroiders time spots by the sensor timing, identifiers only add the
identification (and get it right), star-motion filters fill ``vx, vy`` of tracked stars,
rolling-shutter corrections move every star to one common time ``t_ns``, rate estimators set
``frame.rate``, attitude solvers append estimates near the truth at their time.
"""
from rollingstar.estimators.conformance.checks import (
    EVERY_PLUGIN,
    ROLE_CHECKS,
    Check,
    check_plugin,
    plugin_checks,
)
from rollingstar.estimators.conformance.scenes import ROLE_INPUT

__all__ = ["Check", "EVERY_PLUGIN", "ROLE_CHECKS", "ROLE_INPUT", "check_plugin", "plugin_checks"]
